//! Time of one whole-fruit fit ([`fit_ellipsoid`]) per model on scanned synthetic fruit: a
//! sphere seen from one side, a tilted lobed capsicum seen from two sides, an ellipsoid seen all
//! round; and of one growth measurement between two visits of it ([`volume_ratio`], the fruit's
//! surface against itself, what a visit's end costs per fruit); and of one search for the body
//! under a cluster ([`find_body`], what each turned-away cluster costs when the map around it
//! changed). Run with `cargo bench -p
//! glasshouse-nbv --bench fit`. Wall-clock time is read here
//! only, never in the libraries.

use std::time::Instant;

use glasshouse_geom::FruitSurface;
use glasshouse_nbv::evidence::{find_body, BodyConfig};
use glasshouse_nbv::fit::{fit_ellipsoid, FitConfig, ShapeModel};
use glasshouse_nbv::growth::volume_ratio;
use glasshouse_roimap::{MapConfig, RoiCluster, RoiMap};
use nalgebra::{Point3, Rotation3, Unit, Vector3};

/// An ellipsoid lobe: centre, orientation, semi-axes.
type Lobe = (Point3<f64>, Rotation3<f64>, Vector3<f64>);

fn hit(lobes: &[Lobe], o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
    let one = |(c, r, axes): &Lobe| {
        let oc = r.inverse_transform_vector(&(o - c)).component_div(axes);
        let dd = r.inverse_transform_vector(d).component_div(axes);
        let (a, b, cc) = (
            dd.norm_squared(),
            2.0 * oc.dot(&dd),
            oc.norm_squared() - 1.0,
        );
        let disc = b * b - 4.0 * a * cc;
        let t = (-b - disc.max(0.0).sqrt()) / (2.0 * a);
        (disc >= 0.0 && t > 0.0).then_some(t)
    };
    lobes.iter().filter_map(one).min_by(f64::total_cmp)
}

/// A 120 x 120 fan from 0.4 m in each direction of `towards`, inserted twice.
fn scanned(lobes: &[Lobe], towards: &[Vector3<f64>]) -> (RoiMap, RoiCluster) {
    let mut map = RoiMap::new(MapConfig::default()).expect("valid map");
    let aim = lobes[0].0;
    for t in towards {
        let eye = aim + t.normalize() * 0.4;
        let forward = (aim - eye).normalize();
        let right = forward.cross(&Vector3::z()).normalize();
        let up = right.cross(&forward);
        let (mut points, mut roi) = (Vec::new(), Vec::new());
        for i in 0..120 {
            for j in 0..120 {
                let u = 0.25 * (2.0 * (f64::from(i) + 0.5) / 120.0 - 1.0);
                let v = 0.25 * (2.0 * (f64::from(j) + 0.5) / 120.0 - 1.0);
                let d = (forward + right * u.tan() + up * v.tan()).normalize();
                let h = hit(lobes, &eye, &d);
                points.push((eye + d * h.unwrap_or(0.7)).cast::<f32>());
                roi.push(h.is_some());
            }
        }
        for _ in 0..2 {
            map.insert_scan(&eye, &points, &roi).expect("valid scan");
        }
    }
    let cluster = map.clusters(10).into_iter().max_by_key(|c| c.voxels.len());
    (map, cluster.expect("one cluster"))
}

fn capsicum(c: Point3<f64>) -> Vec<Lobe> {
    let tilt = Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::new(1.0, 0.4, 0.0)), 0.4);
    let up = tilt * Vector3::z();
    (0..4)
        .map(|k| {
            let angle = 0.4 + std::f64::consts::TAU * f64::from(k) / 4.0;
            let radial = tilt * Vector3::new(angle.cos(), angle.sin(), 0.0);
            let lean = Rotation3::from_axis_angle(&Unit::new_normalize(up.cross(&radial)), 0.2);
            let axes = Vector3::new(0.021, 0.019, 0.055);
            (c + radial * 0.015 + up * 0.004, lean * tilt, axes)
        })
        .collect()
}

/// The fastest of `runs` (other work on the machine only ever adds time).
fn fastest_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    (0..runs)
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let c = Point3::new(0.203, -0.107, 1.005);
    let sphere = vec![(c, Rotation3::identity(), Vector3::repeat(0.035))];
    let ellipsoid = vec![(c, Rotation3::identity(), Vector3::new(0.03, 0.038, 0.045))];
    let all_round = [
        Vector3::x(),
        -Vector3::x(),
        Vector3::y(),
        -Vector3::y(),
        Vector3::z(),
    ];
    let cases = [
        (
            "sphere, one side",
            scanned(&sphere, &[Vector3::new(-1.0, -0.2, 0.1)]),
        ),
        (
            "capsicum, two sides",
            scanned(
                &capsicum(c),
                &[Vector3::new(-1.0, -0.2, 0.15), Vector3::y()],
            ),
        ),
        ("ellipsoid, all round", scanned(&ellipsoid, &all_round)),
    ];
    println!(
        "{:<24} {:>8} {:>14} {:>14} {:>12} {:>10}",
        "case", "voxels", "aligned ms", "superell. ms", "growth ms", "body ms"
    );
    for (name, (map, cluster)) in &cases {
        let time = |model| {
            let config = FitConfig {
                model,
                ..FitConfig::default()
            };
            fastest_ms(15, || {
                std::hint::black_box(fit_ellipsoid(map, cluster, &config));
            })
        };
        let surface = FruitSurface {
            solid: fit_ellipsoid(map, cluster, &FitConfig::default()),
            points_m: cluster.voxels.iter().map(|k| map.centre_of(*k)).collect(),
        };
        let growth_ms = fastest_ms(15, || {
            std::hint::black_box(volume_ratio(&surface, &surface));
        });
        let body_ms = fastest_ms(15, || {
            std::hint::black_box(find_body(map, cluster, &BodyConfig::default()));
        });
        println!(
            "{name:<24} {:>8} {:>14.2} {:>14.2} {growth_ms:>12.2} {body_ms:>10.2}",
            cluster.voxels.len(),
            time(ShapeModel::AxisAlignedEllipsoid),
            time(ShapeModel::Superellipsoid)
        );
    }
}
