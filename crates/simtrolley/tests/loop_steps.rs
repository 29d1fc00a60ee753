//! The loop's steps on a simulated trolley: capture, detection, integration, plans, fits, and
//! what the simulated world's noise and pose errors do to the frames.
#![allow(clippy::unwrap_used)]

use glasshouse_detect::DetectorConfig;
use glasshouse_pipeline::*;
use glasshouse_proto::{FrameId, RoiCloud};
use glasshouse_sim::ScenarioKind;
use glasshouse_simtrolley::*;

/// The edge's boot epoch in these tests.
const EPOCH_NS: u64 = 1_790_000_000_000_000_000;

fn sim(scenario: ScenarioKind) -> SimTrolley {
    SimTrolley::new(SimTrolleySettings::new(scenario, 3, (160, 120), 1.0)).unwrap()
}

fn noisy_sim(label_noise: f64, silhouette_px: u32) -> Result<SimTrolley, CaptureError> {
    SimTrolley::new(SimTrolleySettings {
        world: glasshouse_sim::WorldSettings {
            perception: glasshouse_sim::PerceptionNoise {
                label_noise,
                silhouette_px,
                ..Default::default()
            },
            ..Default::default()
        },
        ..SimTrolleySettings::new(ScenarioKind::Two, 3, (160, 120), 1.0)
    })
}

#[test]
fn the_trolley_settings_noise_reaches_its_frames_and_the_detector() {
    let clean = sim(ScenarioKind::Two).capture(1).unwrap().unwrap();
    let zero = noisy_sim(0.0, 0).unwrap().capture(1).unwrap().unwrap();
    assert_eq!(zero, clean);
    let labels = noisy_sim(0.3, 0).unwrap().capture(1).unwrap().unwrap();
    assert_eq!(labels.depth, clean.depth);
    assert_ne!(labels.rgb, clean.rgb);
    let edges = noisy_sim(0.0, 1).unwrap().capture(1).unwrap().unwrap();
    assert_eq!(edges.rgb, clean.rgb);
    let zeros = |f: &glasshouse_proto::RgbdFrame| f.depth.iter().filter(|&&d| d == 0).count();
    assert!(zeros(&edges) > zeros(&clean) + 100);
    // The unchanged detector labels background as fruit: many more ROI points.
    let roi = |f: &glasshouse_proto::RgbdFrame| {
        let cloud = detect_frame(f, FrameId::new(0, 1), "d", &DetectorConfig::default()).unwrap();
        cloud.roi.iter().filter(|&&r| r).count()
    };
    assert!(
        roi(&labels) > 2 * roi(&clean),
        "{} vs {}",
        roi(&labels),
        roi(&clean)
    );
    for bad in [-0.1, 1.5, f64::NAN] {
        let err = noisy_sim(bad, 0).unwrap_err();
        assert!(matches!(err, CaptureError::World(_)), "{err}");
    }
    assert!(noisy_sim(0.0, 100).is_err());
}

#[test]
fn one_depth_rule_invalid_and_over_range_are_zero() {
    let mut trolley = sim(ScenarioKind::Two);
    let frame = trolley.capture(1).unwrap().unwrap();
    assert_eq!(frame.depth.len(), 160 * 120);
    assert_eq!(frame.depth_scale_m, DEPTH_SCALE_M);
    let image = trolley.scene().render(
        &glasshouse_sim::CameraModel::with_resolution(160, 120),
        &trolley.world_from_camera(),
        noise_seed(3, 1),
    );
    for (&d_m, &packed) in image.depth_m.iter().zip(&frame.depth) {
        let units = f64::from(d_m) / f64::from(DEPTH_SCALE_M);
        if d_m.is_finite() && (0.5..65535.5).contains(&units) {
            assert_eq!(packed, units.round() as u16);
        } else {
            assert_eq!(packed, 0);
        }
    }
}

#[test]
fn the_steps_capture_detect_integrate_plan_and_fit() {
    let mut trolley = sim(ScenarioKind::Two);
    let frame = trolley.capture(1).unwrap().unwrap();
    let cloud = detect_frame(&frame, FrameId::new(0, 1), "d1", &DetectorConfig::default()).unwrap();
    assert!(cloud.roi.iter().any(|&r| r));
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    // No info yet: the cloud is integrated, planning waits.
    assert_eq!(planner.integrate(&cloud, 0).unwrap(), FrameVerdict::Fresh);
    assert!(planner.plan(&frame.world_from_camera, 1).unwrap().is_none());
    planner.set_info(trolley.info()).unwrap();
    assert!(planner.filters_reach());
    // The same frame again is not inserted twice.
    let known = planner.map().len();
    assert_eq!(planner.integrate(&cloud, 0).unwrap(), FrameVerdict::Repeat);
    assert_eq!(planner.map().len(), known);
    let plan = planner.plan(&frame.world_from_camera, 1).unwrap().unwrap();
    assert!(!plan.views.is_empty());
    // The trolley's robot is known, so every view is ranked by the time it takes too.
    let timed = |t: Option<f64>| t.is_some_and(|t| t.is_finite() && t >= 0.0);
    assert!(plan.views.iter().all(|v| timed(v.motion_s)), "{plan:?}");
    for w in plan.views.windows(2) {
        assert!(w[0].rank_utility >= w[1].rank_utility);
    }
    // Seeded: the same plan again.
    let again = planner.plan(&frame.world_from_camera, 1).unwrap().unwrap();
    let poses = |p: &glasshouse_nbv::Plan| {
        p.views
            .iter()
            .map(|v| (v.world_from_camera, v.utility))
            .collect::<Vec<_>>()
    };
    assert_eq!(poses(&plan), poses(&again));
    let update = planner.map_update(1, "p1");
    assert!(!update.voxels.is_empty());
    assert!(planner.map_update(1, "p1").voxels.is_empty());
    let executed = trolley.execute(&[plan.views[0].world_from_camera]);
    assert!(executed.is_none_or(|e| e.index == 0));
}

#[test]
fn a_snapshot_carries_map_ids_and_seq() {
    let mut trolley = sim(ScenarioKind::Two);
    let frame = trolley.capture(1).unwrap().unwrap();
    let frame_id = FrameId::new(EPOCH_NS, 5);
    let cloud = detect_frame(&frame, frame_id, "d1", &DetectorConfig::default()).unwrap();
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.integrate(&cloud, EPOCH_NS).unwrap();
    let snapshot = planner.snapshot("t1", "p1").unwrap();
    assert_eq!(
        (snapshot.based_on_epoch_ns, snapshot.based_on_seq),
        (EPOCH_NS, 5)
    );
    let mut copy = TrolleyPlanner::from_snapshot(PlanningSettings::default(), &snapshot).unwrap();
    assert_eq!(copy.map().len(), planner.map().len());
    assert_eq!(copy.last_frame(), Some(frame_id));
    // The copy goes on where the snapshot ends: the same frame is not inserted again.
    assert_eq!(
        copy.integrate(&cloud, EPOCH_NS).unwrap(),
        FrameVerdict::Repeat
    );
    let coarse = PlanningSettings {
        resolution_m: 0.02,
        ..PlanningSettings::default()
    };
    assert!(matches!(
        TrolleyPlanner::from_snapshot(coarse, &snapshot),
        Err(PlanningError::Snapshot(_))
    ));
    let mut bad = snapshot.clone();
    bad.map.truncate(10);
    assert!(TrolleyPlanner::from_snapshot(PlanningSettings::default(), &bad).is_err());
}

#[test]
fn bad_settings_are_rejected() {
    for bad in [
        PlanningSettings {
            max_range_m: f64::NAN,
            ..PlanningSettings::default()
        },
        PlanningSettings {
            resolution_m: 0.0,
            ..PlanningSettings::default()
        },
    ] {
        assert!(TrolleyPlanner::new(bad).is_err());
    }
    assert!(matches!(
        SimTrolley::new(SimTrolleySettings::new(ScenarioKind::One, 1, (8, 8), 1.0)),
        Err(CaptureError::ImageSize(8, 8))
    ));
}

#[test]
fn the_cloud_carries_the_frame_camera_pose() {
    let frame = glasshouse_proto::samples::rgbd_frame();
    let frame_id = FrameId::new(EPOCH_NS, 7);
    let cloud = detect_frame(&frame, frame_id, "d1", &DetectorConfig::default()).unwrap();
    assert_eq!(cloud.world_from_camera, frame.world_from_camera);
    assert_eq!(cloud.source_frame(), frame_id);
    let origin = frame.world_from_camera.translation.vector;
    assert!((cloud.sensor_origin_in_world.coords - origin).norm() < 1e-9);
}

/// Fits every cluster of the planner's map afresh, keeping what `fruits` reports: the clusters
/// shaped like fruit, and of those the ones that are not a fragment of another.
fn fresh_fits(planner: &TrolleyPlanner) -> Vec<glasshouse_nbv::fit::FruitSolid> {
    let map = planner.map();
    let (min_voxels, config) = (
        planner.settings().min_cluster_voxels,
        &planner.settings().fit,
    );
    let clusters = map.clusters(min_voxels);
    let clusters = glasshouse_nbv::split::split_touching(map, clusters, min_voxels, config);
    // A cluster shaped like a fruit is fitted; one turned away as too small or flat is a fruit
    // when a body lies under it.
    let fit = |c: &glasshouse_roimap::RoiCluster| {
        use glasshouse_nbv::evidence::{ClusterEvidence, Verdict};
        match ClusterEvidence::of(map, c).shape.verdict(&config.evidence) {
            Verdict::Fruit => Some(glasshouse_nbv::fit::fit_ellipsoid(map, c, config)),
            Verdict::TooSmall | Verdict::Flat => {
                glasshouse_pipeline::fits::body_solid(map, c, config)
            }
            _ => None,
        }
    };
    let (fits, counts): (Vec<_>, Vec<usize>) = clusters
        .iter()
        .filter_map(|c| Some((fit(c)?, c.voxels.len())))
        .unzip();
    let fragment = glasshouse_nbv::split::fragments(&fits, &counts);
    fits.into_iter()
        .zip(fragment)
        .filter(|(_, f)| !f)
        .map(|(fit, _)| fit)
        .collect()
}

#[test]
fn kept_fits_equal_fresh_fits_and_only_touched_fruits_are_refitted() {
    let mut trolley = sim(ScenarioKind::Row);
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.set_info(trolley.info()).unwrap();
    let (mut refits, mut fruits_seen) = (0, 0);
    for seq in 1..=12 {
        if seq % 4 == 0 {
            trolley.next_segment().expect("the row has a next segment");
        }
        let frame = trolley.capture(seq).unwrap().unwrap();
        let cloud = detect_frame(
            &frame,
            FrameId::new(EPOCH_NS, seq),
            "d1",
            &DetectorConfig::default(),
        )
        .unwrap();
        planner.integrate(&cloud, EPOCH_NS).unwrap();
        let fitted: Vec<_> = planner.fruits().into_iter().map(|f| f.solid).collect();
        let fresh: Vec<_> = fresh_fits(&planner).iter().map(|s| Some(*s)).collect();
        // Debug text: equal bit for bit, NaN residuals of box fallbacks included.
        let text = |solids: &[Option<glasshouse_geom::FruitSolid>]| format!("{solids:?}");
        assert_eq!(text(&fitted), text(&fresh), "frame {seq}");
        refits += planner.last_refits();
        fruits_seen += fitted.len();
        if let Some(plan) = planner.plan(&frame.world_from_camera, seq).unwrap() {
            let goals: Vec<_> = plan.views.iter().map(|v| v.world_from_camera).collect();
            trolley.execute(&goals);
        }
    }
    assert!(fruits_seen > 0);
    assert!(
        refits < fruits_seen,
        "{refits} refits for {fruits_seen} fruits"
    );
}

#[test]
fn kept_splits_equal_fresh_splits_on_any_threads_and_a_change_beside_a_cluster_tries_it_again() {
    let mut trolley = sim(ScenarioKind::Row);
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    planner.set_info(trolley.info()).unwrap();
    for seq in 1..=6 {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let id = FrameId::new(EPOCH_NS, seq);
        let cloud = detect_frame(&frame, id, "d1", &DetectorConfig::default()).unwrap();
        planner.integrate(&cloud, EPOCH_NS).unwrap();
    }
    let min_voxels = planner.settings().min_cluster_voxels;
    // Clusters of 2 cm and longer are tried (the default, a fruit's length, leaves few after
    // six frames from one place).
    let config = glasshouse_nbv::fit::FitConfig {
        split_extent_m: 0.02,
        ..planner.settings().fit
    };
    let mut map = planner.map().clone();
    let clusters = map.clusters(min_voxels);
    let fresh = |map: &glasshouse_roimap::RoiMap| {
        glasshouse_nbv::split::split_touching(map, map.clusters(min_voxels), min_voxels, &config)
    };
    let mut cache = glasshouse_pipeline::fits::SplitCache::default();
    let mut fits = glasshouse_pipeline::fits::FitCache::default();
    // On several threads the splits and fits are those of one (`fresh` and `afresh`).
    let (first, tried) = cache.update(&map, clusters.iter(), min_voxels, &config, &mut fits, 2);
    assert_eq!(first, fresh(&map));
    assert!(tried > 0, "the row holds clusters long enough to be tried");
    // The fits the splits made are kept: fitting the parts now refits only the others, and
    // gives what fitting each afresh gives.
    let (shapes, refits) = fits.update(&map, &first, &config, 3);
    assert!(
        refits + tried <= first.len(),
        "{refits} refits, {tried} tried, {} parts",
        first.len()
    );
    let fresh_fit = |c| glasshouse_nbv::fit::fit_ellipsoid(&map, c, &config);
    let afresh: Vec<_> = first.iter().map(fresh_fit).collect();
    assert_eq!(format!("{shapes:?}"), format!("{afresh:?}"));
    let (again, tried_again) =
        cache.update(&map, clusters.iter(), min_voxels, &config, &mut fits, 1);
    assert_eq!(
        (again, tried_again),
        (first, 0),
        "nothing changed: every split kept"
    );
    // A free voxel just outside the first tried cluster's box changes: that cluster's fits
    // read it, so it is tried again (its voxels are the same).
    let long = clusters
        .iter()
        .find(|c| (c.max - c.min).max() > config.split_extent_m)
        .expect("a long cluster");
    let beside = map.key_of(&(long.min - nalgebra::Vector3::repeat(0.005)));
    let voxel = glasshouse_roimap::Voxel {
        occupancy_logodds: -1.5,
        roi_logodds: -0.5,
    };
    map.apply_voxels(&[(beside, voxel)]);
    let (after, tried_after) =
        cache.update(&map, clusters.iter(), min_voxels, &config, &mut fits, 1);
    assert_eq!(after, fresh(&map));
    assert!(
        tried_after >= 1 && tried_after < tried,
        "{tried_after} of {tried} tried again"
    );
}

/// Feeds `input` to the node and every action it returns through the pacer at wall time
/// `now_s`; the wait before the last action, in seconds.
fn sorted(
    map: &glasshouse_roimap::RoiMap,
) -> Vec<(glasshouse_roimap::VoxelKey, glasshouse_roimap::Voxel)> {
    let mut v: Vec<_> = map.iter().collect();
    v.sort_by_key(|(k, _)| *k);
    v
}

#[test]
fn confidences_weight_the_roi_evidence_capped_at_the_labels_strength() {
    let mut trolley = sim(ScenarioKind::Two);
    let frame = trolley.capture(1).unwrap().unwrap();
    let cloud = detect_frame(&frame, FrameId::new(0, 1), "d1", &DetectorConfig::default()).unwrap();
    let table = |c: u8| {
        let one = RoiCloud {
            points_in_world: vec![nalgebra::Point3::new(0.3, 0.0, 0.0)],
            roi: vec![c >= 128],
            roi_confidence: vec![c],
            ..cloud.clone()
        };
        roi_evidence_logodds(&one).unwrap()[0]
    };
    assert_eq!(table(255), ROI_EVIDENCE_LOGODDS);
    assert_eq!(table(0), -ROI_EVIDENCE_LOGODDS);
    // 0.6 → ln(1.5); a split vote is almost no evidence; ≥ 0.7 is capped.
    assert!((table(153) - 1.5f32.ln()).abs() < 1e-5);
    assert!(table(128) > 0.0 && table(128) < 0.01);
    assert!(table(127) < 0.0 && table(127) > -0.01);
    assert_eq!(table(200), ROI_EVIDENCE_LOGODDS);

    // Through the planner: the same frame's cloud, once with confidences and once without, gives
    // the same occupancy and, where the votes were split, weaker ROI evidence.
    assert_eq!(cloud.roi_confidence.len(), cloud.points_in_world.len());
    let labels_only = RoiCloud {
        roi_confidence: Vec::new(),
        ..cloud.clone()
    };
    assert!(roi_evidence_logodds(&labels_only).is_none());
    let confidence = PlanningSettings {
        roi_evidence: RoiEvidence::Confidence,
        ..PlanningSettings::default()
    };
    let mut weighted = TrolleyPlanner::new(confidence.clone()).unwrap();
    let mut labelled = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    weighted.integrate(&cloud, 0).unwrap();
    // The default takes the labels, confidences or not.
    labelled.integrate(&cloud, 0).unwrap();
    let mut without = TrolleyPlanner::new(confidence).unwrap();
    without.integrate(&labels_only, 0).unwrap();
    assert_eq!(
        format!("{:?}", sorted(labelled.map())),
        format!("{:?}", sorted(without.map()))
    );
    let (w, l) = (weighted.map(), labelled.map());
    assert_eq!(w.len(), l.len());
    let mut weaker = 0;
    for (key, v) in l.iter() {
        let u = w.get(key).unwrap();
        assert_eq!(u.occupancy_logodds, v.occupancy_logodds);
        assert!(u.roi_logodds.abs() <= v.roi_logodds.abs());
        assert_eq!(u.roi_logodds > 0.0, v.roi_logodds > 0.0, "{key:?}");
        weaker += usize::from(u.roi_logodds.abs() < v.roi_logodds.abs());
    }
    // Fruit edges seen by few pixels.
    assert!(weaker > 0);
}

fn posed_sim(scenario: ScenarioKind, pose: glasshouse_sim::PoseError) -> SimTrolley {
    SimTrolley::new(SimTrolleySettings {
        world: glasshouse_sim::WorldSettings {
            pose,
            ..Default::default()
        },
        ..SimTrolleySettings::new(scenario, 3, (160, 120), 0.5)
    })
    .unwrap()
}

/// Each pose error moves the camera that renders but not the pose the frame reports.
#[test]
fn pose_errors_move_the_true_camera_and_the_frame_reports_the_believed_pose() {
    use glasshouse_sim::PoseError;
    let clean = sim(ScenarioKind::Two).capture(1).unwrap().unwrap();
    let knobs = [
        PoseError {
            hand_eye_error_deg: 0.5,
            ..PoseError::default()
        },
        PoseError {
            hand_eye_error_mm: 5.0,
            ..PoseError::default()
        },
        PoseError {
            joint_noise_deg: 0.05,
            ..PoseError::default()
        },
    ];
    for pose in knobs {
        let mut trolley = posed_sim(ScenarioKind::Two, pose);
        let frame = trolley.capture(1).unwrap().unwrap();
        assert_eq!(frame.world_from_camera, clean.world_from_camera, "{pose:?}");
        assert_ne!(frame.depth, clean.depth, "{pose:?}");
        let truth = trolley.true_world_from_camera(1);
        let offset_m =
            (truth.translation.vector - frame.world_from_camera.translation.vector).norm();
        let angle_rad = (truth.rotation.inverse() * frame.world_from_camera.rotation).angle();
        assert!(offset_m > 1e-5 || angle_rad > 1e-5, "{pose:?}");
        assert!(offset_m < 0.02 && angle_rad < 1f64.to_radians(), "{pose:?}");
    }
    // Joint noise is new every frame; the hand-eye error is the same for the whole run.
    let jittery = posed_sim(ScenarioKind::Two, knobs[2]);
    assert_ne!(
        jittery.true_world_from_camera(1),
        jittery.true_world_from_camera(2)
    );
    let miscalibrated = posed_sim(ScenarioKind::Two, knobs[0]);
    assert_eq!(
        miscalibrated.true_world_from_camera(1),
        miscalibrated.true_world_from_camera(2)
    );
}

/// The rail's odometry error moves the camera along the rail, differently per segment.
#[test]
fn rail_error_moves_the_camera_along_the_rail_per_segment() {
    let rail = glasshouse_sim::PoseError {
        rail_error_mm: 10.0,
        ..Default::default()
    };
    let mut trolley = posed_sim(ScenarioKind::Row, rail);
    let mut offsets_m = Vec::new();
    for seq in 1..=3 {
        let believed = trolley.world_from_camera();
        let offset =
            trolley.true_world_from_camera(seq).translation.vector - believed.translation.vector;
        assert!(
            offset.y.abs() < 1e-12 && offset.z.abs() < 1e-12,
            "{offset:?}"
        );
        offsets_m.push(offset.x);
        assert!(trolley.next_segment().is_some());
    }
    assert!(
        offsets_m.iter().all(|x| x.abs() > 1e-6 && x.abs() < 0.1),
        "{offsets_m:?}"
    );
    assert_ne!(offsets_m[0], offsets_m[1]);
    // A scenario without a rail has no odometry error.
    let gantry = posed_sim(ScenarioKind::Two, rail);
    assert_eq!(gantry.true_world_from_camera(1), gantry.world_from_camera());
}

#[test]
fn clouds_cast_on_several_threads_make_the_same_map_as_on_one() {
    assert_eq!(PlanningSettings::default().insert_threads, 1);
    let mut trolley = sim(ScenarioKind::Two);
    let mut one = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    let mut three = TrolleyPlanner::new(PlanningSettings {
        insert_threads: 3,
        ..PlanningSettings::default()
    })
    .unwrap();
    for seq in 1..=3 {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let id = FrameId::new(EPOCH_NS, seq);
        let cloud = detect_frame(&frame, id, "d1", &DetectorConfig::default()).unwrap();
        one.integrate(&cloud, EPOCH_NS).unwrap();
        three.integrate(&cloud, EPOCH_NS).unwrap();
    }
    assert!(one.map().len() > 1000, "{} voxels", one.map().len());
    let map_bytes = |p: &TrolleyPlanner| p.snapshot("t1", "p1").unwrap().map;
    assert!(map_bytes(&one) == map_bytes(&three), "the maps differ");
    let too_many = PlanningSettings {
        insert_threads: 65,
        ..PlanningSettings::default()
    };
    assert!(matches!(
        TrolleyPlanner::new(too_many),
        Err(PlanningError::Settings(e)) if e.contains("insert_threads")
    ));
}

/// Map updates applied in order (solid voxels shown, freed ones taken away) show exactly the
/// map's solid voxels after every cloud, and a voxel is reported freed only after it was shown.
#[test]
fn map_updates_in_order_show_exactly_the_maps_solid_voxels() {
    use glasshouse_proto::VoxelState;
    use std::collections::BTreeMap;
    let mut trolley = noisy_sim(0.1, 1).unwrap();
    let mut planner = TrolleyPlanner::new(PlanningSettings::default()).unwrap();
    let mut shown: BTreeMap<[i32; 3], VoxelState> = BTreeMap::new();
    let mut freed_after_shown = 0;
    for seq in 1..=6 {
        let frame = trolley.capture(seq).unwrap().unwrap();
        let id = FrameId::new(EPOCH_NS, seq);
        let cloud = detect_frame(&frame, id, "d1", &DetectorConfig::default()).unwrap();
        planner.integrate(&cloud, EPOCH_NS).unwrap();
        for change in planner.map_update(seq, "p1").voxels {
            let [x, y, z] = change.key;
            let now = planner.map().get(glasshouse_roimap::VoxelKey::new(x, y, z));
            assert_eq!(
                now.map(|v| (v.occupancy_logodds, v.roi_logodds)),
                Some((change.occupancy_logodds, change.roi_logodds))
            );
            if change.state == VoxelState::Free {
                assert!(shown.remove(&change.key).is_some(), "{change:?}");
                freed_after_shown += 1;
            } else {
                shown.insert(change.key, change.state);
            }
        }
        let map = planner.map();
        let solid: BTreeMap<[i32; 3], VoxelState> = map
            .iter()
            .filter_map(|(k, v)| {
                let state = match (map.is_roi(k), v.occupancy()) {
                    (true, _) => VoxelState::Roi,
                    (false, glasshouse_roimap::Occupancy::Occupied) => VoxelState::Occupied,
                    _ => return None,
                };
                Some(([k.x, k.y, k.z], state))
            })
            .collect();
        assert_eq!(shown, solid, "after cloud {seq}");
        if let Some(plan) = planner.plan(&frame.world_from_camera, seq).unwrap() {
            trolley.execute(&[plan.views[0].world_from_camera]);
        }
    }
    assert!(shown.len() > 500, "{} solid voxels", shown.len());
    assert!(freed_after_shown > 0, "no shown voxel was freed again");
}
