#![allow(clippy::unwrap_used)]

use glasshouse_geom::FruitEstimate;
use glasshouse_nbv::Method;
use glasshouse_sim::ScenarioKind;
use nalgebra::Vector3;

use super::*;
use crate::TrialConfig;

/// A true fruit `id` at `x` of half size `half_m`, and an estimate of it `off_m` off along y.
fn truth(id: u32, x: f64, half_m: f64) -> FruitTruth {
    FruitTruth::ellipsoid(id, Point3::new(x, 0.0, 1.0), Vector3::repeat(half_m))
}

fn estimate(id: u32, x: f64, half_m: f64, off_m: f64) -> FruitEstimate {
    let c = Point3::new(x, off_m, 1.0);
    let h = Vector3::repeat(half_m);
    FruitEstimate {
        volume_m3: 4.0 / 3.0 * std::f64::consts::PI * half_m.powi(3),
        ..FruitEstimate::from_box(id, c, c - h, c + h)
    }
}

fn visit(truths: Vec<FruitTruth>, fruits: Vec<FruitEstimate>) -> TrialResult {
    TrialResult {
        config: TrialConfig::new(ScenarioKind::Two, Method::OursUu, 1),
        samples: Vec::new(),
        fruits_total: truths.len(),
        views: 0,
        frames: 0,
        unreachable_views: 0,
        frames_without_reachable_view: 0,
        compute_time_s: 0.0,
        fruits,
        fruit_surfaces: Vec::new(),
        clusters: Vec::new(),
        truths,
        registration: Default::default(),
        plans: Vec::new(),
        best_views: Vec::new(),
    }
}

#[test]
fn links_are_judged_by_the_simulators_ids_and_growth_by_the_true_change() {
    // Monday: fruits 10, 11, 12; each estimated 1 cm off.
    let monday = visit(
        vec![
            truth(10, 0.0, 0.03),
            truth(11, 0.2, 0.03),
            truth(12, 0.4, 0.03),
        ],
        vec![
            estimate(1, 0.0, 0.03, 0.01),
            estimate(2, 0.2, 0.03, 0.01),
            estimate(3, 0.4, 0.03, 0.01),
        ],
    );
    // Thursday: 10 grew by a third in size (estimated well), 11 harvested, 12 the same, and a
    // new fruit 13 set 3 cm from where 11 was: the tracker takes it for 11 (a wrong link).
    let thursday = visit(
        vec![
            truth(10, 0.0, 0.04),
            truth(12, 0.4, 0.03),
            truth(13, 0.23, 0.028),
        ],
        vec![
            estimate(5, 0.0, 0.04, 0.01),
            estimate(6, 0.4, 0.03, 0.01),
            estimate(7, 0.23, 0.028, 0.0),
        ],
    );
    let season = season_figures(&[monday, thursday], &[0.0, 3.5], SeasonRules::default());
    // Possible: 10 and 12 (matched on both days); made: three links, two correct.
    assert_eq!(
        (
            season.identity.possible,
            season.identity.made,
            season.identity.correct
        ),
        (2, 3, 2)
    );
    assert!((season.identity.f1() - 0.8).abs() < 1e-12);
    // Only 10 grew: its change estimated exactly.
    assert_eq!(season.growth_errors.len(), 1);
    assert!(season.growth_errors[0] < 1e-9, "{:?}", season.growth_errors);
    assert_eq!(season.visits.len(), 2);
    assert_eq!(season.season_fruits, 3);
}

/// An estimate of a round fruit of radius `r_m` at `x` with its fitted sphere's volume times
/// `volume_scale`, and the voxel centres (5 mm) of its side facing +x.
fn round(id: u32, x: f64, r_m: f64, volume_scale: f64) -> (FruitEstimate, Vec<Point3<f64>>) {
    use glasshouse_nbv::superellipsoid::Superellipsoid;
    let sphere = Superellipsoid::sphere(Point3::new(x, 0.0, 1.0), r_m);
    let mut solid = sphere.to_solid(1.0, 0.0);
    solid.volume_m3 *= volume_scale;
    let e = FruitEstimate {
        solid: Some(solid),
        ..estimate(id, x, r_m, 0.0)
    };
    (e, sphere.seen_voxel_centres(Vector3::x(), 0.005))
}

#[test]
fn growth_is_judged_on_the_change_measured_on_one_shape_when_the_surfaces_are_known() {
    let (monday_fruit, monday_surface) = round(1, 0.0, 0.03, 1.0);
    // Thursday: the fruit grew 10 % in size, its fit came out 30 % too large in volume.
    let (thursday_fruit, thursday_surface) = round(5, 0.012, 0.033, 1.3);
    let mut monday = visit(vec![truth(10, 0.0, 0.03)], vec![monday_fruit]);
    let mut thursday = visit(vec![truth(10, 0.012, 0.033)], vec![thursday_fruit]);
    monday.fruit_surfaces = vec![monday_surface];
    thursday.fruit_surfaces = vec![thursday_surface];
    let season = season_figures(&[monday, thursday], &[0.0, 3.5], SeasonRules::default());
    let (measured, differenced) = (season.growth_errors[0], season.differenced_growth_errors[0]);
    assert!(differenced > 1.0, "{differenced}");
    assert!(
        measured < 0.5 * differenced,
        "{measured} against {differenced}"
    );
}
