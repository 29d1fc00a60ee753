//! Our messages in Foxglove's well-known schemas (JSON encoding), so Foxglove shows a recording
//! with no plugin: camera images and calibration, the camera's frame transform, ROI clouds,
//! fruit solids and ranked views as scene entities. The flatbuffer channels keep everything;
//! these are the same content in the form a viewer knows.

use base64::Engine;
use glasshouse_geom::FruitEstimate;
use glasshouse_proto::keys::{ParsedKey, TrolleyTopic};
use glasshouse_proto::{Header, Message, RankedViews, RgbdFrame, RoiCloud};
use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use serde_json::{json, Value};

/// The world frame every pose is expressed in.
pub const WORLD_FRAME: &str = "world";

/// One message on a Foxglove channel.
#[derive(Clone, Debug, PartialEq)]
pub struct FoxgloveMessage {
    pub topic: String,
    /// The well-known schema, e.g. `foxglove.RawImage`.
    pub schema: &'static str,
    pub json: Vec<u8>,
}

/// The JSON Schema stored with a channel of `schema` (what a JSON reader needs to type it).
pub fn json_schema(schema: &str) -> Vec<u8> {
    let object = |properties: Value| json!({"type": "object", "properties": properties});
    let time = object(json!({"sec": {"type": "integer"}, "nsec": {"type": "integer"}}));
    let vec3 =
        object(json!({"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}}));
    let quat = object(
        json!({"x": {"type": "number"}, "y": {"type": "number"}, "z": {"type": "number"}, "w": {"type": "number"}}),
    );
    let pose = object(json!({"position": vec3, "orientation": quat}));
    let bytes = json!({"type": "string", "contentEncoding": "base64"});
    let array = |items: Value| json!({"type": "array", "items": items});
    let numbers = array(json!({"type": "number"}));
    let body = match schema {
        "foxglove.RawImage" => object(json!({
            "timestamp": time, "frame_id": {"type": "string"}, "width": {"type": "integer"},
            "height": {"type": "integer"}, "encoding": {"type": "string"},
            "step": {"type": "integer"}, "data": bytes})),
        "foxglove.CameraCalibration" => object(json!({
            "timestamp": time, "frame_id": {"type": "string"}, "width": {"type": "integer"},
            "height": {"type": "integer"}, "distortion_model": {"type": "string"},
            "D": numbers, "K": numbers, "R": numbers, "P": numbers})),
        "foxglove.FrameTransform" => object(json!({
            "timestamp": time, "parent_frame_id": {"type": "string"},
            "child_frame_id": {"type": "string"}, "translation": vec3, "rotation": quat})),
        "foxglove.PointCloud" => object(json!({
            "timestamp": time, "frame_id": {"type": "string"}, "pose": pose,
            "point_stride": {"type": "integer"},
            "fields": array(object(json!({"name": {"type": "string"},
                "offset": {"type": "integer"}, "type": {"type": "integer"}}))),
            "data": bytes})),
        // Scene entities carry arrows, cubes, spheres and texts; their shape is Foxglove's.
        _ => object(json!({"deletions": array(json!({"type": "object"})),
            "entities": array(json!({"type": "object"}))})),
    };
    let mut schema_json = body;
    schema_json["title"] = json!(schema);
    serde_json::to_vec(&schema_json).unwrap_or_default()
}

fn time(stamp_ns: u64) -> Value {
    json!({"sec": stamp_ns / 1_000_000_000, "nsec": stamp_ns % 1_000_000_000})
}

fn vec3(v: &Vector3<f64>) -> Value {
    json!({"x": v.x, "y": v.y, "z": v.z})
}

fn quat(q: &UnitQuaternion<f64>) -> Value {
    json!({"x": q.i, "y": q.j, "z": q.k, "w": q.w})
}

fn pose(p: &Isometry3<f64>) -> Value {
    json!({"position": vec3(&p.translation.vector), "orientation": quat(&p.rotation)})
}

fn message(topic: String, schema: &'static str, value: &Value) -> FoxgloveMessage {
    FoxgloveMessage {
        topic,
        schema,
        json: serde_json::to_vec(value).unwrap_or_default(),
    }
}

fn base64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// The Foxglove messages for one of ours on `key` (none for kinds a viewer has no use for).
pub fn convert(key: &ParsedKey, header: &Header, msg: &Message) -> Vec<FoxgloveMessage> {
    let stamp = header.stamp_ns;
    match (key, msg) {
        (
            ParsedKey::Trolley {
                tid: id,
                topic: TrolleyTopic::Rgbd,
            },
            Message::RgbdFrame(f),
        ) => frame(id, stamp, f),
        (
            ParsedKey::Trolley {
                tid: id,
                topic: TrolleyTopic::Roi,
            },
            Message::RoiCloud(c),
        ) => {
            vec![roi_cloud(id, stamp, c)]
        }
        (
            ParsedKey::Trolley {
                tid: id,
                topic: TrolleyTopic::Fruits,
            },
            Message::FruitEstimates(f),
        ) => {
            let topic = format!("/{id}/fruits");
            vec![fruit_scene(
                topic,
                id,
                stamp,
                f.fruits.iter().map(|f| (f.id.to_string(), f)),
            )]
        }
        (
            ParsedKey::Trolley {
                tid: id,
                topic: TrolleyTopic::Views,
            },
            Message::RankedViews(v),
        ) => {
            vec![views_scene(id, stamp, v)]
        }
        (ParsedKey::FleetFruits, Message::FleetFruits(f)) => {
            let fruits = f.fruits.iter().map(|f| (f.fleet_id.clone(), &f.fruit));
            vec![fruit_scene("/fleet/fruits".into(), "fleet", stamp, fruits)]
        }
        _ => Vec::new(),
    }
}

/// Colour and depth images, the calibration, and the camera's transform from the world.
fn frame(tid: &str, stamp: u64, f: &RgbdFrame) -> Vec<FoxgloveMessage> {
    let camera = format!("{tid}/camera");
    let k = &f.intrinsics;
    let (w, h) = (k.width, k.height);
    let image = |encoding: &str, step: u32, data: String| {
        json!({"timestamp": time(stamp), "frame_id": camera, "width": w, "height": h,
               "encoding": encoding, "step": step, "data": data})
    };
    let depth_bytes: Vec<u8> = f.depth.iter().flat_map(|d| d.to_le_bytes()).collect();
    let calibration = json!({
        "timestamp": time(stamp), "frame_id": camera, "width": w, "height": h,
        "distortion_model": "", "D": [],
        "K": [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": [k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0]});
    let transform = json!({
        "timestamp": time(stamp), "parent_frame_id": WORLD_FRAME, "child_frame_id": camera,
        "translation": vec3(&f.world_from_camera.translation.vector),
        "rotation": quat(&f.world_from_camera.rotation)});
    vec![
        message(
            format!("/{tid}/camera/color"),
            "foxglove.RawImage",
            &image("rgb8", w * 3, base64(&f.rgb)),
        ),
        message(
            format!("/{tid}/camera/depth"),
            "foxglove.RawImage",
            &image("16UC1", w * 2, base64(&depth_bytes)),
        ),
        message(
            format!("/{tid}/camera/calibration"),
            "foxglove.CameraCalibration",
            &calibration,
        ),
        message("/tf".into(), "foxglove.FrameTransform", &transform),
    ]
}

/// Field types of `foxglove.PointCloud` (its `NumericType`).
const UINT8: u32 = 1;
const FLOAT32: u32 = 7;

/// World points, each with its ROI flag (x, y, z as f32, then one byte; 13 bytes a point).
fn roi_cloud(tid: &str, stamp: u64, c: &RoiCloud) -> FoxgloveMessage {
    let mut data = Vec::with_capacity(c.points_in_world.len() * 13);
    for (p, roi) in c.points_in_world.iter().zip(&c.roi) {
        data.extend([p.x, p.y, p.z].iter().flat_map(|v| v.to_le_bytes()));
        data.push(u8::from(*roi));
    }
    let field =
        |name: &str, offset: u32, kind: u32| json!({"name": name, "offset": offset, "type": kind});
    let cloud = json!({
        "timestamp": time(stamp), "frame_id": WORLD_FRAME, "pose": pose(&Isometry3::identity()),
        "point_stride": 13,
        "fields": [field("x", 0, FLOAT32), field("y", 4, FLOAT32), field("z", 8, FLOAT32), field("roi", 12, UINT8)],
        "data": base64(&data)});
    message(format!("/{tid}/roi"), "foxglove.PointCloud", &cloud)
}

fn colour(r: f64, g: f64, b: f64, a: f64) -> Value {
    json!({"r": r, "g": g, "b": b, "a": a})
}

/// A `foxglove.SceneEntity` in the world frame, kept until replaced: `primitives` holds the
/// lists it has (arrows, cubes, spheres, texts, ...); the others are empty.
fn entity(stamp: u64, id: String, metadata: Value, primitives: Value) -> Value {
    let mut entity = json!({
        "timestamp": time(stamp), "frame_id": WORLD_FRAME, "id": id,
        "lifetime": time(0), "frame_locked": false, "metadata": metadata,
        "arrows": [], "cubes": [], "spheres": [], "cylinders": [], "lines": [],
        "triangles": [], "texts": [], "models": []});
    if let (Some(all), Value::Object(given)) = (entity.as_object_mut(), primitives) {
        all.extend(given);
    }
    entity
}

/// Each fruit as its fitted solid (an ellipsoid: a scaled sphere) or, without one, its box,
/// labelled with its id and volume. The entities replace the previous scene of the topic.
fn fruit_scene<'a>(
    topic: String,
    owner: &str,
    stamp: u64,
    fruits: impl Iterator<Item = (String, &'a FruitEstimate)>,
) -> FoxgloveMessage {
    let entities: Vec<Value> = fruits
        .map(|(id, f)| {
            let (centre, size, rotation, volume) = match &f.solid {
                Some(s) => (s.centre, s.semi_axes_m * 2.0, s.world_from_body, s.volume_m3),
                None => (f.centre, f.max - f.min, UnitQuaternion::identity(), f.volume_m3),
            };
            let body = Isometry3::from_parts(centre.coords.into(), rotation);
            let label = format!("{id}: {:.0} cm3", volume * 1e6);
            let above = Point3::new(centre.x, centre.y, centre.z + size.z * 0.5 + 0.02);
            let shape = json!({"pose": pose(&body), "size": vec3(&size), "color": colour(0.9, 0.2, 0.1, 0.8)});
            let (spheres, cubes) = if f.solid.is_some() { (vec![shape], vec![]) } else { (vec![], vec![shape]) };
            let text = json!({"pose": pose(&Isometry3::translation(above.x, above.y, above.z)),
                "billboard": true, "font_size": 12.0, "scale_invariant": true,
                "color": colour(1.0, 1.0, 1.0, 1.0), "text": label});
            let confidence = format!("{:.2}", f.confidence);
            let metadata = json!([{"key": "confidence", "value": confidence}]);
            entity(stamp, format!("{owner}/{id}"), metadata, json!({
                "cubes": cubes, "spheres": spheres, "texts": [text]}))
        })
        .collect();
    // Clear what this topic showed before: a fruit merged away must not linger.
    let scene = json!({"deletions": [{"timestamp": time(stamp), "type": 1, "id": ""}], "entities": entities});
    message(topic, "foxglove.SceneUpdate", &scene)
}

/// Ranked views as arrows along each view's optical axis, the best one green.
fn views_scene(tid: &str, stamp: u64, v: &RankedViews) -> FoxgloveMessage {
    // Foxglove's arrows point along their pose's +x; a camera looks along its +z.
    let x_from_z =
        UnitQuaternion::rotation_between(&Vector3::x(), &Vector3::z()).unwrap_or_default();
    let arrows: Vec<Value> = v
        .views
        .iter()
        .enumerate()
        .map(|(i, view)| {
            let arrow_pose = Isometry3::from_parts(
                view.world_from_camera.translation,
                view.world_from_camera.rotation * x_from_z,
            );
            let c = if i == 0 {
                colour(0.1, 0.9, 0.2, 1.0)
            } else {
                colour(0.3, 0.5, 1.0, 0.6)
            };
            json!({"pose": pose(&arrow_pose), "shaft_length": 0.08, "shaft_diameter": 0.006,
                   "head_length": 0.03, "head_diameter": 0.015, "color": c})
        })
        .collect();
    let views_entity = entity(
        stamp,
        format!("{tid}/views"),
        json!([]),
        json!({"arrows": arrows}),
    );
    message(
        format!("/{tid}/views"),
        "foxglove.SceneUpdate",
        &json!({"deletions": [], "entities": [views_entity]}),
    )
}
