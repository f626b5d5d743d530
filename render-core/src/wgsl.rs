//! The WGSL/Rust contract: every constant and uniform struct that a kernel shares with the host
//! is defined here, once, in Rust. [`prelude`] writes them out as WGSL, and [`compose`] puts
//! that prelude and `kernels/common.wgsl` in front of every kernel source before it is
//! compiled, so the kernels use the host's values and layouts by name and cannot drift from
//! them. A kernel that redeclares a prelude name fails to compile.
//!
//! Structs are declared with `wgsl_struct!`, which derives the Rust side (`#[repr(C)]`,
//! bytemuck `Pod`) and the WGSL text from one field list. Fields are 4-byte scalars or 16-byte
//! vectors; a compile-time check ensures every field sits at an offset that WGSL's uniform and
//! storage layout rules (16-byte alignment for `vec4`, struct size a multiple of 16) give it
//! too, so the two layouts are identical byte for byte. Unused slots are named `padding*`.

use crate::types::constants;

/// How a Rust field type is spelt in WGSL, and its WGSL alignment.
pub(crate) trait WgslType {
    const WGSL: &'static str;
    const ALIGN: usize;
}

impl WgslType for u32 {
    const WGSL: &'static str = "u32";
    const ALIGN: usize = 4;
}

impl WgslType for f32 {
    const WGSL: &'static str = "f32";
    const ALIGN: usize = 4;
}

impl WgslType for [f32; 4] {
    const WGSL: &'static str = "vec4<f32>";
    const ALIGN: usize = 16;
}

/// A struct as [`prelude`] writes it, with its Rust layout.
pub(crate) struct StructLayout {
    pub(crate) name: &'static str,
    pub(crate) fields: &'static [FieldLayout],
    /// Rust `size_of` (checked against naga's layout in the tests).
    #[cfg_attr(not(test), allow(dead_code, reason = "read by the layout tests only"))]
    pub(crate) size: usize,
}

pub(crate) struct FieldLayout {
    pub(crate) name: &'static str,
    pub(crate) wgsl_type: &'static str,
    /// Rust `offset_of` (checked against naga's layout in the tests).
    #[cfg_attr(not(test), allow(dead_code, reason = "read by the layout tests only"))]
    pub(crate) offset: usize,
    pub(crate) docs: &'static [&'static str],
}

/// Declares a struct shared with the kernels: the Rust struct (`#[repr(C)]`, `Pod`) plus its
/// [`StructLayout`] (`Self::LAYOUT`), with a compile-time check that the WGSL layout of the
/// same fields has no padding the Rust one lacks.
macro_rules! wgsl_struct {
    (
        $(#[doc = $doc:literal])*
        struct $name:ident {
            $( $(#[doc = $field_doc:literal])* $field:ident: $ty:ty, )*
        }
    ) => {
        $(#[doc = $doc])*
        #[repr(C)]
        #[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
        pub(crate) struct $name {
            $( $(#[doc = $field_doc])* pub(crate) $field: $ty, )*
        }

        impl $name {
            pub(crate) const LAYOUT: StructLayout = StructLayout {
                name: stringify!($name),
                fields: &[$( FieldLayout {
                    name: stringify!($field),
                    wgsl_type: <$ty as WgslType>::WGSL,
                    offset: std::mem::offset_of!($name, $field),
                    docs: &[$($field_doc),*],
                }, )*],
                size: std::mem::size_of::<$name>(),
            };
        }

        const _: () = {
            $( assert!(
                std::mem::offset_of!($name, $field) % <$ty as WgslType>::ALIGN == 0,
                concat!(stringify!($name), ".", stringify!($field), " is misaligned for WGSL"),
            ); )*
            assert!(
                std::mem::size_of::<$name>() % 16 == 0,
                concat!(stringify!($name), " is not a multiple of 16 bytes"),
            );
        };
    };
}

wgsl_struct! {
    /// Camera, image and thresholds of one render (project, rasterize forward and backward,
    /// project backward).
    struct RenderParams {
        /// Rows of camera_from_world's rotation; w holds the translation component.
        camera_row0: [f32; 4],
        camera_row1: [f32; 4],
        camera_row2: [f32; 4],
        /// Pinhole intrinsics in pixels.
        fx: f32,
        fy: f32,
        cx: f32,
        cy: f32,
        width: u32,
        height: u32,
        tiles_x: u32,
        tiles_y: u32,
        gaussian_count: u32,
        /// 1: the backward pass sums each splat's gradient per tile/Gaussian pair (its list
        /// slot), and pair_gradients.wgsl then sums each Gaussian's pairs in depth order, so
        /// the result does not depend on thread timing; 0: straight into the per-Gaussian
        /// sums with atomics, in whatever order the threads arrive (see
        /// `gpu::GradientOrder`).
        pair_gradient_sums: u32,
        padding1: u32,
        padding2: u32,
        /// Splats below this alpha at a pixel are skipped there.
        min_splat_alpha: f32,
        max_splat_alpha: f32,
        /// A pixel stops compositing below this transmittance.
        min_transmittance: f32,
        /// Isotropic variance (px^2) added to every projected covariance.
        low_pass_variance: f32,
        /// Culling: camera z, log-scale and quaternion limits; splat extent in sigmas.
        near_plane: f32,
        max_log_scale: f32,
        min_quaternion_norm_squared: f32,
        extent_sigmas: f32,
        /// Bounds of x/z and y/z of projected means (frustum plus guard band).
        frustum_min_x: f32,
        frustum_max_x: f32,
        frustum_min_y: f32,
        frustum_max_y: f32,
    }
}

wgsl_struct! {
    /// Pair binning (bin.wgsl).
    struct BinParams {
        gaussian_count: u32,
        pair_capacity: u32,
        tiles_x: u32,
        tile_count: u32,
        /// Depth-ordered Gaussians per block (one serial walk each).
        block_size: u32,
        block_count: u32,
        padding0: u32,
        padding1: u32,
    }
}

wgsl_struct! {
    /// One pass of the radix sort (sort.wgsl).
    struct SortParams {
        /// Bit position of this pass's digit.
        shift: u32,
        /// RADIX - 1, or fewer bits on a last pass that covers the remaining key bits only.
        digit_mask: u32,
        block_size: u32,
        block_count: u32,
        /// 1 on a depth sort's first pass: each key's value is its index (values_in is not
        /// read), and culled keys go to a bucket of their own, after every digit, so that later
        /// passes sort only the others (sort.wgsl).
        depth_first_pass: u32,
        padding0: u32,
        padding1: u32,
        padding2: u32,
    }
}

wgsl_struct! {
    /// Prefix scan (scan.wgsl).
    struct ScanParams {
        count: u32,
        /// 1 for an exclusive scan, 0 for an inclusive one.
        exclusive: u32,
        padding0: u32,
        padding1: u32,
    }
}

wgsl_struct! {
    /// Pose-gradient reduction (reduce.wgsl).
    struct ReduceParams {
        count: u32,
        padding0: u32,
        padding1: u32,
        padding2: u32,
    }
}

wgsl_struct! {
    /// Stable compaction of one per-Gaussian array (compact.wgsl).
    struct CompactParams {
        count: u32,
        /// 32-bit values per Gaussian in this array.
        width: u32,
        padding0: u32,
        padding1: u32,
    }
}

wgsl_struct! {
    /// Prune criteria (prune.wgsl).
    struct PruneParams {
        count: u32,
        padding0: u32,
        padding1: u32,
        padding2: u32,
        opacity_logit_threshold: f32,
        /// Largest allowed log-scale.
        max_log_scale: f32,
        /// Largest allowed ratio of largest to smallest scale.
        max_elongation: f32,
        padding3: f32,
    }
}

wgsl_struct! {
    /// Rigid transform of the map (transform.wgsl).
    struct TransformParams {
        gaussian_count: u32,
        /// TRANSFORM_ALL or TRANSFORM_BY_GROUP.
        group_mode: u32,
        transform_count: u32,
        padding0: u32,
    }
}

wgsl_struct! {
    /// One rigid transform of transform.wgsl.
    struct GroupTransform {
        /// Rows of R; w holds the translation component of that row.
        row0: [f32; 4],
        row1: [f32; 4],
        row2: [f32; 4],
        /// q_R as (w, x, y, z).
        rotation_quaternion: [f32; 4],
    }
}

wgsl_struct! {
    /// Image loss (loss.wgsl).
    struct LossParams {
        width: u32,
        height: u32,
        /// LOSS_RUN-pixel runs per row (horizontal passes) and per column (vertical pass).
        runs_per_row: u32,
        runs_per_column: u32,
        w_l1: f32,
        w_ssim: f32,
        w_depth: f32,
        inverse_depth_truncation: f32,
        /// 1 / (3 * pixels).
        rgb_normaliser: f32,
        /// 1 / valid depth pixels (0 if none).
        depth_normaliser: f32,
        padding0: f32,
        padding1: f32,
        /// Number of column runs: offset of the row runs' partials in loss_partials.
        column_run_count: u32,
        padding2: u32,
        padding3: u32,
        padding4: u32,
    }
}

wgsl_struct! {
    /// One Adam step (adam.wgsl).
    struct AdamParams {
        count: u32,
        padding0: u32,
        padding1: u32,
        padding2: u32,
        learning_rate: f32,
        beta1: f32,
        beta2: f32,
        epsilon: f32,
        /// 1 / (1 - beta1^t) and 1 / (1 - beta2^t).
        bias_correction1: f32,
        bias_correction2: f32,
        padding3: f32,
        padding4: f32,
    }
}

/// Every struct of the prelude.
const STRUCTS: [StructLayout; 11] = [
    RenderParams::LAYOUT,
    BinParams::LAYOUT,
    SortParams::LAYOUT,
    ScanParams::LAYOUT,
    ReduceParams::LAYOUT,
    CompactParams::LAYOUT,
    PruneParams::LAYOUT,
    TransformParams::LAYOUT,
    GroupTransform::LAYOUT,
    LossParams::LAYOUT,
    AdamParams::LAYOUT,
];

/// Invocations per workgroup of the 1D kernels (project, gather, tile ranges, prune, compact,
/// transform, Adam).
pub(crate) const WORKGROUP_SIZE: u32 = 256;
/// Invocations per workgroup of the kernels where one invocation walks a block or chunk
/// serially (scan, radix sort).
pub(crate) const SERIAL_WORKGROUP_SIZE: u32 = 64;
/// Values per invocation of the prefix scan.
pub(crate) const SCAN_CHUNK: u32 = 256;
/// Digit width of the radix sort.
pub(crate) const RADIX_BITS: u32 = 8;
/// Invocations per workgroup of the pair binning's block walks. There are only ~100 blocks
/// at 100k Gaussians, and a CPU adapter runs each workgroup on one thread: small workgroups
/// spread the blocks evenly over the threads (64-wide ones left one of two cores walking three
/// quarters of the pairs).
pub(crate) const BIN_WORKGROUP_SIZE: u32 = 8;
/// Gaussians per invocation of project_backward (each invocation sums their pose gradients).
pub(crate) const PROJECT_BACKWARD_CHUNK: u32 = 16;
pub(crate) const PROJECT_BACKWARD_WORKGROUP_SIZE: u32 = 64;
/// Partial pose gradients per invocation of the reduction.
pub(crate) const REDUCE_CHUNK: u32 = 64;
pub(crate) const REDUCE_WORKGROUP_SIZE: u32 = 64;
/// f32 values per Gaussian of the screen-space gradients (mean2d 2, conic 3, opacity 1,
/// colour 3, depth 1).
pub(crate) const SCREEN_GRADIENT_STRIDE: u32 = 10;
/// f32 values per tile/Gaussian pair of the per-pair gradient sums (`GradientOrder::Fixed`,
/// stored in the pairs' depth order): the screen-space gradients padded to three vec4, which
/// pair_gradients.wgsl reads and clears with three vector accesses instead of ten scalar ones.
pub(crate) const PAIR_SUM_STRIDE: u32 = 12;
const _: () =
    assert!(PAIR_SUM_STRIDE.is_multiple_of(4) && PAIR_SUM_STRIDE >= SCREEN_GRADIENT_STRIDE);
/// `group_mode` of transform.wgsl: one transform for every Gaussian, or one per group.
pub(crate) const TRANSFORM_ALL: u32 = 0;
pub(crate) const TRANSFORM_BY_GROUP: u32 = 1;
/// Pixels per invocation of the loss kernels' separable passes.
pub(crate) const LOSS_RUN: u32 = 64;
pub(crate) const LOSS_WORKGROUP_SIZE: u32 = 64;
/// vec4s per pixel of the SSIM's horizontal pass (15 row sums, packed).
pub(crate) const ROW_SUMS_VEC4S_PER_PIXEL: u32 = 4;
/// vec4s per pixel of the SSIM gradient's coefficients (9, packed).
pub(crate) const SSIM_COEFFICIENT_VEC4S_PER_PIXEL: u32 = 3;

/// Words of a frame's status buffer (`frame_status`, one per frame, zero-filled): the pair
/// counts of the binning and a flag per serial walk that can outgrow the adapter's loop limit
/// (see render-core/README.md). Read back by `GpuRenderer::check_pairs`.
pub(crate) const FRAME_STATUS_WORDS: u32 = 8;
/// Pairs the binning kept (at most the frame's pair capacity).
pub(crate) const STATUS_PAIRS_KEPT: u32 = 0;
/// Pairs the frame needed.
pub(crate) const STATUS_PAIRS_NEEDED: u32 = 1;
/// 1 when a binning walk was cut short (bin.wgsl `count_pairs`).
pub(crate) const STATUS_BINNING_CUT_SHORT: u32 = 2;
/// 1 when a forward rasterizer's walk over a tile's list was cut short.
pub(crate) const STATUS_RASTERIZE_CUT_SHORT: u32 = 3;
/// 1 when a backward rasterizer's walk over a tile's list was cut short.
pub(crate) const STATUS_RASTERIZE_BACKWARD_CUT_SHORT: u32 = 4;
const _: () = assert!(STATUS_RASTERIZE_BACKWARD_CUT_SHORT < FRAME_STATUS_WORDS);

/// A constant as the prelude writes it.
enum Value {
    U32(u32),
    I32(i32),
    F32(f32),
}

/// Every constant of the prelude, under the name the kernels use.
fn constants() -> Vec<(&'static str, Value)> {
    use crate::training::{SSIM_C1, SSIM_C2, SSIM_WINDOW_RADIUS, SSIM_WINDOW_SIGMA};
    use Value::{F32, I32, U32};
    vec![
        ("TILE_SIZE", U32(constants::TILE_SIZE)),
        (
            "DEPTH_KEY_DROPPED_BITS",
            U32(constants::DEPTH_KEY_DROPPED_BITS),
        ),
        (
            "LARGEST_VISIBLE_DEPTH_KEY",
            U32(constants::LARGEST_VISIBLE_DEPTH_KEY),
        ),
        ("CULLED_DEPTH_KEY", U32(constants::CULLED_DEPTH_KEY)),
        ("WORKGROUP_SIZE", U32(WORKGROUP_SIZE)),
        ("SERIAL_WORKGROUP_SIZE", U32(SERIAL_WORKGROUP_SIZE)),
        ("SCAN_CHUNK", U32(SCAN_CHUNK)),
        ("RADIX_BITS", U32(RADIX_BITS)),
        ("BIN_WORKGROUP_SIZE", U32(BIN_WORKGROUP_SIZE)),
        ("PROJECT_BACKWARD_CHUNK", U32(PROJECT_BACKWARD_CHUNK)),
        (
            "PROJECT_BACKWARD_WORKGROUP_SIZE",
            U32(PROJECT_BACKWARD_WORKGROUP_SIZE),
        ),
        ("REDUCE_CHUNK", U32(REDUCE_CHUNK)),
        ("REDUCE_WORKGROUP_SIZE", U32(REDUCE_WORKGROUP_SIZE)),
        ("SCREEN_GRADIENT_STRIDE", U32(SCREEN_GRADIENT_STRIDE)),
        ("PAIR_SUM_STRIDE", U32(PAIR_SUM_STRIDE)),
        ("TRANSFORM_ALL", U32(TRANSFORM_ALL)),
        ("TRANSFORM_BY_GROUP", U32(TRANSFORM_BY_GROUP)),
        ("LOSS_RUN", U32(LOSS_RUN)),
        ("LOSS_WORKGROUP_SIZE", U32(LOSS_WORKGROUP_SIZE)),
        ("ROW_SUMS_VEC4S_PER_PIXEL", U32(ROW_SUMS_VEC4S_PER_PIXEL)),
        (
            "SSIM_COEFFICIENT_VEC4S_PER_PIXEL",
            U32(SSIM_COEFFICIENT_VEC4S_PER_PIXEL),
        ),
        ("STATUS_PAIRS_KEPT", U32(STATUS_PAIRS_KEPT)),
        ("STATUS_PAIRS_NEEDED", U32(STATUS_PAIRS_NEEDED)),
        ("STATUS_BINNING_CUT_SHORT", U32(STATUS_BINNING_CUT_SHORT)),
        (
            "STATUS_RASTERIZE_CUT_SHORT",
            U32(STATUS_RASTERIZE_CUT_SHORT),
        ),
        (
            "STATUS_RASTERIZE_BACKWARD_CUT_SHORT",
            U32(STATUS_RASTERIZE_BACKWARD_CUT_SHORT),
        ),
        ("SSIM_WINDOW_RADIUS", I32(SSIM_WINDOW_RADIUS)),
        ("SSIM_WINDOW_SIGMA", F32(SSIM_WINDOW_SIGMA as f32)),
        ("SSIM_C1", F32(SSIM_C1 as f32)),
        ("SSIM_C2", F32(SSIM_C2 as f32)),
    ]
}

/// The WGSL declarations of every shared constant and struct.
pub(crate) fn prelude() -> String {
    let mut out = String::from("// Generated from render-core/src/wgsl.rs: edit the Rust side.\n");
    for (name, value) in constants() {
        let (ty, literal) = match value {
            // Debug prints the shortest decimal that reads back as the same f32.
            Value::F32(v) => ("f32", format!("{v:?}")),
            Value::U32(v) => ("u32", format!("{v}u")),
            Value::I32(v) => ("i32", format!("{v}i")),
        };
        out.push_str(&format!("const {name}: {ty} = {literal};\n"));
    }
    for layout in &STRUCTS {
        out.push_str(&format!("struct {} {{\n", layout.name));
        for field in layout.fields {
            for doc in field.docs {
                out.push_str(&format!("    //{doc}\n"));
            }
            out.push_str(&format!("    {}: {},\n", field.name, field.wgsl_type));
        }
        out.push_str("}\n");
    }
    out
}

/// The kernel sources (`src/kernels/*.wgsl`), to be passed to [`compose`].
pub(crate) mod source {
    /// Shared WGSL helpers and kernel-only constants, part of every kernel.
    pub(crate) const COMMON: &str = include_str!("kernels/common.wgsl");
    pub(crate) const PROJECT: &str = include_str!("kernels/project.wgsl");
    pub(crate) const SCAN: &str = include_str!("kernels/scan.wgsl");
    pub(crate) const SORT: &str = include_str!("kernels/sort.wgsl");
    pub(crate) const BIN: &str = include_str!("kernels/bin.wgsl");
    /// Bindings 0-5, thread-mapping constants and `Splat`, shared by all four rasterizers.
    pub(crate) const RASTERIZE_TILES: &str = include_str!("kernels/rasterize_tiles.wgsl");
    /// Output bindings and per-pixel compositing shared by the two forward rasterizers.
    pub(crate) const RASTERIZE_PIXELS: &str = include_str!("kernels/rasterize_pixels.wgsl");
    pub(crate) const RASTERIZE: &str = include_str!("kernels/rasterize.wgsl");
    pub(crate) const RASTERIZE_SUBGROUP: &str = include_str!("kernels/rasterize_subgroup.wgsl");
    /// Bindings 6-9 and per-pixel gradients shared by the two backward rasterizers.
    pub(crate) const RASTERIZE_BACKWARD_PIXELS: &str =
        include_str!("kernels/rasterize_backward_pixels.wgsl");
    pub(crate) const RASTERIZE_BACKWARD: &str = include_str!("kernels/rasterize_backward.wgsl");
    pub(crate) const RASTERIZE_BACKWARD_SUBGROUP: &str =
        include_str!("kernels/rasterize_backward_subgroup.wgsl");
    /// `add_gradient` of the backward rasterizers: native float atomics, or a
    /// compare-exchange loop.
    pub(crate) const ATOMICS_FLOAT: &str = include_str!("kernels/atomics_float.wgsl");
    pub(crate) const ATOMICS_CAS: &str = include_str!("kernels/atomics_cas.wgsl");
    /// Each Gaussian's gradient from its pairs' sums, in depth order (`GradientOrder::Fixed`).
    pub(crate) const PAIR_GRADIENTS: &str = include_str!("kernels/pair_gradients.wgsl");
    pub(crate) const PROJECT_BACKWARD: &str = include_str!("kernels/project_backward.wgsl");
    pub(crate) const REDUCE: &str = include_str!("kernels/reduce.wgsl");
    pub(crate) const LOSS: &str = include_str!("kernels/loss.wgsl");
    pub(crate) const ADAM: &str = include_str!("kernels/adam.wgsl");
    pub(crate) const PRUNE: &str = include_str!("kernels/prune.wgsl");
    pub(crate) const COMPACT: &str = include_str!("kernels/compact.wgsl");
    pub(crate) const TRANSFORM: &str = include_str!("kernels/transform.wgsl");
}

/// A kernel's full source: the generated [`prelude`], common.wgsl, then `parts` in order.
pub(crate) fn compose(parts: &[&str]) -> String {
    let mut text = prelude();
    for part in [source::COMMON].iter().chain(parts) {
        text.push('\n');
        text.push_str(part);
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every kernel source file of the crate (name, text).
    fn kernel_files() -> Vec<(String, String)> {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src/kernels");
        let mut files: Vec<(String, String)> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|entry| entry.unwrap().path())
            .filter(|path| path.extension().is_some_and(|ext| ext == "wgsl"))
            .map(|path| {
                let name = path.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read_to_string(&path).unwrap())
            })
            .collect();
        files.sort();
        files
    }

    /// Uniform parameters reach the kernels only through generated structs: a struct written
    /// by hand in a .wgsl file for a uniform binding would be a second, unchecked copy.
    #[test]
    fn uniform_bindings_use_generated_structs() {
        let generated: Vec<&str> = STRUCTS.iter().map(|layout| layout.name).collect();
        for (file, text) in kernel_files() {
            for line in text.lines().filter(|line| line.contains("var<uniform>")) {
                let ty = line
                    .rsplit(':')
                    .next()
                    .unwrap()
                    .trim()
                    .trim_end_matches(';');
                assert!(
                    generated.contains(&ty),
                    "{file}: uniform of type {ty} is not declared in wgsl.rs"
                );
            }
        }
    }

    /// The names the prelude declares are declared nowhere else.
    #[test]
    fn kernels_do_not_redeclare_prelude_names() {
        let mut names: Vec<&str> = constants().iter().map(|(name, _)| *name).collect();
        names.extend(STRUCTS.iter().map(|layout| layout.name));
        for (file, text) in kernel_files() {
            for name in &names {
                for keyword in ["const", "struct", "override"] {
                    let declaration = format!("{keyword} {name}");
                    let redeclared = text.lines().any(|line| {
                        line.trim_start().starts_with(&declaration)
                            && !line.trim_start()[declaration.len()..]
                                .starts_with(|c: char| c.is_alphanumeric() || c == '_')
                    });
                    assert!(!redeclared, "{file} redeclares {name}");
                }
            }
        }
    }

    /// Layouts as WGSL computes them (naga, the shader translator wgpu uses) equal the Rust
    /// ones field by field, and every constant reads back with its Rust value.
    #[test]
    fn wgsl_layouts_and_constants_match_rust() {
        let module = naga::front::wgsl::parse_str(&compose(&[])).expect("prelude parses");
        let mut layouter = naga::proc::Layouter::default();
        layouter.update(module.to_ctx()).unwrap();
        for layout in &STRUCTS {
            let (handle, ty) = module
                .types
                .iter()
                .find(|(_, ty)| ty.name.as_deref() == Some(layout.name))
                .unwrap_or_else(|| panic!("{} missing from the prelude", layout.name));
            let naga::TypeInner::Struct { members, span } = &ty.inner else {
                panic!("{} is not a struct", layout.name);
            };
            assert_eq!(*span as usize, layout.size, "size of {}", layout.name);
            assert_eq!(layouter[handle].size as usize, layout.size);
            assert_eq!(
                members.len(),
                layout.fields.len(),
                "fields of {}",
                layout.name
            );
            for (member, field) in members.iter().zip(layout.fields) {
                assert_eq!(member.name.as_deref(), Some(field.name));
                assert_eq!(
                    member.offset as usize, field.offset,
                    "{}.{}",
                    layout.name, field.name
                );
            }
        }
        for (name, value) in constants() {
            let constant = module
                .constants
                .iter()
                .find(|(_, c)| c.name.as_deref() == Some(name))
                .map(|(_, c)| c)
                .unwrap_or_else(|| panic!("constant {name} missing"));
            let literal = match module.global_expressions[constant.init] {
                naga::Expression::Literal(literal) => literal,
                ref other => panic!("{name} = {other:?}"),
            };
            match (value, literal) {
                (Value::U32(v), naga::Literal::U32(w)) => assert_eq!(v, w, "{name}"),
                (Value::I32(v), naga::Literal::I32(w)) => assert_eq!(v, w, "{name}"),
                (Value::F32(v), naga::Literal::F32(w)) => {
                    assert_eq!(v.to_bits(), w.to_bits(), "{name}")
                }
                (_, other) => panic!("{name} has the wrong type: {other:?}"),
            }
        }
    }
}
