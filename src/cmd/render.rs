//! `mac-ego3d render`: renders a saved 3DGS map (PLY) from any viewpoint with render-core and
//! writes the colour image and a 16-bit depth PNG (millimetres).

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use datasets::write_depth_png;
use geometry::depth::DepthImage;
use render_core::context::GpuContext;
use render_core::gpu::{DeviceGaussians, GpuRenderer};
use render_core::types::{Camera, RenderMode};
use splats::RigidTransform;
use splats::ply::load_ply;

/// Depth PNG units: millimetres.
const DEPTH_UNITS_PER_METRE: f64 = 1000.0;
/// Pixels whose accumulated opacity is below this get no depth (0 in the PNG): there the map is
/// mostly empty and depth / alpha would be a guess.
const MIN_ALPHA_FOR_DEPTH: f32 = 0.5;

#[derive(Args)]
pub struct RenderArgs {
    /// Gaussian map in the standard 3DGS PLY layout.
    #[arg(long)]
    map: PathBuf,
    /// Camera-to-world pose, TUM order: "tx ty tz qx qy qz qw".
    #[arg(long, allow_hyphen_values = true)]
    pose: String,
    /// Pinhole intrinsics "fx,fy,cx,cy" in pixels.
    #[arg(long, allow_hyphen_values = true)]
    intrinsics: String,
    /// Image size "WxH".
    #[arg(long, default_value = "640x480")]
    size: String,
    /// Output colour PNG.
    #[arg(long)]
    out_rgb: PathBuf,
    /// Output depth PNG (16-bit millimetres, 0 = no surface).
    #[arg(long)]
    out_depth: Option<PathBuf>,
}

fn parse_numbers(
    text: &str,
    separator: char,
    count: usize,
    what: &str,
) -> anyhow::Result<Vec<f32>> {
    let values: Vec<f32> = text
        .split(separator)
        .filter(|t| !t.trim().is_empty())
        .map(|t| t.trim().parse::<f32>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()
        .with_context(|| format!("{what} {text:?}: not {count} finite numbers"))?;
    if values.len() != count {
        bail!(
            "{what} {text:?}: expected {count} numbers, found {}",
            values.len()
        );
    }
    Ok(values)
}

/// An image size "WxH" given to option `flag`.
pub fn parse_size(text: &str, flag: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .with_context(|| format!("{flag} {text:?}: expected WxH, e.g. 640x480"))?;
    let parse = |v: &str| v.trim().parse::<u32>().ok().filter(|&n| n > 0);
    match (parse(w), parse(h)) {
        (Some(w), Some(h)) => Ok((w, h)),
        _ => bail!("{flag} {text:?}: width and height must be positive integers"),
    }
}

/// The camera of `--pose` (camera-to-world, TUM order "tx ty tz qx qy qz qw") and
/// `--intrinsics` ("fx,fy,cx,cy" in pixels) at `width x height`.
pub fn camera_from_args(
    pose: &str,
    intrinsics: &str,
    width: u32,
    height: u32,
) -> anyhow::Result<Camera> {
    let pose = parse_numbers(pose, ' ', 7, "--pose")?;
    let k = parse_numbers(intrinsics, ',', 4, "--intrinsics")?;
    let (fx, fy, cx, cy) = (k[0], k[1], k[2], k[3]);
    if fx <= 0.0 || fy <= 0.0 {
        bail!("--intrinsics: focal lengths must be positive, got fx={fx} fy={fy}");
    }
    let quaternion_norm = pose[3..7].iter().map(|v| v * v).sum::<f32>().sqrt();
    if quaternion_norm < 1e-6 {
        bail!("--pose: the quaternion (qx qy qz qw) has zero length");
    }
    // TUM order is qx qy qz qw; render-core takes w first.
    let world_from_camera = RigidTransform::from_quaternion_translation(
        [pose[6], pose[3], pose[4], pose[5]],
        [pose[0], pose[1], pose[2]],
    );
    Ok(Camera::from_world_from_camera(
        world_from_camera,
        [fx, fy, cx, cy],
        width,
        height,
    ))
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    let (width, height) = parse_size(&args.size, "--size")?;
    let camera = camera_from_args(&args.pose, &args.intrinsics, width, height)?;
    let map = load_ply(&args.map).with_context(|| format!("reading map {}", args.map.display()))?;

    let context = GpuContext::new().context("creating the wgpu device")?;
    let gaussians = DeviceGaussians::upload(&context, &map).context("uploading the map")?;
    let output =
        GpuRenderer::new(&context).render(&context, &gaussians, &camera, RenderMode::RgbD)?;

    let rgb_values = output.rgb.as_ref().context("renderer returned no colour")?;
    let rgb = image::RgbImage::from_fn(width, height, |x, y| {
        let c = rgb_values[(y * width + x) as usize];
        image::Rgb(c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
    });
    rgb.save(&args.out_rgb)
        .with_context(|| format!("writing {}", args.out_rgb.display()))?;
    if let Some(path) = &args.out_depth {
        let composited = output
            .depth
            .as_ref()
            .context("renderer returned no depth")?;
        let data = composited
            .iter()
            .zip(&output.alpha)
            .map(|(&d, &a)| {
                if a >= MIN_ALPHA_FOR_DEPTH && d > 0.0 {
                    d / a
                } else {
                    0.0
                }
            })
            .collect();
        write_depth_png(
            path,
            &DepthImage {
                width,
                height,
                data,
            },
            DEPTH_UNITS_PER_METRE,
        )?;
    }
    eprintln!(
        "rendered {} Gaussians at {width}x{height} on {}",
        map.len(),
        context.describe()
    );
    Ok(())
}
