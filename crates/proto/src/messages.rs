//! Owned message types and their conversion to and from the generated FlatBuffers code.

use flatbuffers::{FlatBufferBuilder, WIPOffset};
use glasshouse_geom::{Aabb, CameraIntrinsics};
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};

use crate::{fb, Header, MessageKind, ProtoError, Result, PROTOCOL_VERSION};

/// One RGB-D capture. `depth_m = depth[i] * depth_scale_m`; 0 means no measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbdFrame {
    pub intrinsics: CameraIntrinsics,
    pub world_from_camera: Isometry3<f64>,
    pub depth_scale_m: f32,
    pub min_range_m: f32,
    pub max_range_m: f32,
    pub depth: Vec<u16>,
    pub rgb: Vec<u8>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct ArmState {
    pub joint_angles_rad: Vec<f64>,
    pub world_from_camera: Isometry3<f64>,
    pub rail_position_m: f64,
    pub lift_height_m: f64,
    pub moving: bool,
    pub views_done: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ArmModel {
    None,
    Ur5e,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MountKind {
    FreeCamera,
    StaticPole,
    CeilingGantry,
    RailLift,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrolleyInfo {
    pub arm_model: ArmModel,
    pub mount: MountKind,
    pub world_from_base: Isometry3<f64>,
    pub joint_min_rad: Vec<f64>,
    pub joint_max_rad: Vec<f64>,
    pub rail_min_m: f64,
    pub rail_max_m: f64,
    pub lift_min_m: f64,
    pub lift_max_m: f64,
    /// Where the camera centre can be placed.
    pub camera_workspace: Aabb,
    /// Where view targets may lie (the plants).
    pub sampling_region: Aabb,
    pub scenario: String,
    pub scene_seed: u64,
    pub intrinsics: CameraIntrinsics,
}

/// ROI-labelled points in the world frame from one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct RoiCloud {
    pub points_in_world: Vec<Point3<f32>>,
    pub roi: Vec<bool>,
    pub sensor_origin_in_world: Point3<f64>,
    pub source_frame_seq: u64,
    pub invalid_pixels: u32,
    pub detector_id: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewKind {
    Roi,
    Exploration,
}

#[derive(Clone, Debug, PartialEq)]
pub struct RankedView {
    pub world_from_camera: Isometry3<f64>,
    pub utility: f32,
    pub gain: f32,
    pub cost_m: f32,
    pub kind: ViewKind,
}

/// Candidate views, best first.
#[derive(Clone, Debug, PartialEq)]
pub struct RankedViews {
    pub views: Vec<RankedView>,
    /// The frame sequence these views were planned on.
    pub based_on_seq: u64,
    pub planning_time_ms: f32,
    pub planner_id: String,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Fruit {
    pub id: u32,
    pub centre_in_world: Point3<f32>,
    pub box_min: Point3<f32>,
    pub box_max: Point3<f32>,
    pub volume_m3: f32,
    pub voxel_count: u32,
    pub confidence: f32,
    /// The fitted whole-fruit estimate; `None` when the planner made no fit.
    pub fitted: Option<FittedEllipsoid>,
}

/// Axis-aligned ellipsoid estimate of one fruit, world frame, metres.
#[derive(Clone, Debug, PartialEq)]
pub struct FittedEllipsoid {
    pub centre_in_world: Point3<f32>,
    pub semi_axes_m: Vector3<f32>,
    /// `4/3·π·a·b·c`.
    pub volume_m3: f32,
    /// `8·a·b·c`, comparable with the box estimate's volume.
    pub box_volume_m3: f32,
    /// Share of the fitted surface the map has observed, 0..1.
    pub confidence: f32,
    /// False when the fit was degenerate and this is the ellipsoid inscribed in the cluster's box.
    pub is_fit: bool,
}

/// A fruit the tracker follows (id and centre), carried in [`MapSnapshot`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedFruit {
    pub id: u32,
    pub centre_in_world: Point3<f32>,
}

/// One planner's copy of a trolley's state (reply to a snapshot query).
#[derive(Clone, Debug, PartialEq)]
pub struct MapSnapshot {
    pub trolley_id: String,
    pub planner_id: String,
    /// The last RoiCloud frame seq integrated into the map.
    pub based_on_seq: u64,
    /// `glasshouse_roimap` snapshot bytes.
    pub map: Vec<u8>,
    pub tracked_fruits: Vec<TrackedFruit>,
    pub next_fruit_id: u32,
}

/// One fruit of the fleet map.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetFruit {
    pub fleet_id: String,
    pub fruit: Fruit,
    pub sources: Vec<String>,
}

/// Every trolley's fruits merged into one map.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetFruits {
    pub fruits: Vec<FleetFruit>,
    pub planner_id: String,
    pub trolleys: u32,
}

#[derive(Clone, Debug, PartialEq)]
pub struct FruitEstimates {
    pub fruits: Vec<Fruit>,
    pub based_on_seq: u64,
    pub planner_id: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelState {
    Free,
    Occupied,
    Roi,
}

/// One voxel's new value; `key = floor(position / resolution)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VoxelChange {
    pub key: [i32; 3],
    pub occupancy_logodds: f32,
    pub roi_logodds: f32,
    pub state: VoxelState,
}

#[derive(Clone, Debug, PartialEq)]
pub struct MapUpdate {
    pub resolution_m: f32,
    pub map_seq: u64,
    pub based_on_seq: u64,
    pub full: bool,
    pub voxels: Vec<VoxelChange>,
    pub planner_id: String,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlannerStatus {
    pub planner_id: String,
    pub owned_trolleys: Vec<String>,
    pub standby_trolleys: Vec<String>,
    pub clouds_integrated: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub mean_planning_time_ms: f32,
    pub dropped_messages: u64,
    pub map_voxels: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrolleyState {
    Starting,
    Capturing,
    WaitingForViews,
    Moving,
    Done,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrolleyStatus {
    pub state: TrolleyState,
    pub views_done: u32,
    pub frames_published: u64,
    pub unreachable_views: u32,
    pub reannounces: u32,
    pub dropped_messages: u64,
    pub last_views_seq: u64,
    pub message: String,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct DetectorStatus {
    pub detector_id: String,
    pub frames_processed: u64,
    pub dropped_messages: u64,
    pub mean_detect_time_ms: f32,
}

/// Any message of the protocol.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    RgbdFrame(RgbdFrame),
    ArmState(ArmState),
    TrolleyInfo(TrolleyInfo),
    RoiCloud(RoiCloud),
    RankedViews(RankedViews),
    FruitEstimates(FruitEstimates),
    MapUpdate(MapUpdate),
    PlannerStatus(PlannerStatus),
    TrolleyStatus(TrolleyStatus),
    DetectorStatus(DetectorStatus),
    MapSnapshot(MapSnapshot),
    FleetFruits(FleetFruits),
}

impl Message {
    pub fn kind(&self) -> MessageKind {
        match self {
            Message::RgbdFrame(_) => MessageKind::RgbdFrame,
            Message::ArmState(_) => MessageKind::ArmState,
            Message::TrolleyInfo(_) => MessageKind::TrolleyInfo,
            Message::RoiCloud(_) => MessageKind::RoiCloud,
            Message::RankedViews(_) => MessageKind::RankedViews,
            Message::FruitEstimates(_) => MessageKind::FruitEstimates,
            Message::MapUpdate(_) => MessageKind::MapUpdate,
            Message::PlannerStatus(_) => MessageKind::PlannerStatus,
            Message::TrolleyStatus(_) => MessageKind::TrolleyStatus,
            Message::DetectorStatus(_) => MessageKind::DetectorStatus,
            Message::MapSnapshot(_) => MessageKind::MapSnapshot,
            Message::FleetFruits(_) => MessageKind::FleetFruits,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Writing

fn pose_to_fb(pose: &Isometry3<f64>) -> fb::Pose {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    fb::Pose::new(
        &fb::Vec3d::new(t.x, t.y, t.z),
        &fb::Quat::new(q.i, q.j, q.k, q.w),
    )
}

fn intrinsics_to_fb(k: &CameraIntrinsics) -> fb::Intrinsics {
    fb::Intrinsics::new(k.width, k.height, k.fx, k.fy, k.cx, k.cy)
}

fn vec3f(p: &Point3<f32>) -> fb::Vec3 {
    fb::Vec3::new(p.x, p.y, p.z)
}

fn box_to_fb(b: &Aabb) -> fb::Box3 {
    fb::Box3::new(&vec3f(&b.min.cast()), &vec3f(&b.max.cast()))
}

fn view_kind_to_fb(kind: ViewKind) -> fb::ViewKind {
    match kind {
        ViewKind::Roi => fb::ViewKind::Roi,
        ViewKind::Exploration => fb::ViewKind::Exploration,
    }
}

fn voxel_state_to_fb(state: VoxelState) -> fb::VoxelState {
    match state {
        VoxelState::Free => fb::VoxelState::Free,
        VoxelState::Occupied => fb::VoxelState::Occupied,
        VoxelState::Roi => fb::VoxelState::Roi,
    }
}

fn trolley_state_to_fb(state: TrolleyState) -> fb::TrolleyState {
    match state {
        TrolleyState::Starting => fb::TrolleyState::Starting,
        TrolleyState::Capturing => fb::TrolleyState::Capturing,
        TrolleyState::WaitingForViews => fb::TrolleyState::WaitingForViews,
        TrolleyState::Moving => fb::TrolleyState::Moving,
        TrolleyState::Done => fb::TrolleyState::Done,
    }
}

fn strings<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    items: &[String],
) -> WIPOffset<flatbuffers::Vector<'a, flatbuffers::ForwardsUOffset<&'a str>>> {
    let offsets: Vec<_> = items.iter().map(|s| fbb.create_string(s)).collect();
    fbb.create_vector(&offsets)
}

fn write_payload(
    fbb: &mut FlatBufferBuilder<'_>,
    message: &Message,
) -> (fb::Payload, WIPOffset<flatbuffers::UnionWIPOffset>) {
    match message {
        Message::RgbdFrame(m) => {
            let depth = fbb.create_vector(&m.depth);
            let rgb = fbb.create_vector(&m.rgb);
            let intrinsics = intrinsics_to_fb(&m.intrinsics);
            let pose = pose_to_fb(&m.world_from_camera);
            let t = fb::RgbdFrame::create(
                fbb,
                &fb::RgbdFrameArgs {
                    intrinsics: Some(&intrinsics),
                    world_from_camera: Some(&pose),
                    depth_scale_m: m.depth_scale_m,
                    min_range_m: m.min_range_m,
                    max_range_m: m.max_range_m,
                    depth: Some(depth),
                    rgb: Some(rgb),
                },
            );
            (fb::Payload::RgbdFrame, t.as_union_value())
        }
        Message::ArmState(m) => {
            let joints = fbb.create_vector(&m.joint_angles_rad);
            let pose = pose_to_fb(&m.world_from_camera);
            let t = fb::ArmState::create(
                fbb,
                &fb::ArmStateArgs {
                    joint_angles_rad: Some(joints),
                    world_from_camera: Some(&pose),
                    rail_position_m: m.rail_position_m,
                    lift_height_m: m.lift_height_m,
                    moving: m.moving,
                    views_done: m.views_done,
                },
            );
            (fb::Payload::ArmState, t.as_union_value())
        }
        Message::TrolleyInfo(m) => {
            let jmin = fbb.create_vector(&m.joint_min_rad);
            let jmax = fbb.create_vector(&m.joint_max_rad);
            let scenario = fbb.create_string(&m.scenario);
            let base = pose_to_fb(&m.world_from_base);
            let workspace = box_to_fb(&m.camera_workspace);
            let region = box_to_fb(&m.sampling_region);
            let intrinsics = intrinsics_to_fb(&m.intrinsics);
            let t = fb::TrolleyInfo::create(
                fbb,
                &fb::TrolleyInfoArgs {
                    arm_model: match m.arm_model {
                        ArmModel::None => fb::ArmModel::None,
                        ArmModel::Ur5e => fb::ArmModel::Ur5e,
                    },
                    mount: match m.mount {
                        MountKind::FreeCamera => fb::MountKind::FreeCamera,
                        MountKind::StaticPole => fb::MountKind::StaticPole,
                        MountKind::CeilingGantry => fb::MountKind::CeilingGantry,
                        MountKind::RailLift => fb::MountKind::RailLift,
                    },
                    world_from_base: Some(&base),
                    joint_min_rad: Some(jmin),
                    joint_max_rad: Some(jmax),
                    rail_min_m: m.rail_min_m,
                    rail_max_m: m.rail_max_m,
                    lift_min_m: m.lift_min_m,
                    lift_max_m: m.lift_max_m,
                    camera_workspace: Some(&workspace),
                    sampling_region: Some(&region),
                    scenario: Some(scenario),
                    scene_seed: m.scene_seed,
                    intrinsics: Some(&intrinsics),
                },
            );
            (fb::Payload::TrolleyInfo, t.as_union_value())
        }
        Message::RoiCloud(m) => {
            let points: Vec<fb::Vec3> = m.points_in_world.iter().map(vec3f).collect();
            let points = fbb.create_vector(&points);
            let flags: Vec<u8> = m.roi.iter().map(|&r| u8::from(r)).collect();
            let roi = fbb.create_vector(&flags);
            let detector = fbb.create_string(&m.detector_id);
            let o = m.sensor_origin_in_world;
            let origin = fb::Vec3d::new(o.x, o.y, o.z);
            let t = fb::RoiCloud::create(
                fbb,
                &fb::RoiCloudArgs {
                    points: Some(points),
                    roi: Some(roi),
                    sensor_origin: Some(&origin),
                    source_frame_seq: m.source_frame_seq,
                    invalid_pixels: m.invalid_pixels,
                    detector_id: Some(detector),
                },
            );
            (fb::Payload::RoiCloud, t.as_union_value())
        }
        Message::RankedViews(m) => {
            let views: Vec<fb::View> = m
                .views
                .iter()
                .map(|v| {
                    fb::View::new(
                        &pose_to_fb(&v.world_from_camera),
                        v.utility,
                        v.gain,
                        v.cost_m,
                        view_kind_to_fb(v.kind),
                    )
                })
                .collect();
            let views = fbb.create_vector(&views);
            let planner = fbb.create_string(&m.planner_id);
            let t = fb::RankedViews::create(
                fbb,
                &fb::RankedViewsArgs {
                    views: Some(views),
                    based_on_seq: m.based_on_seq,
                    planning_time_ms: m.planning_time_ms,
                    planner_id: Some(planner),
                },
            );
            (fb::Payload::RankedViews, t.as_union_value())
        }
        Message::FruitEstimates(m) => {
            let fruits: Vec<_> = m.fruits.iter().map(|f| write_fruit(fbb, f)).collect();
            let fruits = fbb.create_vector(&fruits);
            let planner = fbb.create_string(&m.planner_id);
            let t = fb::FruitEstimates::create(
                fbb,
                &fb::FruitEstimatesArgs {
                    fruits: Some(fruits),
                    based_on_seq: m.based_on_seq,
                    planner_id: Some(planner),
                },
            );
            (fb::Payload::FruitEstimates, t.as_union_value())
        }
        Message::MapUpdate(m) => {
            let voxels: Vec<fb::VoxelChange> = m
                .voxels
                .iter()
                .map(|v| {
                    fb::VoxelChange::new(
                        v.key[0],
                        v.key[1],
                        v.key[2],
                        v.occupancy_logodds,
                        v.roi_logodds,
                        voxel_state_to_fb(v.state),
                    )
                })
                .collect();
            let voxels = fbb.create_vector(&voxels);
            let planner = fbb.create_string(&m.planner_id);
            let t = fb::MapUpdate::create(
                fbb,
                &fb::MapUpdateArgs {
                    resolution_m: m.resolution_m,
                    map_seq: m.map_seq,
                    based_on_seq: m.based_on_seq,
                    full: m.full,
                    voxels: Some(voxels),
                    planner_id: Some(planner),
                },
            );
            (fb::Payload::MapUpdate, t.as_union_value())
        }
        Message::PlannerStatus(m) => {
            let pid = fbb.create_string(&m.planner_id);
            let owned = strings(fbb, &m.owned_trolleys);
            let standby = strings(fbb, &m.standby_trolleys);
            let t = fb::PlannerStatus::create(
                fbb,
                &fb::PlannerStatusArgs {
                    planner_id: Some(pid),
                    owned_trolleys: Some(owned),
                    standby_trolleys: Some(standby),
                    clouds_integrated: m.clouds_integrated,
                    views_published: m.views_published,
                    last_planning_time_ms: m.last_planning_time_ms,
                    mean_planning_time_ms: m.mean_planning_time_ms,
                    dropped_messages: m.dropped_messages,
                    map_voxels: m.map_voxels,
                },
            );
            (fb::Payload::PlannerStatus, t.as_union_value())
        }
        Message::TrolleyStatus(m) => {
            let message = fbb.create_string(&m.message);
            let t = fb::TrolleyStatus::create(
                fbb,
                &fb::TrolleyStatusArgs {
                    state: trolley_state_to_fb(m.state),
                    views_done: m.views_done,
                    frames_published: m.frames_published,
                    unreachable_views: m.unreachable_views,
                    reannounces: m.reannounces,
                    dropped_messages: m.dropped_messages,
                    last_views_seq: m.last_views_seq,
                    message: Some(message),
                },
            );
            (fb::Payload::TrolleyStatus, t.as_union_value())
        }
        Message::MapSnapshot(m) => {
            let trolley = fbb.create_string(&m.trolley_id);
            let planner = fbb.create_string(&m.planner_id);
            let map = fbb.create_vector(&m.map);
            let tracked: Vec<fb::TrackedFruit> = m
                .tracked_fruits
                .iter()
                .map(|f| fb::TrackedFruit::new(f.id, &vec3f(&f.centre_in_world)))
                .collect();
            let tracked = fbb.create_vector(&tracked);
            let t = fb::MapSnapshot::create(
                fbb,
                &fb::MapSnapshotArgs {
                    trolley_id: Some(trolley),
                    planner_id: Some(planner),
                    based_on_seq: m.based_on_seq,
                    map: Some(map),
                    tracked_fruits: Some(tracked),
                    next_fruit_id: m.next_fruit_id,
                },
            );
            (fb::Payload::MapSnapshot, t.as_union_value())
        }
        Message::FleetFruits(m) => {
            let fruits: Vec<_> = m
                .fruits
                .iter()
                .map(|f| {
                    let fleet_id = fbb.create_string(&f.fleet_id);
                    let fruit = write_fruit(fbb, &f.fruit);
                    let sources: Vec<_> = f.sources.iter().map(|s| fbb.create_string(s)).collect();
                    let sources = fbb.create_vector(&sources);
                    fb::FleetFruit::create(
                        fbb,
                        &fb::FleetFruitArgs {
                            fleet_id: Some(fleet_id),
                            fruit: Some(fruit),
                            sources: Some(sources),
                        },
                    )
                })
                .collect();
            let fruits = fbb.create_vector(&fruits);
            let planner = fbb.create_string(&m.planner_id);
            let t = fb::FleetFruits::create(
                fbb,
                &fb::FleetFruitsArgs {
                    fruits: Some(fruits),
                    planner_id: Some(planner),
                    trolleys: m.trolleys,
                },
            );
            (fb::Payload::FleetFruits, t.as_union_value())
        }
        Message::DetectorStatus(m) => {
            let did = fbb.create_string(&m.detector_id);
            let t = fb::DetectorStatus::create(
                fbb,
                &fb::DetectorStatusArgs {
                    detector_id: Some(did),
                    frames_processed: m.frames_processed,
                    dropped_messages: m.dropped_messages,
                    mean_detect_time_ms: m.mean_detect_time_ms,
                },
            );
            (fb::Payload::DetectorStatus, t.as_union_value())
        }
    }
}

fn write_fruit<'a>(fbb: &mut FlatBufferBuilder<'a>, f: &Fruit) -> WIPOffset<fb::Fruit<'a>> {
    let centre = vec3f(&f.centre_in_world);
    let bbox = fb::Box3::new(&vec3f(&f.box_min), &vec3f(&f.box_max));
    let fitted = f.fitted.as_ref().map(|e| {
        let centre = vec3f(&e.centre_in_world);
        let semi_axes = fb::Vec3::new(e.semi_axes_m.x, e.semi_axes_m.y, e.semi_axes_m.z);
        fb::FittedEllipsoid::create(
            fbb,
            &fb::FittedEllipsoidArgs {
                centre: Some(&centre),
                semi_axes: Some(&semi_axes),
                volume_m3: e.volume_m3,
                box_volume_m3: e.box_volume_m3,
                confidence: e.confidence,
                is_fit: e.is_fit,
            },
        )
    });
    fb::Fruit::create(
        fbb,
        &fb::FruitArgs {
            id: f.id,
            centre: Some(&centre),
            box_: Some(&bbox),
            volume_m3: f.volume_m3,
            voxel_count: f.voxel_count,
            confidence: f.confidence,
            fitted,
        },
    )
}

fn read_fruit(kind: MessageKind, f: fb::Fruit<'_>) -> Result<Fruit> {
    let centre = f
        .centre()
        .ok_or_else(|| content(kind, "fruit centre is missing"))?;
    let bbox = f
        .box_()
        .ok_or_else(|| content(kind, "fruit box is missing"))?;
    let fitted = f
        .fitted()
        .map(|e| -> Result<FittedEllipsoid> {
            let centre = e
                .centre()
                .ok_or_else(|| content(kind, "fitted ellipsoid centre is missing"))?;
            let axes = e
                .semi_axes()
                .ok_or_else(|| content(kind, "fitted ellipsoid semi-axes are missing"))?;
            Ok(FittedEllipsoid {
                centre_in_world: point3f(centre),
                semi_axes_m: Vector3::new(axes.x(), axes.y(), axes.z()),
                volume_m3: e.volume_m3(),
                box_volume_m3: e.box_volume_m3(),
                confidence: e.confidence(),
                is_fit: e.is_fit(),
            })
        })
        .transpose()?;
    Ok(Fruit {
        id: f.id(),
        centre_in_world: point3f(centre),
        box_min: point3f(bbox.min()),
        box_max: point3f(bbox.max()),
        volume_m3: f.volume_m3(),
        voxel_count: f.voxel_count(),
        confidence: f.confidence(),
        fitted,
    })
}

pub(crate) fn write_envelope(header: &Header, message: &Message) -> Vec<u8> {
    let capacity = match message {
        Message::RgbdFrame(f) => f.depth.len() * 2 + f.rgb.len() + 1024,
        Message::RoiCloud(c) => c.points_in_world.len() * 13 + 1024,
        Message::MapUpdate(m) => m.voxels.len() * 24 + 1024,
        _ => 1024,
    };
    let mut fbb = FlatBufferBuilder::with_capacity(capacity);
    let (payload_type, payload) = write_payload(&mut fbb, message);
    let trolley_id = fbb.create_string(&header.trolley_id);
    let source_id = fbb.create_string(&header.source_id);
    let frame_id = fbb.create_string(&header.frame_id);
    let envelope = fb::Envelope::create(
        &mut fbb,
        &fb::EnvelopeArgs {
            version: PROTOCOL_VERSION,
            seq: header.seq,
            stamp_ns: header.stamp_ns,
            trolley_id: Some(trolley_id),
            source_id: Some(source_id),
            frame_id: Some(frame_id),
            payload_type,
            payload: Some(payload),
        },
    );
    fb::finish_envelope_buffer(&mut fbb, envelope);
    fbb.finished_data().to_vec()
}

// ---------------------------------------------------------------------------------------------
// Reading

fn content(kind: MessageKind, reason: impl Into<String>) -> ProtoError {
    ProtoError::Content {
        kind,
        reason: reason.into(),
    }
}

fn pose_from_fb(kind: MessageKind, field: &str, pose: Option<&fb::Pose>) -> Result<Isometry3<f64>> {
    let pose = pose.ok_or_else(|| content(kind, format!("{field} is missing")))?;
    let t = pose.translation();
    let r = pose.rotation();
    let values = [t.x(), t.y(), t.z(), r.x(), r.y(), r.z(), r.w()];
    if values.iter().any(|v| !v.is_finite()) {
        return Err(content(kind, format!("{field} is not finite")));
    }
    let q = Quaternion::new(r.w(), r.x(), r.y(), r.z());
    if q.norm() < 1e-6 {
        return Err(content(
            kind,
            format!("{field} has a zero rotation quaternion"),
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::new(t.x(), t.y(), t.z()),
        UnitQuaternion::from_quaternion(q),
    ))
}

fn intrinsics_from_fb(kind: MessageKind, k: Option<&fb::Intrinsics>) -> Result<CameraIntrinsics> {
    let k = k.ok_or_else(|| content(kind, "intrinsics are missing"))?;
    let intrinsics = CameraIntrinsics {
        width: k.width(),
        height: k.height(),
        fx: k.fx(),
        fy: k.fy(),
        cx: k.cx(),
        cy: k.cy(),
    };
    if !intrinsics.is_valid() {
        return Err(content(kind, format!("invalid intrinsics {intrinsics:?}")));
    }
    Ok(intrinsics)
}

fn point3f(v: &fb::Vec3) -> Point3<f32> {
    Point3::new(v.x(), v.y(), v.z())
}

fn box_from_fb(kind: MessageKind, field: &str, b: Option<&fb::Box3>) -> Result<Aabb> {
    let b = b.ok_or_else(|| content(kind, format!("{field} is missing")))?;
    let aabb = Aabb::new(point3f(b.min()).cast(), point3f(b.max()).cast());
    let finite = aabb
        .min
        .iter()
        .chain(aabb.max.iter())
        .all(|v| v.is_finite());
    if !finite || (0..3).any(|i| aabb.min[i] > aabb.max[i]) {
        return Err(content(
            kind,
            format!("{field} is not a finite box with min <= max"),
        ));
    }
    Ok(aabb)
}

fn string_or_empty(s: Option<&str>) -> String {
    s.unwrap_or_default().to_owned()
}

fn strings_from_fb(
    v: Option<flatbuffers::Vector<'_, flatbuffers::ForwardsUOffset<&str>>>,
) -> Vec<String> {
    v.map(|v| v.iter().map(str::to_owned).collect())
        .unwrap_or_default()
}

fn unknown_enum(kind: MessageKind, field: &str, value: u8) -> ProtoError {
    content(kind, format!("{field} has unknown value {value}"))
}

fn view_kind_from_fb(kind: MessageKind, v: fb::ViewKind) -> Result<ViewKind> {
    match v {
        fb::ViewKind::Roi => Ok(ViewKind::Roi),
        fb::ViewKind::Exploration => Ok(ViewKind::Exploration),
        other => Err(unknown_enum(kind, "view kind", other.0)),
    }
}

fn read_rgbd(m: fb::RgbdFrame<'_>) -> Result<RgbdFrame> {
    let kind = MessageKind::RgbdFrame;
    let intrinsics = intrinsics_from_fb(kind, m.intrinsics())?;
    let world_from_camera = pose_from_fb(kind, "world_from_camera", m.world_from_camera())?;
    let pixels = intrinsics.pixel_count();
    let depth = m.depth().ok_or_else(|| content(kind, "depth is missing"))?;
    let rgb = m.rgb().ok_or_else(|| content(kind, "rgb is missing"))?;
    if depth.len() != pixels {
        return Err(content(
            kind,
            format!("depth has {} values for {pixels} pixels", depth.len()),
        ));
    }
    if rgb.len() != 3 * pixels {
        return Err(content(
            kind,
            format!("rgb has {} bytes for {pixels} pixels", rgb.len()),
        ));
    }
    let scale = m.depth_scale_m();
    if !(scale.is_finite() && scale > 0.0) {
        return Err(content(
            kind,
            format!("depth scale {scale} is not positive"),
        ));
    }
    Ok(RgbdFrame {
        intrinsics,
        world_from_camera,
        depth_scale_m: scale,
        min_range_m: m.min_range_m(),
        max_range_m: m.max_range_m(),
        depth: depth.iter().collect(),
        rgb: rgb.bytes().to_vec(),
    })
}

fn read_message(envelope: &fb::Envelope<'_>, kind: MessageKind) -> Result<Message> {
    let missing = || ProtoError::NoPayload;
    Ok(match kind {
        MessageKind::RgbdFrame => Message::RgbdFrame(read_rgbd(
            envelope.payload_as_rgbd_frame().ok_or_else(missing)?,
        )?),
        MessageKind::ArmState => {
            let m = envelope.payload_as_arm_state().ok_or_else(missing)?;
            Message::ArmState(ArmState {
                joint_angles_rad: m
                    .joint_angles_rad()
                    .map(|v| v.iter().collect())
                    .unwrap_or_default(),
                world_from_camera: pose_from_fb(kind, "world_from_camera", m.world_from_camera())?,
                rail_position_m: m.rail_position_m(),
                lift_height_m: m.lift_height_m(),
                moving: m.moving(),
                views_done: m.views_done(),
            })
        }
        MessageKind::TrolleyInfo => {
            let m = envelope.payload_as_trolley_info().ok_or_else(missing)?;
            Message::TrolleyInfo(TrolleyInfo {
                arm_model: match m.arm_model() {
                    fb::ArmModel::None => ArmModel::None,
                    fb::ArmModel::Ur5e => ArmModel::Ur5e,
                    other => return Err(unknown_enum(kind, "arm model", other.0)),
                },
                mount: match m.mount() {
                    fb::MountKind::FreeCamera => MountKind::FreeCamera,
                    fb::MountKind::StaticPole => MountKind::StaticPole,
                    fb::MountKind::CeilingGantry => MountKind::CeilingGantry,
                    fb::MountKind::RailLift => MountKind::RailLift,
                    other => return Err(unknown_enum(kind, "mount", other.0)),
                },
                world_from_base: pose_from_fb(kind, "world_from_base", m.world_from_base())?,
                joint_min_rad: m
                    .joint_min_rad()
                    .map(|v| v.iter().collect())
                    .unwrap_or_default(),
                joint_max_rad: m
                    .joint_max_rad()
                    .map(|v| v.iter().collect())
                    .unwrap_or_default(),
                rail_min_m: m.rail_min_m(),
                rail_max_m: m.rail_max_m(),
                lift_min_m: m.lift_min_m(),
                lift_max_m: m.lift_max_m(),
                camera_workspace: box_from_fb(kind, "camera_workspace", m.camera_workspace())?,
                sampling_region: box_from_fb(kind, "sampling_region", m.sampling_region())?,
                scenario: string_or_empty(m.scenario()),
                scene_seed: m.scene_seed(),
                intrinsics: intrinsics_from_fb(kind, m.intrinsics())?,
            })
        }
        MessageKind::RoiCloud => {
            let m = envelope.payload_as_roi_cloud().ok_or_else(missing)?;
            let points = m
                .points()
                .ok_or_else(|| content(kind, "points are missing"))?;
            let roi = m
                .roi()
                .ok_or_else(|| content(kind, "roi flags are missing"))?;
            if points.len() != roi.len() {
                return Err(content(
                    kind,
                    format!("{} points but {} roi flags", points.len(), roi.len()),
                ));
            }
            let origin = m
                .sensor_origin()
                .ok_or_else(|| content(kind, "sensor origin is missing"))?;
            let origin = Point3::new(origin.x(), origin.y(), origin.z());
            if origin.iter().any(|v| !v.is_finite()) {
                return Err(content(kind, "sensor origin is not finite"));
            }
            // Non-finite points are kept: the map skips and counts them.
            Message::RoiCloud(RoiCloud {
                points_in_world: points.iter().map(point3f).collect(),
                roi: roi.iter().map(|r| r != 0).collect(),
                sensor_origin_in_world: origin,
                source_frame_seq: m.source_frame_seq(),
                invalid_pixels: m.invalid_pixels(),
                detector_id: string_or_empty(m.detector_id()),
            })
        }
        MessageKind::RankedViews => {
            let m = envelope.payload_as_ranked_views().ok_or_else(missing)?;
            let views = m
                .views()
                .map(|vs| {
                    vs.iter()
                        .map(|v| {
                            Ok(RankedView {
                                world_from_camera: pose_from_fb(
                                    kind,
                                    "view pose",
                                    Some(v.world_from_camera()),
                                )?,
                                utility: v.utility(),
                                gain: v.gain(),
                                cost_m: v.cost_m(),
                                kind: view_kind_from_fb(kind, v.kind())?,
                            })
                        })
                        .collect::<Result<Vec<_>>>()
                })
                .transpose()?
                .unwrap_or_default();
            Message::RankedViews(RankedViews {
                views,
                based_on_seq: m.based_on_seq(),
                planning_time_ms: m.planning_time_ms(),
                planner_id: string_or_empty(m.planner_id()),
            })
        }
        MessageKind::FruitEstimates => {
            let m = envelope.payload_as_fruit_estimates().ok_or_else(missing)?;
            let fruits = m
                .fruits()
                .map(|fs| {
                    fs.iter()
                        .map(|f| read_fruit(kind, f))
                        .collect::<Result<Vec<_>>>()
                })
                .transpose()?
                .unwrap_or_default();
            Message::FruitEstimates(FruitEstimates {
                fruits,
                based_on_seq: m.based_on_seq(),
                planner_id: string_or_empty(m.planner_id()),
            })
        }
        MessageKind::MapUpdate => {
            let m = envelope.payload_as_map_update().ok_or_else(missing)?;
            let voxels = m
                .voxels()
                .map(|vs| {
                    vs.iter()
                        .map(|v| {
                            Ok(VoxelChange {
                                key: [v.x(), v.y(), v.z()],
                                occupancy_logodds: v.occupancy_logodds(),
                                roi_logodds: v.roi_logodds(),
                                state: match v.state() {
                                    fb::VoxelState::Free => VoxelState::Free,
                                    fb::VoxelState::Occupied => VoxelState::Occupied,
                                    fb::VoxelState::Roi => VoxelState::Roi,
                                    other => {
                                        return Err(unknown_enum(kind, "voxel state", other.0))
                                    }
                                },
                            })
                        })
                        .collect::<Result<Vec<_>>>()
                })
                .transpose()?
                .unwrap_or_default();
            let resolution_m = m.resolution_m();
            if !(resolution_m.is_finite() && resolution_m > 0.0) {
                return Err(content(
                    kind,
                    format!("resolution {resolution_m} is not positive"),
                ));
            }
            Message::MapUpdate(MapUpdate {
                resolution_m,
                map_seq: m.map_seq(),
                based_on_seq: m.based_on_seq(),
                full: m.full(),
                voxels,
                planner_id: string_or_empty(m.planner_id()),
            })
        }
        MessageKind::PlannerStatus => {
            let m = envelope.payload_as_planner_status().ok_or_else(missing)?;
            Message::PlannerStatus(PlannerStatus {
                planner_id: string_or_empty(m.planner_id()),
                owned_trolleys: strings_from_fb(m.owned_trolleys()),
                standby_trolleys: strings_from_fb(m.standby_trolleys()),
                clouds_integrated: m.clouds_integrated(),
                views_published: m.views_published(),
                last_planning_time_ms: m.last_planning_time_ms(),
                mean_planning_time_ms: m.mean_planning_time_ms(),
                dropped_messages: m.dropped_messages(),
                map_voxels: m.map_voxels(),
            })
        }
        MessageKind::TrolleyStatus => {
            let m = envelope.payload_as_trolley_status().ok_or_else(missing)?;
            Message::TrolleyStatus(TrolleyStatus {
                state: match m.state() {
                    fb::TrolleyState::Starting => TrolleyState::Starting,
                    fb::TrolleyState::Capturing => TrolleyState::Capturing,
                    fb::TrolleyState::WaitingForViews => TrolleyState::WaitingForViews,
                    fb::TrolleyState::Moving => TrolleyState::Moving,
                    fb::TrolleyState::Done => TrolleyState::Done,
                    other => return Err(unknown_enum(kind, "trolley state", other.0)),
                },
                views_done: m.views_done(),
                frames_published: m.frames_published(),
                unreachable_views: m.unreachable_views(),
                reannounces: m.reannounces(),
                dropped_messages: m.dropped_messages(),
                last_views_seq: m.last_views_seq(),
                message: string_or_empty(m.message()),
            })
        }
        MessageKind::MapSnapshot => {
            let m = envelope.payload_as_map_snapshot().ok_or_else(missing)?;
            Message::MapSnapshot(MapSnapshot {
                trolley_id: string_or_empty(m.trolley_id()),
                planner_id: string_or_empty(m.planner_id()),
                based_on_seq: m.based_on_seq(),
                map: m.map().map(|b| b.bytes().to_vec()).unwrap_or_default(),
                tracked_fruits: m
                    .tracked_fruits()
                    .map(|fs| {
                        fs.iter()
                            .map(|f| TrackedFruit {
                                id: f.id(),
                                centre_in_world: point3f(f.centre()),
                            })
                            .collect()
                    })
                    .unwrap_or_default(),
                next_fruit_id: m.next_fruit_id(),
            })
        }
        MessageKind::FleetFruits => {
            let m = envelope.payload_as_fleet_fruits().ok_or_else(missing)?;
            let fruits = m
                .fruits()
                .map(|fs| {
                    fs.iter()
                        .map(|f| {
                            let fruit = f
                                .fruit()
                                .ok_or_else(|| content(kind, "fleet fruit without its estimate"))?;
                            Ok(FleetFruit {
                                fleet_id: string_or_empty(f.fleet_id()),
                                fruit: read_fruit(kind, fruit)?,
                                sources: f
                                    .sources()
                                    .map(|ss| ss.iter().map(str::to_owned).collect())
                                    .unwrap_or_default(),
                            })
                        })
                        .collect::<Result<Vec<_>>>()
                })
                .transpose()?
                .unwrap_or_default();
            Message::FleetFruits(FleetFruits {
                fruits,
                planner_id: string_or_empty(m.planner_id()),
                trolleys: m.trolleys(),
            })
        }
        MessageKind::DetectorStatus => {
            let m = envelope.payload_as_detector_status().ok_or_else(missing)?;
            Message::DetectorStatus(DetectorStatus {
                detector_id: string_or_empty(m.detector_id()),
                frames_processed: m.frames_processed(),
                dropped_messages: m.dropped_messages(),
                mean_detect_time_ms: m.mean_detect_time_ms(),
            })
        }
    })
}

pub(crate) fn read_envelope(
    envelope: &fb::Envelope<'_>,
    kind: MessageKind,
) -> Result<(Header, Message)> {
    let header = Header {
        seq: envelope.seq(),
        stamp_ns: envelope.stamp_ns(),
        trolley_id: string_or_empty(envelope.trolley_id()),
        source_id: string_or_empty(envelope.source_id()),
        frame_id: string_or_empty(envelope.frame_id()),
    };
    Ok((header, read_message(envelope, kind)?))
}
