//! Seeded procedural content: plant layout per scenario, stems, leaves, fruits, fixed structures.

use glasshouse_geom::Aabb;
use nalgebra::{Point3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::shapes::{Bounds, Cylinder, Shape};
use crate::{FruitColour, FruitTruth, ScenarioKind};

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
        }
    }
}

/// The same relative place in the unripe range as `red` has in the red one, so a green scene
/// draws exactly the random numbers of its red twin and only the colours differ.
fn unripe_twin(red: [f32; 3]) -> [f32; 3] {
    let mut out = [0.0; 3];
    for (a, ((r_lo, r_hi), (g_lo, g_hi))) in RED_FRUIT_RANGE
        .into_iter()
        .zip(UNRIPE_FRUIT_RANGE)
        .enumerate()
    {
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

/// A solid in the scene with its surface colour and, for fruit, its index in the truth list.
#[derive(Clone, Debug)]
pub(crate) struct Solid {
    pub shape: Shape,
    pub albedo: [f32; 3],
    pub fruit_index: Option<u32>,
    /// Part of a plant (counts for the sampling region), as opposed to fixed structure.
    pub is_plant: bool,
}

#[derive(Clone, Debug)]
pub(crate) struct Plant {
    pub base_in_world: Point3<f64>,
    pub height_m: f64,
    pub fruit_count: u32,
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

pub(crate) fn build(kind: ScenarioKind, seed: u64, colour: FruitColour) -> Built {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut solids = Vec::new();
    let (layout, camera_workspace) = match kind {
        ScenarioKind::One => {
            let positions = place_plants(
                &mut rng,
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
            });
            let counts = [7, 7, 0, 0];
            let layout: Vec<_> = positions.into_iter().zip(counts).collect();
            let workspace = Aabb::new(Point3::new(-0.7, -0.7, 0.3), Point3::new(0.7, 0.7, 1.5));
            (layout, workspace)
        }
        ScenarioKind::Two => {
            let positions = place_plants(
                &mut rng,
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
                    x += uniform(&mut rng, (0.45, 0.55));
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
                });
            }
            let workspace = Aabb::new(
                Point3::new(-0.3, -0.75, 0.2),
                Point3::new(x + 0.3, -0.2, 2.0),
            );
            (layout, workspace)
        }
    };

    let mut fruits: Vec<FruitTruth> = Vec::new();
    let mut plants = Vec::new();
    for ((x, y), fruit_count) in layout {
        let plant = Plant {
            base_in_world: Point3::new(x, y, 0.0),
            height_m: uniform(&mut rng, STEM_HEIGHT_M),
            fruit_count,
        };
        add_plant(&mut rng, &plant, &mut fruits, &mut solids);
        plants.push(plant);
    }

    if kind == ScenarioKind::Row && fruits.len() >= 3 {
        // A few unripe fruits: still fruit in the ground truth, but not red.
        let mut recoloured = Vec::new();
        while recoloured.len() < 3 {
            let pick = rng.gen_range(0..fruits.len()) as u32;
            if !recoloured.contains(&pick) {
                recoloured.push(pick);
            }
        }
        for solid in &mut solids {
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

    if colour == FruitColour::Green {
        for solid in &mut solids {
            if solid.fruit_index.is_some() && is_ripe_colour(solid.albedo) {
                solid.albedo = unripe_twin(solid.albedo);
            }
        }
    }

    Built {
        fruits,
        solids,
        plants,
        camera_workspace,
    }
}

/// Fruit ellipsoid as a shape.
fn fruit_shape(f: &FruitTruth) -> Shape {
    Shape::Ellipsoid {
        centre: f.centre.coords,
        radii: f.half_extents_m,
    }
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

/// True when the leaf disc comes within 5 mm of a fruit (sampled over the disc; leaves are small).
fn leaf_touches_fruit(leaf: &Shape, fruits: &[FruitTruth]) -> bool {
    let Shape::Disc {
        centre,
        u,
        v,
        half_u_m,
        half_v_m,
        ..
    } = leaf
    else {
        return false;
    };
    let leaf_bounds = leaf.bounds();
    fruits.iter().any(|f| {
        let fb = Bounds::from_centre_half(&f.centre.coords, &f.half_extents_m);
        if !leaf_bounds.overlaps(&fb, 0.005) {
            return false;
        }
        let grown = f.half_extents_m.add_scalar(0.005);
        let steps = 8;
        (-steps..=steps).any(|i| {
            (-steps..=steps).any(|j| {
                let s = i as f64 / steps as f64;
                let w = j as f64 / steps as f64;
                if s * s + w * w > 1.0 {
                    return false;
                }
                let p = centre + u * (s * half_u_m) + v * (w * half_v_m);
                (p - f.centre.coords).component_div(&grown).norm_squared() <= 1.0
            })
        })
    })
}

fn add_plant(
    rng: &mut ChaCha8Rng,
    plant: &Plant,
    fruits: &mut Vec<FruitTruth>,
    solids: &mut Vec<Solid>,
) {
    let base = plant.base_in_world.coords;
    let stem_radius_m = uniform(rng, STEM_RADIUS_M);
    solids.push(Solid {
        shape: Shape::Cylinder(Cylinder {
            base,
            axis: Vector3::z(),
            length_m: plant.height_m,
            radius_m: stem_radius_m,
        }),
        albedo: STEM_ALBEDO,
        fruit_index: None,
        is_plant: true,
    });

    // Fruits first, so leaves can be placed around them without cutting through them.
    let mut plant_fruits: Vec<(FruitTruth, f64)> = Vec::new();
    let top_z = FRUIT_CENTRE_Z_M.1.min(plant.height_m - 0.08);
    let mut added = 0;
    for _attempt in 0..5000 {
        if added == plant.fruit_count {
            break;
        }
        let half = Vector3::new(
            uniform(rng, FRUIT_HALF_XY_M),
            uniform(rng, FRUIT_HALF_XY_M),
            uniform(rng, FRUIT_HALF_Z_M),
        );
        // Keep clear of the stem: the box's horizontal reach is at most max(hx, hy).
        let min_axis_distance = half.x.max(half.y) + stem_radius_m + 0.002;
        let axis_distance = uniform(rng, (min_axis_distance, FRUIT_MAX_AXIS_DISTANCE_M));
        let azimuth = uniform(rng, (0.0, std::f64::consts::TAU));
        let z = uniform(rng, (FRUIT_CENTRE_Z_M.0, top_z));
        let centre = Point3::new(
            base.x + axis_distance * azimuth.cos(),
            base.y + axis_distance * azimuth.sin(),
            z,
        );
        let candidate = Bounds::from_centre_half(&centre.coords, &half);
        // Disjoint boxes (with 5 mm between) guarantee disjoint ellipsoids.
        let clear = fruits.iter().all(|f| {
            !candidate.overlaps(
                &Bounds::from_centre_half(&f.centre.coords, &f.half_extents_m),
                0.005,
            )
        });
        if !clear {
            continue;
        }
        let truth = FruitTruth {
            id: fruits.len() as u32,
            centre,
            half_extents_m: half,
            volume_m3: 8.0 * half.x * half.y * half.z,
        };
        solids.push(Solid {
            shape: fruit_shape(&truth),
            albedo: uniform_albedo(rng, RED_FRUIT_RANGE),
            fruit_index: Some(truth.id),
            is_plant: true,
        });
        plant_fruits.push((truth.clone(), azimuth));
        fruits.push(truth);
        added += 1;
    }

    let all_fruits: &[FruitTruth] = fruits;
    let mut push_leaf = |rng: &mut ChaCha8Rng,
                         height_range: (f64, f64),
                         azimuth_range: (f64, f64),
                         droop: (f64, f64)| {
        for _attempt in 0..8 {
            let height = uniform(rng, height_range).clamp(0.1, plant.height_m);
            let leaf = leaf_shape(
                Vector3::new(base.x, base.y, height),
                stem_radius_m,
                uniform(rng, azimuth_range),
                uniform(rng, droop),
                uniform(rng, (-1.0, 1.0)),
                uniform(rng, (0.01, 0.06)),
                uniform(rng, LEAF_LENGTH_M),
                uniform(rng, LEAF_WIDTH_M),
            );
            if !leaf_touches_fruit(&leaf, all_fruits) {
                solids.push(Solid {
                    shape: leaf,
                    albedo: uniform_albedo(rng, LEAF_RANGE),
                    fruit_index: None,
                    is_plant: true,
                });
                return;
            }
        }
    };

    // Canopy leaves over each fruit: fruit hang under leaves.
    for (fruit, azimuth) in &plant_fruits {
        let above = fruit.centre.z + fruit.half_extents_m.z;
        for _ in 0..3 {
            push_leaf(
                rng,
                (above + 0.01, above + 0.08),
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
