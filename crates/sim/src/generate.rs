//! Seeded procedural content: plant layout per scenario, stems, leaves, fruits, fixed structures,
//! and the [`SceneOptions`] that make a scene harder (fruit colour and shape, red clutter).

mod capsicum;
mod clutter;
mod options;
mod season;
#[cfg(test)]
mod tests;

use glasshouse_geom::Aabb;
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::shapes::{Bounds, Cylinder, Shape};
use crate::{FruitColour, FruitTruth, ScenarioKind};

pub use options::{
    FruitShape, ParseFruitShapeError, SceneOptions, SceneOptionsError, MAX_DAY, MAX_RED_CLUTTER,
};

/// ChaCha streams of generation. Stream 0 draws everything the default scene has, so an option
/// that is off draws nothing and the default scene stays as it was. Capsicum details have their
/// own stream; red clutter too, so turning it on keeps the rest of the scene.
const CAPSICUM_STREAM: u64 = 1;
const CLUTTER_STREAM: u64 = 2;

/// Albedos (linear 0-255). Chosen so that, under every shading factor in [0.45, 1], red fruit passes
/// the paper's HSI rule and leaves, stems, floor and structures never do (tested in lib.rs).
pub(crate) const FLOOR_ALBEDO: [f32; 3] = [120.0, 112.0, 104.0];
pub(crate) const STRUCTURE_ALBEDO: [f32; 3] = [150.0, 150.0, 155.0];
pub(crate) const STEM_ALBEDO: [f32; 3] = [45.0, 95.0, 35.0];
/// Red fruit albedo range per channel (min, max).
pub(crate) const RED_FRUIT_RANGE: [(f32, f32); 3] = [(190.0, 225.0), (20.0, 40.0), (15.0, 35.0)];
/// Leaf albedo range per channel (min, max).
pub(crate) const LEAF_RANGE: [(f32, f32); 3] = [(45.0, 80.0), (115.0, 160.0), (25.0, 50.0)];
pub(crate) const YELLOW_FRUIT_ALBEDO: [f32; 3] = [230.0, 200.0, 30.0];
pub(crate) const GREEN_FRUIT_ALBEDO: [f32; 3] = [70.0, 125.0, 30.0];
/// Unripe fruit albedo range of the [`FruitColour::Unripe`] variant: a light yellow-green, lighter
/// and yellower than leaves, outside the HSI rule's hue range under every shading factor.
pub(crate) const UNRIPE_FRUIT_RANGE: [(f32, f32); 3] =
    [(135.0, 160.0), (170.0, 195.0), (35.0, 60.0)];
/// Fruit albedo range of [`FruitColour::LeafGreen`]: within the colours of leaves.
pub(crate) const LEAF_GREEN_FRUIT_RANGE: [(f32, f32); 3] =
    [(60.0, 85.0), (120.0, 150.0), (25.0, 45.0)];
/// Capsicum calyx: a dark green.
pub(crate) const CALYX_ALBEDO: [f32; 3] = [38.0, 78.0, 28.0];
/// Orange of some plant labels (red clutter); the other clutter takes [`RED_FRUIT_RANGE`].
pub(crate) const ORANGE_CLUTTER_RANGE: [(f32, f32); 3] =
    [(210.0, 235.0), (90.0, 120.0), (15.0, 35.0)];

/// True for an albedo of the red fruit range: the only colour the HSI rule labels fruit.
pub(crate) fn is_ripe_colour(albedo: [f32; 3]) -> bool {
    in_range(RED_FRUIT_RANGE, albedo)
}

/// True for an albedo of the fruit range of `colour`: what the scene's detector should find.
pub(crate) fn is_fruit_colour(colour: FruitColour, albedo: [f32; 3]) -> bool {
    in_range(colour.albedo_range(), albedo)
}

fn in_range(range: [(f32, f32); 3], albedo: [f32; 3]) -> bool {
    range
        .iter()
        .zip(albedo)
        .all(|(&(lo, hi), a)| (lo..=hi).contains(&a))
}

impl FruitColour {
    /// Per-channel albedo range (min, max) of the fruit in this variant.
    pub(crate) fn albedo_range(self) -> [(f32, f32); 3] {
        match self {
            FruitColour::Red => RED_FRUIT_RANGE,
            FruitColour::Green => UNRIPE_FRUIT_RANGE,
            FruitColour::LeafGreen => LEAF_GREEN_FRUIT_RANGE,
        }
    }
}

/// The same relative place in `range` as `red` has in the red range, so a scene of another
/// fruit colour draws exactly the random numbers of its red twin and only the colours differ.
fn colour_twin(red: [f32; 3], range: [(f32, f32); 3]) -> [f32; 3] {
    let mut out = [0.0; 3];
    for (a, ((r_lo, r_hi), (g_lo, g_hi))) in RED_FRUIT_RANGE.into_iter().zip(range).enumerate() {
        out[a] = g_lo + (red[a] - r_lo) / (r_hi - r_lo) * (g_hi - g_lo);
    }
    out
}

const STEM_RADIUS_M: (f64, f64) = (0.009, 0.012);
const STEM_HEIGHT_M: (f64, f64) = (1.0, 1.5);
const FRUIT_HALF_XY_M: (f64, f64) = (0.025, 0.04);
const FRUIT_HALF_Z_M: (f64, f64) = (0.03, 0.045);
const FRUIT_CENTRE_Z_M: (f64, f64) = (0.4, 1.3);
const FRUIT_MAX_AXIS_DISTANCE_M: f64 = 0.12;
const LEAF_LENGTH_M: (f64, f64) = (0.08, 0.16);
const LEAF_WIDTH_M: (f64, f64) = (0.04, 0.08);
const GENERAL_LEAVES_PER_PLANT: (u32, u32) = (100, 130);
const MIN_PLANT_SPACING_M: f64 = 0.4;

/// What a solid is part of.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Part {
    Structure,
    Stem,
    Leaf,
    /// The fruit body (an ellipsoid, or a capsicum lobe).
    Fruit,
    /// A capsicum's calyx and stalk.
    Calyx,
    Stalk,
    /// Red things that are not fruit: plant clips, labels, red petioles.
    Clutter,
}

/// A solid in the scene with its surface colour and, for fruit, its index in the truth list.
#[derive(Clone, Debug)]
pub(crate) struct Solid {
    pub shape: Shape,
    pub albedo: [f32; 3],
    pub fruit_index: Option<u32>,
    /// Part of a plant (counts for the sampling region), as opposed to fixed structure.
    pub is_plant: bool,
    pub part: Part,
}

impl Solid {
    /// A plant part that is not fruit.
    fn plant_part(shape: Shape, albedo: [f32; 3], part: Part) -> Self {
        Self {
            shape,
            albedo,
            fruit_index: None,
            is_plant: true,
            part,
        }
    }
}

#[derive(Clone, Debug)]
pub(crate) struct Plant {
    pub base_in_world: Point3<f64>,
    pub height_m: f64,
    pub stem_radius_m: f64,
    pub fruit_count: u32,
}

/// One fruit ready to be added: its truth, body solids and the plant parts that come with it.
pub(crate) struct FruitBody {
    pub truth: FruitTruth,
    /// The solids that are the fruit (ellipsoid or lobes); they carry its index and colour.
    pub body: Vec<Shape>,
    /// Calyx and stalk of a capsicum.
    pub attached: Vec<Solid>,
    /// The box other fruit keep 5 mm away from: the body's, grown by the calyx.
    pub keep_out: Bounds,
    pub stalk: Option<Cylinder>,
    /// A leaf is to be pressed against the body.
    pub pressed: bool,
}

impl FruitBody {
    /// The axis-aligned ellipsoid fruit of the paper's scenes.
    fn ellipsoid(id: u32, centre: Point3<f64>, half: Vector3<f64>) -> Self {
        let truth = FruitTruth::ellipsoid(id, centre, half);
        Self {
            body: vec![Shape::Ellipsoid {
                centre: centre.coords,
                radii: half,
            }],
            attached: Vec::new(),
            keep_out: Bounds::from_centre_half(&centre.coords, &half),
            stalk: None,
            pressed: false,
            truth,
        }
    }
}

/// The fruit placed so far, with what later placements must keep clear of.
#[derive(Default)]
pub(crate) struct FruitSet {
    pub truths: Vec<FruitTruth>,
    /// Body solids per fruit, indexed like `truths`.
    pub bodies: Vec<Vec<Shape>>,
    keep_out: Vec<Bounds>,
    stalks: Vec<Cylinder>,
    /// Fruit that get a leaf pressed against them, with their plant's stem base.
    pressed: Vec<(u32, Vector3<f64>)>,
}

/// Gap kept between fruit boxes, and between leaves and fruit.
const FRUIT_GAP_M: f64 = 0.005;

impl FruitSet {
    /// True when `candidate` keeps its gap from every fruit and stalk placed, and its stalk
    /// from every fruit.
    fn admits(&self, candidate: &FruitBody) -> bool {
        // Disjoint boxes (with 5 mm between) guarantee disjoint bodies.
        let clear = self
            .keep_out
            .iter()
            .all(|b| !candidate.keep_out.overlaps(b, FRUIT_GAP_M));
        let stalk_clear = |stalk: &Cylinder, b: &Bounds| !stalk.passes_through(b, 0.002);
        clear
            && self
                .stalks
                .iter()
                .all(|s| stalk_clear(s, &candidate.keep_out))
            && candidate
                .stalk
                .is_none_or(|s| self.keep_out.iter().all(|b| stalk_clear(&s, b)))
    }

    /// Adds the fruit and its solids (the body in fruit `albedo`).
    fn add(
        &mut self,
        fruit: FruitBody,
        albedo: [f32; 3],
        base: Vector3<f64>,
        solids: &mut Vec<Solid>,
    ) {
        let id = fruit.truth.id;
        solids.extend(fruit.body.iter().map(|shape| Solid {
            shape: shape.clone(),
            albedo,
            fruit_index: Some(id),
            is_plant: true,
            part: Part::Fruit,
        }));
        solids.extend(fruit.attached);
        if fruit.pressed {
            self.pressed.push((id, base));
        }
        self.keep_out.push(fruit.keep_out);
        self.stalks.extend(fruit.stalk);
        self.bodies.push(fruit.body);
        self.truths.push(fruit.truth);
    }

    /// True when `shape` (a disc or a cylinder) comes within `clearance_m` of a fruit body other
    /// than `except`: tested at points sampled over the disc or along the cylinder's axis (the
    /// shapes are small).
    fn touches(&self, shape: &Shape, clearance_m: f64, except: Option<u32>) -> bool {
        let bounds = shape.bounds();
        let (points, reach_m) = sample_points(shape);
        self.truths.iter().zip(&self.bodies).any(|(f, body)| {
            let fb = Bounds::from_centre_half(&f.centre.coords, &f.half_extents_m);
            if Some(f.id) == except || !bounds.overlaps(&fb, clearance_m) {
                return false;
            }
            let grown_m = clearance_m + reach_m;
            points
                .iter()
                .any(|p| body.iter().any(|s| s.is_within(p, grown_m)))
        })
    }
}

/// Points covering a small disc (17 x 17 grid within the ellipse) or the axis of a cylinder,
/// with the distance the shape reaches beyond them (the cylinder's radius).
fn sample_points(shape: &Shape) -> (Vec<Vector3<f64>>, f64) {
    match shape {
        Shape::Disc {
            centre,
            u,
            v,
            half_u_m,
            half_v_m,
            ..
        } => {
            let steps = 8;
            let mut points = Vec::new();
            for i in -steps..=steps {
                for j in -steps..=steps {
                    let s = i as f64 / steps as f64;
                    let w = j as f64 / steps as f64;
                    if s * s + w * w <= 1.0 {
                        points.push(centre + u * (s * half_u_m) + v * (w * half_v_m));
                    }
                }
            }
            (points, 0.0)
        }
        Shape::Cylinder(c) => (c.axis_points().collect(), c.radius_m),
        Shape::Ellipsoid { centre, .. } => (vec![*centre], 0.0),
        Shape::OrientedEllipsoid(e) => (vec![e.centre], 0.0),
    }
}

pub(crate) struct Built {
    pub fruits: Vec<FruitTruth>,
    pub solids: Vec<Solid>,
    pub plants: Vec<Plant>,
    pub camera_workspace: Aabb,
}

fn uniform(rng: &mut ChaCha8Rng, range: (f64, f64)) -> f64 {
    // Lerp instead of gen_range so a degenerate range can never panic.
    range.0 + (range.1 - range.0) * rng.gen::<f64>()
}

fn uniform_albedo(rng: &mut ChaCha8Rng, range: [(f32, f32); 3]) -> [f32; 3] {
    range.map(|(lo, hi)| lo + (hi - lo) * rng.gen::<f32>())
}

/// Picks plant base positions with `accept` deciding candidate positions; keeps the spacing rule.
fn place_plants(
    rng: &mut ChaCha8Rng,
    count: usize,
    mut candidate: impl FnMut(&mut ChaCha8Rng) -> (f64, f64),
    fallback: impl Fn(usize) -> (f64, f64),
) -> Vec<(f64, f64)> {
    for _restart in 0..100 {
        let mut placed: Vec<(f64, f64)> = Vec::with_capacity(count);
        for _ in 0..2000 {
            if placed.len() == count {
                break;
            }
            let (x, y) = candidate(rng);
            let spaced = placed.iter().all(|&(px, py)| {
                ((px - x).powi(2) + (py - y).powi(2)).sqrt() >= MIN_PLANT_SPACING_M
            });
            if spaced {
                placed.push((x, y));
            }
        }
        if placed.len() == count {
            return placed;
        }
    }
    (0..count).map(fallback).collect()
}

/// The seeded stream `stream` of generation.
fn stream_rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// Generates the scene of `kind`; the same arguments always give the same scene.
pub(crate) fn build(kind: ScenarioKind, seed: u64, options: &SceneOptions) -> Built {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut capsicum_rng = stream_rng(seed, CAPSICUM_STREAM);
    let (layout, mut solids, camera_workspace) = layout(&mut rng, kind);
    let mut fruits = FruitSet::default();
    let mut plants = Vec::new();
    for ((x, y), fruit_count) in layout {
        let height_m = uniform(&mut rng, STEM_HEIGHT_M);
        let plant = Plant {
            base_in_world: Point3::new(x, y, 0.0),
            height_m,
            stem_radius_m: uniform(&mut rng, STEM_RADIUS_M),
            fruit_count,
        };
        let fruit_rng = (options.fruit_shape == FruitShape::Capsicum).then_some(&mut capsicum_rng);
        add_plant(&mut rng, fruit_rng, &plant, &mut fruits, &mut solids);
        plants.push(plant);
    }
    capsicum::press_leaves(&mut capsicum_rng, &fruits, &mut solids);
    if kind == ScenarioKind::Row {
        add_unripe_fruit(&mut rng, fruits.truths.len(), &mut solids);
    }
    if options.fruit_colour != FruitColour::Red {
        let range = options.fruit_colour.albedo_range();
        for solid in &mut solids {
            if solid.fruit_index.is_some() && is_ripe_colour(solid.albedo) {
                solid.albedo = colour_twin(solid.albedo, range);
            }
        }
    }
    let clutter_share = options.red_clutter_share();
    if clutter_share > 0.0 {
        let mut clutter_rng = stream_rng(seed, CLUTTER_STREAM);
        clutter::add(
            &mut clutter_rng,
            clutter_share,
            &plants,
            &fruits,
            &mut solids,
        );
    }
    let mut built = Built {
        fruits: fruits.truths,
        solids,
        plants,
        camera_workspace,
    };
    if let Some(day) = options.visit_day() {
        season::apply(&mut built, seed, day);
    }
    built
}

/// Plant positions with their fruit counts, the scenario's fixed structures and the camera
/// workspace.
#[allow(clippy::type_complexity)]
fn layout(rng: &mut ChaCha8Rng, kind: ScenarioKind) -> (Vec<((f64, f64), u32)>, Vec<Solid>, Aabb) {
    let mut solids = Vec::new();
    let (layout, camera_workspace) = match kind {
        ScenarioKind::One => {
            let positions = place_plants(
                rng,
                4,
                |r| {
                    let angle = uniform(r, (0.0, std::f64::consts::TAU));
                    let radius = uniform(r, (0.45, 0.8));
                    (radius * angle.cos(), radius * angle.sin())
                },
                |i| {
                    let angle = i as f64 * std::f64::consts::FRAC_PI_2;
                    (0.6 * angle.cos(), 0.6 * angle.sin())
                },
            );
            // The arm's static pole: the arm base sits on top at 0.86 m.
            solids.push(Solid {
                shape: Shape::Cylinder(Cylinder {
                    base: Vector3::zeros(),
                    axis: Vector3::z(),
                    length_m: 0.86,
                    radius_m: 0.05,
                }),
                albedo: STRUCTURE_ALBEDO,
                fruit_index: None,
                is_plant: false,
                part: Part::Structure,
            });
            let counts = [7, 7, 0, 0];
            let layout: Vec<_> = positions.into_iter().zip(counts).collect();
            let workspace = Aabb::new(Point3::new(-0.7, -0.7, 0.3), Point3::new(0.7, 0.7, 1.5));
            (layout, workspace)
        }
        ScenarioKind::Two => {
            let positions = place_plants(
                rng,
                4,
                |r| (uniform(r, (-0.7, 0.7)), uniform(r, (-0.7, 0.7))),
                |i| {
                    (
                        if i % 2 == 0 { -0.5 } else { 0.5 },
                        if i < 2 { -0.5 } else { 0.5 },
                    )
                },
            );
            let layout: Vec<_> = positions.into_iter().map(|p| (p, 7)).collect();
            let workspace = Aabb::new(Point3::new(-1.1, -1.1, 0.2), Point3::new(1.1, 1.1, 1.6));
            (layout, workspace)
        }
        ScenarioKind::Row => {
            let mut x = 0.0;
            let mut layout = Vec::new();
            for i in 0..8 {
                if i > 0 {
                    x += uniform(rng, (0.45, 0.55));
                }
                let fruits = rng.gen_range(5u32..=7);
                layout.push(((x, 0.0), fruits));
            }
            // Pipe rails of the trolley, centred on y = -0.7.
            for rail_y in [-0.425, -0.975] {
                solids.push(Solid {
                    shape: Shape::Cylinder(Cylinder {
                        base: Vector3::new(-1.0, rail_y, 0.1),
                        axis: Vector3::x(),
                        length_m: x + 2.0,
                        radius_m: 0.025,
                    }),
                    albedo: STRUCTURE_ALBEDO,
                    fruit_index: None,
                    is_plant: false,
                    part: Part::Structure,
                });
            }
            let workspace = Aabb::new(
                Point3::new(-0.3, -0.75, 0.2),
                Point3::new(x + 0.3, -0.2, 2.0),
            );
            (layout, workspace)
        }
    };

    (layout, solids, camera_workspace)
}
/// Leaf disc from its attachment: azimuth around the stem, droop below horizontal, roll about its
/// long axis.
#[allow(clippy::too_many_arguments)]
fn leaf_shape(
    stem_point: Vector3<f64>,
    stem_radius_m: f64,
    azimuth_rad: f64,
    droop_rad: f64,
    roll_rad: f64,
    petiole_m: f64,
    length_m: f64,
    width_m: f64,
) -> Shape {
    let outward = Vector3::new(azimuth_rad.cos(), azimuth_rad.sin(), 0.0);
    let u = outward * droop_rad.cos() - Vector3::z() * droop_rad.sin();
    let side = Vector3::z().cross(&outward);
    let up = u.cross(&side);
    let v = side * roll_rad.cos() + up * roll_rad.sin();
    let normal = u.cross(&v);
    let half_u_m = 0.5 * length_m;
    Shape::Disc {
        centre: stem_point + outward * (stem_radius_m + petiole_m) + u * half_u_m,
        normal,
        u,
        v,
        half_u_m,
        half_v_m: 0.5 * width_m,
    }
}

/// A few unripe fruits in the row: still fruit in the ground truth, but not red.
fn add_unripe_fruit(rng: &mut ChaCha8Rng, fruit_count: usize, solids: &mut [Solid]) {
    if fruit_count < 3 {
        return;
    }
    let mut recoloured = Vec::new();
    while recoloured.len() < 3 {
        let pick = rng.gen_range(0..fruit_count) as u32;
        if !recoloured.contains(&pick) {
            recoloured.push(pick);
        }
    }
    for solid in solids {
        if let Some(i) = solid.fruit_index {
            if let Some(pos) = recoloured.iter().position(|&r| r == i) {
                solid.albedo = if pos < 2 {
                    YELLOW_FRUIT_ALBEDO
                } else {
                    GREEN_FRUIT_ALBEDO
                };
            }
        }
    }
}

/// Adds a plant: its stem, its fruit, then leaves over the fruit and all around the stem. With
/// `capsicum_rng` the fruit are capsicums, their details drawn from it.
fn add_plant(
    rng: &mut ChaCha8Rng,
    capsicum_rng: Option<&mut ChaCha8Rng>,
    plant: &Plant,
    fruits: &mut FruitSet,
    solids: &mut Vec<Solid>,
) {
    let base = plant.base_in_world.coords;
    let stem = Cylinder {
        base,
        axis: Vector3::z(),
        length_m: plant.height_m,
        radius_m: plant.stem_radius_m,
    };
    solids.push(Solid::plant_part(
        Shape::Cylinder(stem),
        STEM_ALBEDO,
        Part::Stem,
    ));
    // Fruits first, so leaves can be placed around them without cutting through them.
    let plant_fruits = place_fruits(rng, capsicum_rng, plant, fruits, solids);

    let mut push_leaf = |rng: &mut ChaCha8Rng,
                         height_range: (f64, f64),
                         azimuth_range: (f64, f64),
                         droop: (f64, f64)| {
        for _attempt in 0..8 {
            let height = uniform(rng, height_range).clamp(0.1, plant.height_m);
            let leaf = leaf_shape(
                Vector3::new(base.x, base.y, height),
                plant.stem_radius_m,
                uniform(rng, azimuth_range),
                uniform(rng, droop),
                uniform(rng, (-1.0, 1.0)),
                uniform(rng, (0.01, 0.06)),
                uniform(rng, LEAF_LENGTH_M),
                uniform(rng, LEAF_WIDTH_M),
            );
            if !fruits.touches(&leaf, FRUIT_GAP_M, None) {
                let albedo = uniform_albedo(rng, LEAF_RANGE);
                solids.push(Solid::plant_part(leaf, albedo, Part::Leaf));
                return;
            }
        }
    };

    // Canopy leaves over each fruit: fruit hang under leaves.
    for (top_z, azimuth) in plant_fruits {
        for _ in 0..3 {
            push_leaf(
                rng,
                (top_z + 0.01, top_z + 0.08),
                (azimuth - 0.9, azimuth + 0.9),
                (0.2, 1.1),
            );
        }
    }
    // Leaves all around the stem at every height.
    let leaf_count = rng.gen_range(GENERAL_LEAVES_PER_PLANT.0..=GENERAL_LEAVES_PER_PLANT.1);
    for _ in 0..leaf_count {
        push_leaf(
            rng,
            (0.15, plant.height_m),
            (0.0, std::f64::consts::TAU),
            (-0.3, 1.2),
        );
    }
}

/// Places the plant's fruit; returns the top height and the azimuth around the stem of each.
fn place_fruits(
    rng: &mut ChaCha8Rng,
    mut capsicum_rng: Option<&mut ChaCha8Rng>,
    plant: &Plant,
    fruits: &mut FruitSet,
    solids: &mut Vec<Solid>,
) -> Vec<(f64, f64)> {
    let base = plant.base_in_world.coords;
    let top_z = FRUIT_CENTRE_Z_M.1.min(plant.height_m - 0.08);
    let mut placed = Vec::new();
    for _attempt in 0..5000 {
        if placed.len() == plant.fruit_count as usize {
            break;
        }
        let half = Vector3::new(
            uniform(rng, FRUIT_HALF_XY_M),
            uniform(rng, FRUIT_HALF_XY_M),
            uniform(rng, FRUIT_HALF_Z_M),
        );
        // Keep clear of the stem: the box's horizontal reach is at most max(hx, hy).
        let min_axis_distance = half.x.max(half.y) + plant.stem_radius_m + 0.002;
        let axis_distance = uniform(rng, (min_axis_distance, FRUIT_MAX_AXIS_DISTANCE_M));
        let azimuth = uniform(rng, (0.0, std::f64::consts::TAU));
        let z = uniform(rng, (FRUIT_CENTRE_Z_M.0, top_z));
        let centre = Point3::new(
            base.x + axis_distance * azimuth.cos(),
            base.y + axis_distance * azimuth.sin(),
            z,
        );
        let id = fruits.truths.len() as u32;
        let fruit = match capsicum_rng.as_deref_mut() {
            None => FruitBody::ellipsoid(id, centre, half),
            Some(detail) => match capsicum::body(detail, id, centre, half, plant) {
                Some(fruit) => fruit,
                None => continue,
            },
        };
        if !fruits.admits(&fruit) {
            continue;
        }
        let truth = &fruit.truth;
        placed.push((truth.centre.z + truth.half_extents_m.z, azimuth));
        let albedo = uniform_albedo(rng, RED_FRUIT_RANGE);
        fruits.add(fruit, albedo, base, solids);
    }
    placed
}
