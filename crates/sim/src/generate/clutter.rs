//! Red clutter: plant parts in fruit red that are not fruit, which a colour rule takes for fruit.
//! Reddish leaves (the scene's own leaves recoloured), a clip on each stem, red petioles leaving
//! each stem and a couple of labels hanging at plants. Nothing is placed within reach of fruit.

use nalgebra::Vector3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::{
    uniform, uniform_albedo, FruitSet, Part, Plant, Solid, ORANGE_CLUTTER_RANGE, RED_FRUIT_RANGE,
};
use crate::shapes::{Cylinder, Shape};

const CLIP_LENGTH_M: f64 = 0.015;
const CLIP_RADIUS_M: f64 = 0.005;
/// Red petioles: 5 mm thick, leaving the stem upwards at 10-50°.
const RED_STEM_RADIUS_M: f64 = 0.0025;
const RED_STEM_LENGTH_M: (f64, f64) = (0.06, 0.12);
const RED_STEM_RISE_RAD: (f64, f64) = (0.17, 0.87);
const RED_STEMS_PER_PLANT: (u32, u32) = (2, 3);
/// Labels: 3 x 2 cm, hanging 2 cm off the stem.
const LABELS_PER_SCENE: usize = 2;
const LABEL_HALF_M: (f64, f64) = (0.015, 0.01);
const LABEL_OFF_STEM_M: f64 = 0.02;
/// Clutter keeps this far from fruit.
const CLEARANCE_M: f64 = 0.004;
const PLACEMENT_TRIES: usize = 20;

/// Adds the clutter for leaf share `share` (in (0, 0.2]), drawing only from `rng`.
pub(super) fn add(
    rng: &mut ChaCha8Rng,
    share: f64,
    plants: &[Plant],
    fruits: &FruitSet,
    solids: &mut Vec<Solid>,
) {
    // Every leaf draws its decision and a colour, so the leaves recoloured at a smaller share
    // are among those at a larger one, and the draws after them do not depend on the share.
    for solid in solids.iter_mut().filter(|s| s.part == Part::Leaf) {
        let recolour = rng.gen::<f64>() < share;
        let red = uniform_albedo(rng, RED_FRUIT_RANGE);
        if recolour {
            solid.albedo = red;
        }
    }
    let mut push = |shape: Option<Shape>, albedo: [f32; 3]| {
        if let Some(shape) = shape {
            solids.push(Solid::plant_part(shape, albedo, Part::Clutter));
        }
    };
    for plant in plants {
        let shape = place_clear(rng, fruits, |r| clip(r, plant));
        push(shape, uniform_albedo(rng, RED_FRUIT_RANGE));
        for _ in 0..rng.gen_range(RED_STEMS_PER_PLANT.0..=RED_STEMS_PER_PLANT.1) {
            let shape = place_clear(rng, fruits, |r| red_stem(r, plant));
            push(shape, uniform_albedo(rng, RED_FRUIT_RANGE));
        }
    }
    for k in 0..LABELS_PER_SCENE {
        let Some(plant) = plants.get(rng.gen_range(0..plants.len().max(1))) else {
            return;
        };
        let shape = place_clear(rng, fruits, |r| label(r, plant));
        // Red and orange labels in turn.
        let range = if k % 2 == 0 {
            RED_FRUIT_RANGE
        } else {
            ORANGE_CLUTTER_RANGE
        };
        push(shape, uniform_albedo(rng, range));
    }
}

/// The first of up to [`PLACEMENT_TRIES`] shapes `make` draws that keeps clear of fruit.
fn place_clear(
    rng: &mut ChaCha8Rng,
    fruits: &FruitSet,
    mut make: impl FnMut(&mut ChaCha8Rng) -> Shape,
) -> Option<Shape> {
    (0..PLACEMENT_TRIES)
        .map(|_| make(rng))
        .find(|s| !fruits.touches(s, CLEARANCE_M, None))
}

/// A point on the stem's axis at a random height within `margin_m` of its ends (and above
/// 0.2 m), with a random horizontal direction away from it.
fn stem_point(rng: &mut ChaCha8Rng, plant: &Plant, margin_m: f64) -> (Vector3<f64>, Vector3<f64>) {
    let top_m = (plant.height_m - margin_m).max(0.2);
    let height_m = uniform(rng, (0.2, top_m));
    let azimuth = uniform(rng, (0.0, std::f64::consts::TAU));
    let base = plant.base_in_world.coords;
    (
        Vector3::new(base.x, base.y, height_m),
        Vector3::new(azimuth.cos(), azimuth.sin(), 0.0),
    )
}

/// A short fat cylinder sticking out of the stem: a plant clip.
fn clip(rng: &mut ChaCha8Rng, plant: &Plant) -> Shape {
    let (at, out) = stem_point(rng, plant, 0.1);
    Shape::Cylinder(Cylinder {
        base: at + out * (plant.stem_radius_m - 0.002),
        axis: out,
        length_m: CLIP_LENGTH_M,
        radius_m: CLIP_RADIUS_M,
    })
}

/// A thin cylinder leaving the stem upwards: a red petiole.
fn red_stem(rng: &mut ChaCha8Rng, plant: &Plant) -> Shape {
    let (at, out) = stem_point(rng, plant, 0.05);
    let (s, c) = uniform(rng, RED_STEM_RISE_RAD).sin_cos();
    Shape::Cylinder(Cylinder {
        base: at + out * (plant.stem_radius_m - 0.001),
        axis: out * c + Vector3::z() * s,
        length_m: uniform(rng, RED_STEM_LENGTH_M),
        radius_m: RED_STEM_RADIUS_M,
    })
}

/// An upright label beside the stem, turned up to about 57° from facing away from it (its
/// near edge stays clear of the stem).
fn label(rng: &mut ChaCha8Rng, plant: &Plant) -> Shape {
    let (at, out) = stem_point(rng, plant, 0.1);
    let turn = uniform(rng, (-1.0, 1.0));
    let (s, c) = turn.sin_cos();
    let normal = Vector3::new(out.x * c - out.y * s, out.x * s + out.y * c, 0.0);
    let u = Vector3::z().cross(&normal);
    Shape::Disc {
        centre: at + out * (plant.stem_radius_m + LABEL_OFF_STEM_M),
        normal,
        u,
        v: normal.cross(&u),
        half_u_m: LABEL_HALF_M.0,
        half_v_m: LABEL_HALF_M.1,
    }
}
