//! The wgpu backward pass: per-Gaussian gradients and the camera-pose gradient of a scalar
//! loss, given dL/d(image) on the device.
//!
//! rasterize_backward (rasterize_backward_pixels.wgsl + rasterize_backward_subgroup.wgsl, or
//! rasterize_backward.wgsl without subgroups) accumulates screen-space gradients with atomics
//! (native f32 atomics or a compare-exchange fallback, see [`crate::gpu::GradientAtomics`]):
//! one add per component and subgroup (per invocation without subgroups) after summing over
//! its pixels. With [`crate::gpu::GradientOrder::Fixed`] (the default) it adds into one sum per
//! tile/Gaussian pair, and pair_gradients adds each Gaussian's pairs in depth order, so a run
//! repeats bit for bit; otherwise straight into per-Gaussian sums. project_backward chains them to the
//! parameters, 16 Gaussians per invocation, and writes one pose contribution per 16
//! Gaussians, which reduce sums deterministically. Nothing is read back unless the caller
//! downloads.

use bytemuck::Zeroable;

use crate::context::{GpuContext, GpuError};
use crate::gpu::{DeviceFrame, DeviceGaussians, GpuRenderer, LayoutId, StageTimes, pair_sum_bytes};
use crate::passes::{U32_BYTES, VEC4_BYTES, bind_group, dispatch_linear};
use crate::profile::StageProfiler;
use crate::types::{Camera, GaussianGradients, ImageGradients, PoseGradient};
use crate::wgsl::{
    PROJECT_BACKWARD_CHUNK, PROJECT_BACKWARD_WORKGROUP_SIZE, REDUCE_CHUNK, REDUCE_WORKGROUP_SIZE,
    ReduceParams, SCREEN_GRADIENT_STRIDE, WORKGROUP_SIZE,
};

/// dL/d(image) on the device: per pixel (r, g, b, depth) and alpha.
pub struct DeviceImageGradients {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Per pixel, row-major: `vec4<f32>` dL/d(r, g, b, depth), with respect to the composited
    /// colour and depth of [`crate::RenderOutput`] (not divided by alpha).
    pub v_rgbd: wgpu::Buffer,
    /// Per pixel, row-major: f32 dL/d(alpha).
    pub v_alpha: wgpu::Buffer,
}

impl DeviceImageGradients {
    /// Zero gradients for an image of `camera`'s size (loss kernels write into them).
    pub fn zeros(context: &GpuContext, camera: &Camera) -> Result<Self, GpuError> {
        let pixels = camera.pixel_count() as u64;
        Ok(Self {
            width: camera.width,
            height: camera.height,
            v_rgbd: context.storage_buffer("v_rgbd", pixels * VEC4_BYTES)?,
            v_alpha: context.storage_buffer("v_alpha", pixels * U32_BYTES)?,
        })
    }

    /// Uploads host gradients; empty vectors mean zero.
    pub fn upload(
        context: &GpuContext,
        camera: &Camera,
        gradients: &ImageGradients,
    ) -> Result<Self, GpuError> {
        let pixels = camera.pixel_count();
        for (name, len) in [
            ("v_rgb", gradients.v_rgb.len()),
            ("v_depth", gradients.v_depth.len()),
            ("v_alpha", gradients.v_alpha.len()),
        ] {
            if len != 0 && len != pixels {
                return Err(GpuError::InvalidInput(format!(
                    "{name} has {len} entries for {pixels} pixels"
                )));
            }
        }
        let v_rgbd: Vec<[f32; 4]> = (0..pixels)
            .map(|i| {
                let rgb = gradients.v_rgb.get(i).copied().unwrap_or([0.0; 3]);
                [
                    rgb[0],
                    rgb[1],
                    rgb[2],
                    gradients.v_depth.get(i).copied().unwrap_or(0.0),
                ]
            })
            .collect();
        let v_alpha: Vec<f32> = (0..pixels)
            .map(|i| gradients.v_alpha.get(i).copied().unwrap_or(0.0))
            .collect();
        let min = VEC4_BYTES as usize;
        Ok(Self {
            width: camera.width,
            height: camera.height,
            v_rgbd: context.storage_buffer_init("v_rgbd", bytemuck::cast_slice(&v_rgbd), min),
            v_alpha: context.storage_buffer_init("v_alpha", bytemuck::cast_slice(&v_alpha), min),
        })
    }
}

/// Gradients on the device, packed like [`DeviceGaussians`]; `v_pose` holds two vec4:
/// (translation, 0) and (rotation, 0), see [`PoseGradient`] for the convention.
pub struct DeviceGradients {
    count: u32,
    /// Layout of the Gaussians the gradients belong to (checked by the Adam step).
    pub(crate) gaussian_layout: LayoutId,
    /// dL/d(world-space mean): packed f32 triples, one per Gaussian.
    pub v_means: wgpu::Buffer,
    /// dL/d(natural-log scale): packed f32 triples, one per Gaussian.
    pub v_log_scales: wgpu::Buffer,
    /// dL/d(raw quaternion `[w, x, y, z]`): one `vec4<f32>` per Gaussian.
    pub v_quaternions: wgpu::Buffer,
    /// dL/d(opacity logit): one f32 per Gaussian.
    pub v_opacity_logits: wgpu::Buffer,
    /// dL/d(linear RGB colour): packed f32 triples, one per Gaussian.
    pub v_colours: wgpu::Buffer,
    /// The camera-pose gradient: two `vec4<f32>`, (translation, 0) and (rotation, 0).
    pub v_pose: wgpu::Buffer,
}

impl DeviceGradients {
    /// Gradient buffers for `count` Gaussians of arrangement `layout` (written by the
    /// backward pass).
    fn allocate(context: &GpuContext, count: u32, layout: LayoutId) -> Result<Self, GpuError> {
        let n = u64::from(count);
        Ok(Self {
            count,
            gaussian_layout: layout,
            v_means: context.storage_buffer("v_means", n * 3 * U32_BYTES)?,
            v_log_scales: context.storage_buffer("v_log_scales", n * 3 * U32_BYTES)?,
            v_quaternions: context.storage_buffer("v_quaternions", n * VEC4_BYTES)?,
            v_opacity_logits: context.storage_buffer("v_opacity_logits", n * U32_BYTES)?,
            v_colours: context.storage_buffer("v_colours", n * 3 * U32_BYTES)?,
            v_pose: context.storage_buffer("v_pose", 2 * VEC4_BYTES)?,
        })
    }

    /// Reads back the camera-pose gradient alone (48 bytes): what a pose optimiser needs each
    /// iteration, without the per-Gaussian gradients.
    pub fn read_pose(&self, context: &GpuContext) -> Result<PoseGradient, GpuError> {
        let pose: Vec<[f32; 4]> = context.read_vec(&self.v_pose, 2)?;
        Ok(PoseGradient {
            v_translation: [pose[0][0], pose[0][1], pose[0][2]],
            v_rotation: [pose[1][0], pose[1][1], pose[1][2]],
        })
    }

    /// Reads every gradient back to the host (blocking): the per-Gaussian ones and the pose's.
    pub fn download(&self, context: &GpuContext) -> Result<GaussianGradients, GpuError> {
        let n = self.count as usize;
        Ok(GaussianGradients {
            v_means: context.read_vec(&self.v_means, n)?,
            v_log_scales: context.read_vec(&self.v_log_scales, n)?,
            v_quaternions: context.read_vec(&self.v_quaternions, n)?,
            v_opacity_logits: context.read_vec(&self.v_opacity_logits, n)?,
            v_colours: context.read_vec(&self.v_colours, n)?,
            v_pose: self.read_pose(context)?,
        })
    }
}

impl GpuRenderer {
    /// Backward pass of `frame`, which must have been rendered from `gaussians` (unchanged
    /// since). Returns device-resident gradients; submits work but reads nothing back.
    pub fn backward(
        &self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        frame: &DeviceFrame,
        image_gradients: &DeviceImageGradients,
    ) -> Result<DeviceGradients, GpuError> {
        self.backward_profiled(context, gaussians, frame, image_gradients, None)
    }

    /// [`GpuRenderer::backward`], optionally timing each stage (each stage is then submitted
    /// and waited for on its own: a benchmark tool).
    pub fn backward_profiled(
        &self,
        context: &GpuContext,
        gaussians: &DeviceGaussians,
        frame: &DeviceFrame,
        image_gradients: &DeviceImageGradients,
        stage_times: Option<&mut StageTimes>,
    ) -> Result<DeviceGradients, GpuError> {
        let mut profiler = StageProfiler::new(context, stage_times)?;
        validate_backward(gaussians, frame, image_gradients)?;
        let n = frame.gaussian_count;
        let gradients = DeviceGradients::allocate(context, n, gaussians.layout)?;
        if n == 0 {
            return Ok(gradients);
        }
        let screen_gradients = context.storage_buffer(
            "screen_gradients",
            u64::from(n) * u64::from(SCREEN_GRADIENT_STRIDE) * U32_BYTES,
        )?;
        // GradientOrder::Fixed: one sum per tile/Gaussian pair first, gathered per Gaussian in
        // depth order below. The guard is held until the pass is submitted.
        let mut kept_sums = self.pair_sums.lock().unwrap_or_else(|poisoned| {
            // A pass panicked between using the sums and zeroing them: start from fresh zeros.
            let mut sums = poisoned.into_inner();
            *sums = None;
            sums
        });
        let pair_sums = if frame.pair_gradient_sums {
            let bytes = pair_sum_bytes(frame.pair_capacity);
            if kept_sums
                .as_ref()
                .is_none_or(|buffer| buffer.size() < bytes)
            {
                // Fresh wgpu buffers are zero-filled.
                *kept_sums = Some(context.storage_buffer("pair_sums", bytes)?);
            }
            kept_sums.clone()
        } else {
            None
        };
        let mut encoder = context.device.create_command_encoder(&Default::default());
        self.encode_rasterize_backward(
            context,
            &mut encoder,
            frame,
            image_gradients,
            pair_sums.as_ref().unwrap_or(&screen_gradients),
        );
        profiler.mark(context, &mut encoder, "rasterize backward")?;
        if let Some(pair_sums) = &pair_sums {
            self.encode_pair_gradients(context, &mut encoder, frame, pair_sums, &screen_gradients);
            profiler.mark(context, &mut encoder, "pair gradients")?;
        }
        let pose = self.encode_project_backward(
            context,
            &mut encoder,
            gaussians,
            frame,
            &screen_gradients,
            &gradients,
        )?;
        profiler.mark(context, &mut encoder, "project backward")?;
        let [translation, rotation] = pose;
        let chunks = n.div_ceil(PROJECT_BACKWARD_CHUNK);
        let translation_sum = self.reduce_vec4(context, &mut encoder, translation, chunks)?;
        let rotation_sum = self.reduce_vec4(context, &mut encoder, rotation, chunks)?;
        encoder.copy_buffer_to_buffer(&translation_sum, 0, &gradients.v_pose, 0, VEC4_BYTES);
        encoder.copy_buffer_to_buffer(&rotation_sum, 0, &gradients.v_pose, VEC4_BYTES, VEC4_BYTES);
        profiler.mark(context, &mut encoder, "pose sum")?;
        context.queue.submit([encoder.finish()]);
        Ok(gradients)
    }

    /// rasterize_backward: dL/d(screen-space splat) into `gradient_sums`, per tile/Gaussian pair
    /// when `frame.pair_gradient_sums`, per Gaussian otherwise; one workgroup per tile.
    fn encode_rasterize_backward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        frame: &DeviceFrame,
        image_gradients: &DeviceImageGradients,
        gradient_sums: &wgpu::Buffer,
    ) {
        let pipeline = &self.pipelines.rasterize_backward;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &frame.params_buffer),
                (1, &frame.tile_ranges),
                (2, &frame.intersection_gaussians),
                (3, &frame.splat_position),
                (4, &frame.splat_conic),
                (5, &frame.splat_colour),
                (6, &frame.transmittance),
                (7, &frame.last_entry),
                (8, &image_gradients.v_rgbd),
                (9, &image_gradients.v_alpha),
                (10, gradient_sums),
                (11, &frame.slot_pairs),
                (12, &frame.frame_status),
            ],
        );
        let (tiles_x, tiles_y) = frame.camera.tile_counts();
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(tiles_x, tiles_y, 1);
    }

    /// pair_gradients: each Gaussian's screen-space gradient, its pairs' sums added in
    /// depth order.
    fn encode_pair_gradients(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        frame: &DeviceFrame,
        pair_sums: &wgpu::Buffer,
        screen_gradients: &wgpu::Buffer,
    ) {
        let pipeline = &self.pipelines.pair_gradients;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &frame.bin_params),
                (1, &frame.depth_order),
                (3, &frame.sorted_tile_counts),
                (5, pair_sums),
                (6, screen_gradients),
            ],
        );
        let workgroups = frame.gaussian_count.div_ceil(WORKGROUP_SIZE);
        dispatch_linear(encoder, pipeline, &group, workgroups);
    }

    /// project_backward: parameter gradients into `gradients`; returns the per-chunk pose
    /// contributions (translation, rotation) for the reduction.
    fn encode_project_backward(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: &DeviceGaussians,
        frame: &DeviceFrame,
        screen_gradients: &wgpu::Buffer,
        gradients: &DeviceGradients,
    ) -> Result<[wgpu::Buffer; 2], GpuError> {
        // One pose contribution per chunk of project_backward.
        let chunks = frame.gaussian_count.div_ceil(PROJECT_BACKWARD_CHUNK);
        let pose_bytes = u64::from(chunks) * VEC4_BYTES;
        let pose_translation = context.storage_buffer("pose_translation", pose_bytes)?;
        let pose_rotation = context.storage_buffer("pose_rotation", pose_bytes)?;
        let pipeline = &self.pipelines.project_backward;
        let group = bind_group(
            context,
            pipeline,
            &[
                (0, &frame.params_buffer),
                (1, &gaussians.means),
                (2, &gaussians.log_scales),
                (3, &gaussians.quaternions),
                (4, &gaussians.opacity_logits),
                (5, &frame.splat_conic),
                (6, screen_gradients),
                (7, &gradients.v_means),
                (8, &gradients.v_log_scales),
                (9, &gradients.v_quaternions),
                (10, &gradients.v_opacity_logits),
                (11, &gradients.v_colours),
                (12, &pose_translation),
                (13, &pose_rotation),
            ],
        );
        let workgroups = chunks.div_ceil(PROJECT_BACKWARD_WORKGROUP_SIZE);
        dispatch_linear(encoder, pipeline, &group, workgroups);
        Ok([pose_translation, pose_rotation])
    }

    /// Sums `count` vec4 of `input`; returns a buffer whose first vec4 is the total.
    pub(crate) fn reduce_vec4(
        &self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        input: wgpu::Buffer,
        count: u32,
    ) -> Result<wgpu::Buffer, GpuError> {
        let mut current = input;
        let mut remaining = count;
        while remaining > 1 {
            let chunks = remaining.div_ceil(REDUCE_CHUNK);
            let output =
                context.storage_buffer("reduce partial sums", u64::from(chunks) * VEC4_BYTES)?;
            let params = ReduceParams {
                count: remaining,
                ..Zeroable::zeroed()
            };
            let params = context.uniform_buffer("reduce params", bytemuck::bytes_of(&params));
            let group = bind_group(
                context,
                &self.pipelines.reduce,
                &[(0, &params), (1, &current), (2, &output)],
            );
            dispatch_linear(
                encoder,
                &self.pipelines.reduce,
                &group,
                chunks.div_ceil(REDUCE_WORKGROUP_SIZE),
            );
            current = output;
            remaining = chunks;
        }
        Ok(current)
    }
}

/// The frame must come from these very Gaussians (same arrangement and count), and the image
/// gradients must be of the frame's size.
fn validate_backward(
    gaussians: &DeviceGaussians,
    frame: &DeviceFrame,
    image_gradients: &DeviceImageGradients,
) -> Result<(), GpuError> {
    if gaussians.layout != frame.gaussian_layout {
        return Err(GpuError::InvalidInput(
            "the frame was rendered before the Gaussians were appended to, pruned or \
             reordered: render again"
                .into(),
        ));
    }
    if gaussians.len() != frame.gaussian_count as usize {
        return Err(GpuError::InvalidInput(format!(
            "frame was rendered from {} Gaussians, got {}",
            frame.gaussian_count,
            gaussians.len()
        )));
    }
    if (image_gradients.width, image_gradients.height) != (frame.camera.width, frame.camera.height)
    {
        return Err(GpuError::InvalidInput(
            "image gradients and frame differ in size".into(),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::passes::compute_pipeline;
    use crate::wgsl::source;

    /// A workgroup of 13 invocations: on adapters with subgroups of 8 (lavapipe) the second
    /// subgroup has 5 lanes, a count that is not a power of two.
    const SUBGROUP_SUM_TEST: &str = "
@group(0) @binding(20) var<storage, read_write> subgroup_sum_results: array<vec4<f32>>;

@compute @workgroup_size(13)
fn subgroup_sum_test(@builtin(local_invocation_index) index: u32,
                     @builtin(subgroup_invocation_id) lane: u32) {
    let lanes = subgroupAdd(1u);
    let value = f32(index + 1u);
    let own = SplatGradient(vec4<f32>(value), vec4<f32>(2.0 * value), vec2<f32>(1.0));
    let sum = subgroup_sum(own, lane, lanes);
    subgroup_sum_results[index] = vec4<f32>(sum.a.x, sum.b.w, sum.c.y, f32(subgroupMin(index)));
}
";

    #[test]
    fn subgroup_sums_are_exact_for_any_lane_count() {
        let context = GpuContext::new().expect("a wgpu adapter (lavapipe in CI)");
        if !context.has_subgroups {
            eprintln!("skipped: the adapter has no subgroups");
            return;
        }
        let pipeline = compute_pipeline(
            &context.device,
            "subgroup_sum_test",
            &[
                source::ATOMICS_CAS,
                source::RASTERIZE_TILES,
                source::RASTERIZE_BACKWARD_PIXELS,
                source::RASTERIZE_BACKWARD_SUBGROUP,
                SUBGROUP_SUM_TEST,
            ],
            "subgroup_sum_test",
        );
        const INVOCATIONS: usize = 13;
        let results = context
            .storage_buffer("subgroup sums", (INVOCATIONS * 16) as u64)
            .unwrap();
        let group = bind_group(&context, &pipeline, &[(20, &results)]);
        let mut encoder = context.device.create_command_encoder(&Default::default());
        dispatch_linear(&mut encoder, &pipeline, &group, 1);
        context.queue.submit([encoder.finish()]);
        let sums: Vec<[f32; 4]> = context.read_vec(&results, INVOCATIONS).unwrap();
        let mut lane_counts = Vec::new();
        for (index, sum) in sums.iter().enumerate() {
            // The subgroup's invocations: those reporting the same first index (the lanes are
            // numbered in invocation order, as the rasterizers assume).
            let first = sum[3];
            let members: Vec<usize> = (0..INVOCATIONS).filter(|&j| sums[j][3] == first).collect();
            let values: f32 = members.iter().map(|&j| (j + 1) as f32).sum();
            assert_eq!(sum[0], values, "invocation {index}: sums {sums:?}");
            assert_eq!(sum[1], 2.0 * values, "invocation {index}");
            assert_eq!(sum[2], members.len() as f32, "invocation {index}");
            lane_counts.push(members.len());
        }
        eprintln!("lanes per invocation's subgroup: {lane_counts:?}");
    }
}
