use std::collections::{BTreeMap, BTreeSet};

use super::*;

/// Small seeded generator (SplitMix64) so tests need no extra crates.
struct TestRng(u64);

impl TestRng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
}

fn map() -> RoiMap {
    RoiMap::new(MapConfig::default()).expect("default config is valid")
}

fn p32(x: f64, y: f64, z: f64) -> Point3<f32> {
    Point3::new(x as f32, y as f32, z as f32)
}

fn k(x: i32, y: i32, z: i32) -> VoxelKey {
    VoxelKey::new(x, y, z)
}

const MISS: f32 = -0.4055;
const HIT: f32 = 0.8473;

#[test]
fn default_config_is_the_papers_and_valid() {
    let c = MapConfig::default();
    assert_eq!(c.resolution_m, 0.01);
    assert_eq!(c.hit_logodds, HIT);
    assert_eq!(c.miss_logodds, MISS);
    assert_eq!(c.clamp_min_logodds, -2.0);
    assert_eq!(c.clamp_max_logodds, 3.5110);
    assert_eq!(c.roi_threshold_logodds, 1.0);
    assert_eq!(c.max_range_m, None);
    assert!(c.validate().is_ok());
    for bad in [
        MapConfig {
            resolution_m: 0.0,
            ..c
        },
        MapConfig {
            resolution_m: f64::NAN,
            ..c
        },
        MapConfig {
            clamp_min_logodds: 4.0,
            ..c
        },
        MapConfig {
            max_range_m: Some(-1.0),
            ..c
        },
        MapConfig {
            hit_logodds: f32::INFINITY,
            ..c
        },
    ] {
        assert!(matches!(RoiMap::new(bad), Err(MapError::InvalidConfig(_))));
    }
}

#[test]
fn single_ray_along_x() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    let stats = m
        .insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
        .expect("valid scan");
    assert_eq!(stats.free_updates, 10);
    assert_eq!(stats.occupied_updates, 1);
    for x in 0..10 {
        assert_eq!(m.occupancy(k(x, 0, 0)), Occupancy::Free, "x = {x}");
        assert_eq!(m.get(k(x, 0, 0)).map(|v| v.occupancy_logodds), Some(MISS));
    }
    assert_eq!(m.occupancy(k(10, 0, 0)), Occupancy::Occupied);
    assert_eq!(m.get(k(10, 0, 0)).map(|v| v.occupancy_logodds), Some(HIT));
    assert_eq!(m.len(), 11);
    assert_eq!(m.occupancy(k(11, 0, 0)), Occupancy::Unknown);
    assert_eq!(m.scans_inserted(), 1);
}

#[test]
fn point_in_origin_voxel_frees_nothing() {
    let mut m = map();
    let origin = Point3::new(0.001, 0.001, 0.001);
    let stats = m
        .insert_scan(&origin, &[p32(0.009, 0.009, 0.009)], &[false])
        .expect("valid scan");
    assert_eq!(stats.free_updates, 0);
    assert_eq!(m.occupancy(k(0, 0, 0)), Occupancy::Occupied);
    assert_eq!(m.len(), 1);
}

#[test]
fn occupied_wins_within_a_scan() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    // The second point's voxel (5,0,0) lies on the first point's ray.
    let stats = m
        .insert_scan(
            &origin,
            &[p32(0.105, 0.005, 0.005), p32(0.055, 0.005, 0.005)],
            &[false, false],
        )
        .expect("valid scan");
    assert_eq!(m.occupancy(k(5, 0, 0)), Occupancy::Occupied);
    assert_eq!(m.get(k(5, 0, 0)).map(|v| v.occupancy_logodds), Some(HIT));
    assert_eq!(stats.free_updates, 9);
    assert_eq!(stats.occupied_updates, 2);
}

#[test]
fn each_voxel_updated_once_per_scan() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    // Many rays fanning out share the voxels near the origin.
    let points: Vec<Point3<f32>> = (0..50)
        .map(|i| p32(0.5, 0.005 + 0.002 * f64::from(i), 0.005))
        .collect();
    m.insert_scan(&origin, &points, &vec![false; points.len()])
        .expect("valid scan");
    let origin_voxel = m.get(k(0, 0, 0)).expect("origin voxel known");
    assert_eq!(origin_voxel.occupancy_logodds, MISS);
    assert_eq!(m.get(k(20, 0, 0)).map(|v| v.occupancy_logodds), Some(MISS));
    for (_, v) in m.iter() {
        assert!(v.occupancy_logodds == MISS || v.occupancy_logodds == HIT);
    }
}

#[test]
fn clamping_after_many_scans() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    for _ in 0..20 {
        m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[true])
            .expect("valid scan");
    }
    let free = m.get(k(3, 0, 0)).expect("known");
    let occ = m.get(k(10, 0, 0)).expect("known");
    assert_eq!(free.occupancy_logodds, -2.0);
    assert_eq!(occ.occupancy_logodds, 3.5110);
    assert_eq!(occ.roi_logodds, 3.5110);
    assert_eq!(free.roi_logodds, 0.0, "free voxels get no ROI update");
}

/// One voxel labelled fruit and non-fruit equally often: the paper's asymmetric ROI update
/// (+0.85 / −0.41) makes it fruit, the symmetric model does not; a snapshot keeps the model.
#[test]
fn a_symmetric_roi_model_does_not_let_false_fruit_labels_add_up() {
    let labels = [
        false, false, true, true, false, true, false, false, true, true,
    ];
    let run = |config: MapConfig| {
        let mut m = RoiMap::new(config).expect("valid config");
        let origin = Point3::new(0.005, 0.005, 0.005);
        for &fruit in &labels {
            m.insert_scan(&origin, &[p32(0.205, 0.005, 0.005)], &[fruit])
                .expect("valid scan");
        }
        m
    };
    let paper = run(MapConfig::default());
    assert!(paper.is_roi(k(20, 0, 0)), "{:?}", paper.get(k(20, 0, 0)));
    let symmetric = MapConfig {
        roi_hit_logodds: 0.8473,
        roi_miss_logodds: -0.8473,
        ..MapConfig::default()
    };
    let m = run(symmetric);
    assert!(!m.is_roi(k(20, 0, 0)), "{:?}", m.get(k(20, 0, 0)));
    // Occupancy keeps OctoMap's rule whatever the ROI model.
    assert_eq!(
        m.get(k(20, 0, 0)).map(|v| v.occupancy_logodds),
        paper.get(k(20, 0, 0)).map(|v| v.occupancy_logodds)
    );
    let mut bytes = Vec::new();
    m.write_snapshot(&mut bytes).expect("write");
    let back = RoiMap::read_snapshot(bytes.as_slice()).expect("read");
    assert_eq!(back.config(), &symmetric);
    assert_eq!(back.get(k(20, 0, 0)), m.get(k(20, 0, 0)));
}

#[test]
fn beyond_range_frees_up_to_range_and_marks_nothing() {
    let config = MapConfig {
        max_range_m: Some(0.05),
        ..MapConfig::default()
    };
    let mut m = RoiMap::new(config).expect("valid config");
    let origin = Point3::new(0.005, 0.005, 0.005);
    let stats = m
        .insert_scan(&origin, &[p32(0.205, 0.005, 0.005)], &[true])
        .expect("valid scan");
    assert_eq!(stats.beyond_range, 1);
    assert_eq!(stats.occupied_updates, 0);
    assert_eq!(stats.roi_updates + stats.non_roi_updates, 0);
    // Range end at x = 0.055 lies in voxel 5, which is excluded like an end voxel.
    for x in 0..5 {
        assert_eq!(m.occupancy(k(x, 0, 0)), Occupancy::Free);
    }
    assert_eq!(m.len(), 5);
    assert!(m.iter().all(|(_, v)| v.occupancy() == Occupancy::Free));
    assert_eq!(m.occupancy(k(20, 0, 0)), Occupancy::Unknown);
}

#[test]
fn non_finite_points_skipped_and_counted() {
    let origin = Point3::new(0.005, 0.005, 0.005);
    let good = p32(0.105, 0.005, 0.005);
    let mut clean = map();
    clean
        .insert_scan(&origin, &[good], &[true])
        .expect("valid scan");
    let mut dirty = map();
    let pts = [
        Point3::new(f32::NAN, 0.0, 0.0),
        good,
        Point3::new(0.1, f32::INFINITY, 0.0),
        Point3::new(0.0, 0.0, f32::NEG_INFINITY),
    ];
    let stats = dirty
        .insert_scan(&origin, &pts, &[true, true, false, true])
        .expect("valid scan");
    assert_eq!(stats.points, 4);
    assert_eq!(stats.skipped_non_finite, 3);
    let mut a: Vec<_> = clean.iter().collect();
    let mut b: Vec<_> = dirty.iter().collect();
    a.sort_by_key(|(k, _)| *k);
    b.sort_by_key(|(k, _)| *k);
    assert_eq!(a, b);
}

#[test]
fn bad_input_is_a_typed_error_and_leaves_the_map_untouched() {
    let mut m = map();
    let origin = Point3::new(0.0, 0.0, 0.0);
    assert!(matches!(
        m.insert_scan(&origin, &[p32(0.1, 0.0, 0.0)], &[]),
        Err(MapError::LengthMismatch { points: 1, roi: 0 })
    ));
    assert!(matches!(
        m.insert_scan(
            &Point3::new(f64::NAN, 0.0, 0.0),
            &[p32(0.1, 0.0, 0.0)],
            &[false]
        ),
        Err(MapError::NonFiniteOrigin)
    ));
    assert!(matches!(
        m.insert_scan(&Point3::new(1e9, 0.0, 0.0), &[], &[]),
        Err(MapError::OriginOutOfBounds)
    ));
    assert!(m.is_empty());
    assert_eq!(m.scans_inserted(), 0);
    assert!(m.take_changes().is_empty());
    // A point far outside the key range is skipped rather than walked for ages.
    let stats = m
        .insert_scan(&origin, &[p32(1e8, 0.0, 0.0)], &[false])
        .expect("scan with far point");
    assert_eq!(stats.skipped_out_of_bounds, 1);
    assert!(m.is_empty());
}

#[test]
fn roi_wins_within_a_scan_and_threshold_needs_two_observations() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    // Two points in voxel (10,0,0): one ROI, one not.
    let pts = [p32(0.102, 0.005, 0.005), p32(0.108, 0.006, 0.004)];
    let stats = m
        .insert_scan(&origin, &pts, &[false, true])
        .expect("valid scan");
    assert_eq!(stats.roi_updates, 1);
    assert_eq!(stats.non_roi_updates, 0);
    assert_eq!(m.get(k(10, 0, 0)).map(|v| v.roi_logodds), Some(HIT));
    assert!(!m.is_roi(k(10, 0, 0)), "one observation is below 1.0");
    m.insert_scan(&origin, &pts, &[true, false])
        .expect("valid scan");
    assert!(m.is_roi(k(10, 0, 0)), "two observations reach 1.0");
    assert_eq!(m.roi_keys(), vec![k(10, 0, 0)]);
    // A non-ROI observation lowers it again.
    m.insert_scan(&origin, &pts[..1], &[false])
        .expect("valid scan");
    assert_eq!(
        m.get(k(10, 0, 0)).map(|v| v.roi_logodds),
        Some(HIT + HIT + MISS)
    );
}

#[test]
fn take_changes_returns_each_change_once() {
    let mut m = map();
    let origin = Point3::new(0.005, 0.005, 0.005);
    m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
        .expect("valid scan");
    let changes = m.take_changes();
    assert_eq!(changes.len(), 11);
    assert!(
        changes.windows(2).all(|w| w[0].0 < w[1].0),
        "sorted, unique"
    );
    assert_eq!(
        changes[10],
        (k(10, 0, 0), m.get(k(10, 0, 0)).expect("known"))
    );
    assert!(m.take_changes().is_empty());
    // Saturated voxels stop changing and so stop being reported.
    for _ in 0..10 {
        m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
            .expect("valid scan");
    }
    m.take_changes();
    m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
        .expect("valid scan");
    // ROI log-odds of the end voxel still clamp at -2.0 after 12 misses: everything saturated.
    assert!(m.take_changes().is_empty());
    // apply_voxels records what it changed.
    let v = Voxel {
        occupancy_logodds: 1.0,
        roi_logodds: 2.0,
    };
    m.apply_voxels(&[
        (k(-5, 0, 0), v),
        (k(3, 0, 0), m.get(k(3, 0, 0)).expect("known")),
    ]);
    assert_eq!(m.take_changes(), vec![(k(-5, 0, 0), v)]);
    assert!(m.is_roi(k(-5, 0, 0)));
}

#[test]
fn drained_changes_are_the_taken_ones_with_their_roi_state() {
    let origin = Point3::new(0.005, 0.005, 0.005);
    // Two fans of rays, ROI on every other end point, the second scan over the first.
    let fan = |dz: f64| -> Vec<Point3<f32>> {
        (0..40)
            .map(|i| p32(0.3, -0.2 + 0.01 * f64::from(i), 0.05 + dz))
            .collect()
    };
    let roi: Vec<bool> = (0..40).map(|i| i % 2 == 0).collect();
    let (mut taken, mut drained) = (map(), map());
    let mut seen_roi = 0;
    for dz in [0.0, 0.0, 0.02] {
        for m in [&mut taken, &mut drained] {
            m.insert_scan(&origin, &fan(dz), &roi).expect("valid scan");
        }
        let mut visited = Vec::new();
        drained.drain_changes(|key, voxel, is_roi| {
            assert_eq!(is_roi, taken.is_roi(key), "{key:?}");
            seen_roi += usize::from(is_roi);
            visited.push((key, voxel));
        });
        visited.sort_unstable_by_key(|(key, _)| *key);
        assert_eq!(visited, taken.take_changes());
        assert!(!visited.is_empty());
    }
    assert!(seen_roi > 0, "the scans made ROI voxels");
    let mut after = 0;
    drained.drain_changes(|_, _, _| after += 1);
    assert_eq!(after, 0, "the record is cleared");
}

#[test]
fn negative_coordinates_floor() {
    let m = map();
    assert_eq!(m.key_of(&Point3::new(-0.001, 0.001, -0.015)), k(-1, 0, -2));
    assert_eq!(m.key_of(&Point3::new(0.0, 0.0099, -0.01)), k(0, 0, -1));
    let c = m.centre_of(k(-1, 0, 2));
    assert!((c - Point3::new(-0.005, 0.005, 0.025)).norm() < 1e-12);
    assert_eq!(m.try_key_of(&Point3::new(f64::NAN, 0.0, 0.0)), None);

    let mut m = map();
    let origin = Point3::new(-0.005, -0.005, -0.005);
    m.insert_scan(&origin, &[p32(-0.105, -0.005, -0.005)], &[false])
        .expect("valid scan");
    assert_eq!(m.occupancy(k(-11, -1, -1)), Occupancy::Occupied);
    for x in -10..=-1 {
        assert_eq!(m.occupancy(k(x, -1, -1)), Occupancy::Free);
    }
}

/// Literal transcription of OctoMap 1.9's computeRayKeys / computeUpdate in its precision
/// (`point3d` is float, keys and the walk are double) plus a BTree-based update, as the
/// reference for the optimised insertion.
struct Reference {
    res: f64,
    cells: BTreeMap<VoxelKey, Voxel>,
}

type P3 = [f32; 3];

fn sub(a: P3, b: P3) -> P3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm(a: P3) -> f64 {
    f64::from(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

impl Reference {
    fn new(res: f64) -> Self {
        Self {
            res,
            cells: BTreeMap::new(),
        }
    }

    fn key(&self, p: P3) -> VoxelKey {
        let f = 1.0 / self.res;
        let k = |c: f32| (f * f64::from(c)).floor() as i32;
        VoxelKey::new(k(p[0]), k(p[1]), k(p[2]))
    }

    fn ray_keys(&self, origin: P3, end: P3) -> Vec<VoxelKey> {
        let ko = self.key(origin);
        let ke = self.key(end);
        let mut ray = Vec::new();
        if ko == ke {
            return ray;
        }
        ray.push(ko);
        let mut direction = sub(end, origin);
        let length = norm(direction) as f32;
        for d in &mut direction {
            *d /= length;
        }
        let mut step = [0i32; 3];
        let mut t_max = [f64::MAX; 3];
        let mut t_delta = [f64::MAX; 3];
        let mut cur = [ko.x, ko.y, ko.z];
        for i in 0..3 {
            step[i] = if direction[i] > 0.0 {
                1
            } else if direction[i] < 0.0 {
                -1
            } else {
                0
            };
            if step[i] != 0 {
                let mut border = (f64::from(cur[i]) + 0.5) * self.res;
                border += f64::from((f64::from(step[i]) * self.res * 0.5) as f32);
                t_max[i] = (border - f64::from(origin[i])) / f64::from(direction[i]);
                t_delta[i] = self.res / f64::from(direction[i]).abs();
            }
        }
        loop {
            let dim = if t_max[0] < t_max[1] {
                if t_max[0] < t_max[2] {
                    0
                } else {
                    2
                }
            } else if t_max[1] < t_max[2] {
                1
            } else {
                2
            };
            cur[dim] += step[dim];
            t_max[dim] += t_delta[dim];
            let key = VoxelKey::new(cur[0], cur[1], cur[2]);
            if key == ke {
                break;
            }
            let dist = t_max[0].min(t_max[1]).min(t_max[2]);
            if dist > f64::from(length) {
                break;
            }
            ray.push(key);
        }
        ray
    }

    fn insert(&mut self, origin: &Point3<f64>, pts: &[Point3<f32>], roi: &[bool], max_range: f64) {
        self.insert_with(origin, pts, roi, max_range, false);
    }

    /// As [`Reference::insert`], the points beyond the range freeing one ray per end voxel, to
    /// its centre.
    fn insert_merging_far_rays(
        &mut self,
        origin: &Point3<f64>,
        pts: &[Point3<f32>],
        roi: &[bool],
        max_range: f64,
    ) {
        self.insert_with(origin, pts, roi, max_range, true);
    }

    fn insert_with(
        &mut self,
        origin: &Point3<f64>,
        pts: &[Point3<f32>],
        roi: &[bool],
        max_range: f64,
        merge_far_rays: bool,
    ) {
        let c = MapConfig::default();
        let mut far_ends = BTreeSet::new();
        let o: P3 = [origin.x as f32, origin.y as f32, origin.z as f32];
        let mut free = BTreeSet::new();
        let mut occ = BTreeSet::new();
        let mut roi_set = BTreeSet::new();
        let mut non_roi = BTreeSet::new();
        for (p, &r) in pts.iter().zip(roi) {
            if !p.iter().all(|c| c.is_finite()) {
                continue;
            }
            let p: P3 = [p.x, p.y, p.z];
            let d = norm(sub(p, o));
            if max_range < 0.0 || d <= max_range {
                free.extend(self.ray_keys(o, p));
                occ.insert(self.key(p));
                if r {
                    roi_set.insert(self.key(p));
                } else {
                    non_roi.insert(self.key(p));
                }
            } else {
                let mut dir = sub(p, o);
                for v in &mut dir {
                    *v /= d as f32;
                }
                let m = max_range as f32;
                let mut end = [o[0] + dir[0] * m, o[1] + dir[1] * m, o[2] + dir[2] * m];
                if merge_far_rays {
                    let key = self.key(end);
                    if !far_ends.insert(key) {
                        continue;
                    }
                    end = [key.x, key.y, key.z].map(|k| ((f64::from(k) + 0.5) * self.res) as f32);
                }
                free.extend(self.ray_keys(o, end));
            }
        }
        let upd = |v: f32, d: f32| (v + d).clamp(c.clamp_min_logodds, c.clamp_max_logodds);
        for key in free.difference(&occ) {
            let v = self.cells.entry(*key).or_insert(Voxel::NEW);
            v.occupancy_logodds = upd(v.occupancy_logodds, c.miss_logodds);
        }
        for key in &occ {
            let v = self.cells.entry(*key).or_insert(Voxel::NEW);
            v.occupancy_logodds = upd(v.occupancy_logodds, c.hit_logodds);
        }
        for key in &roi_set {
            let v = self.cells.entry(*key).or_insert(Voxel::NEW);
            v.roi_logodds = upd(v.roi_logodds, c.hit_logodds);
        }
        for key in non_roi.difference(&roi_set) {
            let v = self.cells.entry(*key).or_insert(Voxel::NEW);
            v.roi_logodds = upd(v.roi_logodds, c.miss_logodds);
        }
    }
}

fn random_cloud(rng: &mut TestRng, n: usize) -> (Vec<Point3<f32>>, Vec<bool>) {
    let mut pts = Vec::with_capacity(n);
    let mut roi = Vec::with_capacity(n);
    for i in 0..n {
        // Clustered points so that rays overlap and voxels collide.
        let p = Point3::new(
            rng.uniform(-0.3, 0.3),
            rng.uniform(0.2, 0.5),
            rng.uniform(-0.2, 0.2),
        );
        pts.push(p.cast::<f32>());
        roi.push(i % 3 == 0 || rng.uniform(0.0, 1.0) < 0.2);
    }
    // Some axis-aligned and degenerate rays too.
    pts.push(p32(0.0, 0.3, 0.0));
    roi.push(false);
    pts.push(p32(0.3, 0.0, 0.0));
    roi.push(true);
    (pts, roi)
}

#[test]
fn matches_brute_force_reference() {
    let mut rng = TestRng(42);
    let mut m = map();
    let mut reference = Reference::new(0.01);
    for scan in 0..4 {
        let origin = Point3::new(
            rng.uniform(-0.05, 0.05),
            rng.uniform(-0.05, 0.05),
            rng.uniform(-0.05, 0.05),
        );
        let (pts, roi) = random_cloud(&mut rng, 800);
        m.insert_scan(&origin, &pts, &roi).expect("valid scan");
        reference.insert(&origin, &pts, &roi, -1.0);
        let got: BTreeMap<VoxelKey, Voxel> = m.iter().collect();
        assert_eq!(got.len(), reference.cells.len(), "scan {scan}");
        assert!(got == reference.cells, "scan {scan} differs");
    }
    // A scan whose extent is too large for the dense key box takes the hash-set path.
    let origin = Point3::new(0.013, -0.021, 0.007);
    let far: Vec<Point3<f32>> = (0..60)
        .map(|_| {
            p32(
                rng.uniform(-3.0, 3.0),
                rng.uniform(-3.0, 3.0),
                rng.uniform(-3.0, 3.0),
            )
        })
        .collect();
    let far_roi: Vec<bool> = (0..far.len()).map(|i| i % 2 == 0).collect();
    m.insert_scan(&origin, &far, &far_roi).expect("valid scan");
    reference.insert(&origin, &far, &far_roi, -1.0);
    let got: BTreeMap<VoxelKey, Voxel> = m.iter().collect();
    assert!(got == reference.cells, "sparse path differs");

    // Same with a range limit.
    let config = MapConfig {
        max_range_m: Some(0.35),
        ..MapConfig::default()
    };
    let mut m = RoiMap::new(config).expect("valid config");
    let mut reference = Reference::new(0.01);
    let origin = Point3::new(0.001, -0.003, 0.002);
    let (pts, roi) = random_cloud(&mut rng, 800);
    let stats = m.insert_scan(&origin, &pts, &roi).expect("valid scan");
    assert!(stats.beyond_range > 0);
    reference.insert(&origin, &pts, &roi, 0.35);
    let got: BTreeMap<VoxelKey, Voxel> = m.iter().collect();
    assert!(got == reference.cells);
}

/// Independent geometric check: each ray voxel is touched by the segment, consecutive voxels are
/// face neighbours, and the walk starts at the origin voxel.
#[test]
fn ray_voxels_lie_on_the_segment_and_are_face_connected() {
    let mut rng = TestRng(7);
    let m = map();
    let res = 0.01;
    for _ in 0..300 {
        let origin = Point3::new(
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.1, 0.1),
        );
        let dir = Vector3::new(
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        );
        let range = rng.uniform(0.0, 0.4);
        let mut keys = Vec::new();
        m.walk_ray(&origin, &dir, range, |k, v| {
            assert!(v.is_none());
            keys.push(k);
            true
        });
        assert_eq!(keys[0], m.key_of(&origin));
        let end = origin + dir.normalize() * range;
        assert_eq!(*keys.last().expect("non-empty"), m.key_of(&end));
        for w in keys.windows(2) {
            let d = (w[1].x - w[0].x).abs() + (w[1].y - w[0].y).abs() + (w[1].z - w[0].z).abs();
            assert_eq!(d, 1, "face-connected");
        }
        for key in &keys[..keys.len() - 1] {
            // Slab test of the segment against the voxel cube, with a little slack.
            let lo = m.centre_of(*key) - Vector3::repeat(res / 2.0 + 1e-9);
            let hi = m.centre_of(*key) + Vector3::repeat(res / 2.0 + 1e-9);
            let (mut t0, mut t1) = (0.0f64, 1.0f64);
            for i in 0..3 {
                let o = origin[i];
                let d = end[i] - origin[i];
                if d.abs() < 1e-15 {
                    assert!(o >= lo[i] && o <= hi[i]);
                } else {
                    let (a, b) = ((lo[i] - o) / d, (hi[i] - o) / d);
                    t0 = t0.max(a.min(b));
                    t1 = t1.min(a.max(b));
                }
            }
            assert!(t0 <= t1, "voxel {key:?} not on segment");
        }
    }
}

#[test]
fn walk_segment_visits_the_same_voxels_as_insertion() {
    let mut rng = TestRng(99);
    for _ in 0..50 {
        let origin = Point3::new(
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.1, 0.1),
        );
        let target = Point3::new(
            rng.uniform(-0.5, 0.5),
            rng.uniform(-0.5, 0.5),
            rng.uniform(-0.5, 0.5),
        );
        // Insert in f64 precision terms: use a point exactly representable in f32.
        let target32: Point3<f32> = target.cast();
        let target: Point3<f64> = target32.cast();
        let mut m = map();
        m.insert_scan(&origin, &[target32], &[false])
            .expect("valid scan");
        let mut walked = Vec::new();
        m.walk_segment(&origin.cast::<f32>(), &target32, |k, _| {
            walked.push(k);
            true
        });
        let end_key = m.key_of(&target);
        assert_eq!(walked.last(), Some(&end_key));
        let mut free: Vec<VoxelKey> = m
            .iter()
            .filter(|(_, v)| v.occupancy() == Occupancy::Free)
            .map(|(k, _)| k)
            .collect();
        free.sort();
        let mut walked_free: Vec<VoxelKey> = walked[..walked.len() - 1].to_vec();
        walked_free.sort();
        assert_eq!(free, walked_free);
    }
    // Early stop.
    let m = map();
    let mut n = 0;
    m.walk_ray(
        &Point3::new(0.005, 0.005, 0.005),
        &Vector3::x(),
        1.0,
        |_, _| {
            n += 1;
            n < 3
        },
    );
    assert_eq!(n, 3);
}

fn set(m: &mut RoiMap, keys: &[VoxelKey], occupancy: f32, roi: f32) {
    let v = Voxel {
        occupancy_logodds: occupancy,
        roi_logodds: roi,
    };
    let entries: Vec<(VoxelKey, Voxel)> = keys.iter().map(|&k| (k, v)).collect();
    m.apply_voxels(&entries);
}

fn cube(lo: VoxelKey, hi: VoxelKey) -> Vec<VoxelKey> {
    let mut out = Vec::new();
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                out.push(k(x, y, z));
            }
        }
    }
    out
}

#[test]
fn clusters_of_two_separated_blobs() {
    let mut m = map();
    let a = cube(k(0, 0, 0), k(2, 2, 2));
    let b = cube(k(10, 0, 0), k(11, 1, 1));
    set(&mut m, &a, 2.0, 2.0);
    set(&mut m, &b, 2.0, 2.0);
    // A diagonal-only neighbour joins blob a (26-neighbourhood).
    set(&mut m, &[k(3, 3, 3)], 2.0, 2.0);
    // Occupied but not ROI: not part of any cluster.
    set(&mut m, &[k(5, 0, 0)], 2.0, -1.0);
    let clusters = m.clusters(1);
    assert_eq!(clusters.len(), 2);
    assert_eq!(clusters[0].voxels.len(), 28);
    assert_eq!(clusters[0].voxels[0], k(0, 0, 0));
    assert_eq!(clusters[1].voxels.len(), 8);
    let c1 = &clusters[1];
    assert!((c1.centre - Point3::new(0.11, 0.01, 0.01)).norm() < 1e-9);
    assert!((c1.min - Point3::new(0.10, 0.0, 0.0)).norm() < 1e-9);
    assert!((c1.max - Point3::new(0.12, 0.02, 0.02)).norm() < 1e-9);
    assert!((clusters[0].max - Point3::new(0.04, 0.04, 0.04)).norm() < 1e-9);
    // Minimum size filter.
    let big = m.clusters(10);
    assert_eq!(big.len(), 1);
    assert_eq!(big[0].voxels.len(), 28);
}

#[test]
fn frontiers_on_a_hand_built_map() {
    let mut m = map();
    // A row of free voxels y = 0, x = 0..=4, z = 0; an ROI voxel at (2,1,0) above it in y; an
    // occupied non-ROI voxel at (4,-1,0). Everything else is unknown.
    set(&mut m, &cube(k(0, 0, 0), k(4, 0, 0)), -1.0, 0.0);
    set(&mut m, &[k(2, 1, 0)], 2.0, 2.0);
    set(&mut m, &[k(4, -1, 0)], 2.0, -1.0);
    // (2,0,0) is free, next to the ROI voxel and has unknown neighbours: the only ROI target.
    let everywhere = Aabb::new(Point3::new(-1.0, -1.0, -1.0), Point3::new(1.0, 1.0, 1.0));
    assert_eq!(m.roi_frontier(&everywhere), vec![k(2, 0, 0)]);
    let mut expl = m.exploration_frontier(&everywhere);
    expl.sort();
    assert_eq!(expl, vec![k(2, 0, 0), k(4, 0, 0)]);

    // Region filter: centre of (2,0,0) is (0.025, 0.005, 0.005).
    let left = Aabb::new(Point3::new(-1.0, -1.0, -1.0), Point3::new(0.03, 1.0, 1.0));
    assert_eq!(m.exploration_frontier(&left), vec![k(2, 0, 0)]);
    let none = Aabb::new(Point3::new(0.5, 0.5, 0.5), Point3::new(1.0, 1.0, 1.0));
    assert!(m.roi_frontier(&none).is_empty());

    // Surround (2,0,0) with known voxels: no unknown neighbour, no longer a frontier.
    set(&mut m, &[k(2, -1, 0), k(2, 0, 1), k(2, 0, -1)], -1.0, 0.0);
    assert!(m.roi_frontier(&everywhere).is_empty());
    assert_eq!(m.exploration_frontier(&everywhere), vec![k(4, 0, 0)]);

    // A lone ROI voxel is a target of the paper's map, not of one that needs an ROI neighbour;
    // a second ROI voxel beside it (across a block face) makes both targets. The ROI set is the
    // same either way.
    let mut supported = RoiMap::new(MapConfig {
        roi_target_needs_neighbour: true,
        ..MapConfig::default()
    })
    .expect("valid");
    set(&mut supported, &cube(k(0, 0, 0), k(4, 0, 0)), -1.0, 0.0);
    set(&mut supported, &[k(2, 1, 0)], 2.0, 2.0);
    assert!(supported.roi_frontier(&everywhere).is_empty());
    assert_eq!(supported.roi_keys(), vec![k(2, 1, 0)]);
    set(&mut supported, &[k(2, 1, -1)], 2.0, 2.0);
    assert_eq!(supported.roi_frontier(&everywhere), vec![k(2, 0, 0)]);
    // The neighbour stops being ROI: the lone voxel is no target again.
    set(&mut supported, &[k(2, 1, -1)], 2.0, -1.0);
    assert!(supported.roi_frontier(&everywhere).is_empty());

    // A voxel with one miss counts as free (documented rule).
    let mut m2 = map();
    set(&mut m2, &[k(0, 0, 0)], MISS, 0.0);
    set(&mut m2, &[k(1, 0, 0)], HIT, HIT + HIT);
    assert_eq!(m2.occupancy(k(0, 0, 0)), Occupancy::Free);
    assert_eq!(m2.roi_frontier(&everywhere), vec![k(0, 0, 0)]);
}

#[test]
fn memory_and_debug_are_cheap() {
    let mut m = map();
    let origin = Point3::new(0.0, 0.0, 0.0);
    let mut rng = TestRng(1);
    let (pts, roi) = random_cloud(&mut rng, 200);
    m.insert_scan(&origin, &pts, &roi).expect("valid scan");
    assert!(m.memory_bytes() >= m.len() * std::mem::size_of::<(VoxelKey, Voxel)>());
    let dbg = format!("{m:?}");
    assert!(dbg.len() < 400, "no voxels in Debug: {dbg}");
}

// ---------------------------------------------------------------------------------------------
// Properties and the incremental state, on seeded random scans.

use crate::testdata::{downsample, Workload};

/// Seeded Fisher-Yates shuffle of points and labels together.
fn shuffled(rng: &mut TestRng, pts: &[Point3<f32>], roi: &[bool]) -> (Vec<Point3<f32>>, Vec<bool>) {
    let mut idx: Vec<usize> = (0..pts.len()).collect();
    for i in (1..idx.len()).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        idx.swap(i, j);
    }
    (
        idx.iter().map(|&i| pts[i]).collect(),
        idx.iter().map(|&i| roi[i]).collect(),
    )
}

fn sorted_voxels(m: &RoiMap) -> Vec<(VoxelKey, Voxel)> {
    let mut v: Vec<_> = m.iter().collect();
    v.sort_by_key(|(k, _)| *k);
    v
}

#[test]
fn order_within_a_scan_does_not_matter() {
    let mut rng = TestRng(5);
    for _ in 0..5 {
        let (pts, roi) = random_cloud(&mut rng, 500);
        let (pts2, roi2) = shuffled(&mut rng, &pts, &roi);
        let origin = Point3::new(0.01, -0.02, 0.003);
        let mut a = map();
        let mut b = map();
        let sa = a.insert_scan(&origin, &pts, &roi).expect("valid");
        let sb = b.insert_scan(&origin, &pts2, &roi2).expect("valid");
        assert_eq!(sa, sb);
        assert_eq!(sorted_voxels(&a), sorted_voxels(&b));
    }
}

#[test]
fn end_voxels_are_never_freed_by_their_own_scan() {
    let mut rng = TestRng(11);
    let (pts, roi) = random_cloud(&mut rng, 400);
    let mut m = map();
    let origin = Point3::new(0.0, 0.0, 0.0);
    m.insert_scan(&origin, &pts, &roi).expect("valid");
    for p in &pts {
        let k = m.key_of(&p.cast());
        // One hit, never a miss in the same scan.
        assert_eq!(m.get(k).map(|v| v.occupancy_logodds), Some(HIT));
    }
}

#[test]
fn clamps_hold_for_random_scan_sequences() {
    let mut rng = TestRng(3);
    let mut m = map();
    let c = MapConfig::default();
    for _ in 0..12 {
        let (pts, roi) = random_cloud(&mut rng, 150);
        m.insert_scan(&Point3::new(0.0, 0.0, 0.0), &pts, &roi)
            .expect("valid");
    }
    let mut at_max = 0;
    for (_, v) in m.iter() {
        assert!(v.occupancy_logodds >= c.clamp_min_logodds);
        assert!(v.occupancy_logodds <= c.clamp_max_logodds);
        assert!(v.roi_logodds >= c.clamp_min_logodds && v.roi_logodds <= c.clamp_max_logodds);
        at_max += usize::from(v.occupancy_logodds == c.clamp_max_logodds);
    }
    // The axis-aligned end points are hit every scan: clamped at the top.
    assert!(at_max >= 2);
    assert_eq!(
        m.occupancy_logodds(m.key_of(&Point3::new(0.0, 0.3, 0.0))),
        Some(c.clamp_max_logodds)
    );
}

#[test]
fn threads_give_the_same_map() {
    let w = Workload::small(21, 96, 72, 8, 3);
    let mut one = RoiMap::new(w.map_config()).expect("valid");
    let mut four = RoiMap::new(w.map_config()).expect("valid");
    for s in w.raw_scans() {
        let a = one
            .insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid");
        let b = four
            .insert_scan_threaded(&s.origin, &s.points, &s.roi, 4)
            .expect("valid");
        assert_eq!(a, b);
    }
    assert_eq!(sorted_voxels(&one), sorted_voxels(&four));
}

#[test]
fn workload_scans_match_the_reference_with_range_limit() {
    let w = Workload::small(8, 80, 60, 10, 2);
    let mut m = RoiMap::new(w.map_config()).expect("valid");
    let mut reference = Reference::new(0.01);
    for s in w.raw_scans() {
        let stats = m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        assert!(stats.beyond_range > 0, "corner rays pass the range");
        reference.insert(&s.origin, &s.points, &s.roi, w.max_range_m);
    }
    let got: BTreeMap<VoxelKey, Voxel> = m.iter().collect();
    assert_eq!(got.len(), reference.cells.len());
    assert!(got == reference.cells);
}

#[test]
fn merged_far_rays_match_the_reference() {
    let w = Workload::small(9, 320, 240, 10, 2);
    let config = MapConfig {
        merge_far_rays: true,
        ..w.map_config()
    };
    let mut m = RoiMap::new(config).expect("valid");
    let mut threaded = RoiMap::new(config).expect("valid");
    let mut reference = Reference::new(0.01);
    for s in w.raw_scans() {
        let stats = m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        assert!(stats.beyond_range > 0, "corner rays pass the range");
        assert!(stats.rays < s.points.len(), "{} rays", stats.rays);
        reference.insert_merging_far_rays(&s.origin, &s.points, &s.roi, w.max_range_m);
        let threaded_stats = threaded
            .insert_scan_threaded(&s.origin, &s.points, &s.roi, 3)
            .expect("valid");
        assert_eq!(stats, threaded_stats);
    }
    let got: BTreeMap<VoxelKey, Voxel> = m.iter().collect();
    assert_eq!(got.len(), reference.cells.len());
    assert!(got == reference.cells);
    assert_eq!(sorted_voxels(&m), sorted_voxels(&threaded));
}

#[test]
fn merged_far_rays_leave_the_hits_alone() {
    let w = Workload::small(10, 320, 240, 10, 1);
    let scan = &w.raw_scans()[0];
    let mut config = w.map_config();
    let mut per_point = RoiMap::new(config).expect("valid");
    let one_each = per_point
        .insert_scan(&scan.origin, &scan.points, &scan.roi)
        .expect("valid");
    config.merge_far_rays = true;
    let mut merged = RoiMap::new(config).expect("valid");
    let one_per_voxel = merged
        .insert_scan(&scan.origin, &scan.points, &scan.roi)
        .expect("valid");
    assert_eq!(one_per_voxel.occupied_updates, one_each.occupied_updates);
    assert_eq!(one_per_voxel.roi_updates, one_each.roi_updates);
    assert_eq!(one_per_voxel.non_roi_updates, one_each.non_roi_updates);
    assert_eq!(one_per_voxel.beyond_range, one_each.beyond_range);
    let usable = scan.points.len() - one_each.skipped_non_finite;
    assert_eq!(one_each.rays, usable);
    assert!(one_per_voxel.rays < one_each.rays);
    // The merged rays free nearly the voxels the per-point rays do.
    let free = |m: &RoiMap| -> BTreeSet<VoxelKey> {
        m.iter()
            .filter(|(_, v)| v.occupancy_logodds < 0.0)
            .map(|(k, _)| k)
            .collect()
    };
    let (all, some) = (free(&per_point), free(&merged));
    let shared = all.intersection(&some).count();
    eprintln!(
        "free voxels: per point {}, merged {}, shared {shared}",
        all.len(),
        some.len()
    );
    assert!(shared as f64 >= 0.97 * all.len() as f64);
    assert!(some.len() <= all.len());
}

/// Brute-force frontier definitions (paper-method §3), over all known voxels; ROI targets are
/// the ROI voxels, with an ROI face neighbour when the configuration asks for one.
fn brute_frontiers(m: &RoiMap) -> (Vec<VoxelKey>, Vec<VoxelKey>) {
    let needs_neighbour = m.config().roi_target_needs_neighbour;
    let is_target = |x: VoxelKey| {
        m.is_roi(x) && (!needs_neighbour || x.neighbours(Neighbourhood::Six).any(|y| m.is_roi(y)))
    };
    let mut expl = Vec::new();
    let mut roi = Vec::new();
    for (k, v) in m.iter() {
        if v.occupancy() != Occupancy::Free {
            continue;
        }
        let n: Vec<VoxelKey> = k.neighbours(Neighbourhood::Six).collect();
        let unknown = n.iter().any(|&x| m.occupancy(x) == Occupancy::Unknown);
        if !unknown {
            continue;
        }
        if n.iter().any(|&x| m.occupancy(x) == Occupancy::Occupied) {
            expl.push(k);
        }
        if n.iter().any(|&x| is_target(x)) {
            roi.push(k);
        }
    }
    expl.sort();
    roi.sort();
    (expl, roi)
}

#[test]
fn incremental_frontiers_roi_set_and_counts_match_recomputation() {
    let w = Workload::small(33, 96, 72, 12, 4);
    check_incremental_state(&w, w.map_config());
}

#[test]
fn incremental_frontiers_match_recomputation_with_lone_roi_voxels_untargeted() {
    let w = Workload::small(34, 96, 72, 12, 4);
    let config = MapConfig {
        roi_miss_logodds: -0.8473,
        roi_target_needs_neighbour: true,
        merge_far_rays: true,
        ..w.map_config()
    };
    check_incremental_state(&w, config);
}

fn check_incremental_state(w: &Workload, config: MapConfig) {
    let mut m = RoiMap::new(config).expect("valid");
    let everywhere = Aabb::new(Point3::new(-9.0, -9.0, -9.0), Point3::new(9.0, 9.0, 9.0));
    for (i, s) in w.filtered_scans().iter().enumerate() {
        m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        let (expl, roi) = brute_frontiers(&m);
        assert!(!expl.is_empty());
        assert_eq!(m.exploration_frontier(&everywhere), expl, "scan {i}");
        assert_eq!(m.roi_frontier(&everywhere), roi, "scan {i}");
        let mut brute_roi: Vec<VoxelKey> = m
            .iter()
            .filter(|(_, v)| v.roi_logodds >= 1.0)
            .map(|(k, _)| k)
            .collect();
        brute_roi.sort();
        assert_eq!(m.roi_keys(), brute_roi);
        if i >= 1 {
            assert!(!brute_roi.is_empty(), "two observations make ROI voxels");
            assert!(!roi.is_empty(), "scan {i}: ROI targets");
        }
        let c = m.counts();
        assert_eq!(c.known, m.iter().count());
        assert_eq!(
            c.occupied,
            m.iter().filter(|(_, v)| v.occupancy_logodds > 0.0).count()
        );
        assert_eq!(c.exploration_frontier, expl.len());
        assert_eq!(c.roi_frontier, roi.len());
        assert_eq!(c.roi, brute_roi.len());
    }
    // ROI voxels that stop being ROI leave the set and the frontier (via apply_voxels).
    let roi_now = m.roi_keys();
    let cleared: Vec<(VoxelKey, Voxel)> = roi_now
        .iter()
        .take(roi_now.len() / 2)
        .map(|&k| {
            (
                k,
                Voxel {
                    occupancy_logodds: 1.0,
                    roi_logodds: -1.0,
                },
            )
        })
        .collect();
    m.apply_voxels(&cleared);
    let (expl, roi) = brute_frontiers(&m);
    assert_eq!(m.exploration_frontier(&everywhere), expl);
    assert_eq!(m.roi_frontier(&everywhere), roi);
    assert_eq!(m.roi_keys().len(), roi_now.len() - cleared.len());
}

#[test]
fn snapshot_keeps_the_rules_and_the_roi_frontier() {
    let w = Workload::small(6, 64, 48, 4, 2);
    let config = MapConfig {
        roi_miss_logodds: -0.8473,
        roi_target_needs_neighbour: true,
        ..w.map_config()
    };
    let mut m = RoiMap::new(config).expect("valid");
    for s in w.filtered_scans() {
        m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
    }
    let mut bytes = Vec::new();
    m.write_snapshot(&mut bytes).expect("write");
    let back = RoiMap::read_snapshot(bytes.as_slice()).expect("read");
    assert_eq!(back.config(), m.config());
    let everywhere = Aabb::new(Point3::new(-9.0, -9.0, -9.0), Point3::new(9.0, 9.0, 9.0));
    let targets = m.roi_frontier(&everywhere);
    assert!(!targets.is_empty());
    assert_eq!(back.roi_frontier(&everywhere), targets);
    assert_eq!(brute_frontiers(&back).1, targets);
}

#[test]
fn snapshot_round_trip_and_errors() {
    let w = Workload::small(4, 64, 48, 6, 3);
    let m = w.filtered_map().expect("valid");
    let mut bytes = Vec::new();
    m.write_snapshot(&mut bytes).expect("write");
    // Compact: about 8 bytes per known voxel plus per-block overhead.
    assert!(bytes.len() < m.len() * 8 + m.counts().blocks * 80 + 200);
    let back = RoiMap::read_snapshot(bytes.as_slice()).expect("read");
    assert_eq!(back.config(), m.config());
    assert_same_map(&back, &m);

    // Truncated anywhere: a clear error.
    for cut in [0, 3, 10, 16, bytes.len() / 2, bytes.len() - 1] {
        match RoiMap::read_snapshot(&bytes[..cut]) {
            Err(SnapshotError::Truncated { expected, actual }) => {
                assert_eq!(actual, cut as u64);
                assert!(expected > actual);
            }
            Err(SnapshotError::BadMagic) if cut == 0 => {}
            other => panic!("cut at {cut}: {other:?}"),
        }
    }
    // A flipped bit in the body: checksum mismatch.
    let mut bad = bytes.clone();
    let at = bad.len() / 3;
    bad[at] ^= 0x10;
    assert!(matches!(
        RoiMap::read_snapshot(bad.as_slice()),
        Err(SnapshotError::ChecksumMismatch { .. })
    ));
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(matches!(
        RoiMap::read_snapshot(bad.as_slice()),
        Err(SnapshotError::BadMagic)
    ));
    let mut bad = bytes.clone();
    bad[4] = 9;
    assert!(matches!(
        RoiMap::read_snapshot(bad.as_slice()),
        Err(SnapshotError::UnsupportedVersion(9))
    ));
    assert_eq!(snapshot::crc32(b"123456789"), 0xCBF4_3926);
}

#[test]
fn ply_cloud_round_trip_and_voxel_export() {
    let w = Workload::small(2, 48, 36, 4, 1);
    let s = w.filtered_scan(&w.origins[0]);
    let mut bytes = Vec::new();
    ply::write_cloud(&mut bytes, &s.points, Some(&Point3::new(0.5, -1.25, 2.0))).expect("write");
    let back = ply::read_cloud(bytes.as_slice()).expect("read");
    assert_eq!(back.points, s.points);
    assert_eq!(back.origin, Some(Point3::new(0.5, -1.25, 2.0)));

    // ASCII with extra properties, another element first and no origin.
    let ascii = "ply\nformat ascii 1.0\ncomment made by hand\nelement camera 1\nproperty float f\n\
                 element vertex 2\nproperty uchar red\nproperty double x\nproperty float y\n\
                 property float z\nproperty int label\nelement face 0\n\
                 property list uchar int vertex_indices\nend_header\n7.5\n\
                 255 1.5 2.5 -3.5 4\n0 0.25 0 1e-2 1\n";
    let back = ply::read_cloud(ascii.as_bytes()).expect("read ascii");
    assert_eq!(back.points, vec![p32(1.5, 2.5, -3.5), p32(0.25, 0.0, 0.01)]);
    assert_eq!(back.origin, None);
    assert!(matches!(
        ply::read_cloud("ply\nformat binary_big_endian 1.0\nend_header\n".as_bytes()),
        Err(ply::PlyError::UnsupportedFormat(_))
    ));
    assert!(matches!(
        ply::read_cloud(&bytes[..bytes.len() - 5]),
        Err(ply::PlyError::Truncated(_))
    ));

    // Voxel export: parse it back with the reader (x, y, z) and check the header names.
    let mut m = map();
    m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
    let mut out = Vec::new();
    m.write_ply(&mut out).expect("write");
    let text_end = out
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("header");
    let header = std::str::from_utf8(&out[..text_end]).expect("ascii header");
    for prop in [
        "float x",
        "float y",
        "float z",
        "float occupancy",
        "float roi",
    ] {
        assert!(header.contains(&format!("property {prop}\n")), "{prop}");
    }
    assert_eq!(out.len() - text_end - 11, m.len() * 20);
    let centres = ply::read_cloud(out.as_slice()).expect("readable");
    assert_eq!(centres.points.len(), m.len());
    let first = sorted_voxels(&m)[0].0;
    assert_eq!(centres.points[0], m.centre_of(first).cast::<f32>());
}

#[test]
fn neighbourhoods_and_filtered_workload() {
    assert_eq!(NEIGHBOURS_18.len(), 18);
    assert_eq!(NEIGHBOURS_26.len(), 26);
    let all: BTreeSet<(i32, i32, i32)> = NEIGHBOURS_26.iter().copied().collect();
    assert_eq!(all.len(), 26);
    assert!(!all.contains(&(0, 0, 0)));
    for o in NEIGHBOURS_6 {
        assert!(NEIGHBOURS_18.contains(&o));
    }
    assert!(NEIGHBOURS_18
        .iter()
        .all(|&(x, y, z)| x.abs() + y.abs() + z.abs() <= 2));

    let w = Workload::small(6, 64, 48, 6, 2);
    let m = w.filtered_map().expect("valid");
    // Downsampling keeps one point per voxel.
    let raw = w.raw_scan(&w.origins[0]);
    let f = downsample(&raw, 0.01);
    let keys: BTreeSet<VoxelKey> = f.points.iter().map(|p| m.key_of(&p.cast())).collect();
    assert!(f.points.len() < raw.points.len());
    assert!(
        keys.len() + 5 >= f.points.len(),
        "averaged points stay in (or next to) their voxel"
    );
}

#[test]
fn standard_workload_has_the_documented_size() {
    let w = Workload::standard(1);
    assert_eq!(w.spheres.len(), 30);
    assert_eq!(w.origins.len(), 10);
    for s in &w.spheres {
        assert!((0.03..0.05).contains(&s.radius_m));
        assert!((0.4..1.2).contains(&s.centre.x));
    }
    let raw = w.raw_scan(&w.origins[0]);
    assert_eq!(raw.points.len(), 640 * 480);
    assert!(raw.roi.iter().any(|&r| r));
    let f = downsample(&raw, 0.01);
    assert!(
        (15_000..30_000).contains(&f.points.len()),
        "{}",
        f.points.len()
    );
}

fn voxel_bits(entries: impl Iterator<Item = (VoxelKey, Voxel)>) -> Vec<(VoxelKey, u32, u32)> {
    let mut v: Vec<_> = entries
        .map(|(k, x)| (k, x.occupancy_logodds.to_bits(), x.roi_logodds.to_bits()))
        .collect();
    v.sort_unstable_by_key(|e| e.0);
    v
}

/// Checks the map against the plain reference, value bits included, through `iter` and `get`.
fn assert_matches_reference(m: &RoiMap, reference: &Reference, what: &str) {
    let want = voxel_bits(reference.cells.iter().map(|(k, v)| (*k, *v)));
    assert_eq!(voxel_bits(m.iter()), want, "{what}: iter");
    let got = voxel_bits(
        reference
            .cells
            .keys()
            .filter_map(|&k| m.get(k).map(|v| (k, v))),
    );
    assert_eq!(got, want, "{what}: get");
    for &(k, _, _) in want.iter().step_by(7) {
        let beside = k.offset(0, 0, 1);
        if !reference.cells.contains_key(&beside) {
            assert_eq!(m.get(beside), None, "{what}: unknown voxel");
        }
    }
}

/// The compact storage (one value per block, palettes of exact values, flat blocks) reads back
/// exactly the values of a plain per-voxel reference, over seeded random scans with NaN and
/// infinite points, points beyond the maximum range and origins hundreds of metres from the
/// map's origin; a snapshot restores the same bits.
#[test]
fn compact_layout_reads_back_the_plain_reference() {
    for seed in 0..6u64 {
        let mut rng = TestRng(1000 + seed);
        let range = if seed % 2 == 0 { 0.3 } else { -1.0 };
        let config = MapConfig {
            max_range_m: (range > 0.0).then_some(range),
            ..MapConfig::default()
        };
        let mut m = RoiMap::new(config).expect("valid");
        let mut reference = Reference::new(0.01);
        let base = Vector3::new(
            rng.uniform(-400.0, 400.0),
            rng.uniform(-400.0, 400.0),
            rng.uniform(-50.0, 50.0),
        );
        for scan in 0..14 {
            let origin = Point3::new(
                rng.uniform(-0.05, 0.05),
                rng.uniform(-0.05, 0.05),
                rng.uniform(-0.05, 0.05),
            ) + base;
            let (mut pts, mut roi) = random_cloud(&mut rng, 300);
            for p in &mut pts {
                *p = (p.cast::<f64>() + base).cast::<f32>();
            }
            for bad in [
                p32(f64::NAN, 0.0, 0.0),
                p32(base.x, f64::INFINITY, base.z),
                p32(base.x, base.y, f64::NEG_INFINITY),
            ] {
                pts.push(bad);
                roi.push(scan % 2 == 0);
            }
            let stats = m.insert_scan(&origin, &pts, &roi).expect("valid scan");
            assert_eq!(stats.skipped_non_finite, 3);
            reference.insert(&origin, &pts, &roi, range);
            assert_matches_reference(&m, &reference, &format!("seed {seed} scan {scan}"));
        }
        // More distinct values in one block than a palette holds: the block turns flat and
        // later scans still update it exactly.
        let origin = Point3::from(base);
        let ko = m.key_of(&origin);
        let corner = VoxelKey::new(ko.x & !7, ko.y & !7, ko.z & !7);
        let direct: Vec<(VoxelKey, Voxel)> = (0..300)
            .map(|i| {
                let key = corner.offset(i % 8, (i / 8) % 8, i / 64);
                let v = Voxel {
                    occupancy_logodds: -1.9 + i as f32 * 0.0123,
                    roi_logodds: 0.001 * i as f32,
                };
                (key, v)
            })
            .collect();
        m.apply_voxels(&direct);
        reference.cells.extend(direct.iter().copied());
        let (pts, roi) = random_cloud(&mut rng, 300);
        let pts: Vec<Point3<f32>> = pts
            .iter()
            .map(|p| (p.cast::<f64>() + base).cast())
            .collect();
        m.insert_scan(&origin, &pts, &roi).expect("valid scan");
        reference.insert(&origin, &pts, &roi, range);
        assert_matches_reference(&m, &reference, &format!("seed {seed} flat block"));

        let mut bytes = Vec::new();
        m.write_snapshot(&mut bytes).expect("write");
        let back = RoiMap::read_snapshot(bytes.as_slice()).expect("read");
        assert_matches_reference(&back, &reference, &format!("seed {seed} snapshot"));
        assert_eq!(back.counts(), m.counts());
        assert_eq!(back.roi_keys(), m.roi_keys());
    }
}

type RayTrace = Vec<(VoxelKey, Option<(u32, u32)>)>;

fn voxel_value_bits(v: Option<Voxel>) -> Option<(u32, u32)> {
    v.map(|v| (v.occupancy_logodds.to_bits(), v.roi_logodds.to_bits()))
}

/// Per ray, what `walk_ray` visits; `stop_at_occupied` ends a ray at its first occupied voxel.
fn traces_one_by_one(
    m: &RoiMap,
    origin: &Point3<f64>,
    dirs: &[Vector3<f64>],
    range: f64,
    stop_at_occupied: bool,
) -> Vec<RayTrace> {
    dirs.iter()
        .map(|d| {
            let mut trace = Vec::new();
            m.walk_ray(origin, d, range, |k, v| {
                trace.push((k, voxel_value_bits(v)));
                !(stop_at_occupied && v.is_some_and(|v| v.occupancy_logodds > 0.0))
            });
            trace
        })
        .collect()
}

/// The batch walk gives every ray exactly what `walk_ray` gives it (keys, values, order within
/// the ray, early exit), and the unknown counts equal counting ray by ray; on seeded maps with
/// seeded fans, degenerate directions, zero range and fewer rays than lanes.
#[test]
fn batch_walk_equals_walking_each_ray_alone() {
    for seed in 1..=3u64 {
        let w = testdata::Workload::small(seed, 160, 120, 10, 3);
        let m = w.filtered_map().expect("valid scans");
        assert!(m.counts().occupied > 0);
        let mut rng = TestRng(seed);
        let (view, target) = w.gain_view();
        let mut dirs = testdata::ray_fan(&view, &target, 40, 30, 1.0, 0.8);
        for _ in 0..200 {
            dirs.push(Vector3::new(
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            ));
        }
        dirs.push(Vector3::zeros());
        dirs.push(Vector3::new(f64::NAN, 0.0, 1.0));
        dirs.push(Vector3::new(1.0, 0.0, 0.0));
        let origins = [view, Point3::new(0.0, 0.0, 0.0), w.origins[0]];
        for (origin, range) in origins.iter().zip([1.5, 0.0, 0.4]) {
            for n in [dirs.len(), 3, 0] {
                let dirs = &dirs[..n];
                for stop in [true, false] {
                    let expected = traces_one_by_one(&m, origin, dirs, range, stop);
                    let mut got = vec![RayTrace::new(); dirs.len()];
                    m.walk_rays_from(origin, dirs, range, |ray, k, v| {
                        got[ray].push((k, voxel_value_bits(v)));
                        !(stop && v.is_some_and(|v| v.occupancy_logodds > 0.0))
                    });
                    assert_eq!(got, expected, "seed {seed}, range {range}, {n} rays");
                }
                let counts = m.count_unknown_until_occupied(origin, dirs, range);
                let expected: Vec<RayCount> = traces_one_by_one(&m, origin, dirs, range, true)
                    .iter()
                    .map(|t| RayCount {
                        visited: t.len() as u32,
                        unknown: t.iter().filter(|(_, v)| v.is_none()).count() as u32,
                    })
                    .collect();
                assert_eq!(counts, expected, "seed {seed}, range {range}, {n} rays");
                assert_eq!(
                    testdata::unobserved_gain(&m, origin, dirs, range).to_bits(),
                    testdata::unobserved_gain_batch(&m, origin, dirs, range).to_bits()
                );
            }
        }
    }
}

#[test]
fn changed_since_sees_the_boxes_a_scan_touched_and_only_near_them() {
    let mut m = map();
    let origin = Point3::new(0.001, 0.001, 0.001);
    m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
        .expect("valid scan");
    let before = m.scans_inserted();
    let near_ray = (Point3::new(0.05, 0.0, 0.0), Point3::new(0.06, 0.01, 0.01));
    let far = (Point3::new(1.0, 1.0, 1.0), Point3::new(1.1, 1.1, 1.1));
    assert!(m.changed_since(&near_ray.0, &near_ray.1, 0));
    assert!(!m.changed_since(&near_ray.0, &near_ray.1, before));
    // The same ray again changes its voxels' log-odds: the box near it changed, the far one not.
    m.insert_scan(&origin, &[p32(0.105, 0.005, 0.005)], &[false])
        .expect("valid scan");
    assert!(m.changed_since(&near_ray.0, &near_ray.1, before));
    assert!(!m.changed_since(&far.0, &far.1, before));
    // A scan into the far box changes it.
    let far_origin = Point3::new(1.001, 1.001, 1.001);
    m.insert_scan(&far_origin, &[p32(1.05, 1.05, 1.05)], &[false])
        .expect("valid scan");
    assert!(m.changed_since(&far.0, &far.1, before + 1));
}

#[test]
fn evidence_of_the_labels_hit_and_miss_gives_the_labelled_map() {
    let w = Workload::small(31, 96, 72, 6, 2);
    let c = w.map_config();
    let mut labelled = RoiMap::new(c).expect("valid");
    let mut evidence = RoiMap::new(c).expect("valid");
    for s in w.raw_scans() {
        let deltas: Vec<f32> = s
            .roi
            .iter()
            .map(|&r| {
                if r {
                    c.roi_hit_logodds
                } else {
                    c.roi_miss_logodds
                }
            })
            .collect();
        let a = labelled
            .insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid");
        let b = evidence
            .insert_scan_evidence(&s.origin, &s.points, &deltas, 2)
            .expect("valid");
        assert_eq!(a, b);
    }
    assert_eq!(sorted_voxels(&labelled), sorted_voxels(&evidence));
    assert_eq!(labelled.roi_keys(), evidence.roi_keys());
}

#[test]
fn evidence_is_added_per_voxel_the_largest_delta_winning() {
    let mut m = map();
    let origin = Point3::new(0.0, 0.0, 0.0);
    // Two points in one voxel (0.305 and 0.308 m share key 30), one alone, one without evidence,
    // one with a non-finite delta (no evidence either), one beyond nothing: a plain miss.
    let pts = [
        p32(0.305, 0.0, 0.0),
        p32(0.308, 0.0, 0.0),
        p32(0.0, 0.405, 0.0),
        p32(0.0, 0.0, 0.505),
        p32(0.0, 0.0, -0.505),
        p32(0.0, -0.405, 0.0),
    ];
    let deltas = [0.3, -0.5, 0.6, 0.0, f32::NAN, -0.25];
    let stats = m
        .insert_scan_evidence(&origin, &pts, &deltas, 1)
        .expect("valid");
    assert_eq!((stats.roi_updates, stats.non_roi_updates), (2, 1));
    let roi = |p: Point3<f32>| m.roi_logodds(m.key_of(&p.cast()));
    assert_eq!(roi(pts[0]), Some(0.3));
    assert_eq!(roi(pts[2]), Some(0.6));
    assert_eq!(roi(pts[3]), Some(0.0));
    assert_eq!(roi(pts[4]), Some(0.0));
    assert_eq!(roi(pts[5]), Some(-0.25));
    // Occupancy is the labels' path's: every end voxel hit once.
    for p in pts {
        assert_eq!(m.occupancy_logodds(m.key_of(&p.cast())), Some(HIT));
    }
    // Weak evidence adds up to ROI (threshold 1.0) only over scans, and stays clamped.
    for _ in 0..2 {
        m.insert_scan_evidence(&origin, &pts, &deltas, 1)
            .expect("valid");
    }
    assert!(!m.is_roi(m.key_of(&pts[0].cast())));
    assert!(m.is_roi(m.key_of(&pts[2].cast())));
    assert!(matches!(
        m.insert_scan_evidence(&origin, &pts, &deltas[..2], 1),
        Err(MapError::LengthMismatch { points: 6, roi: 2 })
    ));
}

#[test]
fn solid_blocks_are_the_occupied_and_roi_voxels() {
    let w = Workload::small(35, 96, 72, 12, 3);
    let mut m = RoiMap::new(w.map_config()).expect("valid");
    for s in w.filtered_scans() {
        m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
    }
    let mut from_values: Vec<VoxelKey> = m
        .iter()
        .filter(|(key, voxel)| voxel.occupancy() == Occupancy::Occupied || m.is_roi(*key))
        .map(|(key, _)| key)
        .collect();
    from_values.sort_unstable();
    assert!(!m.roi_voxels().is_empty() && from_values.len() > m.roi_voxels().len());
    let mut from_blocks: Vec<VoxelKey> = m
        .solid_blocks()
        .flat_map(|(bk, mask)| {
            let solid = move |l: &usize| mask[l >> 6] >> (l & 63) & 1 != 0;
            (0..512usize).filter(solid).map(move |l| {
                let at = |b: i32, i: usize| b * 8 + i as i32;
                VoxelKey::new(at(bk.x, l & 7), at(bk.y, (l >> 3) & 7), at(bk.z, l >> 6))
            })
        })
        .collect();
    from_blocks.sort_unstable();
    assert_eq!(from_blocks, from_values);
}

// Incremental clusters.

fn same_clusters(clusters: &Clusters, map: &RoiMap, min_voxels: usize, what: &str) {
    let kept: Vec<RoiCluster> = clusters.iter().cloned().collect();
    assert_eq!(kept, map.clusters(min_voxels), "{what}");
}

#[test]
fn incremental_clusters_match_recomputation_over_scans() {
    let w = Workload::small(35, 96, 72, 12, 6);
    let mut m = RoiMap::new(w.map_config()).expect("valid");
    let mut clusters = Clusters::new(3);
    let mut regrown_only_some = false;
    for (i, s) in w.filtered_scans().iter().enumerate() {
        m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        let update = clusters.update(&m);
        assert_eq!(
            update.full,
            i == 0,
            "scan {i}: only the first grows everything"
        );
        regrown_only_some |= update.kept > 0;
        same_clusters(&clusters, &m, 3, &format!("scan {i}"));
    }
    assert!(!clusters.is_empty());
    assert!(regrown_only_some, "later scans keep untouched clusters");
}

#[test]
fn incremental_clusters_follow_merges_splits_and_removals() {
    // ROI voxels switched on and off at random in a thin slab, so clusters merge, split, shrink
    // below the minimum and vanish; one update in five is skipped (a full regrow follows).
    let mut rng = TestRng(36);
    let mut m = map();
    let mut clusters = Clusters::new(2);
    let (roi, free) = (
        Voxel {
            occupancy_logodds: 2.0,
            roi_logodds: 2.0,
        },
        Voxel {
            occupancy_logodds: 2.0,
            roi_logodds: -1.0,
        },
    );
    let (mut full, mut fewer, mut more) = (0, 0, 0);
    for step in 0..300 {
        let edits: Vec<(VoxelKey, Voxel)> = (0..6)
            .map(|_| {
                let mut c = || (rng.next_u64() % 16) as i32 - 8;
                let key = k(c(), c(), (rng.next_u64() % 2) as i32);
                (
                    key,
                    if rng.next_u64().is_multiple_of(2) {
                        free
                    } else {
                        roi
                    },
                )
            })
            .collect();
        m.apply_voxels(&edits);
        if step % 5 == 4 {
            continue;
        }
        let before = clusters.len();
        full += usize::from(clusters.update(&m).full);
        same_clusters(&clusters, &m, 2, &format!("step {step}"));
        fewer += usize::from(clusters.len() < before);
        more += usize::from(clusters.len() > before);
    }
    assert!(
        full > 1 && full < 100,
        "skipped updates regrow everything: {full}"
    );
    assert!(
        fewer > 10 && more > 10,
        "clusters merged or vanished {fewer}, appeared {more}"
    );
}

/// Some rays stop early, as the gain queries do at occupied voxels.
fn stops_early(ray: u32, c: [i32; 3]) -> bool {
    ray.is_multiple_of(3) && (c[0] + c[1] + c[2]).rem_euclid(41) == 0
}

/// Everything a lane walk gives its visitor, in order.
#[derive(Debug, Default, PartialEq)]
struct LaneRecord {
    /// (ray, key, bit index when inside the plane's box).
    visits: Vec<(u32, [i32; 3], Option<i32>)>,
    ends: Vec<(u32, [i32; 3])>,
}

impl walk::LaneVisitor for LaneRecord {
    fn voxel(&mut self, _: usize, ray: u32, c: [i32; 3], index: i32, inside: bool) -> bool {
        self.visits.push((ray, c, inside.then_some(index)));
        !stops_early(ray, c)
    }

    fn end(&mut self, ray: u32, key_end: [i32; 3]) {
        self.ends.push((ray, key_end));
    }
}

/// Insertion's free marks of `rays` on `level`: the plane and the keys outside it.
fn free_marks(
    level: simd::Level,
    rays: &[(u32, walk::RaySetup)],
    g: &walk::PlaneGeometry,
) -> (Vec<u64>, BTreeSet<VoxelKey>) {
    let mut free = vec![0u64; (g.n.iter().map(|&n| n as usize).product::<usize>()).div_ceil(64)];
    let mut overflow = KeySet::default();
    let mut marker = insert::FreeMarker {
        free: &mut free,
        overflow: &mut overflow,
    };
    walk::walk_lanes_at(level, rays.iter().copied(), g, &mut marker);
    (free, overflow.into_iter().collect())
}

/// The lane walk compiled for every vector unit this CPU has gives the visitor exactly the same
/// calls, in the same order, as the portable build, and each ray's voxels are the scalar walk's:
/// seeded rays from near and far-off origins, plane boxes that cut rays off, early stops.
#[test]
fn every_vector_unit_walks_the_same_voxels() {
    use walk::{walk_lanes_at, PlaneGeometry, RaySetup};
    let mut rng = TestRng(2026);
    let res = 0.01;
    let inv_res = 1.0 / res;
    // The last origin has equal coordinates, so its diagonal rays tie between axes at every
    // step (OctoMap's tie rule decides their voxels).
    for origin in [[0.013f32, -0.2, 0.31], [-4321.5, 2103.25, 7.0], [0.255; 3]] {
        let key_origin = walk::key_of_f32(origin, inv_res).expect("in range");
        let random = (0..500).map(|_| [(); 3].map(|_| rng.uniform(-1.2, 1.2) as f32));
        let diagonal = (0..27 * 2).map(|i| {
            let length = [0.3f32, 0.77][i / 27];
            [i % 3, i / 3 % 3, i / 9 % 3].map(|d| (d as f32 - 1.0) * length)
        });
        let rays: Vec<(u32, RaySetup)> = (0u32..)
            .zip(random.chain(diagonal))
            .filter_map(|(ray, offset)| {
                let end = [0, 1, 2].map(|i| origin[i] + offset[i]);
                let key_end = walk::key_of_f32(end, inv_res)?;
                RaySetup::octomap(origin, end, key_origin, key_end, res).map(|s| (ray, s))
            })
            .collect();
        let ko = [key_origin.x, key_origin.y, key_origin.z];
        // The whole reach, and a box that cuts most rays off.
        for half in [125i32, 40] {
            let g =
                PlaneGeometry::new(ko.map(|k| k - half), [2 * half as u32; 3]).expect("small box");
            let mut portable = LaneRecord::default();
            walk_lanes_at(
                simd::Level::Portable,
                rays.iter().copied(),
                &g,
                &mut portable,
            );
            for (ray, s) in &rays {
                let mut scalar = Vec::new();
                s.walk(|c| {
                    scalar.push(c);
                    !stops_early(*ray, c)
                });
                let lanes: Vec<[i32; 3]> = portable
                    .visits
                    .iter()
                    .filter(|(r, _, _)| r == ray)
                    .map(|&(_, c, _)| c)
                    .collect();
                assert_eq!(lanes, scalar, "ray {ray}");
                for &(_, c, index) in portable.visits.iter().filter(|(r, _, _)| r == ray) {
                    assert_eq!(index, g.index(c).map(|i| i as i32));
                }
            }
            assert!(portable.ends.len() > 100 && portable.visits.len() > 10_000);
            let marks = free_marks(simd::Level::Portable, &rays, &g);
            // Insertion's marker (whole steps at once where it can) marks what the visits name,
            // except the voxels after an early stop, which its rays walk too.
            for &(_, c, index) in &portable.visits {
                match index {
                    Some(i) => assert!(marks.0[i as usize >> 6] >> (i & 63) & 1 == 1),
                    None => assert!(marks.1.contains(&VoxelKey::new(c[0], c[1], c[2]))),
                }
            }
            for level in [simd::Level::Avx2, simd::Level::Avx512] {
                if level <= simd::detected() {
                    let mut wide = LaneRecord::default();
                    walk_lanes_at(level, rays.iter().copied(), &g, &mut wide);
                    assert!(wide == portable, "{level:?} differs from the portable walk");
                    assert!(
                        free_marks(level, &rays, &g) == marks,
                        "{level:?} marks differ"
                    );
                }
            }
        }
    }
}

/// A store's view of a map: its header and the newest record of each block.
fn store_records(
    store: &mut BTreeMap<(i32, i32, i32), Vec<u8>>,
    records: Vec<(VoxelKey, Vec<u8>)>,
) -> usize {
    let n = records.len();
    for (bk, record) in records {
        assert_eq!(stored::stored_block_coord(&record), Some(bk));
        store.insert((bk.x, bk.y, bk.z), record);
    }
    n
}

#[test]
fn stored_blocks_since_a_checkpoint_rebuild_the_map() {
    let w = Workload::small(5, 64, 48, 6, 4);
    let scans = w.filtered_scans();
    let mut m = RoiMap::new(w.map_config()).expect("valid");
    let mut store = BTreeMap::new();
    let mut header = m.stored_header();
    let mut checkpoint_scans = 0;
    for (i, s) in scans.iter().enumerate() {
        m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        let written = store_records(&mut store, m.stored_blocks_since(checkpoint_scans));
        if i > 0 {
            // Incremental: fewer blocks than the map holds.
            assert!(
                written < m.counts().blocks,
                "{written} of {}",
                m.counts().blocks
            );
        }
        checkpoint_scans = m.scans_inserted();
        header = m.stored_header();
        let back = RoiMap::from_stored(&header, store.values().map(Vec::as_slice)).expect("load");
        assert_eq!(sorted_voxels(&back), sorted_voxels(&m), "after scan {i}");
        assert_eq!(back.counts(), m.counts());
        assert_eq!(back.roi_keys(), m.roi_keys());
        assert_eq!(back.scans_inserted(), m.scans_inserted());
    }
    // The store's map goes on exactly as the live one.
    let mut back = RoiMap::from_stored(&header, store.values().map(Vec::as_slice)).expect("load");
    let s = &scans[0];
    m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
    back.insert_scan(&s.origin, &s.points, &s.roi)
        .expect("valid");
    assert_eq!(sorted_voxels(&back), sorted_voxels(&m));
    let everywhere = Aabb::new(Point3::new(-9.0, -9.0, -9.0), Point3::new(9.0, 9.0, 9.0));
    assert_eq!(
        back.exploration_frontier(&everywhere),
        m.exploration_frontier(&everywhere)
    );
}

#[test]
fn damaged_stored_records_are_errors() {
    let m = Workload::small(6, 32, 24, 3, 2)
        .filtered_map()
        .expect("valid");
    let header = m.stored_header();
    let records = m.stored_blocks_since(0);
    let first = records[0].1.as_slice();
    let twice = [first, first];
    assert!(matches!(
        RoiMap::from_stored(&header, twice),
        Err(snapshot::SnapshotError::Corrupt(_))
    ));
    for cut in [0, 11, 12, first.len() - 1] {
        assert!(
            RoiMap::from_stored(&header, [&first[..cut]]).is_err(),
            "cut {cut}"
        );
    }
    assert!(RoiMap::from_stored(&header[..header.len() - 1], [first]).is_err());
    let mut longer = first.to_vec();
    longer.push(0);
    assert!(RoiMap::from_stored(&header, [longer.as_slice()]).is_err());
}

/// Every voxel and derived set of two maps that should be equal.
fn assert_same_map(a: &RoiMap, b: &RoiMap) {
    assert_eq!(sorted_voxels(a), sorted_voxels(b));
    assert_eq!(a.counts(), b.counts());
    assert_eq!(a.scans_inserted(), b.scans_inserted());
    assert_eq!(a.roi_keys(), b.roi_keys());
    let everywhere = Aabb::new(Point3::new(-9.0, -9.0, -9.0), Point3::new(9.0, 9.0, 9.0));
    assert_eq!(
        a.exploration_frontier(&everywhere),
        b.exploration_frontier(&everywhere)
    );
    assert_eq!(a.roi_frontier(&everywhere), b.roi_frontier(&everywhere));
}

#[test]
fn deltas_bring_a_copy_to_the_writers_map_voxel_for_voxel() {
    let w = Workload::small(7, 96, 72, 8, 6);
    let config = MapConfig {
        roi_target_needs_neighbour: true,
        ..w.map_config()
    };
    let mut owner = RoiMap::new(config).expect("valid");
    let scans = w.filtered_scans();
    let insert = |m: &mut RoiMap, range: std::ops::Range<usize>| {
        for s in &scans[range] {
            m.insert_scan(&s.origin, &s.points, &s.roi).expect("valid");
        }
    };
    insert(&mut owner, 0..2);
    let mut full = Vec::new();
    owner.write_snapshot(&mut full).expect("write");
    let mut copy = RoiMap::read_snapshot(full.as_slice()).expect("read");
    // Two deltas one after the other, the second on the map the first made.
    for (from, to) in [(2, 4), (4, 6)] {
        let base = owner.scans_inserted();
        insert(&mut owner, from..to);
        let mut delta = Vec::new();
        owner.write_delta(base, &mut delta).expect("write delta");
        assert!(RoiMap::is_delta(&delta) && !RoiMap::is_delta(&full));
        RoiMap::check_delta(&delta).expect("framed");
        copy.apply_delta(&delta).expect("applies");
        assert_same_map(&copy, &owner);
        assert_eq!(brute_frontiers(&copy).1, brute_frontiers(&owner).1);
    }
    // Only the changed blocks travel: nothing changed, nothing but the header.
    let mut empty = Vec::new();
    owner
        .write_delta(owner.scans_inserted(), &mut empty)
        .expect("write");
    assert!(empty.len() < 200, "{} bytes", empty.len());
    copy.apply_delta(&empty).expect("applies");
    assert_same_map(&copy, &owner);
    // The copy writes the same snapshot's voxels as the owner.
    let mut again = Vec::new();
    copy.write_snapshot(&mut again).expect("write");
    let back = RoiMap::read_snapshot(again.as_slice()).expect("read");
    assert_same_map(&back, &owner);
}

#[test]
fn a_delta_on_another_base_or_damaged_changes_nothing() {
    let w = Workload::small(8, 64, 48, 6, 4);
    let scans = w.filtered_scans();
    let mut owner = RoiMap::new(w.map_config()).expect("valid");
    for s in &scans[..2] {
        owner
            .insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid");
    }
    let mut full = Vec::new();
    owner.write_snapshot(&mut full).expect("write");
    let mut copy = RoiMap::read_snapshot(full.as_slice()).expect("read");
    let before = sorted_voxels(&copy);
    for s in &scans[2..] {
        owner
            .insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid");
    }
    // A base the writer has not reached, and a delta from another base than the copy's.
    assert!(matches!(
        owner.write_delta(owner.scans_inserted() + 1, Vec::new()),
        Err(SnapshotError::DeltaBase { .. })
    ));
    let mut from_one = Vec::new();
    owner.write_delta(1, &mut from_one).expect("write");
    assert!(matches!(
        copy.apply_delta(&from_one),
        Err(SnapshotError::DeltaBase { base: 1, scans: 2 })
    ));
    let mut delta = Vec::new();
    owner.write_delta(2, &mut delta).expect("write");
    let mut bad = delta.clone();
    let at = bad.len() / 2;
    bad[at] ^= 0x04;
    assert!(matches!(
        copy.apply_delta(&bad),
        Err(SnapshotError::ChecksumMismatch { .. })
    ));
    assert!(matches!(
        copy.apply_delta(&full),
        Err(SnapshotError::WrongKind { .. })
    ));
    assert!(matches!(
        RoiMap::read_snapshot(delta.as_slice()),
        Err(SnapshotError::WrongKind { .. })
    ));
    let other = RoiMap::new(MapConfig {
        resolution_m: 0.02,
        ..w.map_config()
    });
    let mut other = other.expect("valid");
    for s in &scans[..2] {
        other
            .insert_scan(&s.origin, &s.points, &s.roi)
            .expect("valid");
    }
    assert!(matches!(
        other.apply_delta(&delta),
        Err(SnapshotError::Corrupt(_))
    ));
    assert_eq!(sorted_voxels(&copy), before);
    assert_eq!(copy.scans_inserted(), 2);
    copy.apply_delta(&delta).expect("the right base applies");
    assert_same_map(&copy, &owner);
}

#[test]
fn unknown_rule_flags_are_corrupt_and_known_ones_read_back() {
    let m = RoiMap::new(MapConfig {
        merge_far_rays: true,
        roi_target_needs_neighbour: true,
        ..MapConfig::default()
    })
    .expect("valid");
    let header = m.stored_header();
    // resolution (f64), seven f32 rules, the range (f64): the flags byte follows.
    const FLAGS_AT: usize = 8 + 7 * 4 + 8;
    assert_eq!(header[FLAGS_AT], 0b11, "both rules set");
    let back = RoiMap::from_stored(&header, std::iter::empty::<&[u8]>()).expect("load");
    assert!(back.config().merge_far_rays && back.config().roi_target_needs_neighbour);
    let mut damaged = header.clone();
    damaged[FLAGS_AT] = 0b100;
    match RoiMap::from_stored(&damaged, std::iter::empty::<&[u8]>()) {
        Err(snapshot::SnapshotError::Corrupt(why)) => assert!(why.contains("rule flags"), "{why}"),
        other => panic!(
            "a flag no rule has was read: {:?}",
            other.map(|m| *m.config())
        ),
    }
}
