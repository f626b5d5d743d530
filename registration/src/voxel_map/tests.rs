//! Map edits, bounded queries against brute force, transforms and view selection.

use super::*;
use crate::kdtree::PointTree;

fn scattered(n: usize, seed: u32) -> Vec<Point3<f32>> {
    // A deterministic low-discrepancy scatter in a 0.5 m cube.
    (0..n)
        .map(|i| {
            let f = (i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) as f32;
            Point3::new(
                (f * 0.000_123_7).sin() * 0.25,
                (f * 0.000_031_3).cos() * 0.25,
                ((f * 0.000_071_9).sin() + 1.0) * 0.25,
            )
        })
        .collect()
}

fn point(id: u64, position: Point3<f32>) -> MapPoint {
    MapPoint {
        id,
        position,
        covariance: Covariance::IDENTITY,
    }
}

#[test]
fn fast_floor_matches_floor() {
    for v in [
        -2.5f32, -2.0, -1e-7, -0.0, 0.0, 0.3, 1.0, 1.999_999, 7.5e8, -7.5e8,
    ] {
        assert_eq!(floor_to_i32(v), v.floor() as i32, "{v}");
    }
    assert_eq!(floor_to_i32(f32::NAN), 0);
}

#[test]
fn incremental_updates_behave_like_a_rebuilt_map() {
    let positions = scattered(3000, 7);
    let mut incremental = VoxelMap::new(0.04);
    for (i, p) in positions.iter().enumerate() {
        assert!(incremental.insert(point(i as u64, *p)).unwrap().is_none());
    }
    // Remove every third point and move every fifth to a new place (replace by id).
    let moved = scattered(3000, 99);
    let mut expected: Vec<Option<Point3<f32>>> = positions.iter().copied().map(Some).collect();
    for i in 0..positions.len() {
        if i % 3 == 0 {
            assert_eq!(incremental.remove(i as u64).unwrap().position, positions[i]);
            expected[i] = None;
        } else if i % 5 == 0 {
            let old = incremental.insert(point(i as u64, moved[i])).unwrap();
            assert_eq!(old.unwrap().position, positions[i]);
            expected[i] = Some(moved[i]);
        }
    }
    assert!(incremental.remove(0).is_none(), "removed twice");
    let mut rebuilt = VoxelMap::new(0.04);
    let survivors: Vec<(u64, Point3<f32>)> = expected
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.map(|p| (i as u64, p)))
        .collect();
    for &(id, p) in &survivors {
        rebuilt.insert(point(id, p)).unwrap();
    }
    assert_eq!(incremental.len(), survivors.len());
    assert_eq!(incremental.voxel_count(), rebuilt.voxel_count());
    let brute = PointTree::new(survivors.iter().map(|s| s.1).collect()).unwrap();
    let radius_sq = 0.03f32 * 0.03;
    for q in scattered(500, 12345) {
        let a = incremental.nearest_within(&q, radius_sq);
        let b = rebuilt.nearest_within(&q, radius_sq);
        let truth = brute.nearest_within(&q, radius_sq);
        assert_eq!(a.map(|x| x.1), b.map(|x| x.1));
        assert_eq!(a.map(|x| x.1), truth.map(|x| x.1));
        assert_eq!(incremental.any_within(&q, radius_sq), truth.is_some());
        if let (Some((slot, _)), Some((index, _))) = (a, truth) {
            assert_eq!(incremental.position(slot), survivors[index as usize].1);
        }
    }
    for &(id, p) in &survivors {
        assert_eq!(incremental.get(id).unwrap().position, p);
    }
    assert!(
        incremental
            .insert(point(1, Point3::new(f32::NAN, 0.0, 0.0)))
            .is_err()
    );
}

/// Nearest matches equal a brute-force search for voxels smaller than the search radius (the
/// ball spans several voxels per axis), about as large, and larger (it reaches at most the
/// next voxel on each axis).
#[test]
fn queries_match_brute_force_whatever_the_voxel_size() {
    let positions = scattered(2000, 3);
    let brute = PointTree::new(positions.clone()).unwrap();
    for voxel_size in [0.004, 0.013, 0.03, 0.04, 0.1] {
        let mut map = VoxelMap::new(voxel_size);
        for (i, p) in positions.iter().enumerate() {
            map.insert(point(i as u64, *p)).unwrap();
        }
        for radius in [0.005f32, 0.03] {
            for q in scattered(300, 777) {
                let found = map.nearest_within(&q, radius * radius);
                let truth = brute.nearest_within(&q, radius * radius);
                assert_eq!(found.map(|f| f.1), truth.map(|t| t.1), "voxel {voxel_size}");
            }
        }
    }
}

/// A hinted query answers as an unhinted one: when the hint holds the query's voxel (the same
/// point moved a little), when it holds another voxel (moved across a border), and when it
/// points nowhere or past the map's voxels.
#[test]
fn hinted_queries_answer_as_unhinted_ones() {
    let map = {
        let mut map = VoxelMap::new(0.04);
        for (i, p) in scattered(3000, 7).iter().enumerate() {
            map.insert(point(i as u64, *p)).unwrap();
        }
        map
    };
    let radius_sq = 0.013f32 * 0.013;
    let queries = scattered(400, 4242);
    let mut hints = vec![NO_HINT; queries.len()];
    hints[1] = map.voxel_count() as u32 + 5;
    let (mut kept, mut changed) = (0, 0);
    for step in 0..6 {
        // Steps of 4 mm: most queries stay in their voxel, some cross into the next.
        let shift = Vector3::new(0.004f32, -0.003, 0.002) * step as f32;
        for (query, hint) in queries.iter().zip(hints.iter_mut()) {
            let moved = query + shift;
            let before = *hint;
            let hinted = map.nearest_within_hinted(&moved, radius_sq, hint);
            assert_eq!(hinted, map.nearest_within(&moved, radius_sq), "{moved:?}");
            match map.voxels.get(*hint as usize) {
                Some(voxel) => assert_eq!(voxel.key, map.key_of(&moved)),
                None => assert_eq!(*hint, NO_HINT, "an empty voxel leaves no hint"),
            }
            if step > 0 && before != NO_HINT {
                if *hint == before {
                    kept += 1;
                } else {
                    changed += 1;
                }
            }
        }
    }
    assert!(kept > 0 && changed > 0, "kept {kept}, changed {changed}");
}

#[test]
fn transforming_points_moves_them_and_their_covariances() {
    let mut map = VoxelMap::new(0.04);
    let a = Point3::new(0.0f32, 0.0, 1.0);
    let b = Point3::new(1.0f32, 0.0, 1.0);
    let mut flat = point(1, a);
    // A plane-like covariance with its thin axis along z.
    flat.covariance = Covariance([1.0, 0.0, 0.0, 1.0, 0.0, 1e-3]);
    map.insert(flat).unwrap();
    map.insert(point(2, b)).unwrap();
    // Point 1 moves 0.5 m along x and turns 90 degrees about y; point 2 stays.
    let turn = Isometry3::from_parts(
        nalgebra::Translation3::new(0.5, 0.0, 0.0),
        nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0),
    );
    let moved = map.transform_points(|id| (id == 1).then_some(turn));
    assert_eq!(moved, 1);
    assert_eq!(map.len(), 2);
    let expected = (turn * a.cast::<f64>()).cast::<f32>();
    let (slot, distance_sq) = map
        .nearest_in_map(&expected, 1e-6)
        .expect("moved point found");
    assert!(distance_sq < 1e-10);
    assert_eq!(map.points[slot as usize].unwrap().id, 1);
    assert!(
        map.nearest_in_map(&a, 1e-4).is_none(),
        "nothing left at the old place"
    );
    assert_eq!(map.get(2).unwrap().position, b);
    // The thin axis now lies along x.
    let c = map.get(1).unwrap().covariance.to_matrix();
    assert!(
        (c[(0, 0)] - 1e-3).abs() < 1e-6 && (c[(2, 2)] - 1.0).abs() < 1e-6,
        "{c}"
    );
}

#[test]
fn view_selection_restricts_queries_to_the_frustum() {
    let k = Intrinsics::new(100.0, 100.0, 49.5, 49.5, 100, 100);
    let mut map = VoxelMap::new(0.04);
    let in_front = Point3::new(0.0, 0.0, 2.0);
    let behind = Point3::new(0.0, 0.0, -2.0);
    let too_far = Point3::new(0.0, 0.0, 12.0);
    for (id, p) in [(1, in_front), (2, behind), (3, too_far)] {
        map.insert(point(id, p)).unwrap();
    }
    let camera = Isometry3::identity();
    assert_eq!(map.select_view(&ViewFrustum::new(&camera, &k, 10.0)), 1);
    assert_eq!(map.ids_in_view().collect::<Vec<_>>(), vec![1]);
    assert!(map.nearest_within(&behind, 1e-4).is_none());
    assert!(map.nearest_within(&in_front, 1e-4).is_some());
    assert!(map.nearest_in_map(&behind, 1e-4).is_some());
    // Turning the camera around selects the other point.
    let turned = Isometry3::rotation(Vector3::new(0.0, std::f64::consts::PI, 0.0));
    map.select_view(&ViewFrustum::new(&turned, &k, 10.0));
    assert_eq!(map.ids_in_view().collect::<Vec<_>>(), vec![2]);
    map.clear_view();
    assert_eq!(map.ids_in_view().count(), 3);
}
