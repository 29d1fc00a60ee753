//! Small, valid example messages of every kind, for tests and for fault injection.

use glasshouse_geom::{
    look_at, Aabb, CameraIntrinsics, FruitEstimate, FruitSolid, FruitSurface, Rgb, RgbSum,
    SolidKind,
};
use nalgebra::{Isometry3, Point3, Vector3};

use crate::*;

fn pose() -> Isometry3<f64> {
    look_at(&Point3::new(0.1, -0.4, 1.0), &Point3::new(0.0, 0.3, 0.8))
}

fn region() -> Aabb {
    Aabb::new(Point3::new(-1.0, -1.0, 0.0), Point3::new(1.0, 1.0, 1.5))
}

/// The boot epoch of the samples' publisher (2026-01-01T00:00:00Z).
pub const SAMPLE_EPOCH_NS: u64 = 1_767_225_600_000_000_000;

/// The ownership epoch of the samples' planner: its term began a second after the publisher's
/// boot.
pub const SAMPLE_OWNER_EPOCH: u64 = SAMPLE_EPOCH_NS + 1_000_000_000;

/// A header for trolley `t1`.
pub fn header(seq: u64) -> Header {
    Header {
        seq,
        epoch_ns: SAMPLE_EPOCH_NS,
        stamp_ns: 1_000_000 * seq,
        trolley_id: "t1".into(),
        source_id: "sample".into(),
        frame_id: "world".into(),
    }
}

/// A small valid message of `kind`.
pub fn message(kind: MessageKind) -> Message {
    match kind {
        MessageKind::RgbdFrame => rgbd_frame().into(),
        MessageKind::ArmState => arm_state().into(),
        MessageKind::TrolleyInfo => trolley_info().into(),
        MessageKind::RoiCloud => roi_cloud().into(),
        MessageKind::RankedViews => ranked_views().into(),
        MessageKind::FruitEstimates => fruit_estimates().into(),
        MessageKind::MapUpdate => map_update().into(),
        MessageKind::PlannerStatus => planner_status().into(),
        MessageKind::TrolleyStatus => trolley_status().into(),
        MessageKind::DetectorStatus => detector_status().into(),
        MessageKind::MapSnapshot => map_snapshot().into(),
        MessageKind::FleetFruits => fleet_fruits().into(),
    }
}

fn intrinsics() -> CameraIntrinsics {
    CameraIntrinsics::from_horizontal_fov(8, 6, 80f64.to_radians())
}

/// A small valid RgbdFrame.
pub fn rgbd_frame() -> RgbdFrame {
    let intrinsics = intrinsics();
    RgbdFrame {
        intrinsics,
        world_from_camera: pose(),
        depth_scale_m: 0.001,
        min_range_m: 0.15,
        max_range_m: 3.0,
        depth: (0..48).map(|i| 500 + i * 10).collect(),
        rgb: (0..144).map(|i| (i * 7 % 256) as u8).collect(),
        depth_encoding: Default::default(),
        rgb_encoding: Default::default(),
    }
}

/// A small valid ArmState.
pub fn arm_state() -> ArmState {
    ArmState {
        joint_angles_rad: vec![0.0, -1.57, 1.2, 0.3, 1.57, 0.0],
        world_from_camera: pose(),
        rail_position_m: 1.5,
        lift_height_m: 0.2,
        moving: true,
        views_done: 3,
    }
}

/// A small valid TrolleyInfo.
pub fn trolley_info() -> TrolleyInfo {
    let intrinsics = intrinsics();
    TrolleyInfo {
        world_from_base: Isometry3::translation(0.0, -0.7, 0.3),
        camera_workspace: region(),
        sampling_region: region().inflated(0.1),
        scenario: "row".into(),
        scene_seed: 7,
        intrinsics,
        robot: Some(Box::new(glasshouse_arm::Robot::row(
            glasshouse_arm::Interval::new(0.0, 20.0),
        ))),
        owner_epoch: SAMPLE_OWNER_EPOCH,
        owner_id: "p1".into(),
        visit: 2,
    }
}

/// A small valid RoiCloud.
pub fn roi_cloud() -> RoiCloud {
    RoiCloud {
        points_in_world: vec![
            Point3::new(0.1, 0.2, 0.3),
            Point3::new(0.4, 0.5, 0.6),
            Point3::new(f32::NAN, 0.0, 0.0),
        ],
        roi: vec![true, false, false],
        sensor_origin_in_world: Point3::new(0.0, -0.5, 1.0),
        world_from_camera: look_at(&Point3::new(0.0, -0.5, 1.0), &Point3::new(0.0, 0.3, 0.8)),
        source_frame_seq: 42,
        source_frame_epoch_ns: SAMPLE_EPOCH_NS,
        invalid_pixels: 5,
        detector_id: "d1".into(),
        roi_confidence: vec![230, 40, 0],
        // The one ROI point's colour.
        roi_rgb: vec![200, 30, 20],
    }
}

/// A small valid RankedViews.
pub fn ranked_views() -> RankedViews {
    RankedViews {
        views: vec![
            RankedView {
                world_from_camera: pose(),
                utility: 0.5,
                gain: 0.6,
                cost_m: 0.5,
                kind: ViewKind::Roi,
            },
            RankedView {
                world_from_camera: Isometry3::translation(0.2, 0.0, 1.0),
                utility: 0.3,
                gain: 0.35,
                cost_m: 0.25,
                kind: ViewKind::Exploration,
            },
        ],
        based_on_seq: 42,
        based_on_epoch_ns: SAMPLE_EPOCH_NS,
        planning_time_ms: 12.5,
        planner_id: "p1".into(),
        owner_epoch: SAMPLE_OWNER_EPOCH,
    }
}

/// A fruit seen on visits 0 and 2 (`fruit_id` its estimate on the current one, 0: none),
/// green on the first and red on the last.
pub fn fruit_histories(fruit_id: u32) -> Vec<FruitHistory> {
    let record = |visit: u32, grown: f64, colour: Rgb| FruitVisit {
        visit,
        centre: Point3::new(0.25, -0.5, 1.0),
        // Values a wire f32 holds exactly, so that a round trip compares equal.
        size_m: Vector3::new(0.0625, 0.078125, 0.09375) * grown,
        volume_m3: 2f64.powi(-13) * grown.powi(3),
        colour: Some(colour),
        // The growth measured on one shape, where it was (not on the first record).
        volume_ratio: (visit > 0).then_some(grown.powi(3)),
    };
    vec![FruitHistory {
        season_id: 5,
        fruit_id,
        visits: vec![
            record(0, 1.0, Rgb::new(110, 150, 40)),
            record(2, 1.25, Rgb::new(190, 35, 25)),
        ],
        last_surface: None,
    }]
}

/// [`fruit_histories`] as a snapshot keeps them: with the last visit's solid and surface.
pub fn fruit_histories_with_surfaces() -> Vec<FruitHistory> {
    let mut histories = fruit_histories(0);
    for h in &mut histories {
        h.last_surface = sample_fruit().solid.map(|solid| FruitSurface {
            solid,
            points_m: vec![
                Point3::new(0.125, 0.25, 0.875),
                Point3::new(0.0625, 0.25, 0.9375),
            ],
        });
    }
    histories
}

/// A small valid FruitEstimates.
pub fn fruit_estimates() -> FruitEstimates {
    FruitEstimates {
        fruits: vec![sample_fruit()],
        based_on_seq: 42,
        planner_id: "p1".into(),
        owner_epoch: SAMPLE_OWNER_EPOCH,
        visit: 2,
        history: fruit_histories(sample_fruit().id),
    }
}

/// A small valid MapUpdate.
pub fn map_update() -> MapUpdate {
    MapUpdate {
        resolution_m: 0.01,
        map_seq: 9,
        based_on_seq: 42,
        full: false,
        voxels: vec![
            VoxelChange {
                key: [1, -2, 3],
                occupancy_logodds: 0.8473,
                roi_logodds: 0.8473,
                state: VoxelState::Occupied,
            },
            VoxelChange {
                key: [-4, 5, 6],
                occupancy_logodds: -0.4055,
                roi_logodds: 0.0,
                state: VoxelState::Free,
            },
        ],
        planner_id: "p1".into(),
        registration: Some(frame_registration()),
        owner_epoch: SAMPLE_OWNER_EPOCH,
    }
}

/// A registration that applied its correction (half a degree about z, 6 mm along x).
pub fn frame_registration() -> FrameRegistration {
    FrameRegistration {
        frame: FrameId::new(SAMPLE_EPOCH_NS, 42),
        verdict: RegistrationVerdict::Applied,
        reason: RegistrationReason::None,
        world_correction: Some(RigidCorrection {
            translation_m: nalgebra::Vector3::new(0.006, -0.001, 0.0),
            rotation_vector_rad: nalgebra::Vector3::new(0.0, 0.0, 0.5f64.to_radians()),
        }),
        rotation_deg: Some(0.5),
        sensor_shift_m: Some(0.0065),
        max_point_shift_m: Some(0.009),
        rms_before_m: Some(0.0042),
        rms_after_m: Some(0.0018),
        inliers: Some(1800),
        inlier_share: Some(0.86),
        unconstrained_directions: Some(0),
        iterations: Some(5),
        hand_eye_correction: Some(RigidCorrection {
            translation_m: nalgebra::Vector3::new(0.002, 0.003, -0.001),
            rotation_vector_rad: nalgebra::Vector3::new(0.004, 0.0, -0.002),
        }),
        ..FrameRegistration::default()
    }
}

/// A small valid PlannerStatus.
pub fn planner_status() -> PlannerStatus {
    PlannerStatus {
        planner_id: "p1".into(),
        owned_trolleys: vec!["t1".into(), "t2".into()],
        standby_trolleys: vec!["t3".into()],
        clouds_integrated: 10,
        views_published: 9,
        last_planning_time_ms: 30.0,
        mean_planning_time_ms: 28.0,
        dropped_messages: 1,
        map_voxels: 12345,
        refused_clouds: 1,
        stage_totals: StageTimes {
            integrate_ms: 500.0,
            cluster_ms: 20.5,
            track_ms: 1.25,
            fit_ms: 80.0,
            plan_ms: 300.0,
            publish_ms: 40.0,
        },
        catch_up_ms: 210.0,
        registrations: RegistrationTotals {
            applied: 6,
            kept_as_sent: 2,
            rejected: 1,
            skipped: 1,
        },
        stale_epoch: 2,
        stepped_down: 1,
        unassigned_clouds: 3,
        colourless_clouds: 1,
        standby_decodes_ahead: 4,
        decoded_ahead_adopted: 2,
    }
}

/// A small valid TrolleyStatus.
pub fn trolley_status() -> TrolleyStatus {
    TrolleyStatus {
        state: TrolleyState::Moving,
        views_done: 4,
        frames_published: 5,
        unreachable_views: 1,
        reannounces: 0,
        dropped_messages: 2,
        last_views_seq: 4,
        message: "moving".into(),
        refused_views: 3,
        stale_views: 1,
        owner_epoch: SAMPLE_OWNER_EPOCH,
        owner_terms: vec![
            OwnerTerm {
                planner_id: "p2".into(),
                owner_epoch: SAMPLE_OWNER_EPOCH - 1_000,
                views_executed: 1,
            },
            OwnerTerm {
                planner_id: "p1".into(),
                owner_epoch: SAMPLE_OWNER_EPOCH,
                views_executed: 3,
            },
        ],
    }
}

/// A small valid DetectorStatus.
pub fn detector_status() -> DetectorStatus {
    DetectorStatus {
        detector_id: "d1".into(),
        frames_processed: 7,
        dropped_messages: 0,
        mean_detect_time_ms: 8.0,
    }
}

/// A small valid MapSnapshot.
pub fn map_snapshot() -> MapSnapshot {
    MapSnapshot {
        trolley_id: "t1".into(),
        planner_id: "p2".into(),
        based_on_seq: 42,
        based_on_epoch_ns: SAMPLE_EPOCH_NS,
        map: vec![1, 2, 3, 4, 5],
        tracked_fruits: vec![TrackedFruit {
            id: 3,
            centre_in_world: Point3::new(0.1, 0.2, 0.9),
            colour: RgbSum {
                r: 1900,
                g: 350,
                b: 250,
                samples: 10,
            },
        }],
        next_fruit_id: 4,
        owner_epoch: SAMPLE_OWNER_EPOCH,
        visit: 2,
        season: fruit_histories_with_surfaces(),
        hand_eye: Some(HandEye {
            camera_believed_from_true: Isometry3::translation(0.004, -0.002, 0.001),
            scans_seen: 3,
            scans: vec![HandEyeScan {
                world_from_camera: Isometry3::translation(0.5, 0.0, 1.2),
                points_in_camera: vec![Point3::new(0.1, 0.0, 0.8), Point3::new(0.0, 0.1, 0.9)],
                normals_in_camera: vec![Vector3::new(0.0, 0.0, -1.0), Vector3::new(0.0, 0.6, -0.8)],
            }],
        }),
    }
}

/// A small valid FleetFruits.
pub fn fleet_fruits() -> FleetFruits {
    FleetFruits {
        fruits: vec![FleetFruit {
            fleet_id: "t1/3".into(),
            fruit: sample_fruit(),
            sources: vec!["t1/3".into(), "t2/8".into()],
        }],
        planner_id: "p1".into(),
        trolleys: 2,
    }
}

/// A fitted fruit whose values are exact in `f32`, as the wire carries them.
fn sample_fruit() -> FruitEstimate {
    let p = |x: f32, y: f32, z: f32| Point3::new(x, y, z).cast::<f64>();
    let semi = nalgebra::Vector3::new(0.03f32, 0.03, 0.04);
    let (a, b, c) = (semi.x, semi.y, semi.z);
    FruitEstimate {
        id: 3,
        centre: p(0.1, 0.2, 0.9),
        min: p(0.07, 0.17, 0.86),
        max: p(0.13, 0.23, 0.94),
        volume_m3: f64::from(0.06f32 * 0.06 * 0.08),
        voxel_count: 120,
        confidence: f64::from(0.6f32),
        view_directions: 3,
        solid: Some(FruitSolid {
            kind: SolidKind::Ellipsoid,
            centre: p(0.1, 0.2, 0.91),
            semi_axes_m: semi.cast(),
            world_from_body: nalgebra::UnitQuaternion::from_euler_angles(0.3, 0.0, 0.1),
            exponents: [0.5, 1.0],
            taper: f64::from(0.2f32),
            volume_m3: f64::from(4.0 / 3.0 * std::f32::consts::PI * a * b * c),
            box_min: p(0.065, 0.165, 0.87),
            box_max: p(0.135, 0.235, 0.95),
            box_volume_m3: f64::from(0.07f32 * 0.07 * 0.08),
            confidence: 0.75,
            rms_residual_m: f64::from(0.002f32),
        }),
        colour: Some(Rgb::new(190, 35, 25)),
    }
}
