//! PLY round trip, foreign layouts, and malformed input.

use splats::GaussianCloud;
use splats::ply::{PlyError, SH_C0, load_ply, read_ply, save_ply, write_ply};

fn sample_cloud() -> GaussianCloud {
    let mut cloud = GaussianCloud::default();
    for i in 0..5 {
        let f = i as f32;
        cloud.push(
            [f, -f * 0.5, 2.0 + f],
            [-3.0 + 0.1 * f, -2.5, -2.0 - 0.1 * f],
            [0.9, 0.1 * f, -0.2, 0.3],
            -1.0 + 0.5 * f,
            [0.1 * f, 0.5, 1.0 - 0.2 * f],
        );
    }
    cloud
}

fn assert_clouds_close(a: &GaussianCloud, b: &GaussianCloud) {
    assert_eq!(a.len(), b.len());
    assert_eq!(a.means, b.means);
    assert_eq!(a.log_scales, b.log_scales);
    assert_eq!(a.quaternions, b.quaternions);
    assert_eq!(a.opacity_logits, b.opacity_logits);
    for (x, y) in a.colours.iter().zip(&b.colours) {
        for c in 0..3 {
            assert!((x[c] - y[c]).abs() < 1e-6, "colour {x:?} vs {y:?}");
        }
    }
}

#[test]
fn round_trip_through_a_file() {
    let cloud = sample_cloud();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("map.ply");
    save_ply(&path, &cloud).unwrap();
    let loaded = load_ply(&path).unwrap();
    assert_clouds_close(&cloud, &loaded);
}

#[test]
fn empty_cloud_round_trips() {
    let mut bytes = Vec::new();
    write_ply(&mut bytes, &GaussianCloud::default()).unwrap();
    assert!(read_ply(bytes.as_slice()).unwrap().is_empty());
}

/// A file as other 3DGS tools write it: different order, f_rest_*, a double and a uchar.
fn foreign_file() -> Vec<u8> {
    let header = "ply\nformat binary_little_endian 1.0\ncomment from elsewhere\n\
        element vertex 2\nproperty float rot_0\nproperty float rot_1\nproperty float rot_2\n\
        property float rot_3\nproperty double x\nproperty float y\nproperty float z\n\
        property float f_rest_0\nproperty float f_rest_1\nproperty uchar flag\n\
        property float scale_0\nproperty float scale_1\nproperty float scale_2\n\
        property float opacity\nproperty float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n\
        end_header\n";
    let mut bytes = header.as_bytes().to_vec();
    for row in 0..2 {
        let r = row as f32;
        for v in [1.0f32, 0.0, 0.0, r] {
            bytes.extend(v.to_le_bytes());
        }
        bytes.extend((10.0f64 + f64::from(r)).to_le_bytes());
        for v in [20.0f32 + r, 30.0 + r, 99.0, 98.0] {
            bytes.extend(v.to_le_bytes());
        }
        bytes.push(7);
        for v in [-1.0f32, -2.0, -3.0 - r, 0.25, 0.0, 1.0, -1.0] {
            bytes.extend(v.to_le_bytes());
        }
    }
    bytes
}

#[test]
fn imports_other_property_orders_and_ignores_extras() {
    let cloud = read_ply(foreign_file().as_slice()).unwrap();
    assert_eq!(cloud.len(), 2);
    assert_eq!(cloud.means[1], [11.0, 21.0, 31.0]);
    assert_eq!(cloud.quaternions[1], [1.0, 0.0, 0.0, 1.0]);
    assert_eq!(cloud.log_scales[1], [-1.0, -2.0, -4.0]);
    assert_eq!(cloud.opacity_logits[0], 0.25);
    assert_eq!(cloud.colours[0], [0.5, 0.5 + SH_C0, 0.5 - SH_C0]);
}

#[test]
fn truncated_data_names_the_row_and_property() {
    let bytes = foreign_file();
    // Cut inside row 1, just after its four rotation floats and 4 bytes of x.
    let row_bytes = 4 * 4 + 8 + 4 * 4 + 1 + 4 * 7;
    let cut = bytes.len() - row_bytes + 4 * 4 + 4;
    let error = read_ply(&bytes[..cut]).unwrap_err();
    match &error {
        PlyError::Truncated {
            row,
            count,
            property,
        } => {
            assert_eq!((*row, *count), (1, 2));
            assert_eq!(property, "x");
        }
        other => panic!("unexpected error {other:?}"),
    }
    assert!(error.to_string().contains("row 1"), "{error}");
}

#[test]
fn missing_property_is_named() {
    let text = String::from_utf8_lossy(&foreign_file()).into_owned();
    let without_opacity = text.replacen("property float opacity\n", "", 1);
    let error = read_ply(without_opacity.as_bytes()).unwrap_err();
    assert!(
        matches!(error, PlyError::MissingProperty("opacity")),
        "{error:?}"
    );
    assert!(error.to_string().contains("`opacity`"));
}

#[test]
fn garbage_and_unsupported_inputs_are_errors_not_panics() {
    let cases: Vec<Vec<u8>> = vec![
        Vec::new(),
        b"not a ply file at all".to_vec(),
        b"ply\nformat ascii 1.0\nelement vertex 1\nend_header\n".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nelement vertex -3\nend_header\n".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty quaternion x\nend_header\n".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty list uchar int idx\nend_header\n".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nproperty float x\nend_header\n".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nelement face 3\nproperty float a\nend_header\n\x00".to_vec(),
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n".to_vec(),
        vec![0xFF; 10_000],
    ];
    for (i, bytes) in cases.iter().enumerate() {
        let result = read_ply(bytes.as_slice());
        assert!(result.is_err(), "case {i} parsed: {result:?}");
    }
    let mut random = 0x1234_5678_u64;
    let valid = foreign_file();
    for _ in 0..200 {
        // Random single-byte corruptions of a valid file must never panic.
        let mut bytes = valid.clone();
        random = random.wrapping_mul(6364136223846793005).wrapping_add(1);
        let position = (random >> 33) as usize % bytes.len();
        bytes[position] = (random >> 17) as u8;
        let truncate_to = (random >> 45) as usize % (bytes.len() + 1);
        let _ = read_ply(&bytes[..truncate_to]);
        let _ = read_ply(bytes.as_slice());
    }
}

#[test]
fn inconsistent_cloud_is_refused_on_export() {
    let mut cloud = sample_cloud();
    cloud.colours.pop();
    let error = write_ply(Vec::new(), &cloud).unwrap_err();
    assert!(matches!(error, PlyError::InvalidCloud(_)), "{error:?}");
}
