//! A revisit's remembered fruit as a gain: a view that sees more of the previous visit's fruit
//! not yet found again is worth more.
//!
//! On a revisit the map starts from a prior that holds little but the previous visit's fruit
//! voxels as hints ([`RoiMap::unobserved_hints`]), so nearly every candidate sees only unknown
//! space and the unobserved-voxel gain cannot tell a view of four remembered fruit from a view
//! of a bare stem: the nearest view wins. Here each remembered fruit (a connected group of hint
//! voxels no scan of this visit has touched) is one point, its voxels' mean, and a candidate
//! gains [`crate::PlannerConfig::remembered_fruit_gain`] for each such point inside its field
//! of view, within the gain rays' range and with no occupied voxel on the line of sight.

use glasshouse_roimap::{Neighbourhood, RoiMap, VoxelKey};
use nalgebra::{Isometry3, Point3};

/// Nearer than this the camera sees nothing in focus (the depth camera's minimum range).
const MIN_SEEN_DISTANCE_M: f64 = 0.15;

/// The previous visit's fruit not yet seen again, one point each, and how a view sees them.
#[derive(Clone, Debug)]
pub struct RememberedFruit {
    centres: Vec<Point3<f64>>,
    max_distance_m: f64,
    /// Tangents of the half fields of view, horizontal and vertical.
    half_fov_tan: (f64, f64),
    occlusion_occupancy_logodds: f32,
}

impl RememberedFruit {
    /// Groups `hints` into 26-connected fruit.
    pub fn new(map: &RoiMap, hints: &[VoxelKey], config: &crate::PlannerConfig) -> Self {
        let mut sorted = hints.to_vec();
        sorted.sort_unstable();
        sorted.dedup();
        Self {
            centres: group_centres(map, &sorted),
            max_distance_m: config.gain_ray_range_m,
            half_fov_tan: (
                (config.horizontal_fov_rad / 2.0).tan(),
                (config.vertical_fov_rad / 2.0).tan(),
            ),
            occlusion_occupancy_logodds: config.occlusion_occupancy_logodds,
        }
    }

    /// How many remembered fruit there are.
    pub fn len(&self) -> usize {
        self.centres.len()
    }

    pub fn is_empty(&self) -> bool {
        self.centres.is_empty()
    }

    /// The remembered fruit a camera at `world_from_camera` (optical frame: z forward, x right,
    /// y down) sees: in its field of view, within range, nothing occupied in between.
    pub fn seen_from(&self, map: &RoiMap, world_from_camera: &Isometry3<f64>) -> usize {
        let camera_in_world = Point3::from(world_from_camera.translation.vector);
        self.centres
            .iter()
            .filter(|centre| {
                let in_camera = world_from_camera.inverse_transform_point(centre);
                let distance_m = in_camera.coords.norm();
                let (tan_x, tan_y) = self.half_fov_tan;
                in_camera.z > 0.0
                    && (MIN_SEEN_DISTANCE_M..=self.max_distance_m).contains(&distance_m)
                    && in_camera.x.abs() <= tan_x * in_camera.z
                    && in_camera.y.abs() <= tan_y * in_camera.z
                    && self.line_of_sight(map, centre, &camera_in_world)
            })
            .count()
    }

    /// No voxel on the segment from the fruit to the camera is occupied beyond the threshold.
    fn line_of_sight(&self, map: &RoiMap, from: &Point3<f64>, to: &Point3<f64>) -> bool {
        let towards = to - from;
        let distance_m = towards.norm();
        let mut clear = true;
        map.walk_ray(from, &(towards / distance_m), distance_m, |_, voxel| {
            clear = voxel.is_none_or(|v| v.occupancy_logodds <= self.occlusion_occupancy_logodds);
            clear
        });
        clear
    }
}

/// The mean voxel centre of each 26-connected group of `keys` (sorted), in the order of each
/// group's smallest key.
fn group_centres(map: &RoiMap, keys: &[VoxelKey]) -> Vec<Point3<f64>> {
    let mut grouped = vec![false; keys.len()];
    let mut centres = Vec::new();
    for start in 0..keys.len() {
        if grouped[start] {
            continue;
        }
        grouped[start] = true;
        let (mut stack, mut sum, mut count) = (vec![start], nalgebra::Vector3::zeros(), 0.0);
        while let Some(index) = stack.pop() {
            sum += map.centre_of(keys[index]).coords;
            count += 1.0;
            for neighbour in keys[index].neighbours(Neighbourhood::TwentySix) {
                if let Ok(found) = keys.binary_search(&neighbour) {
                    if !grouped[found] {
                        grouped[found] = true;
                        stack.push(found);
                    }
                }
            }
        }
        centres.push(Point3::from(sum / count));
    }
    centres
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::PlannerConfig;
    use glasshouse_roimap::MapConfig;
    use nalgebra::{UnitQuaternion, Vector3};

    /// A map whose only known voxels are two remembered fruit: 3x3x3 hint cubes around
    /// (1, 0, 0) and (1, 0.5, 0).
    fn two_fruit() -> (RoiMap, Vec<VoxelKey>) {
        let map = RoiMap::new(MapConfig::default()).unwrap();
        let mut hints = Vec::new();
        for centre in [Point3::new(1.0, 0.0, 0.0), Point3::new(1.0, 0.5, 0.0)] {
            let key = map.key_of(&centre);
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        hints.push(key.offset(dx, dy, dz));
                    }
                }
            }
        }
        hints.sort_unstable();
        (map, hints)
    }

    /// A camera at `position` looking along world +x (optical z).
    fn looking_along_x(position: Point3<f64>) -> Isometry3<f64> {
        let rotation = UnitQuaternion::face_towards(&Vector3::x(), &-Vector3::z());
        Isometry3::from_parts(position.coords.into(), rotation)
    }

    #[test]
    fn connected_hints_make_one_fruit_each() {
        let (map, hints) = two_fruit();
        let remembered = RememberedFruit::new(&map, &hints, &PlannerConfig::default());
        assert_eq!(remembered.len(), 2);
        let near = |p: &Point3<f64>| {
            (p - map.centre_of(map.key_of(&Point3::new(1.0, 0.0, 0.0)))).norm() < 1e-9
        };
        assert!(remembered.centres.iter().any(near));
    }

    #[test]
    fn a_view_counts_the_fruit_in_its_field_of_view_and_range() {
        let (map, hints) = two_fruit();
        let remembered = RememberedFruit::new(&map, &hints, &PlannerConfig::default());
        // 0.6 m in front of both: 0.25 m apart sideways, inside the 80° field of view.
        let both = looking_along_x(Point3::new(0.4, 0.25, 0.0));
        assert_eq!(remembered.seen_from(&map, &both), 2);
        // Right in front of one, the other 45° off at 0.5 m: outside the 40° half field.
        let one = looking_along_x(Point3::new(0.5, 0.0, 0.0));
        assert_eq!(remembered.seen_from(&map, &one), 1);
        // Looking away.
        let away = Isometry3::from_parts(
            both.translation,
            UnitQuaternion::face_towards(&-Vector3::x(), &-Vector3::z()),
        );
        assert_eq!(remembered.seen_from(&map, &away), 0);
        // Beyond the gain rays' range (1 m).
        let far = looking_along_x(Point3::new(-0.2, 0.25, 0.0));
        assert_eq!(remembered.seen_from(&map, &far), 0);
    }

    #[test]
    fn an_occupied_voxel_between_hides_a_fruit() {
        let (mut map, hints) = two_fruit();
        let remembered = RememberedFruit::new(&map, &hints, &PlannerConfig::default());
        let camera = looking_along_x(Point3::new(0.4, 0.25, 0.0));
        // A leaf on the line from the camera to the first fruit, seen from a sensor beside it.
        let leaf = Point3::new(0.7, 0.125, 0.0);
        let leaf_points: Vec<Point3<f32>> = (0..3).map(|_| leaf.cast::<f32>()).collect();
        for _ in 0..3 {
            map.insert_scan(&Point3::new(0.7, 0.125, 0.5), &leaf_points, &[false; 3])
                .unwrap();
        }
        assert_eq!(remembered.seen_from(&map, &camera), 1);
    }
}
