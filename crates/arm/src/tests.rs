#![allow(clippy::unwrap_used)]

use std::f64::consts::{FRAC_PI_2, PI, TAU};
use std::path::PathBuf;
use std::sync::OnceLock;

use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::kinematics::wrap_pi;
use crate::*;

fn random_q(rng: &mut ChaCha8Rng, limits: &JointLimits) -> JointVector {
    std::array::from_fn(|i| rng.gen_range(limits.lower[i]..=limits.upper[i]))
}

/// Position error plus the largest rotation-matrix element error.
fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    let dr = a.rotation.to_rotation_matrix().matrix() - b.rotation.to_rotation_matrix().matrix();
    (a.translation.vector - b.translation.vector).norm() + dr.abs().max()
}

fn same_angles(a: &JointVector, b: &JointVector, tol: f64) -> bool {
    a.iter().zip(b).all(|(x, y)| wrap_pi(x - y).abs() < tol)
}

fn paper_map() -> &'static ReachabilityMap {
    static MAP: OnceLock<ReachabilityMap> = OnceLock::new();
    MAP.get_or_init(|| {
        let dir = temp_dir("paper");
        let params = ReachabilityParams::paper(&ArmModel::ur5e());
        let started = std::time::Instant::now();
        let map = ReachabilityMap::load_or_build(&dir, &params).unwrap();
        let bytes = std::fs::metadata(ReachabilityMap::cache_path(&dir, &params))
            .map(|m| m.len())
            .unwrap_or(0);
        eprintln!(
            "paper reachability map: built and cached in {:?}, {bytes} bytes, {} cells reached, \
             extent {:?}",
            started.elapsed(),
            map.reached_cell_count(),
            map.extent_in_base()
        );
        let _ = std::fs::remove_dir_all(&dir);
        map
    })
}

fn temp_dir(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("glasshouse-arm-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

#[test]
fn dh_forward_kinematics_matches_known_ur5e_poses() {
    let arm = ArmModel::ur5e();
    let dh = arm.dh;
    // All zeros: the arm lies stretched along -x at shoulder height, the flange pointing along -y
    // (wrist 2 axis) ... positions from the DH table: x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
    let f = arm.base_from_flange(&[0.0; 6]).unwrap();
    let expected = Vector3::new(dh.a2 + dh.a3, -(dh.d4 + dh.d6), dh.d1 - dh.d5);
    assert!((f.translation.vector - expected).norm() < 1e-12, "{f}");
    // Upright: shoulder lift -90°, wrist 1 -90°: the forearm points up, the wrist stack on top.
    let f = arm
        .base_from_flange(&[0.0, -FRAC_PI_2, 0.0, -FRAC_PI_2, 0.0, 0.0])
        .unwrap();
    let expected = Vector3::new(0.0, -(dh.d4 + dh.d6), dh.d1 - dh.a2 - dh.a3 + dh.d5);
    assert!((f.translation.vector - expected).norm() < 1e-12, "{f}");
    // Joint 1 turns everything about the base z axis.
    let q = [0.7, -1.1, 0.9, -0.4, 1.3, 0.2];
    let mut q0 = q;
    q0[0] = 0.0;
    let rotated = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7)
        * arm.base_from_flange(&q0).unwrap().translation.vector;
    assert!((arm.base_from_flange(&q).unwrap().translation.vector - rotated).norm() < 1e-12);
    // The camera sits 3 cm in front of the flange, looking along its z.
    let cam = arm.base_from_camera(&q).unwrap();
    let fl = arm.base_from_flange(&q).unwrap();
    let ahead = fl.rotation * Vector3::z() * 0.03;
    assert!((cam.translation.vector - fl.translation.vector - ahead).norm() < 1e-12);
}

#[test]
fn fk_of_every_ik_solution_reproduces_random_poses() {
    let arm = ArmModel::ur5e();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut eight = 0;
    let mut original_found = 0;
    let trials = 2000;
    for _ in 0..trials {
        let q = random_q(&mut rng, &arm.limits);
        let goal = arm.base_from_camera(&q).unwrap();
        let solutions = arm.ik_camera(&goal, None).unwrap();
        assert!(!solutions.is_empty(), "no solution for {q:?}");
        assert!(solutions.len() <= 8, "{} solutions", solutions.len());
        if solutions.len() == 8 {
            eight += 1;
        }
        for s in &solutions {
            assert!(arm.limits.contains(s));
            let err = pose_error(&arm.base_from_camera(s).unwrap(), &goal);
            assert!(err < 1e-6, "FK error {err} for solution {s:?} of {q:?}");
        }
        // Away from the wrist singularity the original configuration is among the solutions.
        if q[4].sin().abs() > 1e-3 && solutions.iter().any(|s| same_angles(s, &q, 1e-6)) {
            original_found += 1;
        }
    }
    // Most poses have all eight (the rest lose elbow or shoulder variants out of reach).
    assert!(eight > trials / 2, "only {eight} poses with 8 solutions");
    assert!(
        original_found > trials * 99 / 100,
        "original found {original_found}"
    );
}

#[test]
fn ik_handles_the_wrist_singularity() {
    let arm = ArmModel::ur5e();
    let q = [0.3, -1.2, 1.4, -0.5, 0.0, 0.8];
    let goal = arm.base_from_flange(&q).unwrap();
    let solutions = arm.ik_flange(&goal).unwrap();
    assert!(!solutions.is_empty() && solutions.len() <= 8);
    for s in &solutions {
        assert!(pose_error(&arm.base_from_flange(s).unwrap(), &goal) < 1e-6);
    }
}

#[test]
fn solve_camera_pose_in_the_world_for_every_mount() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let robots = [
        Robot::scenario_one(),
        Robot::scenario_two(),
        Robot::row(Interval::new(-1.0, 4.0)),
    ];
    for robot in &robots {
        for _ in 0..100 {
            let ranges = robot.mount.axis_ranges();
            let values: Vec<f64> = ranges
                .iter()
                .map(|r| rng.gen_range(r.min..=r.max))
                .collect();
            let state = match robot.mount {
                Mount::Fixed { .. } => MountState::Fixed,
                Mount::CeilingGantry { .. } => MountState::Gantry {
                    x_m: values[0],
                    y_m: values[1],
                    extension_m: values[2],
                },
                Mount::RailLift { .. } => MountState::Rail {
                    position_m: values[0],
                    lift_m: values[1],
                },
            };
            let q = random_q(&mut rng, &robot.arm.limits);
            let goal = robot.world_from_camera(&q, &state).unwrap();
            let solutions = robot.solve_camera_pose(&goal, &state).unwrap();
            assert!(!solutions.is_empty() && solutions.len() <= 8);
            for s in &solutions {
                let err = pose_error(&robot.world_from_camera(s, &state).unwrap(), &goal);
                assert!(err < 1e-6);
            }
            // Near the current configuration: the closest solution is the configuration itself.
            if q[4].sin().abs() > 1e-3 {
                let near = robot.solve_camera_pose_near(&goal, &state, &q).unwrap();
                let best = best_solution(&q, &near).unwrap();
                assert!(joint_distance(&best, &q) < 1e-6, "{best:?} vs {q:?}");
                assert_eq!(near.first(), Some(&best));
            }
        }
    }
}

#[test]
fn bad_and_unreachable_poses() {
    let robot = Robot::scenario_one();
    let nan_translation = Isometry3::translation(f64::NAN, 0.0, 1.0);
    assert!(matches!(
        robot.solve_camera_pose(&nan_translation, &MountState::Fixed),
        Err(ArmError::NonFinite { .. })
    ));
    let nan_rotation = Isometry3::from_parts(
        Translation3::new(0.3, 0.0, 1.0),
        UnitQuaternion::new_unchecked(Quaternion::new(f64::NAN, 0.0, 0.0, 0.0)),
    );
    assert!(robot
        .solve_camera_pose(&nan_rotation, &MountState::Fixed)
        .is_err());
    assert!(robot.arm.ik_flange(&nan_translation).is_err());
    // 2 m from the base: out of reach.
    let far = Isometry3::translation(2.0, 0.0, 0.86);
    assert!(robot
        .solve_camera_pose(&far, &MountState::Fixed)
        .unwrap()
        .is_empty());
    assert!(matches!(
        robot.place_mount_for(&far, None),
        Err(ArmError::Unreachable)
    ));
    // Wrong or out-of-range mount states.
    let pose = Isometry3::translation(0.4, 0.0, 1.0);
    let wrong = MountState::Rail {
        position_m: 0.0,
        lift_m: 0.0,
    };
    assert!(matches!(
        robot.solve_camera_pose(&pose, &wrong),
        Err(ArmError::MountStateMismatch { .. })
    ));
    let gantry = Robot::scenario_two();
    let outside = MountState::Gantry {
        x_m: 3.0,
        y_m: 0.0,
        extension_m: 0.0,
    };
    assert!(matches!(
        gantry.solve_camera_pose(&pose, &outside),
        Err(ArmError::MountOutOfLimits { .. })
    ));
    // Joint vectors.
    assert!(robot.arm.base_from_camera(&[f64::NAN; 6]).is_err());
    assert!(matches!(
        robot.arm.limits.check(&[0.0, 0.0, 7.0, 0.0, 0.0, 0.0]),
        Err(ArmError::JointOutOfLimits { joint: 2, .. })
    ));
    assert!(best_solution(&[0.0; 6], &[]).is_none());
}

#[test]
fn elbow_limits_filter_solutions() {
    let mut arm = ArmModel::ur5e();
    arm.limits = JointLimits::ur5e_elbow_pi();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..200 {
        let q = random_q(&mut rng, &arm.limits);
        let goal = arm.base_from_camera(&q).unwrap();
        for s in arm.ik_camera(&goal, Some(&q)).unwrap() {
            assert!(s[2].abs() <= PI + 1e-12);
            assert!(pose_error(&arm.base_from_camera(&s).unwrap(), &goal) < 1e-6);
        }
    }
    // A limit range that excludes a solution's angle drops it.
    arm.limits.lower[0] = 0.1;
    arm.limits.upper[0] = 0.2;
    let goal = arm
        .base_from_camera(&[1.5, -1.0, 1.0, 0.0, 1.0, 0.0])
        .unwrap();
    for s in arm.ik_camera(&goal, None).unwrap() {
        assert!((0.1..=0.2).contains(&s[0]));
    }
}

#[test]
fn gantry_base_hangs_upside_down_and_mount_placement_reaches_goals() {
    let robot = Robot::scenario_two();
    let state = MountState::Gantry {
        x_m: 0.5,
        y_m: -0.2,
        extension_m: 0.7,
    };
    let base = robot.world_from_base(&state).unwrap();
    assert!((base.translation.vector - Vector3::new(0.5, -0.2, 1.5)).norm() < 1e-12);
    assert!((base.rotation * Vector3::z() + Vector3::z()).norm() < 1e-12);
    // Goals looking at plants in the simulated scene's workspace are placed and solved.
    let targets = [
        Point3::new(0.3, 0.2, 0.6),
        Point3::new(-0.6, 0.5, 1.0),
        Point3::new(0.7, -0.7, 0.3),
    ];
    for robot in [Robot::scenario_two(), Robot::row(Interval::new(-1.0, 4.0))] {
        for t in targets {
            let target = match robot.mount {
                Mount::RailLift { .. } => Point3::new(t.x + 1.0, 0.0, t.z + 0.5),
                _ => t,
            };
            let eye = target + Vector3::new(-0.2, -0.35, 0.1);
            let goal = look_at(&eye, &target);
            let (state, solutions) = robot.place_mount_for(&goal, None).unwrap();
            assert!(!solutions.is_empty());
            let pose = robot.world_from_camera(&solutions[0], &state).unwrap();
            assert!(pose_error(&pose, &goal) < 1e-6);
        }
    }
}

/// Optical frame at `eye` looking at `target`, image x horizontal.
fn look_at(eye: &Point3<f64>, target: &Point3<f64>) -> Isometry3<f64> {
    let z = (target - eye).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = nalgebra::Rotation3::from_basis_unchecked(&[x, y, z]);
    Isometry3::from_parts(
        Translation3::from(eye.coords),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

#[test]
fn collision_with_a_pole_is_caught_for_configurations_and_paths() {
    let robot = Robot::scenario_one();
    let mut scene = robot.mount.structure(&MountState::Fixed).unwrap();
    // The home (upright) configuration and a stretched one are free with the mount's own pole
    // and the floor.
    let home = [0.0, -FRAC_PI_2, 0.0, -FRAC_PI_2, 0.0, 0.0];
    let stretched = [0.0; 6];
    for q in [home, stretched] {
        let world = CollisionWorld::obstacles(&scene);
        assert_eq!(
            robot
                .check_configuration(&q, &MountState::Fixed, &world)
                .unwrap(),
            None
        );
    }
    // A second pole under the stretched upper arm (which lies along -x, 0.138 m towards -y).
    scene.push(Obstacle::Capsule {
        a: Point3::new(-0.3, -0.138, 0.0),
        b: Point3::new(-0.3, -0.138, 2.0),
        radius_m: 0.03,
    });
    let world = CollisionWorld::obstacles(&scene);
    let contact = robot
        .check_configuration(&stretched, &MountState::Fixed, &world)
        .unwrap()
        .unwrap();
    assert_eq!(contact.with, ContactWith::Obstacle(scene.len() - 1));
    assert_eq!(contact.link_name, "upper_arm");
    // Turning the base from -1.5 to +1.5 rad sweeps the arm through it; both ends are free.
    let mut from = stretched;
    from[0] = -1.5;
    let mut to = stretched;
    to[0] = 1.5;
    for q in [from, to] {
        assert_eq!(
            robot
                .check_configuration(&q, &MountState::Fixed, &world)
                .unwrap(),
            None
        );
    }
    let hit = robot
        .check_path(&from, &to, &MountState::Fixed, 2f64.to_radians(), &world)
        .unwrap()
        .unwrap();
    assert!(hit.fraction > 0.0 && hit.fraction < 1.0);
    // Turning the other way round (from -1.5 down to -4.78 = +1.5 - 2π) misses it.
    let mut around = to;
    around[0] = 1.5 - TAU;
    assert_eq!(
        robot
            .check_path(
                &from,
                &around,
                &MountState::Fixed,
                2f64.to_radians(),
                &world
            )
            .unwrap(),
        None
    );
    // Bad inputs.
    assert!(robot
        .check_path(&from, &to, &MountState::Fixed, 0.0, &world)
        .is_err());
    assert!(robot
        .check_configuration(&[9.0, 0.0, 0.0, 0.0, 0.0, 0.0], &MountState::Fixed, &world)
        .is_err());
    let bad = [Obstacle::Capsule {
        a: Point3::new(f64::NAN, 0.0, 0.0),
        b: Point3::origin(),
        radius_m: 0.1,
    }];
    assert!(robot
        .check_configuration(&home, &MountState::Fixed, &CollisionWorld::obstacles(&bad))
        .is_err());
}

#[test]
fn floor_and_ceiling_collisions() {
    let robot = Robot::scenario_two();
    let state = MountState::Gantry {
        x_m: 0.0,
        y_m: 0.0,
        extension_m: 1.2,
    };
    let scene = robot.mount.structure(&state).unwrap();
    let mut floor = scene.clone();
    floor.push(Obstacle::HalfSpace {
        point: Point3::origin(),
        outward_normal: Vector3::z(),
    });
    let world = CollisionWorld::obstacles(&floor);
    // Fully extended pole (base at 1.0 m), arm stretched straight down along the base z axis:
    // the wrist reaches d1 - a2 - a3 + d5 = 1.08 m below the base, through the floor.
    let down = [0.0, -FRAC_PI_2, 0.0, -FRAC_PI_2, 0.0, 0.0];
    let capsules = robot.link_capsules(&down, &state).unwrap();
    let lowest = capsules
        .iter()
        .map(|c| c.a.z.min(c.b.z) - c.radius_m)
        .fold(f64::INFINITY, f64::min);
    assert!(lowest < -0.05, "lowest {lowest}");
    let contact = robot.check_configuration(&down, &state, &world).unwrap();
    assert_eq!(
        contact.map(|c| c.with),
        Some(ContactWith::Obstacle(floor.len() - 1))
    );
    // Retracted, the arm hangs far above the floor.
    let up = MountState::Gantry {
        x_m: 0.0,
        y_m: 0.0,
        extension_m: 0.0,
    };
    let scene_up = robot.mount.structure(&up).unwrap();
    let world_up = CollisionWorld::obstacles(&scene_up);
    assert_eq!(
        robot.check_configuration(&down, &up, &world_up).unwrap(),
        None
    );
    // Pointing the upper arm back up into the 2.6 m ceiling from a retracted base (2.2 m) hits it.
    let into_ceiling = [0.0, FRAC_PI_2, 0.0, 0.0, 0.0, 0.0];
    assert!(robot
        .check_configuration(&into_ceiling, &up, &world_up)
        .unwrap()
        .is_some());
}

#[test]
fn occupied_voxels_are_found_along_links() {
    let robot = Robot::scenario_one();
    let q = [0.0; 6];
    let capsules = robot.link_capsules(&q, &MountState::Fixed).unwrap();
    let forearm = capsules
        .iter()
        .find(|c| robot.arm.links[c.link].name == "forearm")
        .unwrap();
    let middle = nalgebra::center(&forearm.a, &forearm.b);
    let res = 0.01;
    let key = |p: Point3<f64>| (p / res).map(|v| v.floor() as i64);
    // A single occupied voxel at the forearm's axis, and one just outside its surface.
    let inside = key(middle);
    let occupied = move |p: Point3<f64>| key(p) == inside;
    let world = CollisionWorld::obstacles(&[]).with_voxels(&occupied, res);
    let contact = robot
        .check_configuration(&q, &MountState::Fixed, &world)
        .unwrap()
        .unwrap();
    assert_eq!(contact.link_name, "forearm");
    assert!(matches!(contact.with, ContactWith::Voxel(_)));
    let outside = key(middle + Vector3::new(0.0, 0.0, forearm.radius_m + 0.03));
    let near_miss = move |p: Point3<f64>| key(p) == outside;
    let world = CollisionWorld::obstacles(&[]).with_voxels(&near_miss, res);
    assert_eq!(
        robot
            .check_configuration(&q, &MountState::Fixed, &world)
            .unwrap(),
        None
    );
    // ... which a 4 cm margin catches.
    let world = world.with_margin(0.04);
    assert!(robot
        .check_configuration(&q, &MountState::Fixed, &world)
        .unwrap()
        .is_some());
    // Absurd resolutions and margins are errors, not endless loops.
    let tiny = CollisionWorld::obstacles(&[]).with_voxels(&occupied, 1e-9);
    assert!(robot
        .check_configuration(&q, &MountState::Fixed, &tiny)
        .is_err());
    let wide = CollisionWorld::obstacles(&[]).with_margin(f64::INFINITY);
    assert!(robot
        .check_configuration(&q, &MountState::Fixed, &wide)
        .is_err());
    // An empty map never collides.
    let empty = |_: Point3<f64>| false;
    let world = CollisionWorld::obstacles(&[]).with_voxels(&empty, res);
    assert_eq!(
        robot
            .check_configuration(&q, &MountState::Fixed, &world)
            .unwrap(),
        None
    );
}

#[test]
fn reachability_map_contains_fk_samples_and_excludes_far_points() {
    let map = paper_map();
    let arm = ArmModel::ur5e();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    // Joints 2-5 on the 10° sampling grid, joints 1 and 6 anywhere: always inside (joint 1 is
    // handled exactly by the rotational symmetry, joint 6 only rolls the on-axis camera).
    let step = 10f64.to_radians();
    for _ in 0..20_000 {
        let mut q = random_q(&mut rng, &arm.limits);
        for v in &mut q[1..5] {
            *v = (*v / step).round() * step;
        }
        let p = Point3::from(arm.base_from_camera(&q).unwrap().translation.vector);
        assert!(map.contains_in_base(&p), "{q:?} -> {p}");
    }
    // Continuous joints: inside except for the rare sample within millimetres of the edge of
    // the reach, in a boundary cell that no grid sample hit.
    let mut missed = Vec::new();
    let trials = 20_000;
    for _ in 0..trials {
        let q = random_q(&mut rng, &arm.limits);
        let p = Point3::from(arm.base_from_camera(&q).unwrap().translation.vector);
        if !map.contains_in_base(&p) {
            missed.push(p);
        }
    }
    eprintln!("continuous samples missed: {} of {trials}", missed.len());
    assert!(
        missed.len() <= trials / 2000,
        "{} of {trials} missed",
        missed.len()
    );
    for p in &missed {
        // Each miss lies at the outer edge: within 2 cm of a reached cell further in.
        let r = p.x.hypot(p.y);
        let inward = Point3::new(p.x * (r - 0.02) / r, p.y * (r - 0.02) / r, p.z);
        let shoulder = Point3::new(0.0, 0.0, arm.dh.d1);
        let towards_shoulder = p + (shoulder - p).normalize() * 0.02;
        assert!(
            map.contains_in_base(&inward) || map.contains_in_base(&towards_shoulder),
            "{p}"
        );
    }
    for _ in 0..2000 {
        let dir = Vector3::new(
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        );
        let Some(dir) = dir.try_normalize(1e-3) else {
            continue;
        };
        assert!(!map.contains_in_base(&Point3::from(dir * 1.2)), "{dir}");
    }
    assert!(!map.contains_in_base(&Point3::new(f64::NAN, 0.0, 0.0)));
    let (r, z_lo, z_hi) = map.extent_in_base().unwrap();
    assert!(
        r > 0.9 && r < 1.1 && z_lo < -0.8 && z_hi > 1.0,
        "{r} {z_lo} {z_hi}"
    );
}

#[test]
fn reachability_for_moving_mounts() {
    let map = paper_map();
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let robots = [Robot::scenario_two(), Robot::row(Interval::new(-1.0, 4.0))];
    let mut misses = 0;
    for robot in &robots {
        for _ in 0..2000 {
            let values: Vec<f64> = robot
                .mount
                .axis_ranges()
                .iter()
                .map(|r| rng.gen_range(r.min..=r.max))
                .collect();
            let state = match robot.mount {
                Mount::CeilingGantry { .. } => MountState::Gantry {
                    x_m: values[0],
                    y_m: values[1],
                    extension_m: values[2],
                },
                _ => MountState::Rail {
                    position_m: values[0],
                    lift_m: values[1],
                },
            };
            let q = random_q(&mut rng, &robot.arm.limits);
            let p = Point3::from(
                robot
                    .world_from_camera(&q, &state)
                    .unwrap()
                    .translation
                    .vector,
            );
            // Sampled continuously, so allow the rare boundary miss (see the test above).
            if !map.contains_in_world(&robot.mount, &state, &p).unwrap() {
                misses += 1;
            }
            assert!(map.reachable_for_some_state(&robot.mount, &p).unwrap());
        }
    }
    assert!(misses <= 2, "{misses} misses");
    let gantry = &robots[0].mount;
    // Under the square, from the floor up to the ceiling: reachable; below the floor beyond the
    // lowest base (1.0 m) minus the reach: not; far outside the square: not.
    assert!(map
        .reachable_for_some_state(gantry, &Point3::new(0.9, -0.9, 0.3))
        .unwrap());
    assert!(!map
        .reachable_for_some_state(gantry, &Point3::new(0.0, 0.0, -0.3))
        .unwrap());
    assert!(!map
        .reachable_for_some_state(gantry, &Point3::new(2.5, 0.0, 1.0))
        .unwrap());
    let rail = &robots[1].mount;
    // Along the rails up to lift + reach, not 1.5 m beside them.
    assert!(map
        .reachable_for_some_state(rail, &Point3::new(3.9, 0.0, 3.0))
        .unwrap());
    assert!(!map
        .reachable_for_some_state(rail, &Point3::new(1.0, 0.8, 1.0))
        .unwrap());
    assert!(map
        .reachable_for_some_state(rail, &Point3::new(f64::NAN, 0.0, 1.0))
        .is_err());
    // Fixed mounts use the exact per-cell query.
    let one = Mount::scenario_one();
    assert!(map
        .reachable_for_some_state(&one, &Point3::new(0.5, 0.0, 1.0))
        .unwrap());
    assert!(!map
        .reachable_for_some_state(&one, &Point3::new(1.3, 0.0, 0.86))
        .unwrap());
}

#[test]
fn restricted_base_joint_map_contains_its_samples() {
    let mut arm = ArmModel::ur5e();
    arm.limits.lower[0] = -FRAC_PI_2;
    arm.limits.upper[0] = FRAC_PI_2;
    let map = ReachabilityMap::build(&ReachabilityParams::paper(&arm)).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    for _ in 0..5000 {
        let q = random_q(&mut rng, &arm.limits);
        let p = Point3::from(arm.base_from_camera(&q).unwrap().translation.vector);
        assert!(map.contains_in_base(&p), "{q:?}");
    }
    assert!(map.reached_cell_count() > 0);
}

#[test]
fn reachability_cache_round_trip_and_corrupt_file_rebuilt() {
    let dir = temp_dir("cache");
    let mut params = ReachabilityParams::paper(&ArmModel::ur5e());
    params.step_rad = 20f64.to_radians();
    let (built, status) = ReachabilityMap::load_or_build_with_status(&dir, &params).unwrap();
    assert_eq!(status, CacheStatus::Built);
    let path = ReachabilityMap::cache_path(&dir, &params);
    let bytes = std::fs::read(&path).unwrap();
    let (loaded, status) = ReachabilityMap::load_or_build_with_status(&dir, &params).unwrap();
    assert_eq!(status, CacheStatus::Loaded);
    assert_eq!(loaded, built);
    // One flipped bit in the table.
    let mut corrupt = bytes.clone();
    let middle = corrupt.len() / 2;
    corrupt[middle] ^= 0x10;
    std::fs::write(&path, &corrupt).unwrap();
    let (rebuilt, status) = ReachabilityMap::load_or_build_with_status(&dir, &params).unwrap();
    assert_eq!(status, CacheStatus::Rebuilt);
    assert_eq!(rebuilt, built);
    assert_eq!(std::fs::read(&path).unwrap(), bytes);
    // Truncated and garbage files.
    for junk in [&bytes[..bytes.len() / 3], b"not a map".as_slice(), &[]] {
        std::fs::write(&path, junk).unwrap();
        let (map, status) = ReachabilityMap::load_or_build_with_status(&dir, &params).unwrap();
        assert_eq!(status, CacheStatus::Rebuilt);
        assert_eq!(map, built);
    }
    // Other parameters get another file; no temporary files are left behind.
    let mut other = params.clone();
    other.cell_m = 0.03;
    assert_ne!(other.cache_file_name(), params.cache_file_name());
    let map = ReachabilityMap::load_or_build(&dir, &other).unwrap();
    assert_eq!(map.params(), &other);
    let names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "{names:?}");
    // Invalid parameters are errors.
    let mut bad = params.clone();
    bad.step_rad = f64::NAN;
    assert!(ReachabilityMap::load_or_build(&dir, &bad).is_err());
    bad.step_rad = 0.0;
    assert!(ReachabilityMap::build(&bad).is_err());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn cache_key_is_stable() {
    let params = ReachabilityParams::paper(&ArmModel::ur5e());
    assert_eq!(params.cache_key(), params.clone().cache_key());
    let mut moved = params.clone();
    moved.flange_from_camera = Isometry3::translation(0.0, 0.05, 0.03);
    assert_ne!(moved.cache_key(), params.cache_key());
}

#[test]
fn off_axis_camera_map_samples_joint_six() {
    let mut arm = ArmModel::ur5e();
    arm.flange_from_camera = Isometry3::translation(0.0, -0.06, 0.02);
    let mut params = ReachabilityParams::paper(&arm);
    params.step_rad = 20f64.to_radians();
    let map = ReachabilityMap::build(&params).unwrap();
    // A coarse map: most random samples fall into reached cells.
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let hits = (0..2000)
        .filter(|_| {
            let q = random_q(&mut rng, &arm.limits);
            let p = Point3::from(arm.base_from_camera(&q).unwrap().translation.vector);
            map.contains_in_base(&p)
        })
        .count();
    assert!(hits > 1900, "{hits}");
}
