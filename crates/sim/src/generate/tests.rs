#![allow(clippy::unwrap_used)]

use nalgebra::{Isometry3, Rotation3};

use super::*;
use crate::shapes::OrientedEllipsoid;
use crate::tests::corners;
use crate::{look_at, shade, CameraModel, RgbdImage, Scene};

/// FNV-1a over a stream of 64-bit words.
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }

    fn word(&mut self, w: u64) {
        for byte in w.to_le_bytes() {
            self.0 = (self.0 ^ u64::from(byte)).wrapping_mul(0x0100_0000_01b3);
        }
    }

    fn floats(&mut self, values: &[f64]) {
        for v in values {
            self.word(v.to_bits());
        }
    }

    fn vector(&mut self, v: &Vector3<f64>) {
        self.floats(&[v.x, v.y, v.z]);
    }
}

fn hash_shape(h: &mut Fnv, shape: &Shape) {
    match shape {
        Shape::Ellipsoid { centre, radii } => {
            h.word(0);
            h.vector(centre);
            h.vector(radii);
        }
        Shape::Disc {
            centre,
            normal,
            u,
            v,
            half_u_m,
            half_v_m,
        } => {
            h.word(1);
            for w in [centre, normal, u, v] {
                h.vector(w);
            }
            h.floats(&[*half_u_m, *half_v_m]);
        }
        Shape::OrientedEllipsoid(e) => {
            h.word(3);
            h.vector(&e.centre);
            h.floats(e.axes.as_slice());
            h.vector(&e.radii);
        }
        Shape::Cylinder(c) => {
            h.word(2);
            h.vector(&c.base);
            h.vector(&c.axis);
            h.floats(&[c.length_m, c.radius_m]);
        }
    }
}

/// Digest of everything generation decides: shapes in BVH order with their albedos, fruit
/// indices, labels and plant flags, the fruit boxes and the plants.
fn scene_digest(scene: &Scene) -> u64 {
    let mut h = Fnv::new();
    for (i, shape) in scene.shapes.iter().enumerate() {
        hash_shape(&mut h, shape);
        for a in scene.albedo[i] {
            h.word(u64::from(a.to_bits()));
        }
        h.word(scene.fruit_index[i].map_or(u64::MAX, u64::from));
        h.word(u64::from(scene.looks_like_fruit[i]));
        h.word(u64::from(scene.is_plant[i]));
    }
    for f in &scene.fruits {
        h.word(u64::from(f.id));
        h.floats(&[f.centre.x, f.centre.y, f.centre.z, f.volume_m3]);
        h.vector(&f.half_extents_m);
    }
    for p in &scene.plants {
        h.floats(&[p.base_in_world.x, p.base_in_world.y, p.height_m]);
        h.word(u64::from(p.fruit_count));
    }
    h.0
}

/// Digests of `generate_with_fruit` before scene options existed (scenario, seed, colour).
const DIGESTS_BEFORE_OPTIONS: [(ScenarioKind, u64, FruitColour, u64); 12] = [
    (
        ScenarioKind::One,
        3,
        FruitColour::Red,
        0xf67b_7ff4_b155_a272,
    ),
    (
        ScenarioKind::One,
        3,
        FruitColour::Green,
        0xa2b7_468c_ad21_d81c,
    ),
    (
        ScenarioKind::One,
        11,
        FruitColour::Red,
        0x2375_b6d3_cec9_126e,
    ),
    (
        ScenarioKind::One,
        11,
        FruitColour::Green,
        0xc11d_1d44_9157_881f,
    ),
    (
        ScenarioKind::Two,
        3,
        FruitColour::Red,
        0x23af_1644_1844_c277,
    ),
    (
        ScenarioKind::Two,
        3,
        FruitColour::Green,
        0xc61f_461d_c14a_aa90,
    ),
    (
        ScenarioKind::Two,
        11,
        FruitColour::Red,
        0x6f88_4c42_beed_03e0,
    ),
    (
        ScenarioKind::Two,
        11,
        FruitColour::Green,
        0x2b64_4799_18a4_59d8,
    ),
    (
        ScenarioKind::Row,
        3,
        FruitColour::Red,
        0x748e_391c_11c1_0f7b,
    ),
    (
        ScenarioKind::Row,
        3,
        FruitColour::Green,
        0x4a4f_e5ea_9278_899e,
    ),
    (
        ScenarioKind::Row,
        11,
        FruitColour::Red,
        0x4ca3_b048_632d_b9b2,
    ),
    (
        ScenarioKind::Row,
        11,
        FruitColour::Green,
        0x11db_1fe9_d4ce_d9f2,
    ),
];

#[test]
fn default_options_give_the_scenes_of_before() {
    let defaults = SceneOptions::default();
    assert_eq!(defaults.fruit_colour, FruitColour::Red);
    assert_eq!(defaults.fruit_shape, FruitShape::Ellipsoid);
    assert_eq!(defaults.red_clutter, 0.0);
    for (kind, seed, colour, digest) in DIGESTS_BEFORE_OPTIONS {
        let scene = Scene::generate_with_fruit(kind, seed, colour);
        assert_eq!(scene_digest(&scene), digest, "{kind} {seed} {colour}");
        let options = SceneOptions {
            fruit_colour: colour,
            ..defaults
        };
        let scene = Scene::generate_with(kind, seed, &options);
        assert_eq!(scene_digest(&scene), digest, "{kind} {seed} {colour}");
        assert_eq!(scene.options(), options);
        if colour == FruitColour::Red {
            assert_eq!(scene_digest(&Scene::generate(kind, seed)), digest);
        }
    }
}

#[test]
fn ellipsoid_fruit_bodies_are_the_exact_ellipsoids() {
    let scene = Scene::generate(ScenarioKind::Two, 4);
    for f in scene.fruits() {
        let h = f.half_extents_m;
        let exact = 4.0 / 3.0 * std::f64::consts::PI * h.x * h.y * h.z;
        assert_eq!(f.body_volume_m3, exact);
        assert_eq!(f.body_centre, f.centre);
        assert_eq!(f.axis, Vector3::z());
    }
}

fn rotated_ellipsoid(
    centre: Vector3<f64>,
    radii: Vector3<f64>,
    angles: (f64, f64, f64),
) -> OrientedEllipsoid {
    let axes = Rotation3::from_euler_angles(angles.0, angles.1, angles.2).into_inner();
    OrientedEllipsoid {
        centre,
        axes,
        radii,
    }
}

fn union_box(lobes: &[OrientedEllipsoid]) -> Bounds {
    lobes
        .iter()
        .map(|l| Shape::OrientedEllipsoid(*l).bounds())
        .reduce(|a, b| a.union(&b))
        .unwrap()
}

#[test]
fn union_volume_matches_analytic_volumes() {
    let radii = Vector3::new(0.03, 0.02, 0.045);
    let exact = 4.0 / 3.0 * std::f64::consts::PI * radii.x * radii.y * radii.z;
    let a = rotated_ellipsoid(Vector3::new(0.1, -0.2, 0.8), radii, (0.4, -0.7, 1.1));
    let (volume, centroid) = capsicum::union_volume(&[a], &union_box(&[a]));
    assert!((volume / exact - 1.0).abs() < 0.003, "{volume} vs {exact}");
    assert!((centroid - a.centre).norm() < 1e-4, "{centroid}");
    // An overlap counts once: the same ellipsoid twice has the same volume.
    let (twice, _) = capsicum::union_volume(&[a, a], &union_box(&[a, a]));
    assert!((twice - volume).abs() < 1e-12);
    // Disjoint ellipsoids add up, and the centroid lies between them.
    let b = OrientedEllipsoid {
        centre: a.centre + Vector3::new(0.2, 0.0, 0.0),
        ..a
    };
    let (both, centroid) = capsicum::union_volume(&[a, b], &union_box(&[a, b]));
    assert!((both / (2.0 * exact) - 1.0).abs() < 0.003, "{both}");
    assert!((centroid - (a.centre + b.centre) / 2.0).norm() < 1e-4);
}

/// Pepper scenes of every kind over a few seeds (capsicum-shaped, other options default).
fn capsicum_scenes() -> Vec<(ScenarioKind, u64, Built, Scene)> {
    let options = SceneOptions {
        fruit_shape: FruitShape::Capsicum,
        ..SceneOptions::default()
    };
    let mut out = Vec::new();
    for kind in [ScenarioKind::One, ScenarioKind::Two, ScenarioKind::Row] {
        for seed in 0..3 {
            let built = build(kind, seed, &options);
            out.push((
                kind,
                seed,
                built,
                Scene::generate_with(kind, seed, &options),
            ));
        }
    }
    out
}

/// Volume of a union of ellipsoids by brute force: cell centres inside any, 1 mm cells.
fn brute_force_volume(lobes: &[OrientedEllipsoid]) -> f64 {
    let b = union_box(lobes);
    let step = 0.001;
    let n = |i: usize| ((b.max[i] - b.min[i]) / step).ceil() as usize;
    let mut inside = 0usize;
    for i in 0..n(0) {
        for j in 0..n(1) {
            for k in 0..n(2) {
                let p = Vector3::new(i as f64, j as f64, k as f64).add_scalar(0.5) * step
                    + Vector3::from(b.min);
                inside += usize::from(lobes.iter().any(|l| l.contains(&p)));
            }
        }
    }
    inside as f64 * step.powi(3)
}

fn lobes_of(built: &Built, id: u32) -> Vec<OrientedEllipsoid> {
    built
        .solids
        .iter()
        .filter(|s| s.fruit_index == Some(id))
        .filter_map(|s| match s.shape {
            Shape::OrientedEllipsoid(e) => Some(e),
            _ => None,
        })
        .collect()
}

#[test]
fn capsicum_fruit_have_plausible_bodies_and_truth() {
    for (kind, seed, built, scene) in capsicum_scenes() {
        let default = Scene::generate(kind, seed);
        assert_eq!(
            scene.fruits().len(),
            default.fruits().len(),
            "{kind} {seed}"
        );
        assert_eq!(scene.plant_bases(), default.plant_bases());
        for f in scene.fruits() {
            let litres = f.body_volume_m3 * 1e3;
            assert!(
                (0.03..=0.3).contains(&litres),
                "{kind} {seed} fruit {}: {litres} l",
                f.id
            );
            let fill = f.body_volume_m3 / f.volume_m3;
            assert!(
                (0.3..=0.75).contains(&fill),
                "{kind} {seed} fruit {}: fill {fill}",
                f.id
            );
            assert!(
                f.aabb().contains(&f.body_centre),
                "{kind} {seed} fruit {}",
                f.id
            );
            assert!((f.axis.norm() - 1.0).abs() < 1e-12);
            assert!(
                f.axis.z >= (std::f64::consts::PI / 6.0).cos() - 1e-12,
                "{}",
                f.axis
            );
            let lobes = lobes_of(&built, f.id);
            assert!((3..=4).contains(&lobes.len()), "{}", lobes.len());
            // The truth box is the lobes' box, exactly.
            let b = union_box(&lobes);
            assert!((Vector3::from(b.centre()) - f.centre.coords).norm() < 1e-12);
            assert!((b.half() - f.half_extents_m).norm() < 1e-12);
        }
        // Every lobe of a fruit carries its colour; calyx and stalk come one each per fruit.
        for id in 0..scene.fruits().len() as u32 {
            let albedos: Vec<[f32; 3]> = built
                .solids
                .iter()
                .filter(|s| s.fruit_index == Some(id))
                .map(|s| s.albedo)
                .collect();
            assert!(albedos.windows(2).all(|w| w[0] == w[1]));
        }
        let count = |part: Part| built.solids.iter().filter(|s| s.part == part).count();
        assert_eq!(count(Part::Calyx), scene.fruits().len());
        assert_eq!(count(Part::Stalk), scene.fruits().len());
        for s in built
            .solids
            .iter()
            .filter(|s| matches!(s.part, Part::Calyx | Part::Stalk))
        {
            assert!(s.fruit_index.is_none() && s.is_plant);
        }
        check_disjoint_boxes(&scene);
    }
}

#[test]
fn capsicum_body_volume_agrees_with_brute_force() {
    let (_, _, built, scene) = capsicum_scenes().swap_remove(1);
    for f in &scene.fruits()[..3] {
        let brute = brute_force_volume(&lobes_of(&built, f.id));
        let ratio = f.body_volume_m3 / brute;
        assert!((ratio - 1.0).abs() < 0.01, "fruit {}: {ratio}", f.id);
    }
}

fn check_disjoint_boxes(scene: &Scene) {
    let fruits = scene.fruits();
    for (i, f) in fruits.iter().enumerate() {
        for g in &fruits[i + 1..] {
            let (a, b) = (f.aabb(), g.aabb());
            let overlap = (0..3).all(|k| a.min[k] < b.max[k] && b.min[k] < a.max[k]);
            assert!(!overlap, "fruits {} and {} overlap", f.id, g.id);
        }
    }
}

/// Fruit with a leaf within 1 mm of their body.
fn fruit_touched_by_leaves(built: &Built) -> usize {
    let leaves: Vec<&Shape> = built
        .solids
        .iter()
        .filter(|s| s.part == Part::Leaf)
        .map(|s| &s.shape)
        .collect();
    let body_of = |id: u32| {
        let solids = built
            .solids
            .iter()
            .filter(move |s| s.fruit_index == Some(id));
        solids.map(|s| s.shape.clone()).collect()
    };
    built
        .fruits
        .iter()
        .filter(|f| {
            let mut one = FruitSet::default();
            one.truths.push((*f).clone());
            one.bodies.push(body_of(f.id));
            leaves.iter().any(|leaf| one.touches(leaf, 0.001, None))
        })
        .count()
}

#[test]
fn about_a_third_of_capsicums_are_pressed_against_a_leaf() {
    let (mut touched, mut total) = (0, 0);
    for (kind, seed, built, _) in capsicum_scenes() {
        touched += fruit_touched_by_leaves(&built);
        total += built.fruits.len();
        // In the paper's scenes no leaf comes near a fruit.
        let plain = build(kind, seed, &SceneOptions::default());
        assert_eq!(fruit_touched_by_leaves(&plain), 0, "{kind} {seed}");
    }
    let share = touched as f64 / total as f64;
    assert!((0.2..0.5).contains(&share), "{touched} of {total}");
}

/// The detector's default HSI rule.
fn is_roi(rgb: &[u8]) -> bool {
    glasshouse_detect::HsiRule::default().is_roi(rgb[0], rgb[1], rgb[2])
}

/// True when the HSI rule takes `albedo` for fruit under every shading factor.
fn roi_under_any_shading(albedo: [f32; 3]) -> (bool, bool) {
    let labels: Vec<bool> = (0..=100)
        .map(|i| i as f64 / 100.0)
        .chain([-1.0])
        .map(|n_dot_l| is_roi(&shade(albedo, n_dot_l)))
        .collect();
    (labels.iter().all(|&l| l), labels.iter().any(|&l| l))
}

#[test]
fn clutter_looks_like_fruit_and_leaf_green_fruit_calyx_and_stalk_do_not() {
    for albedo in corners(RED_FRUIT_RANGE)
        .into_iter()
        .chain(corners(ORANGE_CLUTTER_RANGE))
    {
        assert_eq!(roi_under_any_shading(albedo), (true, true), "{albedo:?}");
    }
    let mut never = corners(LEAF_GREEN_FRUIT_RANGE);
    never.extend([CALYX_ALBEDO, STEM_ALBEDO]);
    for albedo in never {
        assert_eq!(roi_under_any_shading(albedo), (false, false), "{albedo:?}");
    }
    // Leaf green lies within the leaves' colours.
    for (fruit, leaf) in LEAF_GREEN_FRUIT_RANGE.iter().zip(LEAF_RANGE) {
        let overlap = fruit.1.min(leaf.1) - fruit.0.max(leaf.0);
        assert!(overlap >= 0.6 * (fruit.1 - fruit.0), "{fruit:?} {leaf:?}");
    }
}

/// A noise-free camera (depth valid exactly where the truth labels count a pixel).
fn exact_camera(width: u32, height: u32) -> CameraModel {
    let mut camera = CameraModel::with_resolution(width, height);
    camera.depth_noise_std_at_1m_m = 0.0;
    camera
}

/// Views of every plant from eight sides at fruit height.
fn ring_views(scene: &Scene) -> Vec<Isometry3<f64>> {
    let mut poses = vec![scene.initial_camera_pose()];
    for base in scene.plant_bases() {
        for k in 0..8 {
            let a = k as f64 * std::f64::consts::TAU / 8.0;
            let eye = Point3::new(base.x + 0.5 * a.cos(), base.y + 0.5 * a.sin(), 0.85);
            poses.push(look_at(&eye, &Point3::new(base.x, base.y, 0.85)));
        }
    }
    poses
}

/// Over `poses`: pixels with depth the HSI rule labels fruit that see fruit, and that do not.
fn hsi_pixels(scene: &Scene, poses: &[Isometry3<f64>]) -> (usize, usize) {
    let camera = exact_camera(160, 120);
    let (mut on_fruit, mut elsewhere) = (0, 0);
    for pose in poses {
        let image: RgbdImage = scene.render(&camera, pose, 0);
        let truth = scene.fruit_label_image(&camera, pose);
        for (pixel, rgb) in image.rgb.chunks_exact(3).enumerate() {
            if image.depth_m[pixel].is_finite() && is_roi(rgb) {
                if truth[pixel] == 1 {
                    on_fruit += 1;
                } else {
                    elsewhere += 1;
                }
            }
        }
    }
    (on_fruit, elsewhere)
}

#[test]
fn the_camera_sees_capsicums_and_the_colour_rule_finds_only_them() {
    let options = SceneOptions {
        fruit_shape: FruitShape::Capsicum,
        ..SceneOptions::default()
    };
    let scene = Scene::generate_with(ScenarioKind::Two, 3, &options);
    let pose = scene.initial_camera_pose();
    let camera = CameraModel::with_resolution(160, 120);
    let image = scene.render(&camera, &pose, 7);
    let valid = image.depth_m.iter().filter(|d| d.is_finite()).count();
    assert!(valid > 10_000, "{valid}");
    let seen: u32 = scene.fruit_pixel_counts(&camera, &pose).iter().sum();
    assert!(seen >= 40, "{seen} fruit pixels");
    // Calyces and stalks are green: every red pixel is fruit.
    let (on_fruit, elsewhere) = hsi_pixels(&scene, &[pose]);
    assert!(on_fruit >= 40 && elsewhere == 0, "{on_fruit} {elsewhere}");
}

#[test]
fn packet_render_matches_single_rays_on_capsicums() {
    let options = SceneOptions {
        fruit_shape: FruitShape::Capsicum,
        ..SceneOptions::default()
    };
    let scene = Scene::generate_with(ScenarioKind::One, 2, &options);
    let camera = exact_camera(96, 72);
    let mut stack = Vec::new();
    let mut lobe_pixels = 0;
    for pose in ring_views(&scene).iter().take(5) {
        let image = scene.render(&camera, pose, 0);
        let k = camera.intrinsics;
        let rotation = pose.rotation.to_rotation_matrix();
        for v in 0..k.height as usize {
            for u in 0..k.width as usize {
                let pixel = v * k.width as usize + u;
                let dir_in_camera = k.ray_direction(u as f64, v as f64);
                let ray =
                    crate::shapes::Ray::new(pose.translation.vector, rotation * dir_in_camera);
                let hit = scene.trace(&ray, None, &mut stack);
                let depth = image.depth_m[pixel];
                if let Some(hit) = hit.filter(|_| depth.is_finite()) {
                    assert_eq!(depth, (hit.t * dir_in_camera.z) as f32, "pixel {u},{v}");
                    let shape = hit.shape.map(|i| &scene.shapes[i]);
                    lobe_pixels += usize::from(matches!(shape, Some(Shape::OrientedEllipsoid(_))));
                }
            }
        }
    }
    assert!(lobe_pixels > 100, "{lobe_pixels}");
}

#[test]
fn leaf_green_fruit_have_leaf_colours_and_the_colour_rule_misses_them() {
    let options = SceneOptions {
        fruit_colour: FruitColour::LeafGreen,
        ..SceneOptions::default()
    };
    let scene = Scene::generate_with(ScenarioKind::Two, 3, &options);
    let red = Scene::generate(ScenarioKind::Two, 3);
    assert_eq!(scene.fruit_colour(), FruitColour::LeafGreen);
    let mut fruit_solids = 0;
    for (i, albedo) in scene.albedo.iter().enumerate() {
        if scene.fruit_index[i].is_some() {
            fruit_solids += 1;
            assert!(
                is_fruit_colour(FruitColour::LeafGreen, *albedo),
                "{albedo:?}"
            );
            assert!(scene.looks_like_fruit[i]);
        }
    }
    assert_eq!(fruit_solids, scene.fruits().len());
    // The same geometry as the red twin, and the same truth.
    assert_eq!(
        scene.ground_truth_json().replace("leaf-green", "red"),
        red.ground_truth_json()
    );
    let poses = ring_views(&scene);
    let (on_fruit, elsewhere) = hsi_pixels(&scene, &poses);
    assert_eq!((on_fruit, elsewhere), (0, 0));
    let (red_on_fruit, _) = hsi_pixels(&red, &poses);
    assert!(red_on_fruit > 1000, "{red_on_fruit}");
}

fn with_clutter(share: f64) -> SceneOptions {
    SceneOptions {
        red_clutter: share,
        ..SceneOptions::default()
    }
}

#[test]
fn red_clutter_fools_the_colour_rule_more_as_it_grows() {
    let mut false_pixels = Vec::new();
    for share in [0.0, 0.1, 0.2] {
        let scene = Scene::generate_with(ScenarioKind::Two, 3, &with_clutter(share));
        let (on_fruit, elsewhere) = hsi_pixels(&scene, &ring_views(&scene));
        assert!(on_fruit > 1000, "{share}: {on_fruit}");
        false_pixels.push(elsewhere);
    }
    // Nothing red but fruit without clutter; with it, false fruit pixels grow with the share
    // (mostly reddened leaves; clips, petioles and labels add a few).
    assert_eq!(false_pixels[0], 0);
    assert!(false_pixels[1] > 1000, "{false_pixels:?}");
    let growth = false_pixels[2] as f64 / false_pixels[1] as f64;
    assert!((1.5..2.7).contains(&growth), "{false_pixels:?}");
}

#[test]
fn red_clutter_adds_red_plant_parts_and_keeps_the_rest_of_the_scene() {
    let plain = build(ScenarioKind::Row, 5, &SceneOptions::default());
    let low = build(ScenarioKind::Row, 5, &with_clutter(0.1));
    let high = build(ScenarioKind::Row, 5, &with_clutter(0.2));
    let n = plain.solids.len();
    let reddened = |b: &Built| -> Vec<usize> {
        (0..n)
            .filter(|&i| b.solids[i].albedo != plain.solids[i].albedo)
            .collect()
    };
    for clutter in [&low, &high] {
        assert_eq!(clutter.fruits.len(), plain.fruits.len());
        for (a, b) in plain.solids.iter().zip(&clutter.solids) {
            assert_eq!(format!("{:?}", a.shape), format!("{:?}", b.shape));
            assert_eq!(a.fruit_index, b.fruit_index);
        }
        for &i in &reddened(clutter) {
            assert_eq!(clutter.solids[i].part, Part::Leaf);
            assert!(is_ripe_colour(clutter.solids[i].albedo));
        }
        let extra = &clutter.solids[n..];
        // A clip and 2-3 petioles per plant, two labels; a few may find no room.
        assert!(
            (8 * 3..=8 * 4 + 2).contains(&extra.len()),
            "{}",
            extra.len()
        );
        for s in extra {
            assert!(s.part == Part::Clutter && s.fruit_index.is_none() && s.is_plant);
            assert_eq!(
                roi_under_any_shading(s.albedo),
                (true, true),
                "{:?}",
                s.albedo
            );
        }
        assert_eq!(extra.len(), low.solids.len() - n);
    }
    // The leaves reddened at 0.1 are reddened at 0.2 too; about the share of all leaves.
    let leaves = plain.solids.iter().filter(|s| s.part == Part::Leaf).count() as f64;
    let (some, more) = (reddened(&low), reddened(&high));
    assert!(some.iter().all(|i| more.contains(i)));
    for (count, share) in [(some.len(), 0.1), (more.len(), 0.2)] {
        let expected = share * leaves;
        let sd = (leaves * share * (1.0 - share)).sqrt();
        assert!(
            (count as f64 - expected).abs() < 4.0 * sd,
            "{count} vs {expected}"
        );
    }
    // Clutter is not fruit of the scene's colour.
    let scene = Scene::generate_with(ScenarioKind::Row, 5, &with_clutter(0.2));
    for (i, &looks) in scene.looks_like_fruit.iter().enumerate() {
        assert_eq!(
            looks,
            scene.fruit_index[i].is_some() && is_ripe_colour(scene.albedo[i])
        );
    }
}

#[test]
fn scene_options_parse_validate_and_read_from_json() {
    for (name, shape) in [
        ("ellipsoid", FruitShape::Ellipsoid),
        ("Capsicum", FruitShape::Capsicum),
    ] {
        assert_eq!(name.parse::<FruitShape>().unwrap(), shape);
        assert_eq!(shape.to_string().parse::<FruitShape>().unwrap(), shape);
    }
    let err = "pepper".parse::<FruitShape>().unwrap_err().to_string();
    assert!(err.contains("pepper") && err.contains("ellipsoid") && err.contains("capsicum"));
    for (name, colour) in [
        ("red", FruitColour::Red),
        ("ripe", FruitColour::Red),
        ("green", FruitColour::Green),
        ("unripe", FruitColour::Green),
        ("leaf-green", FruitColour::LeafGreen),
        ("Leaf_Green", FruitColour::LeafGreen),
    ] {
        assert_eq!(name.parse::<FruitColour>().unwrap(), colour);
        assert_eq!(colour.to_string().parse::<FruitColour>().unwrap(), colour);
    }
    assert!("blue"
        .parse::<FruitColour>()
        .unwrap_err()
        .to_string()
        .contains("leaf-green"));

    let json = r#"{"fruit_colour": "leaf-green", "fruit_shape": "capsicum", "red_clutter": 0.1}"#;
    let options: SceneOptions = serde_json::from_str(json).unwrap();
    assert_eq!(
        options,
        SceneOptions {
            fruit_colour: FruitColour::LeafGreen,
            fruit_shape: FruitShape::Capsicum,
            red_clutter: 0.1,
            day: None,
        }
    );
    let back: SceneOptions =
        serde_json::from_str(&serde_json::to_string(&options).unwrap()).unwrap();
    assert_eq!(back, options);
    let partial: SceneOptions = serde_json::from_str(r#"{"red_clutter": 0.05}"#).unwrap();
    assert_eq!(partial, with_clutter(0.05));
    assert!(serde_json::from_str::<SceneOptions>(r#"{"red_cluter": 0.1}"#).is_err());
    assert!(serde_json::from_str::<SceneOptions>(r#"{"fruit_shape": "cube"}"#).is_err());

    for ok in [0.0, 0.1, MAX_RED_CLUTTER] {
        assert_eq!(with_clutter(ok).validate(), Ok(()));
    }
    for bad in [-0.01, 0.21, 1.0, f64::NAN, f64::INFINITY] {
        let err = with_clutter(bad).validate().unwrap_err();
        assert!(matches!(err, SceneOptionsError::RedClutter(_)));
        assert!(err.to_string().contains("[0, 0.2]"), "{err}");
    }
    // Generation clamps what validation refuses.
    let clamped = Scene::generate_with(ScenarioKind::One, 1, &with_clutter(5.0));
    let at_max = Scene::generate_with(ScenarioKind::One, 1, &with_clutter(MAX_RED_CLUTTER));
    assert_eq!(scene_digest(&clamped), scene_digest(&at_max));
    let nan = Scene::generate_with(ScenarioKind::One, 1, &with_clutter(f64::NAN));
    assert_eq!(
        scene_digest(&nan),
        scene_digest(&Scene::generate(ScenarioKind::One, 1))
    );
}

#[test]
fn ground_truth_json_gives_the_body() {
    let options = SceneOptions {
        fruit_shape: FruitShape::Capsicum,
        ..SceneOptions::default()
    };
    let scene = Scene::generate_with(ScenarioKind::One, 4, &options);
    let v: serde_json::Value = serde_json::from_str(&scene.ground_truth_json()).unwrap();
    assert_eq!(v["options"]["fruit_shape"], "capsicum");
    let f = &scene.fruits()[2];
    let j = &v["fruits"][2];
    assert_eq!(j["body_volume_m3"].as_f64().unwrap(), f.body_volume_m3);
    assert_eq!(j["body_centre_m"][1].as_f64().unwrap(), f.body_centre.y);
    assert_eq!(j["axis"][0].as_f64().unwrap(), f.axis.x);
    assert_eq!(j["volume_m3"].as_f64().unwrap(), f.volume_m3);
}

fn visit(kind: ScenarioKind, seed: u64, day: f64) -> Scene {
    let options = SceneOptions {
        fruit_shape: FruitShape::Capsicum,
        day: Some(day),
        ..SceneOptions::default()
    };
    Scene::generate_with(kind, seed, &options)
}

#[test]
fn fruit_keep_their_ids_over_visits_and_grow_set_and_are_harvested() {
    let days = [0.0, 3.5, 7.0, 10.5];
    let (mut set_later, mut harvested) = (0, 0);
    for seed in 1..=3 {
        let generated = Scene::generate_with(
            ScenarioKind::Two,
            seed,
            &SceneOptions {
                fruit_shape: FruitShape::Capsicum,
                ..SceneOptions::default()
            },
        );
        let final_volume: std::collections::BTreeMap<u32, f64> = generated
            .fruits()
            .iter()
            .map(|f| (f.id, f.body_volume_m3))
            .collect();
        let visits: Vec<Scene> = days
            .iter()
            .map(|&d| visit(ScenarioKind::Two, seed, d))
            .collect();
        let of = |scene: &Scene, id: u32| scene.fruits().iter().find(|f| f.id == id).cloned();
        for (k, pair) in visits.windows(2).enumerate() {
            let (before, after) = (&pair[0], &pair[1]);
            for f in before.fruits() {
                let Some(later) = of(after, f.id) else {
                    harvested += 1;
                    continue;
                };
                // Grown, by at most what the growth rate allows, never past the final size.
                let (v0, v1) = (f.body_volume_m3, later.body_volume_m3);
                let most = (1.0 + season::GROWTH_PER_DAY * 3.5 / 0.55).powi(3);
                assert!(
                    v1 >= v0 && v1 <= v0 * most + 1e-12,
                    "fruit {} day {k}: {v0} -> {v1}",
                    f.id
                );
                assert!(v1 <= final_volume[&f.id] * (1.0 + 1e-9));
                // Still hanging from the same place: the stalk end does not move.
                assert!((later.body_centre - f.body_centre).norm() < 0.03);
            }
            set_later += after
                .fruits()
                .iter()
                .filter(|f| of(before, f.id).is_none())
                .count();
        }
        // The same day twice is the same scene.
        let again = visit(ScenarioKind::Two, seed, 7.0);
        let ids = |s: &Scene| {
            s.fruits()
                .iter()
                .map(|f| (f.id, f.body_volume_m3.to_bits()))
                .collect::<Vec<_>>()
        };
        assert_eq!(ids(&again), ids(&visits[2]));
    }
    assert!(
        set_later > 0 && harvested > 0,
        "set {set_later}, harvested {harvested}"
    );
}

#[test]
fn a_later_visit_looks_different_to_the_camera() {
    let (monday, thursday) = (
        visit(ScenarioKind::Two, 4, 0.0),
        visit(ScenarioKind::Two, 4, 3.5),
    );
    let pose = monday.initial_camera_pose();
    let camera = CameraModel::with_resolution(160, 120);
    let (a, b) = (
        monday.render(&camera, &pose, 1),
        thursday.render(&camera, &pose, 1),
    );
    let changed = a
        .depth_m
        .iter()
        .zip(&b.depth_m)
        .filter(|(x, y)| x.to_bits() != y.to_bits())
        .count();
    assert!(changed > 200, "{changed} pixels changed");
    // Visits keep the fruit index consistent with the truth list.
    let counts = thursday.fruit_pixel_counts(&camera, &pose);
    assert_eq!(counts.len(), thursday.fruits().len());
}

#[test]
fn a_visit_day_out_of_range_is_refused() {
    for day in [-1.0, 400.0] {
        let options = SceneOptions {
            day: Some(day),
            ..SceneOptions::default()
        };
        assert_eq!(options.validate(), Err(SceneOptionsError::Day(day)));
    }
}
