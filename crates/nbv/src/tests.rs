use glasshouse_geom::optical_axis;
use glasshouse_roimap::{MapConfig, Voxel};

use super::*;

fn k(x: i32, y: i32, z: i32) -> VoxelKey {
    VoxelKey::new(x, y, z)
}

fn empty_map() -> RoiMap {
    RoiMap::new(MapConfig::default()).expect("default map config is valid")
}

/// Sets every voxel of the inclusive key box to the given log-odds.
fn set_box(map: &mut RoiMap, lo: VoxelKey, hi: VoxelKey, occupancy: f32, roi: f32) {
    let v = Voxel {
        occupancy_logodds: occupancy,
        roi_logodds: roi,
    };
    let mut entries = Vec::new();
    for x in lo.x..=hi.x {
        for y in lo.y..=hi.y {
            for z in lo.z..=hi.z {
                entries.push((k(x, y, z), v));
            }
        }
    }
    map.apply_voxels(&entries);
}

fn aabb(min: [f64; 3], max: [f64; 3]) -> Aabb {
    Aabb::new(Point3::from(min), Point3::from(max))
}

fn position(pose: &Isometry3<f64>) -> Point3<f64> {
    Point3::from(pose.translation.vector)
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize()
        .dot(&b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

const BLOB_CENTRE: [f64; 3] = [0.0, 0.02, 1.0];

/// An occupied ROI blob of 4x4x4 voxels centred at `BLOB_CENTRE`, known free space in front of
/// it (y < 0.04) and around its sides, unknown space behind it (y >= 0.04).
fn blob_map() -> RoiMap {
    let mut map = empty_map();
    set_box(&mut map, k(-30, -60, 70), k(30, 3, 130), -1.0, 0.0);
    set_box(&mut map, k(-2, 0, 98), k(1, 3, 101), 2.0, 2.0);
    map
}

fn blob_context(map: &RoiMap) -> PlanningContext<'_> {
    PlanningContext {
        map,
        world_from_camera: look_along(&Point3::new(0.0, -0.4, 1.0), &Vector3::y()),
        camera_workspace: aabb([-0.4, -0.6, 0.6], [0.4, -0.2, 1.4]),
        sampling_region: aabb([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5]),
        reach: None,
        motion_time: None,
        remembered_fruit: &[],
        settled_voxels: &[],
        roi_stalled: false,
    }
}

#[test]
fn method_names_parse_and_display() {
    for m in Method::ALL {
        assert_eq!(m.to_string().parse::<Method>(), Ok(m));
    }
    assert_eq!("ours-up".parse::<Method>(), Ok(Method::OursUp));
    assert_eq!(" Explo-UU ".parse::<Method>(), Ok(Method::ExploUu));
    let err = "ours".parse::<Method>().expect_err("not a method");
    let msg = err.to_string();
    for name in ["ours-uu", "ours-up", "explo-uu", "explo-up"] {
        assert!(msg.contains(name), "{msg}");
    }
    assert_eq!(Method::OursUp.gain(), GainKind::Proximity);
    assert_eq!(Method::ExploUu.gain(), GainKind::UnobservedVoxels);
    assert!(Method::OursUu.uses_roi_sampling());
    assert!(!Method::ExploUp.uses_roi_sampling());
}

#[test]
fn default_config_is_the_papers_and_validated() {
    let c = PlannerConfig::default();
    assert!(c.validate().is_ok());
    assert!((c.vertical_fov_rad.to_degrees() - 64.36).abs() < 0.01);
    assert!((c.occlusion_occupancy_logodds - 0.405_465).abs() < 1e-5);
    for bad in [
        PlannerConfig {
            min_view_distance_m: 0.6,
            ..c
        },
        PlannerConfig { fan_width: 0, ..c },
        PlannerConfig {
            horizontal_fov_rad: f64::NAN,
            ..c
        },
        PlannerConfig {
            max_ranked_views: 0,
            ..c
        },
    ] {
        assert!(matches!(bad.validate(), Err(PlanError::InvalidConfig(_))));
    }
    let map = empty_map();
    let mut ctx = blob_context(&map);
    ctx.camera_workspace = aabb([1.0, 0.0, 0.0], [0.0, 1.0, 1.0]);
    assert!(matches!(
        plan_views(&ctx, &c, 0),
        Err(PlanError::InvalidRegion { .. })
    ));
}

#[test]
fn settled_clutter_draws_no_roi_targets_and_keeps_its_roi_voxels() {
    let map = blob_map();
    let config = PlannerConfig::default();
    let blob_voxels = |xs: std::ops::RangeInclusive<i32>| {
        let mut keys: Vec<VoxelKey> = xs
            .flat_map(|x| (0..=3).flat_map(move |y| (98..=101).map(move |z| k(x, y, z))))
            .collect();
        keys.sort_unstable();
        keys
    };
    let whole = blob_voxels(-2..=1);
    let settled = PlanningContext {
        settled_voxels: &whole,
        ..blob_context(&map)
    };
    let plan = plan_views(&settled, &config, 7).expect("valid plan");
    assert_eq!(plan.roi_targets, 0);
    assert_eq!(plan.used_kind, ViewKind::Exploration);
    assert!(map.is_roi(map.key_of(&Point3::from(BLOB_CENTRE))));
    // Half the blob settled (a red leaf touching a fruit): the targets beside the other half,
    // the x = 2 face (4 x 4) included, stay; those beside the settled half alone go.
    let half = blob_voxels(-2..=-1);
    let touching = PlanningContext {
        settled_voxels: &half,
        ..blob_context(&map)
    };
    let kept = plan_views(&touching, &config, 7)
        .expect("valid plan")
        .roi_targets;
    assert!((4..16).contains(&kept), "{kept} of 16 targets kept");
}

#[test]
fn a_stalled_roi_search_takes_exploration_views_only_when_they_beat_the_threshold() {
    let map = blob_map();
    let config = PlannerConfig::default();
    // A workspace wide enough for cameras beside the blob, where its frontier faces.
    let wide = |roi_stalled| PlanningContext {
        camera_workspace: aabb([-1.0, -1.0, 0.2], [1.0, 1.0, 1.8]),
        roi_stalled,
        ..blob_context(&map)
    };
    let paper = plan_views(&wide(false), &config, 7).expect("valid plan");
    assert_eq!(paper.used_kind, ViewKind::Roi);
    let plan = plan_views(&wide(true), &config, 7).expect("valid plan");
    assert_eq!(plan.used_kind, ViewKind::Exploration);
    assert!(!plan.views.is_empty());
    for view in &plan.views {
        assert_eq!(view.kind, ViewKind::Exploration);
        assert!(view.utility > config.utility_threshold, "{}", view.utility);
    }
    // In front of the blob no exploration candidate fits the workspace: nothing of that list
    // beats the threshold, so the ROI list stays, stalled or not.
    let narrow = PlanningContext {
        roi_stalled: true,
        ..blob_context(&map)
    };
    let kept = plan_views(&narrow, &config, 7).expect("valid plan");
    assert_eq!(kept.used_kind, ViewKind::Roi);
}

#[test]
fn more_roi_tries_draw_until_the_samples_survive() {
    let map = blob_map();
    let paper = PlannerConfig::default();
    let tried = PlannerConfig {
        roi_tries: 2000,
        ..paper
    };
    let scored = |config: &PlannerConfig| {
        plan_views(&blob_context(&map), config, 7)
            .expect("valid plan")
            .candidates_scored
    };
    // Both plans score the same exploration candidates (their own seed stream, E of them):
    // the paper's R ROI candidates (0 < R < 100) against the 100 the tries draw.
    let (of_paper, of_tried) = (scored(&paper), scored(&tried));
    assert!(of_tried > of_paper, "{of_tried} vs {of_paper}");
    assert!(
        of_tried - of_paper < paper.roi_samples,
        "{of_tried} vs {of_paper}"
    );
    assert!(of_tried >= paper.roi_samples, "{of_tried}");
    let too_many = PlannerConfig {
        roi_tries: 100_001,
        ..paper
    };
    assert!(matches!(
        too_many.validate(),
        Err(PlanError::InvalidConfig(_))
    ));
}

#[test]
fn top_roi_view_looks_at_the_blob_from_the_workspace() {
    let map = blob_map();
    let ctx = blob_context(&map);
    let config = PlannerConfig::default();
    let plan = plan_views(&ctx, &config, 7).expect("valid plan");
    assert_eq!(plan.roi_targets, 16);
    assert_eq!(plan.used_kind, ViewKind::Roi);
    assert!(!plan.views.is_empty() && plan.views.len() <= config.max_ranked_views);
    for w in plan.views.windows(2) {
        assert!(w[0].utility >= w[1].utility, "best first");
    }
    let blob = Point3::from(BLOB_CENTRE);
    for view in &plan.views {
        assert_eq!(view.kind, ViewKind::Roi);
        assert!(view.utility > config.utility_threshold);
        let eye = position(&view.world_from_camera);
        assert!(ctx.camera_workspace.contains(&eye));
        let angle = angle_deg(&optical_axis(&view.world_from_camera), &(blob - eye));
        assert!(angle < 10.0, "angle {angle}");
        let d = (blob - eye).norm();
        assert!((0.27..=0.53).contains(&d), "distance {d}");
        assert!((view.utility - (view.gain - 0.2 * view.cost_m)).abs() < 1e-12);
    }
}

#[test]
fn same_seed_same_plan() {
    let map = blob_map();
    let ctx = blob_context(&map);
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let a = plan_views(&ctx, &config, 1234).expect("valid plan");
        let b = plan_views(&ctx, &config, 1234).expect("valid plan");
        assert_eq!(a.views.len(), b.views.len());
        assert_eq!(a.candidates_scored, b.candidates_scored);
        for (x, y) in a.views.iter().zip(&b.views) {
            assert_eq!(x.world_from_camera, y.world_from_camera);
            assert_eq!(x.utility, y.utility);
        }
        let c = plan_views(&ctx, &config, 1235).expect("valid plan");
        assert!(!c.views.is_empty());
        if method.uses_roi_sampling() {
            assert_ne!(
                a.views[0].world_from_camera, c.views[0].world_from_camera,
                "another seed samples other views"
            );
        } else {
            assert_eq!(a.used_kind, ViewKind::Exploration);
        }
    }
}

#[test]
fn unobserved_gain_is_one_into_unknown_and_zero_into_known_free() {
    let config = PlannerConfig {
        gain_ray_range_m: 0.25,
        ..PlannerConfig::default()
    };
    let pose = look_along(
        &Point3::new(0.005, 0.005, 1.005),
        &Vector3::new(1.0, 0.3, 0.2),
    );
    let map = empty_map();
    let gain = GainEvaluator::new(&map, &config).gain(&pose);
    assert_eq!(gain, 1.0);

    let mut known = empty_map();
    set_box(&mut known, k(-35, -35, 65), k(35, 35, 135), -0.4055, 0.0);
    let gain = GainEvaluator::new(&known, &config).gain(&pose);
    assert_eq!(gain, 0.0);

    // A wall right in front: rays stop at it, nothing unknown is counted.
    let mut walled = empty_map();
    set_box(&mut walled, k(0, -40, 60), k(1, 40, 140), -1.0, 0.0);
    set_box(&mut walled, k(2, -40, 60), k(2, 40, 140), 2.0, 0.0);
    let gain = GainEvaluator::new(&walled, &config).gain(&look_along(
        &Point3::new(0.005, 0.005, 1.005),
        &Vector3::x(),
    ));
    assert_eq!(gain, 0.0);
}

#[test]
fn unobserved_gain_of_the_batch_walk_equals_the_ray_by_ray_walk() {
    // Known free, occupied and unknown boxes around the camera, looked at from many directions.
    let mut map = empty_map();
    set_box(&mut map, k(-30, -30, 70), k(29, 29, 129), -0.4, 0.0);
    set_box(&mut map, k(12, -8, 90), k(14, 8, 110), 2.0, 0.0);
    set_box(&mut map, k(-20, 5, 95), k(-18, 25, 125), 0.9, 0.0);
    set_box(&mut map, k(0, -25, 80), k(6, -20, 84), -2.0, 0.0);
    let config = PlannerConfig::default();
    let evaluator = GainEvaluator::new(&map, &config);
    let eye = Point3::new(0.0031, -0.0127, 1.0049);
    let mut gains = Vec::new();
    for (i, &x) in [1.0, -1.0, 0.3, 0.0].iter().enumerate() {
        for &y in &[0.0, 0.7, -0.2] {
            let pose = look_along(&eye, &Vector3::new(x, y, 0.1 * i as f64 - 0.1));
            let batch = evaluator.gain(&pose);
            assert_eq!(batch.to_bits(), evaluator.gain_ray_by_ray(&pose).to_bits());
            gains.push(batch);
        }
    }
    // The poses see different mixes of known and unknown voxels.
    assert!(gains.iter().any(|&g| g > 0.2) && gains.iter().any(|&g| g < 0.9));
}

#[test]
fn fan_is_cast_around_the_optical_axis() {
    // Known free column above the camera, unknown everywhere else.
    let mut map = empty_map();
    set_box(&mut map, k(-10, -10, 100), k(9, 9, 199), -1.0, 0.0);
    let config = PlannerConfig::default();
    let evaluator = GainEvaluator::new(&map, &config);
    let eye = Point3::new(0.005, 0.005, 1.005);
    // Optical axis +x (unknown), image up (-y of camera) = world +z (known free).
    let sideways = look_along(&eye, &Vector3::x());
    assert!((sideways.rotation * -Vector3::y() - Vector3::z()).norm() < 1e-9);
    let side_gain = evaluator.gain(&sideways);
    assert!(side_gain > 0.8, "side gain {side_gain}");
    let up_gain = evaluator.gain(&look_along(&eye, &Vector3::z()));
    assert!(up_gain < side_gain - 0.2, "up {up_gain} side {side_gain}");
}

#[test]
fn proximity_gain_rises_near_roi() {
    let config = PlannerConfig {
        method: Method::OursUp,
        ..PlannerConfig::default()
    };
    let pose = look_along(&Point3::new(0.005, -0.25, 1.005), &Vector3::y());
    let empty = empty_map();
    let base = GainEvaluator::new(&empty, &config).gain(&pose);
    assert!(
        (base - 0.5).abs() < 1e-12,
        "unknown voxels weigh 0.5: {base}"
    );
    let mut map = empty_map();
    set_box(&mut map, k(-2, 0, 98), k(1, 3, 101), 2.0, 2.0);
    let near = GainEvaluator::new(&map, &config).gain(&pose);
    assert!(near > 0.55 && near <= 1.0, "near {near}");
    // U_U ignores ROI: the same map scores lower-or-equal in share terms but never above 1.
    let uu = GainEvaluator::new(&map, &PlannerConfig::default()).gain(&pose);
    assert!(uu > near && uu <= 1.0);
}

#[test]
fn exploration_when_there_is_no_roi() {
    // A wall (occupied, no ROI) at y = 0 with known free space in front and unknown behind.
    let mut map = empty_map();
    set_box(&mut map, k(-20, -40, 80), k(20, -1, 120), -1.0, 0.0);
    set_box(&mut map, k(-20, 0, 80), k(20, 0, 120), 2.0, -1.0);
    let ctx = PlanningContext {
        map: &map,
        world_from_camera: look_along(&Point3::new(0.0, -0.4, 1.0), &Vector3::y()),
        camera_workspace: aabb([-0.6, -0.7, 0.5], [0.6, -0.1, 1.5]),
        sampling_region: aabb([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5]),
        reach: None,
        motion_time: None,
        remembered_fruit: &[],
        settled_voxels: &[],
        roi_stalled: false,
    };
    for method in [Method::OursUu, Method::OursUp, Method::ExploUu] {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let plan = plan_views(&ctx, &config, 3).expect("valid plan");
        assert_eq!(plan.roi_targets, 0);
        assert!(plan.exploration_frontier > 0);
        assert_eq!(plan.used_kind, ViewKind::Exploration);
        assert!(!plan.views.is_empty());
        for view in &plan.views {
            assert_eq!(view.kind, ViewKind::Exploration);
            let eye = position(&view.world_from_camera);
            assert!(ctx.camera_workspace.contains(&eye));
            // Looking back towards the wall (normal points to -y).
            assert!(optical_axis(&view.world_from_camera).y > 0.0);
        }
    }
}

#[test]
fn never_empty_on_an_empty_map() {
    let map = empty_map();
    let ctx = PlanningContext {
        map: &map,
        world_from_camera: look_along(&Point3::new(0.0, 0.0, 1.0), &Vector3::y()),
        camera_workspace: aabb([-0.5, -0.5, 0.5], [0.5, 0.0, 1.5]),
        sampling_region: aabb([-1.0, 0.2, 0.0], [1.0, 0.8, 2.0]),
        reach: None,
        motion_time: None,
        remembered_fruit: &[],
        settled_voxels: &[],
        roi_stalled: false,
    };
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let plan = plan_views(&ctx, &config, 11).expect("valid plan");
        assert_eq!(plan.used_kind, ViewKind::Exploration);
        assert!(!plan.views.is_empty());
        assert!(plan.views.len() <= config.max_ranked_views);
        assert!(plan.candidates_scored >= plan.views.len());
        for view in &plan.views {
            assert!(ctx
                .camera_workspace
                .contains(&position(&view.world_from_camera)));
            assert!(view.utility.is_finite());
        }
    }
    // A flat (zero-volume) workspace still yields a view.
    let flat = PlanningContext {
        camera_workspace: aabb([0.0, -0.3, 1.0], [0.0, -0.3, 1.0]),
        ..ctx
    };
    let plan = plan_views(&flat, &PlannerConfig::default(), 5).expect("valid plan");
    assert!(!plan.views.is_empty());
    // Nothing above the threshold: the best views are returned anyway.
    let strict = PlannerConfig {
        utility_threshold: 5.0,
        ..PlannerConfig::default()
    };
    let plan = plan_views(&ctx, &strict, 5).expect("valid plan");
    assert!(!plan.views.is_empty());
}

fn cluster_at(centre: [f64; 3], half_voxels: i32) -> RoiCluster {
    let res = 0.01;
    let c = k(
        (centre[0] / res).floor() as i32,
        (centre[1] / res).floor() as i32,
        (centre[2] / res).floor() as i32,
    );
    let mut voxels = Vec::new();
    for x in -half_voxels..=half_voxels {
        for y in -half_voxels..=half_voxels {
            for z in -half_voxels..=half_voxels {
                voxels.push(c.offset(x, y, z));
            }
        }
    }
    let side = f64::from(2 * half_voxels + 1) * res;
    let min = Point3::new(
        f64::from(c.x - half_voxels) * res,
        f64::from(c.y - half_voxels) * res,
        f64::from(c.z - half_voxels) * res,
    );
    RoiCluster {
        voxels,
        centre: Point3::from(centre),
        min,
        max: min + Vector3::repeat(side),
    }
}

#[test]
fn tracker_keeps_ids_for_moving_clusters_and_never_reuses_them() {
    let mut tracker = FruitTracker::default();
    let first = tracker.update(&[
        cluster_at([0.0, 0.0, 1.0], 2),
        cluster_at([0.3, 0.0, 1.0], 2),
    ]);
    assert_eq!(first.iter().map(|e| e.id).collect::<Vec<_>>(), vec![1, 2]);
    assert_eq!(first[0].voxel_count, 125);
    assert!((first[0].volume_m3 - 0.05f64.powi(3)).abs() < 1e-12);
    assert_eq!(first[0].confidence, 1.0);

    // Moved slightly, listed in another order, plus a new one.
    let second = tracker.update(&[
        cluster_at([0.8, 0.0, 1.0], 2),
        cluster_at([0.32, 0.01, 1.0], 2),
        cluster_at([0.01, 0.0, 1.01], 2),
    ]);
    assert_eq!(
        second.iter().map(|e| e.id).collect::<Vec<_>>(),
        vec![3, 2, 1]
    );

    // Two clusters near one old fruit: the nearer keeps the id, the other is new.
    let third = tracker.update(&[
        cluster_at([0.04, 0.0, 1.01], 2),
        cluster_at([0.015, 0.0, 1.01], 2),
    ]);
    assert_eq!(third.iter().map(|e| e.id).collect::<Vec<_>>(), vec![4, 1]);

    // Fruit 2 vanished; when it reappears it gets a fresh id, never an old one.
    let fourth = tracker.update(&[cluster_at([0.32, 0.01, 1.0], 2)]);
    assert_eq!(fourth[0].id, 5);
    assert!(tracker.update(&[]).is_empty());
}

#[test]
fn confidence_is_the_seen_share_of_the_box_surface() {
    // Only the bottom face (z = lowest layer) of a 3x3x3 box: 9 of 26 surface voxels.
    let full = cluster_at([0.0, 0.0, 1.0], 1);
    let lowest = full.voxels.iter().map(|v| v.z).min().expect("non-empty");
    let mut face = full.clone();
    face.voxels.retain(|v| v.z == lowest);
    // The key box of a single face is flat: every voxel is on its surface.
    assert_eq!(fruit_confidence(&face), 1.0);
    // Add one voxel on the top layer corner: box is 3x3x3, 10 of 26 surface voxels present.
    let top_corner = full.voxels.iter().copied().max().expect("non-empty");
    face.voxels.push(top_corner);
    assert!((fruit_confidence(&face) - 10.0 / 26.0).abs() < 1e-12);
    let hollow_missing: RoiCluster = RoiCluster {
        voxels: Vec::new(),
        ..full
    };
    assert_eq!(fruit_confidence(&hollow_missing), 0.0);
}

/// The views, every number written exactly (`Debug` of an f64 round-trips).
fn views_of(plan: &Plan) -> String {
    format!("{:?}", plan.views)
}

#[test]
fn a_reach_predicate_drops_the_poses_it_rejects() {
    let map = blob_map();
    // The robot reaches only the left half of the camera workspace (x < 0).
    let left_only = |pose: &Isometry3<f64>| pose.translation.vector.x < 0.0;
    let ctx = PlanningContext {
        reach: Some(&left_only),
        remembered_fruit: &[],
        ..blob_context(&map)
    };
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        for seed in 0..4 {
            let plan = plan_views(&ctx, &config, seed).expect("valid plan");
            assert!(!plan.views.is_empty(), "{method} seed {seed}");
            for view in &plan.views {
                assert!(left_only(&view.world_from_camera), "{method}: {view:?}");
            }
            // Deterministic with a predicate too.
            let again = plan_views(&ctx, &config, seed).expect("valid plan");
            assert_eq!(views_of(&plan), views_of(&again));
        }
    }
}

#[test]
fn an_accepting_predicate_changes_nothing() {
    let map = blob_map();
    let accept = |_: &Isometry3<f64>| true;
    let with = PlanningContext {
        reach: Some(&accept),
        remembered_fruit: &[],
        ..blob_context(&map)
    };
    let without = blob_context(&map);
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let (a, b) = (
            plan_views(&with, &config, 9).expect("valid plan"),
            plan_views(&without, &config, 9).expect("valid plan"),
        );
        assert_eq!(views_of(&a), views_of(&b));
        assert_eq!(a.candidates_scored, b.candidates_scored);
    }
}

#[test]
fn nothing_reachable_gives_an_empty_plan_not_a_panic() {
    let map = empty_map();
    let reject = |_: &Isometry3<f64>| false;
    let ctx = PlanningContext {
        map: &map,
        world_from_camera: look_along(&Point3::new(0.0, 0.0, 1.0), &Vector3::y()),
        camera_workspace: aabb([-0.5, -0.5, 0.5], [0.5, 0.0, 1.5]),
        sampling_region: aabb([-1.0, 0.2, 0.0], [1.0, 0.8, 2.0]),
        reach: Some(&reject),
        motion_time: None,
        remembered_fruit: &[],
        settled_voxels: &[],
        roi_stalled: false,
    };
    for method in Method::ALL {
        let config = PlannerConfig {
            method,
            ..PlannerConfig::default()
        };
        let plan = plan_views(&ctx, &config, 11).expect("valid plan");
        assert!(plan.views.is_empty());
        assert_eq!(plan.candidates_scored, 0);
    }
}

#[test]
fn a_motion_time_ranks_quicker_views_first_and_leaves_the_choice_of_list_alone() {
    let map = blob_map();
    // Views on the left (x near -0.3) are quick to reach, the others take up to 3.5 s.
    let seconds = |pose: &Isometry3<f64>| Some((pose.translation.vector.x + 0.3).abs() * 5.0);
    let timed = PlanningContext {
        motion_time: Some(&seconds),
        ..blob_context(&map)
    };
    let untimed = blob_context(&map);
    let config = PlannerConfig {
        cost_weight_per_s: 1.5,
        ..PlannerConfig::default()
    };
    let first_s = |plan: &Plan| seconds(&plan.views[0].world_from_camera).unwrap_or(f64::NAN);
    let mut quicker = 0;
    for seed in 0..4 {
        let a = plan_views(&timed, &config, seed).expect("valid plan");
        let b = plan_views(&untimed, &config, seed).expect("valid plan");
        assert_eq!(
            a.used_kind, b.used_kind,
            "the list is chosen by the utility"
        );
        assert_eq!(a.candidates_scored, b.candidates_scored);
        for w in a.views.windows(2) {
            assert!(w[0].rank_utility >= w[1].rank_utility, "ranked by time too");
        }
        for v in &a.views {
            let t = v.motion_s.expect("timed");
            assert!(
                (v.rank_utility - (v.utility - 1.5 * t)).abs() < 1e-12,
                "{v:?}"
            );
            assert!((v.utility - (v.gain - config.cost_weight_per_m * v.cost_m)).abs() < 1e-12);
        }
        assert!(b.views.iter().all(|v| v.motion_s.is_none()));
        assert!(first_s(&a) <= first_s(&b), "seed {seed}");
        quicker += usize::from(first_s(&a) < first_s(&b));
    }
    assert!(quicker > 0, "the time changed the first view of some plan");
    // A weight of 0 gives the paper's plans.
    let paper = PlannerConfig::default();
    let (a, b) = (
        plan_views(&timed, &paper, 3),
        plan_views(&untimed, &paper, 3),
    );
    assert_eq!(
        views_of(&a.expect("valid plan")),
        views_of(&b.expect("valid plan"))
    );
}

#[test]
fn roi_targets_near_the_camera_are_drawn_more_often_when_asked() {
    let map = empty_map();
    let mut ctx = blob_context(&map);
    ctx.camera_workspace = aabb([-2.0, -2.0, -1.0], [3.0, 2.0, 3.0]);
    // The camera at (0, -0.4, 1.0): one target 0.4 m away, one 1.27 m away.
    let (near, far) = (
        map.key_of(&Point3::new(0.0, 0.0, 1.0)),
        map.key_of(&Point3::new(1.2, 0.0, 1.0)),
    );
    let near_share = |config: &PlannerConfig| {
        let poses = sample_roi_views(&ctx, config, &[near, far], &mut rng_stream(7, 0));
        let at_near = poses
            .iter()
            .filter(|p| {
                (position(p) - map.centre_of(near)).norm() <= config.max_view_distance_m + 0.01
            })
            .count();
        at_near as f64 / poses.len() as f64
    };
    let uniform = near_share(&PlannerConfig::default());
    assert!(
        (0.35..=0.65).contains(&uniform),
        "uniform draw: {uniform} near"
    );
    let weighted = near_share(&PlannerConfig {
        roi_target_near_m: 0.2,
        ..PlannerConfig::default()
    });
    assert!(weighted > 0.95, "weighted draw: {weighted} near");
    let bad = PlannerConfig {
        roi_target_near_m: f64::NAN,
        ..PlannerConfig::default()
    };
    assert!(bad.validate().is_err());
}
