//! Capsicum-like fruit: 3 or 4 lobes around a tilted fruit axis, leaning in towards the tip so
//! the body tapers, a calyx on top and a stalk up to the stem; some pressed against a leaf. The
//! lobes are the fruit; calyx, stalk and leaf are plant parts.

use std::f64::consts::TAU;

use nalgebra::{Matrix3, Point3, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::{
    uniform, uniform_albedo, FruitBody, FruitSet, Part, Plant, Solid, CALYX_ALBEDO, FRUIT_GAP_M,
    LEAF_LENGTH_M, LEAF_RANGE, LEAF_WIDTH_M, STEM_ALBEDO,
};
use crate::shapes::{Bounds, Cylinder, OrientedEllipsoid, Shape};
use crate::FruitTruth;

/// Largest angle of the fruit axis from vertical.
const MAX_TILT_RAD: f64 = std::f64::consts::PI / 6.0;
/// How far each lobe's long axis leans out from the fruit axis towards the top (so the lobes
/// converge towards the tip).
const LOBE_LEAN_RAD: (f64, f64) = (0.15, 0.3);
/// Lobe centres off the fruit axis, and lobe semi-axes (radial, tangential), in body radii.
const LOBE_OFFSET: f64 = 0.42;
const LOBE_RADIAL: f64 = 0.6;
const LOBE_TANGENTIAL: f64 = 0.62;
/// Lobe semi-axis along its length, in body half-lengths.
const LOBE_AXIAL: f64 = 0.95;
/// Per-lobe size variation (a factor).
const LOBE_SCALE: (f64, f64) = (0.92, 1.05);
/// Calyx radius in body radii, and its half thickness.
const CALYX_RADIUS: (f64, f64) = (0.45, 0.55);
const CALYX_HALF_THICKNESS_M: (f64, f64) = (0.005, 0.008);
const STALK_RADIUS_M: (f64, f64) = (0.0025, 0.0035);
/// Height the stalk climbs from the calyx to the stem.
const STALK_RISE_M: (f64, f64) = (0.05, 0.1);
/// Share of fruit with a leaf pressed against them.
const PRESSED_SHARE: f64 = 1.0 / 3.0;
/// Gap between a pressed leaf and the body (touching, without cutting into it).
const PRESSED_GAP_M: f64 = 0.0005;
/// Column spacing of the numerical volume.
const VOLUME_STEP_M: f64 = 0.001;

/// A capsicum at `centre` with body radius `(hx + hy) / 2` and half-length `hz` (of `half`),
/// or None when its body would touch the stem.
pub(super) fn body(
    rng: &mut ChaCha8Rng,
    id: u32,
    centre: Point3<f64>,
    half: Vector3<f64>,
    plant: &Plant,
) -> Option<FruitBody> {
    let (radius_m, half_length_m) = (0.5 * (half.x + half.y), half.z);
    let (axis, e1, e2) = tilted_frame(rng);
    let lobes = lobes(rng, &centre.coords, [axis, e1, e2], radius_m, half_length_m);
    let body_box = lobes
        .iter()
        .map(|l| Shape::OrientedEllipsoid(*l).bounds())
        .reduce(|a, b| a.union(&b))?;
    let calyx_radius_m = uniform(rng, CALYX_RADIUS) * radius_m;
    let calyx_half_m = uniform(rng, CALYX_HALF_THICKNESS_M);
    // Where the fruit axis leaves the body at the top: the calyx sits in the dip between lobes.
    let top_m = lobes
        .iter()
        .filter_map(|l| l.chord(&centre.coords, &axis))
        .map(|(_, s1)| s1)
        .fold(0.0, f64::max);
    let calyx = OrientedEllipsoid {
        centre: centre.coords + axis * top_m,
        axes: Matrix3::from_columns(&[e1, e2, axis]),
        radii: Vector3::new(calyx_radius_m, calyx_radius_m, calyx_half_m),
    };
    let stalk = stalk(rng, &(calyx.centre + axis * (0.5 * calyx_half_m)), plant);
    let pressed = rng.gen::<f64>() < PRESSED_SHARE;
    if !clear_of_stem(&body_box, plant) {
        return None;
    }
    let (body_volume_m3, body_centre) = union_volume(&lobes, &body_box);
    let (half_extents_m, box_centre) = (body_box.half(), body_box.centre());
    Some(FruitBody {
        truth: FruitTruth {
            id,
            centre: Point3::from(box_centre),
            half_extents_m,
            volume_m3: 8.0 * half_extents_m.x * half_extents_m.y * half_extents_m.z,
            body_centre: Point3::from(body_centre),
            body_volume_m3,
            axis,
        },
        body: lobes.into_iter().map(Shape::OrientedEllipsoid).collect(),
        keep_out: body_box.union(&Shape::OrientedEllipsoid(calyx).bounds()),
        attached: vec![
            Solid::plant_part(Shape::OrientedEllipsoid(calyx), CALYX_ALBEDO, Part::Calyx),
            Solid::plant_part(Shape::Cylinder(stalk), STEM_ALBEDO, Part::Stalk),
        ],
        stalk: Some(stalk),
        pressed,
    })
}

/// A random fruit axis up to [`MAX_TILT_RAD`] from vertical, with two unit vectors across it.
fn tilted_frame(rng: &mut ChaCha8Rng) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    let tilt = uniform(rng, (0.0, MAX_TILT_RAD));
    let towards = uniform(rng, (0.0, TAU));
    let (st, ct) = tilt.sin_cos();
    let (sa, ca) = towards.sin_cos();
    let axis = Vector3::new(st * ca, st * sa, ct);
    let e1 = Vector3::new(ct * ca, ct * sa, -st);
    (axis, e1, axis.cross(&e1))
}

/// The lobes around `axis` (frame `[axis, e1, e2]`), evenly spread, each leaning out towards
/// the top.
fn lobes(
    rng: &mut ChaCha8Rng,
    centre: &Vector3<f64>,
    [axis, e1, e2]: [Vector3<f64>; 3],
    radius_m: f64,
    half_length_m: f64,
) -> Vec<OrientedEllipsoid> {
    let count = rng.gen_range(3u32..=4);
    let phase = uniform(rng, (0.0, TAU));
    let (sl, cl) = uniform(rng, LOBE_LEAN_RAD).sin_cos();
    (0..count)
        .map(|k| {
            let angle = phase + TAU * k as f64 / count as f64;
            let out = e1 * angle.cos() + e2 * angle.sin();
            let long = axis * cl + out * sl;
            let radial = out * cl - axis * sl;
            let scale = uniform(rng, LOBE_SCALE);
            OrientedEllipsoid {
                centre: centre + out * (LOBE_OFFSET * radius_m),
                axes: Matrix3::from_columns(&[radial, long.cross(&radial), long]),
                radii: Vector3::new(
                    LOBE_RADIAL * radius_m * scale,
                    LOBE_TANGENTIAL * radius_m * scale,
                    LOBE_AXIAL * half_length_m * scale,
                ),
            }
        })
        .collect()
}

/// A thin stalk from `start` (inside the calyx) to the stem's axis, higher up.
fn stalk(rng: &mut ChaCha8Rng, start: &Vector3<f64>, plant: &Plant) -> Cylinder {
    let radius_m = uniform(rng, STALK_RADIUS_M);
    let base = plant.base_in_world.coords;
    let top_z = (start.z + uniform(rng, STALK_RISE_M)).min(plant.height_m);
    let to_stem = Vector3::new(base.x, base.y, top_z) - start;
    let length_m = to_stem.norm();
    Cylinder {
        base: *start,
        axis: to_stem / length_m.max(1e-9),
        length_m,
        radius_m,
    }
}

/// True when the box keeps 2 mm from the stem horizontally.
fn clear_of_stem(b: &Bounds, plant: &Plant) -> bool {
    let p = plant.base_in_world;
    let gap = |i: usize, c: f64| (b.min[i] - c).max(c - b.max[i]).max(0.0);
    gap(0, p.x).hypot(gap(1, p.y)) >= plant.stem_radius_m + 0.002
}

/// Volume and centroid of a union of ellipsoids inside `bounds`: vertical chords through columns
/// at most [`VOLUME_STEP_M`] apart, the chords of a column merged so overlaps count once. Exact
/// along z, a midpoint rule across x and y.
pub(crate) fn union_volume(lobes: &[OrientedEllipsoid], bounds: &Bounds) -> (f64, Vector3<f64>) {
    let cells = |i: usize| {
        ((bounds.max[i] - bounds.min[i]) / VOLUME_STEP_M)
            .ceil()
            .max(1.0)
    };
    let (nx, ny) = (cells(0), cells(1));
    let (dx, dy) = (
        (bounds.max[0] - bounds.min[0]) / nx,
        (bounds.max[1] - bounds.min[1]) / ny,
    );
    let columns: Vec<ZChords> = lobes.iter().map(ZChords::new).collect();
    let mut chords = Vec::with_capacity(lobes.len());
    let (mut volume, mut moment) = (0.0, Vector3::zeros());
    for i in 0..nx as usize {
        let x = bounds.min[0] + (i as f64 + 0.5) * dx;
        for j in 0..ny as usize {
            let y = bounds.min[1] + (j as f64 + 0.5) * dy;
            chords.clear();
            chords.extend(columns.iter().filter_map(|c| c.at(x, y)));
            let (length, z_moment) = merged_length(&mut chords);
            volume += length;
            moment += Vector3::new(x * length, y * length, z_moment);
        }
    }
    let centroid = if volume > 0.0 {
        moment / volume
    } else {
        bounds.centre()
    };
    (volume * dx * dy, centroid)
}

/// Vertical chords of one ellipsoid, with what does not depend on the column computed once: in
/// the ellipsoid's unit-sphere frame the line `(x, y, z)` is `x m0 + y m1 + at_origin + z m2`
/// (`m0..m2` the columns of `unit_from_world`).
struct ZChords {
    m0: Vector3<f64>,
    m1: Vector3<f64>,
    m2: Vector3<f64>,
    at_origin: Vector3<f64>,
}

impl ZChords {
    fn new(e: &OrientedEllipsoid) -> Self {
        let m = e.unit_from_world();
        Self {
            m0: m.column(0).into_owned(),
            m1: m.column(1).into_owned(),
            m2: m.column(2).into_owned(),
            at_origin: -(m * e.centre),
        }
    }

    /// The interval of `z` inside the ellipsoid on the vertical line through `(x, y)`.
    fn at(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let o = self.m0 * x + self.m1 * y + self.at_origin;
        let d = &self.m2;
        let (a, b, c) = (d.dot(d), o.dot(d), o.dot(&o) - 1.0);
        let disc = b * b - a * c;
        (disc > 0.0).then(|| {
            let sq = disc.sqrt();
            ((-b - sq) / a, (-b + sq) / a)
        })
    }
}

/// Total length of the union of intervals, and its first moment `∫ z dz`.
fn merged_length(chords: &mut [(f64, f64)]) -> (f64, f64) {
    chords.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut length, mut moment) = (0.0, 0.0);
    let mut current: Option<(f64, f64)> = None;
    for &(lo, hi) in chords.iter() {
        current = match current {
            Some((a, b)) if lo <= b => Some((a, b.max(hi))),
            _ => {
                if let Some((a, b)) = current {
                    length += b - a;
                    moment += 0.5 * (b * b - a * a);
                }
                Some((lo, hi))
            }
        };
    }
    if let Some((a, b)) = current {
        length += b - a;
        moment += 0.5 * (b * b - a * a);
    }
    (length, moment)
}

/// Presses a leaf against each fruit chosen for it: a leaf whose plane touches the body's
/// outermost point in a direction away from the stem, kept only when it clears other fruit.
pub(super) fn press_leaves(rng: &mut ChaCha8Rng, fruits: &FruitSet, solids: &mut Vec<Solid>) {
    for &(id, stem_base) in &fruits.pressed {
        let (Some(truth), Some(body)) = (
            fruits.truths.get(id as usize),
            fruits.bodies.get(id as usize),
        ) else {
            continue;
        };
        let lobes: Vec<OrientedEllipsoid> = body
            .iter()
            .filter_map(|s| match s {
                Shape::OrientedEllipsoid(e) => Some(*e),
                _ => None,
            })
            .collect();
        for _attempt in 0..8 {
            let leaf = pressed_leaf(rng, &lobes, &(truth.centre.coords - stem_base));
            if let Some(leaf) = leaf.filter(|l| !fruits.touches(l, FRUIT_GAP_M, Some(id))) {
                let albedo = uniform_albedo(rng, LEAF_RANGE);
                solids.push(Solid::plant_part(leaf, albedo, Part::Leaf));
                break;
            }
        }
    }
}

/// A leaf disc touching the body's outermost point along a random direction roughly away from
/// the stem (`outward`, horizontal part used), the touching point within the leaf.
fn pressed_leaf(
    rng: &mut ChaCha8Rng,
    lobes: &[OrientedEllipsoid],
    outward: &Vector3<f64>,
) -> Option<Shape> {
    let yaw = outward.y.atan2(outward.x) + uniform(rng, (-1.6, 1.6));
    let (se, ce) = uniform(rng, (-0.3, 0.5)).sin_cos();
    let normal = Vector3::new(ce * yaw.cos(), ce * yaw.sin(), se);
    let (touch, _) = lobes
        .iter()
        .map(|l| l.support(&normal))
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    // The leaf's long axis hangs roughly down the body, rolled a little.
    let down = (Vector3::z() - normal * normal.z).try_normalize(1e-9)?;
    let (sr, cr) = uniform(rng, (-0.8, 0.8)).sin_cos();
    let u = down * cr + normal.cross(&down) * sr;
    let v = normal.cross(&u);
    let half_u_m = 0.5 * uniform(rng, LEAF_LENGTH_M);
    let half_v_m = 0.5 * uniform(rng, LEAF_WIDTH_M);
    let offset =
        u * (uniform(rng, (-0.5, 0.5)) * half_u_m) + v * (uniform(rng, (-0.3, 0.3)) * half_v_m);
    Some(Shape::Disc {
        centre: touch + normal * PRESSED_GAP_M + offset,
        normal,
        u,
        v,
        half_u_m,
        half_v_m,
    })
}
