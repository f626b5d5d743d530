//! A static point cloud indexed by a kd-tree (kiddo): the neighbour search behind per-point
//! covariances, and the G-ICP target when the target does not change (frame-to-frame tracking,
//! the consensus aligning two keyframes' Gaussians). The incremental map is [`super::voxel_map`].

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::Point3;

use crate::covariance::{Covariance, complete_from_tree, covariances_from_grid};
use crate::gicp::RegistrationTarget;
use crate::points::PointCloud;

/// A cloud that cannot be indexed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PointTreeError {
    /// A point has a NaN or infinite coordinate, which would corrupt the tree's splits.
    #[error("point {index} has non-finite coordinates {position:?}")]
    NonFinitePoint {
        /// Index of the first such point in the cloud.
        index: usize,
        /// Its position.
        position: Point3<f32>,
    },
    /// The cloud has more points than kiddo's 32-bit item indices can address.
    #[error("{count} points do not fit the kd-tree's 32-bit item indices")]
    TooManyPoints {
        /// Number of points in the cloud.
        count: usize,
    },
    /// The cloud has covariances, but not exactly one per point.
    #[error("{covariances} covariances for {points} points")]
    CovarianceCountMismatch {
        /// Number of points in the cloud.
        points: usize,
        /// Number of covariances in the cloud.
        covariances: usize,
    },
}

/// A point cloud with a kd-tree over its positions. Build once, query from many threads.
pub struct PointTree {
    cloud: PointCloud,
    /// `None` for an empty cloud (kiddo has no meaning for an empty tree's nearest point).
    tree: Option<ImmutableKdTree<f32, 3>>,
}

impl std::fmt::Debug for PointTree {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PointTree")
            .field("points", &self.cloud.len())
            .field("has_covariances", &self.cloud.has_covariances())
            .finish()
    }
}

impl PointTree {
    /// Indexes bare positions (covariances can be estimated afterwards).
    pub fn new(positions: Vec<Point3<f32>>) -> Result<Self, PointTreeError> {
        Self::from_cloud(PointCloud::from_positions(positions))
    }

    /// Indexes a cloud, keeping its covariances and pixels. Refuses non-finite points, which would
    /// corrupt the tree's splits, and a covariance list of the wrong length.
    pub fn from_cloud(cloud: PointCloud) -> Result<Self, PointTreeError> {
        Self::check(&cloud)?;
        let tree = Self::build(&cloud.positions)?;
        Ok(Self { cloud, tree })
    }

    /// Builds the tree and estimates every point's G-ICP covariance from its k nearest neighbours.
    /// The image grid answers most points without the tree
    /// ([`crate::covariance::estimate_covariances`]), so the tree's build (serial) runs beside
    /// that pass instead of before it.
    pub fn with_covariances(
        cloud: PointCloud,
        neighbours: usize,
        epsilon: f64,
    ) -> Result<Self, PointTreeError> {
        Self::check(&cloud)?;
        let (tree, from_grid) = rayon::join(
            || Self::build(&cloud.positions),
            || covariances_from_grid(&cloud, neighbours, epsilon),
        );
        let mut tree = Self { cloud, tree: tree? };
        tree.cloud.covariances = complete_from_tree(&tree, from_grid, neighbours, epsilon);
        Ok(tree)
    }

    fn check(cloud: &PointCloud) -> Result<(), PointTreeError> {
        if let Some(index) = cloud
            .positions
            .iter()
            .position(|p| !p.iter().all(|v| v.is_finite()))
        {
            return Err(PointTreeError::NonFinitePoint {
                index,
                position: cloud.positions[index],
            });
        }
        if !cloud.covariances.is_empty() && !cloud.has_covariances() {
            return Err(PointTreeError::CovarianceCountMismatch {
                points: cloud.len(),
                covariances: cloud.covariances.len(),
            });
        }
        Ok(())
    }

    fn build(positions: &[Point3<f32>]) -> Result<Option<ImmutableKdTree<f32, 3>>, PointTreeError> {
        if positions.is_empty() {
            return Ok(None);
        }
        let coordinates: Vec<[f32; 3]> = positions.iter().map(|p| [p.x, p.y, p.z]).collect();
        ImmutableKdTree::new_from_slice(&coordinates)
            .map(Some)
            .map_err(|_| PointTreeError::TooManyPoints {
                count: positions.len(),
            })
    }

    /// The indexed cloud; point `i` is the tree's item `i`.
    pub fn cloud(&self) -> &PointCloud {
        &self.cloud
    }

    /// Drops the tree and returns the cloud.
    pub fn into_cloud(self) -> PointCloud {
        self.cloud
    }

    /// The cloud's positions, indexed like the tree's items.
    pub fn positions(&self) -> &[Point3<f32>] {
        &self.cloud.positions
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.cloud.len()
    }

    /// True when the cloud has no points (and so no tree).
    pub fn is_empty(&self) -> bool {
        self.cloud.is_empty()
    }

    /// The kiddo tree; item `i` is `positions()[i]`.
    ///
    /// # Panics
    /// On an empty cloud, which has no tree; check [`Self::is_empty`] first.
    pub fn kd_tree(&self) -> &ImmutableKdTree<f32, 3> {
        self.tree
            .as_ref()
            .expect("kd_tree() called on an empty PointTree")
    }

    /// Index and squared distance of the nearest point, if the cloud is not empty.
    pub fn nearest(&self, query: &Point3<f32>) -> Option<(u32, f32)> {
        let tree = self.tree.as_ref()?;
        let found = tree
            .query(&[query.x, query.y, query.z])
            .nearest_one::<SquaredEuclidean<f32>>()
            .execute();
        Some((found.item, found.distance))
    }
}

impl RegistrationTarget for PointTree {
    fn nearest_within(&self, query: &Point3<f32>, max_distance_sq: f32) -> Option<(u32, f32)> {
        self.nearest(query).filter(|&(_, d)| d <= max_distance_sq)
    }

    fn position(&self, index: u32) -> Point3<f32> {
        self.cloud.positions[index as usize]
    }

    fn covariance(&self, index: u32) -> Covariance {
        self.cloud
            .covariances
            .get(index as usize)
            .copied()
            .unwrap_or(Covariance::IDENTITY)
    }

    fn target_len(&self) -> usize {
        self.cloud.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_matches_brute_force_and_bad_input_is_refused() {
        let positions: Vec<Point3<f32>> = (0..500)
            .map(|i| {
                let f = i as f32;
                Point3::new((f * 0.37).sin(), (f * 0.11).cos(), f * 0.003)
            })
            .collect();
        let tree = PointTree::new(positions.clone()).unwrap();
        for q in [Point3::new(0.1, 0.2, 0.3), Point3::new(-1.0, 0.5, 1.2)] {
            let (index, d) = tree.nearest(&q).unwrap();
            let brute = positions
                .iter()
                .map(|p| (p - q).norm_squared())
                .fold(f32::INFINITY, f32::min);
            assert!((d - brute).abs() < 1e-6);
            assert!(((positions[index as usize] - q).norm_squared() - brute).abs() < 1e-6);
        }
        assert!(
            PointTree::new(Vec::new())
                .unwrap()
                .nearest(&Point3::origin())
                .is_none()
        );
        assert!(matches!(
            PointTree::new(vec![Point3::new(f32::NAN, 0.0, 0.0)]),
            Err(PointTreeError::NonFinitePoint { index: 0, .. })
        ));
    }
}
