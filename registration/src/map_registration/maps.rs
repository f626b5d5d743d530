//! The two levels a map is prepared at: the feature level (normals, descriptors and colour
//! signatures for matching) and the refinement level (covariances and normals for G-ICP and the
//! verification).

use crate::covariance::smallest_eigenvector;
use crate::map_registration::MapRegistrationConfig;
use crate::{PointCloud, PointTree};
use nalgebra::Vector3;

use super::colour::{self, Rgb};
use super::correspondences::{MATCH_LEN, MatchDescriptor};
use super::downsample::Cloud;
use super::fpfh;

/// A downsampled map with everything the later stages need.
pub(super) struct PreparedMap {
    pub tree: PointTree,
    pub normals: Vec<Option<Vector3<f32>>>,
    pub features: fpfh::Features,
    /// Per feature: the FPFH descriptor and the weighted colour signature.
    pub descriptors: Vec<MatchDescriptor>,
    /// Per point, when colour is used.
    pub colours: Option<Vec<Rgb>>,
}

/// Normals, descriptors and, with `colours`, colour signatures of a downsampled map, its colours
/// multiplied by `gains` for the signatures (another camera's white balance).
pub(super) fn prepare(
    cloud: Cloud,
    voxel_m: f64,
    gains: [f32; 3],
    config: &MapRegistrationConfig,
) -> PreparedMap {
    let tree = PointTree::with_covariances(
        PointCloud::from_positions(cloud.points),
        config.covariance_neighbours,
        config.covariance_epsilon,
    )
    .expect("downsampled points are finite and few");
    let normal_radius = config.normal_radius_voxels * voxel_m;
    let feature_radius = config.feature_radius_voxels * voxel_m;
    let neighbourhoods = fpfh::radius_neighbours(&tree, normal_radius.max(feature_radius));
    let (normals, features) = fpfh::describe_with(
        tree.positions(),
        &neighbourhoods,
        (normal_radius, config.min_normal_neighbours),
        (feature_radius, config.min_feature_neighbours),
    );
    let signatures = cloud.colours.as_ref().map(|colours| {
        let balanced;
        let colours = if gains == [1.0; 3] {
            colours
        } else {
            balanced = colour::balanced(colours, gains);
            &balanced
        };
        colour::signatures(colours, &neighbourhoods, &features.indices)
    });
    let weight = config.colour_weight as f32;
    let descriptors = (0..features.len())
        .map(|k| {
            let mut d = [0.0f32; MATCH_LEN];
            d[..fpfh::DESCRIPTOR_LEN].copy_from_slice(&features.descriptors[k]);
            if let Some(signature) = signatures.as_ref().and_then(|s| s[k].as_ref()) {
                for (to, from) in d[fpfh::DESCRIPTOR_LEN..].iter_mut().zip(signature) {
                    *to = weight * from;
                }
            }
            d
        })
        .collect();
    PreparedMap {
        tree,
        normals,
        features,
        descriptors,
        colours: cloud.colours,
    }
}

/// A refinement-level map: covariances for G-ICP, normals (the covariances' normal directions)
/// for the verification.
pub(super) struct RefinementMap {
    tree: PointTree,
    normals: Vec<Option<Vector3<f32>>>,
    colours: Option<Vec<Rgb>>,
}

impl RefinementMap {
    pub(super) fn new(cloud: Cloud, config: &MapRegistrationConfig) -> Self {
        let tree = PointTree::with_covariances(
            PointCloud::from_positions(cloud.points),
            config.covariance_neighbours,
            config.covariance_epsilon,
        )
        .expect("downsampled points are finite and few");
        // The plane covariance I - (1 - eps) n n^T has n as its smallest eigenvector.
        let normals = tree
            .cloud()
            .covariances
            .iter()
            .map(|c| Some(smallest_eigenvector(&c.to_matrix()).cast::<f32>()))
            .collect();
        Self {
            tree,
            normals,
            colours: cloud.colours,
        }
    }
}

/// What G-ICP's final stage and the verification see of one map: the refinement level's
/// [`RefinementMap`], or the feature level's [`PreparedMap`] when that is already fine enough.
#[derive(Clone, Copy)]
pub(super) struct FineView<'m> {
    pub tree: &'m PointTree,
    pub normals: &'m [Option<Vector3<f32>>],
    pub colours: Option<&'m [Rgb]>,
}

impl PreparedMap {
    pub(super) fn fine_view(&self) -> FineView<'_> {
        FineView {
            tree: &self.tree,
            normals: &self.normals,
            colours: self.colours.as_deref(),
        }
    }
}

impl RefinementMap {
    pub(super) fn fine_view(&self) -> FineView<'_> {
        FineView {
            tree: &self.tree,
            normals: &self.normals,
            colours: self.colours.as_deref(),
        }
    }
}
