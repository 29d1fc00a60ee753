//! A scene over days (`SceneOptions::day`): the same plants looked at again a few days later.
//!
//! Each fruit has a life drawn from the scene's seed (its own stream, so the scene of day 0 is the
//! same whatever day is asked for next): most are on the plant at day 0, part grown, and swell by
//! [`GROWTH_PER_DAY`] of their final size per day (linear size, so their volume grows by about
//! three times that share) until full size; a share set later (new fruit, small at first); a
//! share of the grown ones is harvested on a day (gone from then on). Leaves drift a little about
//! a direction of their own (angle and offset growing with the square root of the days), and a
//! share of them grows later. A fruit keeps its id over the days: the truth identity across
//! visits. Body solids shrink towards the fruit's stalk end, so calyx and stalk stay attached.

use nalgebra::{Rotation3, Unit, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::{stream_rng, uniform, Built, Part};
use crate::shapes::{OrientedEllipsoid, Shape};
use crate::FruitTruth;

const SEASON_STREAM: u64 = 3;
/// Linear size gained per day, as a share of the final size.
pub const GROWTH_PER_DAY: f64 = 0.03;
/// Size at day 0 of the fruit already on the plant, as a share of the final size.
const START_SCALE: (f64, f64) = (0.6, 1.0);
/// Share of fruit set after day 0, the day they set and their size then.
const NEW_FRUIT_SHARE: f64 = 0.15;
const SET_DAY: (f64, f64) = (0.5, 14.0);
const SET_SCALE: f64 = 0.55;
/// Share of the fruit at least this grown at day 0 harvested, and the day they are.
const HARVEST_SHARE: f64 = 0.35;
const HARVEST_SCALE: f64 = 0.9;
const HARVEST_DAY: (f64, f64) = (1.0, 14.0);
/// Leaf drift per square root of a day: angle (rad) and offset (m) at most.
const LEAF_TURN_RAD: f64 = 0.05;
const LEAF_SHIFT_M: f64 = 0.004;
/// Share of leaves that grow after day 0, and the day they appear.
const NEW_LEAF_SHARE: f64 = 0.1;

/// One fruit's life over the days.
#[derive(Clone, Copy, Debug)]
struct FruitLife {
    set_day: f64,
    /// Size when set (day 0 for the fruit already there).
    start_scale: f64,
    harvest_day: f64,
}

impl FruitLife {
    fn draw(rng: &mut ChaCha8Rng) -> Self {
        // Every fruit draws the same numbers, so one fruit's life does not shift another's.
        let (new, set_day, start) = (
            rng.gen::<f64>(),
            uniform(rng, SET_DAY),
            uniform(rng, START_SCALE),
        );
        let (harvested, harvest_day) = (rng.gen::<f64>(), uniform(rng, HARVEST_DAY));
        let is_new = new < NEW_FRUIT_SHARE;
        let picked = !is_new && start >= HARVEST_SCALE && harvested < HARVEST_SHARE;
        Self {
            set_day: if is_new { set_day } else { 0.0 },
            start_scale: if is_new { SET_SCALE } else { start },
            harvest_day: if picked { harvest_day } else { f64::INFINITY },
        }
    }

    /// Its size on `day` as a share of its final size; None while not set or once harvested.
    fn scale_on(&self, day: f64) -> Option<f64> {
        if day < self.set_day || day >= self.harvest_day {
            return None;
        }
        Some((self.start_scale + GROWTH_PER_DAY * (day - self.set_day)).min(1.0))
    }
}

/// How one leaf drifts and when it grows.
struct LeafLife {
    axis: Unit<Vector3<f64>>,
    turn_rad: f64,
    shift_m: Vector3<f64>,
    appear_day: f64,
}

impl LeafLife {
    fn draw(rng: &mut ChaCha8Rng) -> Self {
        let mut unit = || {
            Vector3::new(rng.gen::<f64>(), rng.gen::<f64>(), rng.gen::<f64>())
                .map(|v| 2.0 * v - 1.0)
        };
        let axis = Unit::try_new(unit(), 1e-6).unwrap_or(Vector3::z_axis());
        let shift = unit();
        let (turn, size, new, appear) = (
            rng.gen::<f64>(),
            rng.gen::<f64>(),
            rng.gen::<f64>(),
            uniform(rng, SET_DAY),
        );
        Self {
            axis,
            turn_rad: (2.0 * turn - 1.0) * LEAF_TURN_RAD,
            shift_m: shift.normalize() * size * LEAF_SHIFT_M,
            appear_day: if new < NEW_LEAF_SHARE { appear } else { 0.0 },
        }
    }
}

/// The scene of `built` as it is `day` days after the first visit.
pub(crate) fn apply(built: &mut Built, seed: u64, day: f64) {
    let mut rng = stream_rng(seed, SEASON_STREAM);
    let lives: Vec<FruitLife> = built
        .fruits
        .iter()
        .map(|_| FruitLife::draw(&mut rng))
        .collect();
    let scales: Vec<Option<f64>> = lives.iter().map(|l| l.scale_on(day)).collect();
    let anchors: Vec<Vector3<f64>> = built.fruits.iter().map(stalk_end).collect();
    // The fruit present on the day, renumbered in order; their ids stay.
    let mut index_of = vec![None; built.fruits.len()];
    let mut fruits = Vec::new();
    for (i, truth) in built.fruits.iter().enumerate() {
        if let Some(s) = scales[i] {
            index_of[i] = Some(fruits.len() as u32);
            fruits.push(grown(truth, &anchors[i], s));
        }
    }
    let sqrt_day = day.max(0.0).sqrt();
    let mut solids = Vec::with_capacity(built.solids.len());
    for mut solid in std::mem::take(&mut built.solids) {
        let leaf = (solid.part == Part::Leaf).then(|| LeafLife::draw(&mut rng));
        if let Some(i) = solid.fruit_index.map(|i| i as usize) {
            let (Some(Some(s)), Some(index)) = (scales.get(i), index_of.get(i).copied().flatten())
            else {
                continue;
            };
            solid.shape = scaled(&solid.shape, &anchors[i], *s);
            solid.fruit_index = Some(index);
        }
        if let Some(leaf) = leaf {
            if day < leaf.appear_day {
                continue;
            }
            solid.shape = drifted(&solid.shape, &leaf, sqrt_day);
        }
        solids.push(solid);
    }
    built.solids = solids;
    built.fruits = fruits;
}

/// Where the fruit hangs from: the top of its body along its axis (tip to stalk).
fn stalk_end(truth: &FruitTruth) -> Vector3<f64> {
    let reach = truth.axis.abs().dot(&truth.half_extents_m);
    truth.body_centre.coords + truth.axis * reach
}

/// The truth of a fruit at `s` of its final size, grown from `anchor`.
fn grown(truth: &FruitTruth, anchor: &Vector3<f64>, s: f64) -> FruitTruth {
    let about =
        |p: &nalgebra::Point3<f64>| nalgebra::Point3::from(anchor + (p.coords - anchor) * s);
    FruitTruth {
        centre: about(&truth.centre),
        half_extents_m: truth.half_extents_m * s,
        volume_m3: truth.volume_m3 * s.powi(3),
        body_centre: about(&truth.body_centre),
        body_volume_m3: truth.body_volume_m3 * s.powi(3),
        ..truth.clone()
    }
}

/// A fruit body solid at `s` of its size, towards `anchor`.
fn scaled(shape: &Shape, anchor: &Vector3<f64>, s: f64) -> Shape {
    let at = |c: &Vector3<f64>| anchor + (c - anchor) * s;
    match shape {
        Shape::Ellipsoid { centre, radii } => Shape::Ellipsoid {
            centre: at(centre),
            radii: radii * s,
        },
        Shape::OrientedEllipsoid(e) => Shape::OrientedEllipsoid(OrientedEllipsoid {
            centre: at(&e.centre),
            radii: e.radii * s,
            axes: e.axes,
        }),
        other => other.clone(),
    }
}

/// A leaf turned and shifted by its drift after `sqrt_day` square-root days.
fn drifted(shape: &Shape, leaf: &LeafLife, sqrt_day: f64) -> Shape {
    let Shape::Disc {
        centre,
        normal,
        u,
        v,
        half_u_m,
        half_v_m,
    } = shape
    else {
        return shape.clone();
    };
    let turn = Rotation3::from_axis_angle(&leaf.axis, leaf.turn_rad * sqrt_day);
    Shape::Disc {
        centre: centre + leaf.shift_m * sqrt_day,
        normal: turn * normal,
        u: turn * u,
        v: turn * v,
        half_u_m: *half_u_m,
        half_v_m: *half_v_m,
    }
}
