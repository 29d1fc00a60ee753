//! Simulated glasshouse: seeded plant scenes, ray-cast RGB-D camera, fruit ground truth.
//!
//! A [`Scene`] is generated from a [`ScenarioKind`] and a `u64` seed: capsicum-like plants (a stem,
//! many thin leaves that hide fruit, red pepper-like fruits hanging under the leaves), a floor at
//! `z = 0` and the fixed structure of the scenario (the arm's pole, trolley rails). Everything is
//! an analytic primitive in a bounding-volume hierarchy; [`Scene::render`] ray casts every pixel of
//! a pinhole [`CameraModel`] into an [`RgbdImage`] with range limits, grazing-angle dropouts and
//! depth noise that grows with the square of the depth, all deterministic from seeds.
//!
//! Frames follow `glasshouse_geom`: world `z` up in metres, camera optical frame `x` right, `y`
//! down, `z` forward; camera poses are `world_from_camera`.

mod artefacts;
mod depth;
mod generate;
mod light;
mod shapes;
mod trolley;
mod world;

use std::fmt;
use std::str::FromStr;

use glasshouse_geom::{look_at, Aabb, CameraIntrinsics, FruitEstimate};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

pub use artefacts::{
    PerceptionNoise, PerceptionNoiseError, MAX_SILHOUETTE_PX, SILHOUETTE_MISSING_SHARE,
    SILHOUETTE_MIXED_SHARE, SILHOUETTE_STEP_M,
};
pub use depth::{d435_rms_m, DepthNoiseModel, ParseDepthNoiseError};
pub use generate::{
    FruitShape, ParseFruitShapeError, SceneOptions, SceneOptionsError, MAX_DAY, MAX_RED_CLUTTER,
};
pub use light::{COVERED_SKY_SHARE, DROPOUT_HIGHLIGHT, EXPOSURE_RANGE};
pub use trolley::SimArm;
pub use world::{
    ParseWorldPresetError, PoseError, PoseErrorError, WorldError, WorldPreset, WorldSettings,
};

use artefacts::{LabelFlips, SurfaceImage, FLOOR_SURFACE};
use light::{Lighting, SurfaceHit};

use generate::{Plant, Solid, FLOOR_ALBEDO};
use shapes::{Bvh, Packet, Ray, Shape, NO_HIT, PACKET, PACKET_HEIGHT, PACKET_WIDTH};

/// Minimum distance from the camera centre to any solid for a position to count as free (the
/// arm crate's, which planners also keep).
pub use glasshouse_arm::CAMERA_CLEARANCE_M;

/// Shading: `albedo * (AMBIENT + DIFFUSE * max(0, n·l))`.
pub const AMBIENT: f32 = 0.45;
pub const DIFFUSE: f32 = 0.55;

/// Colour of pixels whose ray meets nothing.
const SKY_RGB: [u8; 3] = [170, 200, 230];

/// The simulated set-ups: the paper's two scenarios and a glasshouse row for the fleet. Settings
/// files and JSON spell them as on the command line (`"1"`, `"2"`, `"row"`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum ScenarioKind {
    /// Paper §VII-A scenario 1: arm on a static pole, four plants, two with seven fruits.
    One,
    /// Paper scenario 2: arm hanging from a ceiling gantry, four plants with seven fruits each.
    Two,
    /// A glasshouse row of eight plants beside a pipe-rail trolley.
    Row,
}

/// A scenario name that is not one of the accepted spellings.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown scenario {0:?}; valid names: 1, one, scenario1, 2, two, scenario2, row")]
pub struct ParseScenarioError(pub String);

impl FromStr for ScenarioKind {
    type Err = ParseScenarioError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "1" | "one" | "scenario1" => Ok(ScenarioKind::One),
            "2" | "two" | "scenario2" => Ok(ScenarioKind::Two),
            "row" => Ok(ScenarioKind::Row),
            _ => Err(ParseScenarioError(s.to_string())),
        }
    }
}

impl TryFrom<String> for ScenarioKind {
    type Error = ParseScenarioError;

    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<ScenarioKind> for String {
    fn from(kind: ScenarioKind) -> String {
        kind.to_string()
    }
}

impl fmt::Display for ScenarioKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ScenarioKind::One => "1",
            ScenarioKind::Two => "2",
            ScenarioKind::Row => "row",
        })
    }
}

/// The colour of a scene's fruit: ripe red (the paper's scenes, found by the HSI rule), the
/// unripe variant (a light yellow-green the HSI rule does not accept) or leaf green (within the
/// colours of the leaves, so colour alone cannot tell fruit from leaf). Settings and the command
/// line spell them `red`, `green` and `leaf-green`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FruitColour {
    #[default]
    Red,
    Green,
    #[serde(rename = "leaf-green")]
    LeafGreen,
}

/// A fruit colour that is not one of the accepted spellings.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
#[error("unknown fruit colour {0:?}; valid: red (ripe), green (unripe), leaf-green")]
pub struct ParseFruitColourError(pub String);

impl FromStr for FruitColour {
    type Err = ParseFruitColourError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "red" | "ripe" => Ok(FruitColour::Red),
            "green" | "unripe" => Ok(FruitColour::Green),
            "leaf-green" | "leaf_green" | "leafgreen" => Ok(FruitColour::LeafGreen),
            _ => Err(ParseFruitColourError(s.to_string())),
        }
    }
}

impl fmt::Display for FruitColour {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FruitColour::Red => "red",
            FruitColour::Green => "green",
            FruitColour::LeafGreen => "leaf-green",
        })
    }
}

/// One part of a scene a trolley works on at a time (see [`Scene::segments`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub camera_workspace: Aabb,
    pub sampling_region: Aabb,
}

/// Ground truth of one fruit in the world frame: its axis-aligned box and its body (the
/// ellipsoid, or the union of a capsicum's lobes; calyx and stalk are not fruit).
#[derive(Clone, Debug, Serialize)]
pub struct FruitTruth {
    pub id: u32,
    /// Centre and half size of the body's axis-aligned box.
    pub centre: Point3<f64>,
    pub half_extents_m: Vector3<f64>,
    /// Box volume, `8 * hx * hy * hz`, kept for compatibility: the fruit's volume is
    /// `body_volume_m3`.
    pub volume_m3: f64,
    /// Centroid of the body.
    pub body_centre: Point3<f64>,
    /// Volume of the body: `4/3 π hx hy hz` for an ellipsoid; for a capsicum the union of its
    /// lobes, computed numerically at generation (1 mm columns, exact along each; well within
    /// 1 %).
    pub body_volume_m3: f64,
    /// Unit axis of the fruit, from the tip towards the stalk (`z` for ellipsoids).
    pub axis: Vector3<f64>,
}

impl FruitTruth {
    /// An axis-aligned ellipsoid fruit filling the box `centre ± half_extents_m`.
    pub fn ellipsoid(id: u32, centre: Point3<f64>, half_extents_m: Vector3<f64>) -> Self {
        let h = half_extents_m;
        Self {
            id,
            centre,
            half_extents_m,
            volume_m3: 8.0 * h.x * h.y * h.z,
            body_centre: centre,
            body_volume_m3: 4.0 / 3.0 * std::f64::consts::PI * h.x * h.y * h.z,
            axis: Vector3::z(),
        }
    }

    pub fn aabb(&self) -> Aabb {
        Aabb::new(
            self.centre - self.half_extents_m,
            self.centre + self.half_extents_m,
        )
    }

    /// Keys `k = floor(p / resolution_m)` of the voxels whose centres `(k + 0.5) * resolution_m`
    /// lie inside the box: the one box rule, [`glasshouse_geom::box_voxel_keys`].
    pub fn voxel_keys(&self, resolution_m: f64) -> Vec<[i32; 3]> {
        glasshouse_geom::box_voxel_keys(&self.aabb(), resolution_m)
    }

    /// The fruit as an estimate would be if it were perfect: the body's own centroid and volume,
    /// the box around it, its voxels of `resolution_m`, confidence 1 and no solid.
    pub fn estimate(&self, resolution_m: f64) -> FruitEstimate {
        let aabb = self.aabb();
        FruitEstimate {
            volume_m3: self.body_volume_m3,
            voxel_count: self.voxel_keys(resolution_m).len(),
            confidence: 1.0,
            ..FruitEstimate::from_box(self.id, self.body_centre, aabb.min, aabb.max)
        }
    }
}

/// Pinhole RGB-D camera: intrinsics, valid depth range, noise and grazing-angle dropout.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub intrinsics: CameraIntrinsics,
    pub min_range_m: f64,
    pub max_range_m: f64,
    /// Depth noise standard deviation at 1 m; it scales with depth squared.
    pub depth_noise_std_at_1m_m: f64,
    /// Pixels whose ray meets the surface with |cos(ray, normal)| below this are invalid.
    pub grazing_cos_min: f64,
}

impl CameraModel {
    /// The authors' simulated camera: 640x480, 80° horizontal field of view, 0.15-3.0 m.
    pub fn paper_default() -> Self {
        Self::with_resolution(640, 480)
    }

    /// The paper camera's field of view, range and noise at another image size.
    pub fn with_resolution(width: u32, height: u32) -> Self {
        Self {
            intrinsics: CameraIntrinsics::from_horizontal_fov(width, height, 80f64.to_radians()),
            min_range_m: 0.15,
            max_range_m: 3.0,
            depth_noise_std_at_1m_m: 0.0015,
            grazing_cos_min: 0.1,
        }
    }
}

/// A rendered frame: depth along the optical axis (NaN = invalid) and RGB8, both row-major.
#[derive(Clone, Debug)]
pub struct RgbdImage {
    pub intrinsics: CameraIntrinsics,
    pub depth_m: Vec<f32>,
    pub rgb: Vec<u8>,
}

impl RgbdImage {
    /// Depth as integer units of `depth_scale_m` (0 = invalid, as depth cameras publish it).
    /// Depths that do not fit a `u16` are invalid too.
    pub fn depth_as_u16(&self, depth_scale_m: f64) -> Vec<u16> {
        self.depth_m
            .iter()
            .map(|&d| {
                let units = (d as f64 / depth_scale_m).round();
                if units.is_finite() && units >= 1.0 && units <= u16::MAX as f64 {
                    units as u16
                } else {
                    0
                }
            })
            .collect()
    }
}

/// A generated glasshouse scene with its ground truth. Cheap to query, immutable after generation.
#[derive(Clone, Debug)]
pub struct Scene {
    kind: ScenarioKind,
    seed: u64,
    /// `options.fruit_colour`, kept at hand for the renderer.
    fruit_colour: FruitColour,
    options: SceneOptions,
    fruits: Vec<FruitTruth>,
    plants: Vec<Plant>,
    /// Shapes in BVH order, with per-shape albedo, fruit index, whether it is fruit of the
    /// scene's colour (red clutter is not) and whether it is part of a plant alongside.
    shapes: Vec<Shape>,
    albedo: Vec<[f32; 3]>,
    fruit_index: Vec<Option<u32>>,
    looks_like_fruit: Vec<bool>,
    is_plant: Vec<bool>,
    bvh: Bvh,
    camera_workspace: Aabb,
    sampling_region: Aabb,
    initial_camera_pose: Isometry3<f64>,
}

/// What a single camera ray sees.
struct RayHit {
    t: f64,
    shape: Option<usize>,
    normal: Vector3<f64>,
}

impl Scene {
    /// Generates the scenario; the same `(kind, seed)` always gives the same scene.
    pub fn generate(kind: ScenarioKind, seed: u64) -> Scene {
        Self::generate_with(kind, seed, &SceneOptions::default())
    }

    /// [`Scene::generate`] with the fruit in `fruit_colour`: the green scene has exactly the
    /// geometry of its red twin; only the fruit colours differ.
    pub fn generate_with_fruit(kind: ScenarioKind, seed: u64, fruit_colour: FruitColour) -> Scene {
        let options = SceneOptions {
            fruit_colour,
            ..SceneOptions::default()
        };
        Self::generate_with(kind, seed, &options)
    }

    /// The scenario with `options`; the same `(kind, seed, options)` always gives the same
    /// scene, and the default options give [`Scene::generate`]'s. Options out of range (see
    /// [`SceneOptions::validate`]) are clamped.
    pub fn generate_with(kind: ScenarioKind, seed: u64, options: &SceneOptions) -> Scene {
        let built = generate::build(kind, seed, options);
        let plant_bounds = built
            .solids
            .iter()
            .filter(|s| s.is_plant)
            .map(|s| s.shape.bounds())
            .reduce(|a, b| a.union(&b));
        let sampling_region = match plant_bounds {
            Some(b) => Aabb::new(Point3::from(b.min), Point3::from(b.max)).inflated(0.1),
            None => built.camera_workspace,
        };
        let bounds: Vec<_> = built.solids.iter().map(|s| s.shape.bounds()).collect();
        let (mut bvh, order) = Bvh::build(&bounds);
        let ordered: Vec<&Solid> = order.iter().filter_map(|&i| built.solids.get(i)).collect();
        let ordered_shapes: Vec<Shape> = ordered.iter().map(|s| s.shape.clone()).collect();
        bvh.set_shapes(&ordered_shapes);
        let colour = options.fruit_colour;
        let mut scene = Scene {
            kind,
            seed,
            fruit_colour: colour,
            options: *options,
            fruits: built.fruits,
            plants: built.plants,
            shapes: ordered_shapes,
            albedo: ordered.iter().map(|s| s.albedo).collect(),
            fruit_index: ordered.iter().map(|s| s.fruit_index).collect(),
            looks_like_fruit: ordered
                .iter()
                .map(|s| s.fruit_index.is_some() && generate::is_fruit_colour(colour, s.albedo))
                .collect(),
            is_plant: ordered.iter().map(|s| s.is_plant).collect(),
            bvh,
            camera_workspace: built.camera_workspace,
            sampling_region,
            initial_camera_pose: Isometry3::identity(),
        };
        scene.initial_camera_pose = scene.choose_initial_pose();
        scene
    }

    pub fn kind(&self) -> ScenarioKind {
        self.kind
    }

    pub fn fruit_colour(&self) -> FruitColour {
        self.fruit_colour
    }

    /// The options the scene was generated with.
    pub fn options(&self) -> SceneOptions {
        self.options
    }

    pub fn seed(&self) -> u64 {
        self.seed
    }

    pub fn fruits(&self) -> &[FruitTruth] {
        &self.fruits
    }

    /// Plant stem bases on the floor, in generation order.
    pub fn plant_bases(&self) -> Vec<Point3<f64>> {
        self.plants.iter().map(|p| p.base_in_world).collect()
    }

    /// Where the camera centre may be placed (a box around the arm's reach, for sampling).
    pub fn camera_workspace(&self) -> Aabb {
        self.camera_workspace
    }

    /// Clearance the arm keeps from the mount's structure when placed at the initial view.
    pub const ARM_CLEARANCE_M: f64 = glasshouse_arm::ARM_CLEARANCE_M;

    /// The UR5e on this scenario's mount: the static pole at the origin (1), the ceiling gantry
    /// over the 2 x 2 m square (2), or the rail trolley along the row, its travel spanning the
    /// row's workspace (row).
    pub fn robot(&self) -> glasshouse_arm::Robot {
        match self.kind {
            ScenarioKind::One => glasshouse_arm::Robot::scenario_one(),
            ScenarioKind::Two => glasshouse_arm::Robot::scenario_two(),
            ScenarioKind::Row => glasshouse_arm::Robot::row(glasshouse_arm::Interval::new(
                self.camera_workspace.min.x,
                self.camera_workspace.max.x,
            )),
        }
    }

    /// The plants' bounding box inflated by 10 cm: where view targets may lie.
    pub fn sampling_region(&self) -> Aabb {
        self.sampling_region
    }

    /// The parts of the scene a trolley works through one after the other: in the row, slices
    /// of `segment_length_m` along the row (x), each a (camera workspace, sampling region) pair
    /// clipped to its slice (the sampling region reaches 10 cm past it, so fruit on a boundary
    /// is seen from both sides); elsewhere one segment, the whole scene. Empty for a length that
    /// is not finite and positive.
    pub fn segments(&self, segment_length_m: f64) -> Vec<Segment> {
        if !(segment_length_m.is_finite() && segment_length_m > 0.0) {
            return Vec::new();
        }
        if self.kind != ScenarioKind::Row {
            return vec![Segment {
                camera_workspace: self.camera_workspace,
                sampling_region: self.sampling_region,
            }];
        }
        let (x0, x1) = (self.sampling_region.min.x, self.sampling_region.max.x);
        let count = ((x1 - x0) / segment_length_m).ceil().max(1.0) as usize;
        (0..count)
            .map(|i| {
                let lo = x0 + i as f64 * segment_length_m;
                let hi = (lo + segment_length_m).min(x1);
                let clip = |b: &Aabb, margin_m: f64| {
                    let mut c = *b;
                    c.min.x = (lo - margin_m).max(b.min.x);
                    c.max.x = (hi + margin_m).min(b.max.x);
                    c
                };
                Segment {
                    camera_workspace: clip(&self.camera_workspace, 0.0),
                    sampling_region: clip(&self.sampling_region, 0.1),
                }
            })
            .collect()
    }

    /// A free pose inside the workspace looking at a fruit-bearing plant and seeing some fruit.
    pub fn initial_camera_pose(&self) -> Isometry3<f64> {
        self.initial_camera_pose
    }

    /// Inside the camera workspace and at least [`CAMERA_CLEARANCE_M`] from every solid (floor
    /// included).
    pub fn is_camera_position_free(&self, p: &Point3<f64>) -> bool {
        self.camera_workspace.contains(p)
            && p.z >= CAMERA_CLEARANCE_M
            && !self
                .bvh
                .any_within(&self.shapes, &p.coords, CAMERA_CLEARANCE_M)
    }

    /// Ground truth as JSON: scenario, seed, options and per fruit its box (centre, full size,
    /// volume) and its body (centroid, volume, axis).
    pub fn ground_truth_json(&self) -> String {
        let fruits: Vec<serde_json::Value> = self
            .fruits
            .iter()
            .map(|f| {
                let size = f.half_extents_m * 2.0;
                let body = f.body_centre;
                serde_json::json!({
                    "id": f.id,
                    "centre_m": [f.centre.x, f.centre.y, f.centre.z],
                    "size_m": [size.x, size.y, size.z],
                    "volume_m3": f.volume_m3,
                    "body_centre_m": [body.x, body.y, body.z],
                    "body_volume_m3": f.body_volume_m3,
                    "axis": [f.axis.x, f.axis.y, f.axis.z],
                })
            })
            .collect();
        serde_json::json!({
            "scenario": self.kind.to_string(),
            "seed": self.seed,
            "options": self.options,
            "fruits": fruits,
        })
        .to_string()
    }

    /// First surface along a world ray (floor included), or None for the sky.
    /// Closest hit of a ray (shapes, then the floor); `hint` as in [`Bvh::closest_hit`].
    fn trace(&self, ray: &Ray, hint: Option<usize>, stack: &mut Vec<(u32, f32)>) -> Option<RayHit> {
        let floor_t = floor_hit(&ray.origin, &ray.dir);
        let t_limit = floor_t.unwrap_or(f64::INFINITY);
        if let Some((t, i)) = self.bvh.closest_hit(ray, t_limit, hint, stack) {
            let shape = self.shapes.get(i)?;
            return Some(RayHit {
                t,
                shape: Some(i),
                normal: shape.normal_at(&ray.at(t)),
            });
        }
        floor_t.map(|t| RayHit {
            t,
            shape: None,
            normal: Vector3::z(),
        })
    }

    /// Ray casts the camera at `world_from_camera`. Deterministic for a given `noise_seed`; the
    /// noise is drawn in row-major pixel order for valid pixels only.
    pub fn render(
        &self,
        camera: &CameraModel,
        world_from_camera: &Isometry3<f64>,
        noise_seed: u64,
    ) -> RgbdImage {
        self.render_with(
            camera,
            world_from_camera,
            noise_seed,
            &PerceptionNoise::default(),
        )
    }

    /// [`Scene::render`] with imperfect perception on top (label noise, silhouette artefacts),
    /// also seeded from `noise_seed`; clean `perception` renders exactly what `render` does.
    pub fn render_with(
        &self,
        camera: &CameraModel,
        world_from_camera: &Isometry3<f64>,
        noise_seed: u64,
        perception: &PerceptionNoise,
    ) -> RgbdImage {
        let k = camera.intrinsics;
        let fruit_range = self.fruit_colour.albedo_range();
        let mut labels = LabelFlips::new(perception, noise_seed, fruit_range);
        let mut seen = (perception.silhouette_px > 0)
            .then(|| SurfaceImage::new(k.width as usize, k.height as usize));
        let pixel_count = k.pixel_count();
        let mut depth_m = vec![f32::NAN; pixel_count];
        let mut rgb = vec![0u8; 3 * pixel_count];
        let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
        let mut spare_normal: Option<f64> = None;
        let mut lighting = Lighting::new(perception, noise_seed);
        // Colours before exposure, when the light model sets it from the whole frame.
        let mut radiance = if lighting.needs_exposure() {
            vec![-1.0f32; 3 * pixel_count]
        } else {
            Vec::new()
        };
        let stereo = perception.depth_noise == DepthNoiseModel::D435;
        let mut shadow_stack = Vec::with_capacity(64);
        let rotation = world_from_camera.rotation.to_rotation_matrix();
        let origin = world_from_camera.translation.vector;
        let (width, height) = (k.width as usize, k.height as usize);
        // Rays are traced in packets, a band of PACKET_HEIGHT rows at a time, then shaded row by row so
        // that the noise is drawn in row-major order.
        let mut band_t = vec![0f64; PACKET_HEIGHT * width];
        let mut band_hit = vec![NO_HIT; PACKET_HEIGHT * width];
        // Camera-frame direction (its z turns ray length into depth) and world-frame direction.
        let mut band_dir = vec![(Vector3::zeros(), Vector3::zeros()); PACKET_HEIGHT * width];
        let mut stack = Vec::with_capacity(64);
        let mut packet = Packet::new(origin);
        for band_v in (0..height).step_by(PACKET_HEIGHT) {
            for tile_u in (0..width).step_by(PACKET_WIDTH) {
                packet.switch_off();
                for lane in 0..PACKET {
                    let (du, dv) = (lane % PACKET_WIDTH, lane / PACKET_WIDTH);
                    let (u, v) = (tile_u + du, band_v + dv);
                    if u >= width || v >= height {
                        continue;
                    }
                    let dir_in_camera = k.ray_direction(u as f64, v as f64);
                    let ray = Ray::new(origin, rotation * dir_in_camera);
                    // Nothing lies below the floor, so it need not bound the search: a lane that
                    // hits no shape is tested against the floor when shaded.
                    packet.t[lane] = f64::INFINITY;
                    band_dir[dv * width + u] = (dir_in_camera, ray.dir);
                    packet.rays[lane] = ray;
                }
                self.bvh.closest_hits(&mut packet, &mut stack);
                for lane in 0..PACKET {
                    let (u, dv) = (tile_u + lane % PACKET_WIDTH, lane / PACKET_WIDTH);
                    if u < width && band_v + dv < height {
                        band_t[dv * width + u] = packet.t[lane];
                        band_hit[dv * width + u] = packet.hit[lane];
                    }
                }
            }
            for dv in 0..PACKET_HEIGHT.min(height - band_v) {
                for u in 0..width {
                    let pixel = (band_v + dv) * width + u;
                    let slot = dv * width + u;
                    let mut t = band_t[slot];
                    let mut surface = band_hit[slot];
                    let (dir_in_camera, dir_in_world) = band_dir[slot];
                    let (normal, albedo) = match self.shapes.get(surface as usize) {
                        Some(shape) => (
                            shape.normal_at(&(origin + dir_in_world * t)),
                            self.albedo
                                .get(surface as usize)
                                .copied()
                                .unwrap_or(FLOOR_ALBEDO),
                        ),
                        None => match floor_hit(&origin, &dir_in_world) {
                            Some(floor_t) => {
                                t = floor_t;
                                surface = FLOOR_SURFACE;
                                (Vector3::z(), FLOOR_ALBEDO)
                            }
                            None => {
                                rgb[3 * pixel..3 * pixel + 3].copy_from_slice(&SKY_RGB);
                                continue;
                            }
                        },
                    };
                    // Two-sided shading: turn the normal towards the camera.
                    let cos_incidence = dir_in_world.dot(&normal);
                    let facing = if cos_incidence > 0.0 { -normal } else { normal };
                    let fruit = self.looks_like_fruit.get(surface as usize) == Some(&true);
                    let hit = SurfaceHit {
                        point: origin + dir_in_world * t,
                        facing,
                        view_dir: dir_in_world,
                        albedo: labels.albedo_seen(fruit, albedo),
                        is_fruit: matches!(self.fruit_index.get(surface as usize), Some(Some(_))),
                    };
                    let shade = self.shade_lit(&mut lighting, &hit, &mut shadow_stack);
                    let highlight_dropout = shade.dropout;
                    match radiance.get_mut(3 * pixel..3 * pixel + 3) {
                        Some(slot) => slot.copy_from_slice(&shade.colour),
                        // Clean shading is already rounded to RGB8.
                        None => rgb[3 * pixel..3 * pixel + 3]
                            .copy_from_slice(&shade.colour.map(|c| c as u8)),
                    }
                    let depth = t * dir_in_camera.z;
                    if let Some(seen) = seen.as_mut() {
                        seen.surface[pixel] = surface;
                        seen.depth_m[pixel] = depth;
                    }
                    if cos_incidence.abs() < camera.grazing_cos_min
                        || !(camera.min_range_m..=camera.max_range_m).contains(&depth)
                        || highlight_dropout
                    {
                        continue;
                    }
                    let std_m = camera.depth_noise_std_at_1m_m * depth * depth;
                    let noisy = if stereo {
                        // The stereo model adds its noise once the whole image is known.
                        depth
                    } else if std_m > 0.0 {
                        depth + std_m * standard_normal(&mut rng, &mut spare_normal)
                    } else {
                        depth
                    };
                    if (camera.min_range_m..=camera.max_range_m).contains(&noisy) {
                        depth_m[pixel] = noisy as f32;
                    }
                }
            }
        }
        if lighting.needs_exposure() {
            lighting.expose(&radiance, &mut rgb);
        }
        if stereo {
            let range_m = (camera.min_range_m, camera.max_range_m);
            depth::apply_stereo_noise(&mut depth_m, width, height, noise_seed, range_m);
        }
        if let Some(seen) = &seen {
            let range_m = (camera.min_range_m, camera.max_range_m);
            let is_plant = &self.is_plant;
            artefacts::add_silhouette_artefacts(
                &mut depth_m,
                seen,
                is_plant,
                perception,
                noise_seed,
                range_m,
            );
        }
        RgbdImage {
            intrinsics: k,
            depth_m,
            rgb,
        }
    }

    /// Pixels with valid depth that see each fruit (indexed like [`Scene::fruits`]), noise-free.
    /// A visibility oracle for tests and evaluation.
    pub fn fruit_pixel_counts(
        &self,
        camera: &CameraModel,
        world_from_camera: &Isometry3<f64>,
    ) -> Vec<u32> {
        let mut counts = vec![0u32; self.fruits.len()];
        self.for_each_fruit_pixel(camera, world_from_camera, |_, fruit| {
            if let Some(c) = counts.get_mut(fruit as usize) {
                *c += 1;
            }
        });
        counts
    }

    /// Row-major per-pixel labels from the renderer's hit ids, noise-free: 1 where a pixel with
    /// valid depth sees a fruit (of any colour), 0 elsewhere. Training labels for a learned
    /// detector.
    pub fn fruit_label_image(
        &self,
        camera: &CameraModel,
        world_from_camera: &Isometry3<f64>,
    ) -> Vec<u8> {
        let mut labels = vec![0u8; camera.intrinsics.pixel_count()];
        self.for_each_fruit_pixel(camera, world_from_camera, |pixel, _| {
            if let Some(l) = labels.get_mut(pixel) {
                *l = 1;
            }
        });
        labels
    }

    /// Calls `visit(pixel, fruit index)` for every pixel whose noise-free ray meets a fruit at a
    /// depth and angle the camera measures.
    fn for_each_fruit_pixel(
        &self,
        camera: &CameraModel,
        world_from_camera: &Isometry3<f64>,
        mut visit: impl FnMut(usize, u32),
    ) {
        let k = camera.intrinsics;
        let rotation = world_from_camera.rotation.to_rotation_matrix();
        let mut stack = Vec::with_capacity(64);
        let origin = world_from_camera.translation.vector;
        let mut hint = None;
        for v in 0..k.height {
            for u in 0..k.width {
                let dir_in_camera = k.ray_direction(u as f64, v as f64);
                let ray = Ray::new(origin, rotation * dir_in_camera);
                let traced = self.trace(&ray, hint, &mut stack);
                hint = traced.as_ref().and_then(|h| h.shape);
                let Some(hit) = traced else {
                    continue;
                };
                let depth = hit.t * dir_in_camera.z;
                let fruit = hit
                    .shape
                    .and_then(|i| self.fruit_index.get(i).copied().flatten());
                if let Some(f) = fruit {
                    if ray.dir.dot(&hit.normal).abs() >= camera.grazing_cos_min
                        && (camera.min_range_m..=camera.max_range_m).contains(&depth)
                    {
                        visit(v as usize * k.width as usize + u as usize, f);
                    }
                }
            }
        }
    }

    /// Tries views of the first fruit-bearing plant from the workspace side, nearest the preferred
    /// direction first, and keeps the first free one that sees enough fruit.
    fn choose_initial_pose(&self) -> Isometry3<f64> {
        let probe = CameraModel::with_resolution(160, 120);
        let robot = self.robot();
        let ws = self.camera_workspace;
        let fallback = look_at(&ws.centre(), &self.sampling_region.centre());
        let Some(plant) = self
            .plants
            .iter()
            .find(|p| p.fruit_count > 0)
            .or(self.plants.first())
        else {
            return fallback;
        };
        let base = plant.base_in_world;
        let plant_fruits: Vec<&FruitTruth> = self
            .fruits
            .iter()
            .filter(|f| {
                ((f.centre.x - base.x).powi(2) + (f.centre.y - base.y).powi(2)).sqrt() < 0.2
            })
            .collect();
        let target_z = if plant_fruits.is_empty() {
            0.8
        } else {
            plant_fruits.iter().map(|f| f.centre.z).sum::<f64>() / plant_fruits.len() as f64
        };
        let eye_z = target_z.clamp(ws.min.z, ws.max.z);
        let towards = match self.kind {
            ScenarioKind::Row => Vector3::new(0.0, -1.0, 0.0),
            _ => {
                let c = ws.centre();
                Vector3::new(c.x - base.x, c.y - base.y, 0.0)
                    .try_normalize(1e-9)
                    .unwrap_or_else(Vector3::x)
            }
        };
        let target = Point3::new(base.x, base.y, target_z);
        let mut best: Option<(u32, Isometry3<f64>)> = None;
        for distance_m in [0.45, 0.38, 0.52, 0.32, 0.6] {
            for step in 0..13 {
                // 0, +15°, -15°, +30°, ... up to ±90°.
                let magnitude = ((step + 1) / 2) as f64 * 15f64.to_radians();
                let angle = if step % 2 == 1 { magnitude } else { -magnitude };
                let (s, c) = angle.sin_cos();
                let dir = Vector3::new(
                    c * towards.x - s * towards.y,
                    s * towards.x + c * towards.y,
                    0.0,
                );
                let eye = Point3::new(
                    base.x + dir.x * distance_m,
                    base.y + dir.y * distance_m,
                    eye_z,
                );
                if !self.is_camera_position_free(&eye) {
                    continue;
                }
                let pose = look_at(&eye, &target);
                if robot.pose_at(&pose, &[], Self::ARM_CLEARANCE_M).is_err() {
                    continue;
                }
                let seen: u32 = self.fruit_pixel_counts(&probe, &pose).iter().sum();
                if seen >= 40 {
                    return pose;
                }
                if best.as_ref().is_none_or(|(b, _)| seen > *b) {
                    best = Some((seen, pose));
                }
            }
        }
        best.map(|(_, pose)| pose).unwrap_or(fallback)
    }
}

/// Fixed light from above, slightly oblique so upright surfaces are not all equally lit.
/// Where a ray meets the floor, the infinite plane z = 0 seen from above only.
fn floor_hit(origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<f64> {
    (dir.z < -1e-12 && origin.z > 0.0).then(|| -origin.z / dir.z)
}

fn light_direction() -> Vector3<f64> {
    Vector3::new(0.3, 0.2, 1.0).normalize()
}

/// Lambert shading with ambient, rounded to RGB8.
pub fn shade(albedo: [f32; 3], n_dot_l: f64) -> [u8; 3] {
    let factor = AMBIENT + DIFFUSE * (n_dot_l.max(0.0) as f32);
    // Albedo and factor are non-negative: adding 0.5 and truncating rounds like `round`, and the
    // cast saturates at 255.
    albedo.map(|a| (a * factor + 0.5) as u8)
}

/// Standard normal by Marsaglia's polar method (no trigonometry), caching the second value of
/// each pair.
pub(crate) fn standard_normal(rng: &mut ChaCha8Rng, spare: &mut Option<f64>) -> f64 {
    if let Some(z) = spare.take() {
        return z;
    }
    loop {
        let x = 2.0 * rng.gen::<f64>() - 1.0;
        let y = 2.0 * rng.gen::<f64>() - 1.0;
        let r2 = x * x + y * y;
        if r2 > 0.0 && r2 < 1.0 {
            let scale = (-2.0 * r2.ln() / r2).sqrt();
            *spare = Some(y * scale);
            return x * scale;
        }
    }
}

#[cfg(test)]
mod tests;

#[cfg(test)]
mod camera_tests;
