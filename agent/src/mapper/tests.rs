//! Targets at mapping resolution, keyframe pose refinement, tracked pose moves and the scene
//! scale, on small synthetic scenes.

use render_core::types::{Camera, RasterConfig};

use super::iteration::pose_change;
use super::state::scene_scale;
use super::*;

#[test]
fn downscaling_averages_colour_and_valid_depth_only() {
    let rgb = RgbImage::from_fn(4, 2, |x, _| image::Rgb([(x * 50) as u8, 0, 255]));
    let mut depth = DepthImage::new(4, 2);
    depth.data = vec![1.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0];
    let target = downscale_target(&rgb, &depth, 2);
    assert_eq!((target.width, target.height), (2, 1));
    assert!((target.rgb[0][0] - 25.0 / 255.0).abs() < 1e-6);
    assert!((target.rgb[1][2] - 1.0).abs() < 1e-6);
    // Block 0 has valid depths 1 and 3; block 1 has none.
    assert_eq!(target.depth.unwrap(), vec![2.0, 0.0]);
}

/// A textured wall of Gaussians 2 m in front of the origin, facing the camera.
fn textured_wall() -> GaussianCloud {
    let mut cloud = GaussianCloud::default();
    for row in 0..40 {
        for column in 0..50 {
            let (x, y) = (-0.6 + 0.025 * column as f32, -0.5 + 0.025 * row as f32);
            let colour = [
                0.5 + 0.4 * (9.0 * x).sin(),
                0.5 + 0.4 * (7.0 * y).cos(),
                0.5 + 0.4 * (5.0 * (x + y)).sin(),
            ];
            cloud.push(
                [x, y, 2.0],
                [0.015f32.ln(); 3],
                [1.0, 0.0, 0.0, 0.0],
                3.0,
                colour,
            );
        }
    }
    cloud
}

/// The keyframe `world_from_camera` would record, its images rendered at `true_pose`.
fn keyframe_seen_from(
    keyframe_id: usize,
    cloud: &GaussianCloud,
    true_pose: &Isometry3<f64>,
    world_from_camera: Isometry3<f64>,
    new_gaussians: GaussianCloud,
) -> MappingKeyframe {
    let intrinsics = Intrinsics::new(120.0, 120.0, 80.0, 60.0, 160, 120);
    let camera = Camera::new(RigidTransform::from(true_pose), &intrinsics);
    let view = render_core::reference::render(
        cloud,
        &camera,
        render_core::RenderMode::RgbD,
        &RasterConfig::default(),
    );
    let colours = view.rgb.expect("rgb rendered");
    let rgb = RgbImage::from_fn(160, 120, |x, y| {
        let c = colours[(y * 160 + x) as usize];
        image::Rgb(c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
    });
    let mut depth = DepthImage::new(160, 120);
    let depths = view.depth.expect("depth rendered");
    depth.data = depths
        .iter()
        .zip(&view.alpha)
        .map(|(&d, &a)| if a > 0.5 { d / a } else { 0.0 })
        .collect();
    MappingKeyframe {
        keyframe_id,
        frame_index: keyframe_id,
        timestamp_s: keyframe_id as f64,
        kind: KeyframeKind::Mapping,
        world_from_camera,
        intrinsics,
        rgb,
        depth,
        new_gaussians,
    }
}

/// A mapping state on the test device (lavapipe on CI), with nothing in it yet.
fn mapper_state(mapping: &MappingConfig) -> MapperState {
    let context = GpuContext::new().expect("a wgpu adapter (lavapipe on CI)");
    MapperState::new(
        context,
        &TrackingConfig::default(),
        mapping,
        Arc::new(MapperProgress::default()),
    )
}

/// The second keyframe's pose error (metres) after `iterations` mapper iterations on two
/// keyframes of the wall, the second recorded 10 mm off where its images were taken; the map
/// itself is held fixed (zero learning rates) so only the pose can move.
fn pose_error_after(refine_keyframe_poses: bool, iterations: usize) -> f64 {
    let cloud = textured_wall();
    let true_pose = Isometry3::translation(0.05, 0.02, 0.0);
    let recorded = Isometry3::translation(0.058, 0.014, 0.0);
    let mapping = MappingConfig {
        image_downscale: 1,
        lr_means: 0.0,
        lr_colours: 0.0,
        lr_opacity: 0.0,
        lr_log_scales: 0.0,
        refine_keyframe_poses,
        lr_pose_translation_m: 5e-4,
        ..MappingConfig::default()
    };
    let mut state = mapper_state(&mapping);
    let identity = Isometry3::identity();
    state
        .insert_keyframe(keyframe_seen_from(
            0,
            &cloud,
            &identity,
            identity,
            cloud.clone(),
        ))
        .unwrap();
    state
        .insert_keyframe(keyframe_seen_from(
            1,
            &cloud,
            &true_pose,
            recorded,
            GaussianCloud::default(),
        ))
        .unwrap();
    for _ in 0..iterations {
        state.iterate().unwrap();
    }
    // The correction field takes each keyframe's recorded pose onto its refined one (the
    // identity at the first keyframe, and everywhere without refinement).
    let field = state.keyframe_pose_corrections();
    assert_eq!(field.is_empty(), !refine_keyframe_poses);
    let refined = Isometry3::from(&state.keyframes[1].camera.camera_from_world).inverse();
    let moved = field.at(1.0) * recorded;
    assert!((moved.translation.vector - refined.translation.vector).norm() < 1e-6);
    assert!(moved.rotation.angle_to(&refined.rotation) < 1e-5);
    assert!(field.at(0.0).translation.vector.norm() < 1e-9);
    let true_camera_from_world = RigidTransform::from(&true_pose.inverse());
    pose_change(
        &true_camera_from_world,
        &state.keyframes[1].camera.camera_from_world,
    )
    .0
}

#[test]
fn refined_keyframe_poses_move_towards_where_the_images_were_taken() {
    let before = pose_error_after(false, 60);
    let after = pose_error_after(true, 60);
    // Off by 10 mm; without refinement the pose stays where tracking put it.
    assert!((before - 0.01).abs() < 1e-4, "{before}");
    assert!(after < 0.5 * before, "refined pose error {after} m");
}

#[test]
fn pose_change_measures_translation_and_rotation_between_cameras() {
    let reference = RigidTransform::from(&Isometry3::translation(0.1, 0.0, 0.0));
    let moved = RigidTransform::from(&Isometry3::new(
        nalgebra::Vector3::new(0.1, 0.03, 0.04),
        nalgebra::Vector3::new(0.0, 0.0, 0.02),
    ));
    let (metres, radians) = pose_change(&reference, &moved);
    assert!((radians - 0.02).abs() < 1e-5, "{radians}");
    assert!(metres > 0.04 && metres < 0.06, "{metres}");
}

#[test]
fn scene_scale_is_the_radius_around_the_centroid() {
    let mut cloud = GaussianCloud::default();
    for x in [-1.0, 1.0] {
        cloud.push([x, 0.0, 2.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, [0.0; 3]);
    }
    assert!((scene_scale(&cloud) - 1.0).abs() < 1e-12);
    assert_eq!(scene_scale(&GaussianCloud::default()), 1.0);
}
