//! The tracking target: an incremental voxel hash map of map points (or trackable Gaussians) with
//! covariances, KISS-ICP style.
//!
//! Why a voxel hash and not a kd-tree: the map grows at every tracking keyframe (its trackable
//! points) and moves when a consensus correction arrives (the mapper's optimisation does not move
//! it). A hash map of voxels absorbs an insertion or a removal in O(1) without rebalancing, and a nearest-neighbour query bounded by the
//! correspondence distance only visits the few voxels that can hold an answer. The voxels also
//! give the frustum selection its granularity: [`VoxelMap::select_view`] marks the voxels that
//! intersect the predicted view, and queries then ignore the rest (docs/method.md, One agent: Tracking,
//! the selection of map candidates).
//!
//! Query cost: with voxels three times the correspondence distance (the default from
//! [`VoxelMap::for_correspondence_distance`]), the ball around a query overlaps at most 2 x 2 x 2
//! voxels. The query's own voxel is searched first; a neighbouring voxel is looked up only if its
//! box is closer than the best match so far, which after alignment (matches a few millimetres
//! away) usually leaves one hash lookup per query, and none when G-ICP repeats a source point's
//! query with the voxel it was answered in as a hint
//! ([`crate::gicp::RegistrationTarget::nearest_within_hinted`]). Hash lookups and the neighbour
//! loop cost more than scanning a few more points in the home voxel, so larger voxels are faster
//! up to 3 x the correspondence distance (timings: docs/benchmarks.md).

use nalgebra::{Isometry3, Point3, Vector3};
use rustc_hash::FxHashMap;

use geometry::camera::Intrinsics;

use crate::covariance::Covariance;
use crate::gicp::{NO_HINT, RegistrationTarget};
use crate::points::PointCloud;
use crate::voxel_points::VoxelPoints;

/// Caller-chosen identity of a map point (e.g. a Gaussian's index in the agent's map).
pub type MapPointId = u64;

/// Voxel edge per metre of correspondence distance: any factor of 2 or more keeps a bounded query
/// within 2 x 2 x 2 voxels; 3 was the fastest measured (see the module documentation).
pub const VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE: f64 = 3.0;

/// A point of the map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapPoint {
    /// Caller-chosen identity; at most one point per id is in the map.
    pub id: MapPointId,
    /// World frame.
    pub position: Point3<f32>,
    /// G-ICP covariance in the world frame.
    pub covariance: Covariance,
}

/// Integer voxel coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
struct VoxelKey {
    x: i32,
    y: i32,
    z: i32,
}

#[derive(Clone)]
struct Voxel {
    key: VoxelKey,
    /// Each point's position with its slot, laid out for the query scan (see [`VoxelPoints`]).
    points: VoxelPoints,
    /// Equal to the map's `view_epoch` when the voxel intersects the selected view.
    in_view_epoch: u32,
}

/// The region of space a camera at a predicted pose can observe: inside the image's viewing
/// pyramid, at depth (along the optical axis) below `max_depth_m`.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewFrustum {
    camera_from_world: Isometry3<f64>,
    /// Inward unit normals of the four side planes through the camera centre (camera frame).
    side_normals: [Vector3<f64>; 4],
    max_depth_m: f64,
}

impl ViewFrustum {
    /// The frustum of a camera at `world_from_camera` (maps camera coordinates to world) with
    /// these intrinsics, cut at `max_depth_m` metres along the optical axis. The sides pass
    /// through the outer edges of the image's border pixels.
    pub fn new(
        world_from_camera: &Isometry3<f64>,
        intrinsics: &Intrinsics,
        max_depth_m: f64,
    ) -> Self {
        // Image edges sit half a pixel outside the first and last pixel centres.
        let left = (-0.5 - intrinsics.cx) / intrinsics.fx;
        let right = (intrinsics.width as f64 - 0.5 - intrinsics.cx) / intrinsics.fx;
        let top = (-0.5 - intrinsics.cy) / intrinsics.fy;
        let bottom = (intrinsics.height as f64 - 0.5 - intrinsics.cy) / intrinsics.fy;
        // A point (x, y, z) is inside when x >= left z, x <= right z, y >= top z, y <= bottom z.
        let side_normals = [
            Vector3::new(1.0, 0.0, -left).normalize(),
            Vector3::new(-1.0, 0.0, right).normalize(),
            Vector3::new(0.0, 1.0, -top).normalize(),
            Vector3::new(0.0, -1.0, bottom).normalize(),
        ];
        Self {
            camera_from_world: world_from_camera.inverse(),
            side_normals,
            max_depth_m,
        }
    }

    /// True when a sphere (world frame) reaches into the frustum. Conservative: a sphere near a
    /// corner of the pyramid may pass without touching it, never the other way round.
    pub fn touches_sphere(&self, centre_world: &Point3<f64>, radius: f64) -> bool {
        let c = self.camera_from_world * centre_world;
        c.z >= -radius
            && c.z <= self.max_depth_m + radius
            && self
                .side_normals
                .iter()
                .all(|n| n.dot(&c.coords) >= -radius)
    }

    /// True when a point (world frame) is inside the frustum.
    pub fn contains(&self, point_world: &Point3<f64>) -> bool {
        self.touches_sphere(point_world, 0.0)
    }
}

/// Incremental voxel hash map of points with covariances. See the module documentation.
#[derive(Clone)]
pub struct VoxelMap {
    voxel_size: f32,
    voxel_index_of: FxHashMap<VoxelKey, u32>,
    voxels: Vec<Voxel>,
    /// Slot-indexed storage; `None` marks a free slot (recycled through `free_slots`). Slots are
    /// the indices G-ICP sees as target indices, stable while a point stays in the map.
    points: Vec<Option<MapPoint>>,
    free_slots: Vec<u32>,
    slot_of_id: FxHashMap<MapPointId, u32>,
    /// Current view selection; 0 means none (queries search the whole map).
    view_epoch: u32,
    next_epoch: u32,
}

impl std::fmt::Debug for VoxelMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VoxelMap")
            .field("voxel_size", &self.voxel_size)
            .field("points", &self.len())
            .field("voxels", &self.voxels.len())
            .finish()
    }
}

impl VoxelMap {
    /// A map with voxels of `voxel_size_m` edge.
    ///
    /// # Panics
    /// If the voxel size is not a positive finite number.
    pub fn new(voxel_size_m: f64) -> Self {
        assert!(
            voxel_size_m.is_finite() && voxel_size_m > 0.0,
            "voxel size must be positive, got {voxel_size_m}"
        );
        Self {
            voxel_size: voxel_size_m as f32,
            voxel_index_of: FxHashMap::default(),
            voxels: Vec::new(),
            points: Vec::new(),
            free_slots: Vec::new(),
            slot_of_id: FxHashMap::default(),
            view_epoch: 0,
            next_epoch: 1,
        }
    }

    /// A map of a whole cloud (positions and covariances; ids are the point indices), e.g. the
    /// previous frame as a frame-to-frame target. Non-finite points are skipped.
    ///
    /// # Panics
    /// If the cloud has no covariances.
    pub fn from_cloud(cloud: &PointCloud, voxel_size_m: f64) -> Self {
        assert!(cloud.has_covariances(), "from_cloud needs covariances");
        let mut map = Self::new(voxel_size_m);
        for (index, (position, covariance)) in
            cloud.positions.iter().zip(&cloud.covariances).enumerate()
        {
            let _refused_non_finite = map.insert(MapPoint {
                id: index as MapPointId,
                position: *position,
                covariance: *covariance,
            });
        }
        map
    }

    /// A map whose voxels suit queries bounded by `max_correspondence_m` (the usual choice).
    pub fn for_correspondence_distance(max_correspondence_m: f64) -> Self {
        Self::new(VOXEL_SIZE_PER_CORRESPONDENCE_DISTANCE * max_correspondence_m)
    }

    /// Voxel edge in metres.
    pub fn voxel_size(&self) -> f64 {
        self.voxel_size as f64
    }

    /// Points in the map.
    pub fn len(&self) -> usize {
        self.slot_of_id.len()
    }

    /// True when the map holds no points.
    pub fn is_empty(&self) -> bool {
        self.slot_of_id.is_empty()
    }

    /// Occupied voxels.
    pub fn voxel_count(&self) -> usize {
        self.voxels.len()
    }

    /// Removes every point (keeps allocations).
    pub fn clear(&mut self) {
        self.voxel_index_of.clear();
        self.voxels.clear();
        self.points.clear();
        self.free_slots.clear();
        self.slot_of_id.clear();
        self.view_epoch = 0;
    }

    fn key_of(&self, p: &Point3<f32>) -> VoxelKey {
        let scale = 1.0 / self.voxel_size;
        VoxelKey {
            x: floor_to_i32(p.x * scale),
            y: floor_to_i32(p.y * scale),
            z: floor_to_i32(p.z * scale),
        }
    }

    /// Adds a point, replacing (and returning) the point that had the same id. Non-finite
    /// positions are refused (returned as `Err`), since they belong to no voxel.
    pub fn insert(&mut self, point: MapPoint) -> Result<Option<MapPoint>, MapPoint> {
        if !point.position.iter().all(|v| v.is_finite()) {
            return Err(point);
        }
        let replaced = self.remove(point.id);
        let slot = match self.free_slots.pop() {
            Some(slot) => {
                self.points[slot as usize] = Some(point);
                slot
            }
            None => {
                self.points.push(Some(point));
                (self.points.len() - 1) as u32
            }
        };
        self.slot_of_id.insert(point.id, slot);
        let key = self.key_of(&point.position);
        let voxel_index = match self.voxel_index_of.get(&key) {
            Some(&index) => index as usize,
            None => {
                self.voxel_index_of.insert(key, self.voxels.len() as u32);
                self.voxels.push(Voxel {
                    key,
                    points: VoxelPoints::default(),
                    // A new voxel is outside the current selection until the next select_view.
                    in_view_epoch: 0,
                });
                self.voxels.len() - 1
            }
        };
        let voxel = &mut self.voxels[voxel_index];
        voxel.points.push(point.position.coords.into(), slot);
        Ok(replaced)
    }

    /// Removes the point with that id, returning it.
    pub fn remove(&mut self, id: MapPointId) -> Option<MapPoint> {
        let slot = self.slot_of_id.remove(&id)?;
        let point = self.points[slot as usize]
            .take()
            .expect("slot_of_id only names occupied slots");
        self.free_slots.push(slot);
        let key = self.key_of(&point.position);
        let voxel_index = self.voxel_index_of[&key] as usize;
        let voxel = &mut self.voxels[voxel_index];
        let listed = voxel.points.remove_slot(slot);
        assert!(listed, "a point is listed in the voxel of its position");
        if voxel.points.is_empty() {
            self.voxel_index_of.remove(&key);
            self.voxels.swap_remove(voxel_index);
            if let Some(moved) = self.voxels.get(voxel_index) {
                self.voxel_index_of.insert(moved.key, voxel_index as u32);
            }
        }
        Some(point)
    }

    /// Moves every point for which `transform_of` gives a transform (`p -> R p + t`, covariance
    /// `R C R^T`); the others stay where they are, untouched (so a correction that moves a small
    /// part of the map costs only that part). Ids are kept; queries see the new positions. A
    /// point whose new position is not finite is dropped (it belongs to no voxel). Returns how
    /// many points moved.
    pub fn transform_points(
        &mut self,
        mut transform_of: impl FnMut(MapPointId) -> Option<Isometry3<f64>>,
    ) -> usize {
        let moving: Vec<(MapPointId, Isometry3<f64>)> = self
            .iter()
            .filter_map(|point| Some((point.id, transform_of(point.id)?)))
            .collect();
        for (id, transform) in &moving {
            let Some(mut point) = self.remove(*id) else {
                continue;
            };
            let rotation = transform.rotation.to_rotation_matrix().into_inner();
            point.position = (transform * point.position.cast::<f64>()).cast::<f32>();
            point.covariance = Covariance::from_matrix(
                &(rotation * point.covariance.to_matrix() * rotation.transpose()),
            );
            // Finite positions are always accepted; a non-finite transform loses the point.
            let _ = self.insert(point);
        }
        moving.len()
    }

    /// The point with that id, if it is in the map.
    pub fn get(&self, id: MapPointId) -> Option<&MapPoint> {
        let slot = *self.slot_of_id.get(&id)?;
        self.points[slot as usize].as_ref()
    }

    /// Every point, in no particular order.
    pub fn iter(&self) -> impl Iterator<Item = &MapPoint> {
        self.points.iter().flatten()
    }

    /// About `max_points` points of the selected view (the whole map when none is selected),
    /// spread evenly: every n-th point of each voxel, counted across voxels. World frame.
    pub fn sample_view(&self, max_points: usize) -> Vec<Point3<f32>> {
        self.sample(max_points, true)
    }

    /// [`Self::sample_view`] over the whole map, whatever view is selected.
    pub fn sample_all(&self, max_points: usize) -> Vec<Point3<f32>> {
        self.sample(max_points, false)
    }

    fn sample(&self, max_points: usize, only_selected_view: bool) -> Vec<Point3<f32>> {
        let use_view = only_selected_view && self.view_epoch != 0;
        let selected = |voxel: &&Voxel| !use_view || voxel.in_view_epoch == self.view_epoch;
        let total: usize = self
            .voxels
            .iter()
            .filter(selected)
            .map(|v| v.points.len())
            .sum();
        let step = total.div_ceil(max_points.max(1)).max(1);
        let mut sample = Vec::with_capacity(total / step + 1);
        let mut counter = 0usize;
        for voxel in self.voxels.iter().filter(selected) {
            for slot in voxel.points.slots() {
                if counter.is_multiple_of(step)
                    && let Some(point) = &self.points[slot as usize]
                {
                    sample.push(point.position);
                }
                counter += 1;
            }
        }
        sample
    }

    /// Restricts later queries to the voxels that reach into `view` (the candidates of docs/method.md,
    /// One agent: Tracking: map points in the predicted view frustum within truncation depth). Returns how
    /// many voxels were selected. The selection holds until the next call or [`Self::clear_view`];
    /// points inserted meanwhile into new voxels are not selected.
    pub fn select_view(&mut self, view: &ViewFrustum) -> usize {
        let epoch = self.next_epoch;
        // Epoch 0 means "no selection"; wrapping past it would re-select stale voxels.
        self.next_epoch = self.next_epoch.checked_add(1).unwrap_or_else(|| {
            for voxel in &mut self.voxels {
                voxel.in_view_epoch = 0;
            }
            1
        });
        let size = self.voxel_size as f64;
        let radius = size * 3f64.sqrt() / 2.0;
        let mut selected = 0;
        for voxel in &mut self.voxels {
            let centre = Point3::new(
                (voxel.key.x as f64 + 0.5) * size,
                (voxel.key.y as f64 + 0.5) * size,
                (voxel.key.z as f64 + 0.5) * size,
            );
            if view.touches_sphere(&centre, radius) {
                voxel.in_view_epoch = epoch;
                selected += 1;
            }
        }
        self.view_epoch = epoch;
        selected
    }

    /// Queries search the whole map again.
    pub fn clear_view(&mut self) {
        self.view_epoch = 0;
    }

    /// Ids of the points in the selected view's voxels (all points without a selection).
    pub fn ids_in_view(&self) -> impl Iterator<Item = MapPointId> + '_ {
        self.voxels
            .iter()
            .filter(|v| self.view_epoch == 0 || v.in_view_epoch == self.view_epoch)
            .flat_map(|v| v.points.slots())
            .filter_map(|slot| self.points[slot as usize].as_ref().map(|p| p.id))
    }

    /// Nearest point to `query` within `sqrt(max_distance_sq)`, over the whole map (ignoring any
    /// view selection): slot and squared distance.
    pub fn nearest_in_map(&self, query: &Point3<f32>, max_distance_sq: f32) -> Option<(u32, f32)> {
        self.nearest(query, max_distance_sq, false, false, None)
    }

    /// The nearest point as described on [`Self::nearest_in_map`]; `home_hint`, if given, is a
    /// voxel index to try for the query's own voxel before the hash lookup, updated to the voxel
    /// found ([`NO_HINT`] when the query's voxel is empty).
    fn nearest(
        &self,
        query: &Point3<f32>,
        max_distance_sq: f32,
        only_selected_view: bool,
        stop_at_first_voxel_hit: bool,
        home_hint: Option<&mut u32>,
    ) -> Option<(u32, f32)> {
        if max_distance_sq.is_nan() || max_distance_sq < 0.0 || self.voxels.is_empty() {
            return None;
        }
        let use_view = only_selected_view && self.view_epoch != 0;
        let home = self.key_of(query);
        let mut best: Option<(u32, f32)> = None;
        let mut best_sq = max_distance_sq;
        // The voxel's point nearer than `best_sq`, if any (lowering `best_sq` to it).
        let scan_voxel = |voxel: &Voxel, best_sq: &mut f32| {
            if use_view && voxel.in_view_epoch != self.view_epoch {
                return None;
            }
            voxel.points.nearest(query.coords.into(), best_sq)
        };
        let scan = |key: &VoxelKey, best_sq: &mut f32| {
            scan_voxel(
                &self.voxels[*self.voxel_index_of.get(key)? as usize],
                best_sq,
            )
        };
        // A point queried again after a small move is usually still in the same voxel: checking
        // the hinted voxel's key costs one load where the hash lookup costs several.
        let hinted = home_hint.as_deref().copied().filter(|&index| {
            self.voxels
                .get(index as usize)
                .is_some_and(|v| v.key == home)
        });
        let home_index = hinted.or_else(|| self.voxel_index_of.get(&home).copied());
        if let Some(hint) = home_hint {
            *hint = home_index.unwrap_or(NO_HINT);
        }
        let home_match =
            home_index.and_then(|index| scan_voxel(&self.voxels[index as usize], &mut best_sq));
        if let Some(found) = home_match {
            if stop_at_first_voxel_hit {
                return Some(found);
            }
            best = Some(found);
        }
        let size = self.voxel_size;
        // Squared distance from the query to the slab of voxels at coordinate `k` on one axis.
        let gap_sq = |k: i32, home_k: i32, q: f32| -> f32 {
            let gap = if k < home_k {
                q - (k + 1) as f32 * size
            } else if k > home_k {
                k as f32 * size - q
            } else {
                0.0
            };
            gap * gap
        };
        // Other voxels that the search ball reaches, each looked up only if its box is closer
        // than the best match so far.
        let (low, high) = if max_distance_sq <= size * size {
            // The ball reaches no farther than the next voxel on each axis: it reaches that voxel
            // only where the home voxel's face is nearer than the best match so far. After
            // alignment the best match is millimetres away and most queries keep to their home
            // voxel, visiting no neighbour.
            let range = |home_k: i32, q: f32| {
                let below = gap_sq(home_k - 1, home_k, q) <= best_sq;
                let above = gap_sq(home_k + 1, home_k, q) <= best_sq;
                (home_k - i32::from(below), home_k + i32::from(above))
            };
            let (x, y, z) = (
                range(home.x, query.x),
                range(home.y, query.y),
                range(home.z, query.z),
            );
            (
                VoxelKey {
                    x: x.0,
                    y: y.0,
                    z: z.0,
                },
                VoxelKey {
                    x: x.1,
                    y: y.1,
                    z: z.1,
                },
            )
        } else {
            let reach = max_distance_sq.sqrt();
            (
                self.key_of(&(query - Vector3::repeat(reach))),
                self.key_of(&(query + Vector3::repeat(reach))),
            )
        };
        for x in low.x..=high.x {
            let gx = gap_sq(x, home.x, query.x);
            for y in low.y..=high.y {
                let gxy = gx + gap_sq(y, home.y, query.y);
                for z in low.z..=high.z {
                    if (x, y, z) == (home.x, home.y, home.z) {
                        continue;
                    }
                    if gxy + gap_sq(z, home.z, query.z) > best_sq {
                        continue;
                    }
                    if let Some(found) = scan(&VoxelKey { x, y, z }, &mut best_sq) {
                        if stop_at_first_voxel_hit {
                            return Some(found);
                        }
                        best = Some(found);
                    }
                }
            }
        }
        best
    }
}

/// `v.floor() as i32` without a call into libm (`f32::floor` is one on x86-64 without SSE4.1;
/// it showed as ~3 % of the tracking profile); exact for |v| < 2^31, 0 for NaN.
fn floor_to_i32(v: f32) -> i32 {
    let truncated = v as i32;
    truncated - i32::from(truncated as f32 > v)
}

impl RegistrationTarget for VoxelMap {
    fn nearest_within(&self, query: &Point3<f32>, max_distance_sq: f32) -> Option<(u32, f32)> {
        self.nearest(query, max_distance_sq, true, false, None)
    }

    fn nearest_within_hinted(
        &self,
        query: &Point3<f32>,
        max_distance_sq: f32,
        hint: &mut u32,
    ) -> Option<(u32, f32)> {
        self.nearest(query, max_distance_sq, true, false, Some(hint))
    }

    fn any_within(&self, query: &Point3<f32>, max_distance_sq: f32) -> bool {
        // The home voxel holds a match for most queries; stopping there skips the neighbour
        // lookups that only the nearest match needs.
        self.nearest(query, max_distance_sq, true, true, None)
            .is_some()
    }

    fn position(&self, index: u32) -> Point3<f32> {
        self.points[index as usize]
            .as_ref()
            .expect("G-ICP only asks for slots a query returned")
            .position
    }

    fn covariance(&self, index: u32) -> Covariance {
        self.points[index as usize]
            .as_ref()
            .expect("G-ICP only asks for slots a query returned")
            .covariance
    }

    fn target_len(&self) -> usize {
        self.len()
    }
}

#[cfg(test)]
mod tests;
