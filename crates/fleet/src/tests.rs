use std::collections::BTreeMap;

use crate::membership::{Assignment, Membership, MembershipEvent, OwnershipChange, Role};
use glasshouse_geom::FruitEstimate;
use nalgebra::{Point3, Vector3};

use crate::merge::{merge_fruits, TrolleyFruit, MERGE_DISTANCE_M};
use crate::rendezvous::{first_ranked, fnv1a64, mix64, rank_planners, top_two, weight};

fn ids(prefix: &str, n: usize) -> Vec<String> {
    (0..n).map(|i| format!("{prefix}-{i}")).collect()
}

/// Deterministic Fisher-Yates shuffle driven by splitmix64.
fn shuffle<T>(v: &mut [T], seed: u64) {
    let mut state = seed;
    for i in (1..v.len()).rev() {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let j = (mix64(state) % (i as u64 + 1)) as usize;
        v.swap(i, j);
    }
}

// ---------------------------------------------------------------------------------------------
// rendezvous

#[test]
fn hash_parts_match_reference_vectors() {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    // FNV-1a 64 test vectors (Fowler/Noll/Vo reference).
    assert_eq!(fnv1a64(OFFSET, b""), 0xcbf2_9ce4_8422_2325);
    assert_eq!(fnv1a64(OFFSET, b"a"), 0xaf63_dc4c_8601_ec8c);
    assert_eq!(fnv1a64(OFFSET, b"foobar"), 0x8594_4171_f739_67e8);
    // First outputs of splitmix64 seeded with 0: mix64(k * golden gamma).
    assert_eq!(mix64(0x9e37_79b9_7f4a_7c15), 0xe220_a839_7b1d_cdaf);
    assert_eq!(
        mix64(0x9e37_79b9_7f4a_7c15u64.wrapping_mul(2)),
        0x6e78_9e6a_a1b9_65f4
    );
}

#[test]
fn weight_is_the_documented_composition() {
    let expected = mix64(fnv1a64(0xcbf2_9ce4_8422_2325, b"planner-a\0trolley-1"));
    assert_eq!(weight("trolley-1", "planner-a"), expected);
    // The separator keeps ("ab", "c") and ("a", "bc") apart.
    assert_ne!(weight("c", "ab"), weight("bc", "a"));
    // Both arguments matter.
    assert_ne!(
        weight("trolley-1", "planner-a"),
        weight("trolley-2", "planner-a")
    );
    assert_ne!(
        weight("trolley-1", "planner-a"),
        weight("trolley-1", "planner-b")
    );
}

#[test]
fn rank_is_deterministic_and_independent_of_input_order() {
    let planners = ids("planner", 6);
    for t in 0..50 {
        let trolley = format!("trolley-{t}");
        let reference: Vec<String> = rank_planners(&trolley, &planners)
            .into_iter()
            .map(str::to_owned)
            .collect();
        assert_eq!(reference.len(), planners.len());
        // Sorted by weight descending.
        let weights: Vec<u64> = reference.iter().map(|p| weight(&trolley, p)).collect();
        assert!(weights.windows(2).all(|w| w[0] >= w[1]), "{weights:?}");
        for seed in 0..10 {
            let mut shuffled = planners.clone();
            shuffle(&mut shuffled, seed * 7919 + t);
            assert_eq!(rank_planners(&trolley, &shuffled), reference);
        }
        assert_eq!(rank_planners(&trolley, &planners), reference);
    }
}

#[test]
fn rank_counts_duplicates_once_and_handles_empty() {
    let planners: Vec<String> = ["p1", "p2", "p1", "p3", "p2", "p1"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let ranked = rank_planners("t", &planners);
    assert_eq!(ranked.len(), 3);
    let mut sorted = ranked.clone();
    sorted.sort_unstable();
    assert_eq!(sorted, ["p1", "p2", "p3"]);
    assert!(rank_planners("t", &[]).is_empty());
    assert_eq!(top_two("t", []), (None, None));
    assert_eq!(top_two("t", ["p1", "p1"]), (Some("p1"), None));
}

#[test]
fn top_two_agrees_with_rank() {
    for n in 1..7 {
        let mut planners = ids("p", n);
        // With duplicates, in several orders.
        planners.extend(ids("p", n / 2));
        for t in 0..100 {
            let trolley = format!("t{t}");
            shuffle(&mut planners, t);
            let ranked = rank_planners(&trolley, &planners);
            let expected = (ranked.first().copied(), ranked.get(1).copied());
            assert_eq!(
                top_two(&trolley, planners.iter().map(String::as_str)),
                expected
            );
            let first = first_ranked(&trolley, planners.iter().map(String::as_str));
            assert_eq!(first, expected.0);
        }
    }
}

#[test]
fn removing_a_non_owner_keeps_the_owner() {
    for n in 3..=5 {
        let planners = ids("planner", n);
        for t in 0..200 {
            let trolley = format!("trolley-{t:03}");
            let ranked = rank_planners(&trolley, &planners);
            let owner = ranked[0];
            for gone in &ranked[1..] {
                let rest: Vec<String> = planners.iter().filter(|p| p != gone).cloned().collect();
                assert_eq!(
                    rank_planners(&trolley, &rest)[0],
                    owner,
                    "{trolley} without {gone}"
                );
            }
        }
    }
}

#[test]
fn removing_the_owner_promotes_the_replica() {
    for n in 3..=5 {
        let planners = ids("planner", n);
        for t in 0..200 {
            let trolley = format!("trolley-{t:03}");
            let ranked = rank_planners(&trolley, &planners);
            let rest: Vec<String> = planners
                .iter()
                .filter(|p| *p != ranked[0])
                .cloned()
                .collect();
            let after = rank_planners(&trolley, &rest);
            // The replica becomes owner, the third becomes replica: the rest keep their order.
            assert_eq!(after, ranked[1..], "{trolley}");
        }
    }
}

#[test]
fn a_joining_planner_only_takes_trolleys() {
    let planners = ids("planner", 4);
    let mut more = planners.clone();
    more.push("planner-new".to_owned());
    let mut taken = 0;
    for t in 0..300 {
        let trolley = format!("trolley-{t:03}");
        let before = rank_planners(&trolley, &planners)[0];
        let after = rank_planners(&trolley, &more)[0];
        if after != before {
            assert_eq!(after, "planner-new");
            taken += 1;
        }
    }
    // About 1/5 of 300.
    assert!((30..=90).contains(&taken), "new planner took {taken}");
}

#[test]
fn load_spreads_over_three_planners() {
    let planners = ids("planner", 3);
    let mut owned: BTreeMap<&str, usize> = BTreeMap::new();
    let mut replicated: BTreeMap<&str, usize> = BTreeMap::new();
    for t in 0..300 {
        let trolley = format!("trolley-{t:03}");
        let ranked = rank_planners(&trolley, &planners);
        *owned.entry(ranked[0]).or_default() += 1;
        *replicated.entry(ranked[1]).or_default() += 1;
    }
    assert_eq!(owned.len(), 3);
    for (p, &n) in &owned {
        assert!((60..=138).contains(&n), "{p} owns {n} of 300: {owned:?}");
    }
    for (p, &n) in &replicated {
        assert!(
            (60..=138).contains(&n),
            "{p} replicates {n} of 300: {replicated:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// membership

fn assignment(owner: &str, replica: Option<&str>) -> Assignment {
    Assignment {
        owner: owner.to_owned(),
        replica: replica.map(str::to_owned),
    }
}

/// The expected assignment from ranking `planners` directly.
fn ranked_assignment(trolley: &str, planners: &[&str]) -> Option<Assignment> {
    let planners: Vec<String> = planners.iter().map(|s| s.to_string()).collect();
    let ranked = rank_planners(trolley, &planners);
    ranked
        .first()
        .map(|o| assignment(o, ranked.get(1).copied()))
}

#[test]
fn trolley_without_planners_has_no_assignment_until_one_joins() {
    let mut m = Membership::new();
    assert!(m.trolley_joined("t1").is_empty());
    assert_eq!(m.assignment("t1"), None);
    let changes = m.server_joined("p1");
    assert_eq!(
        changes,
        vec![OwnershipChange {
            trolley: "t1".into(),
            before: None,
            after: Some(assignment("p1", None)),
        }]
    );
    assert!(changes[0].owner_changed());
    assert_eq!(m.assignment("t1"), Some(assignment("p1", None)));
    // Unknown trolleys have no assignment, but can be ranked.
    assert_eq!(m.assignment("t-unknown"), None);
    assert_eq!(m.rank("t-unknown"), ["p1"]);
}

#[test]
fn membership_change_events_follow_joins_and_leaves() {
    let mut m = Membership::new();
    m.server_joined("p1");
    m.server_joined("p2");
    let trolleys = ["t1", "t2", "t3", "t4", "t5", "t6"];

    // A trolley joining: one change, from nothing to its ranked assignment.
    for t in trolleys {
        let changes = m.trolley_joined(t);
        assert_eq!(
            changes,
            vec![OwnershipChange {
                trolley: t.into(),
                before: None,
                after: ranked_assignment(t, &["p1", "p2"]),
            }]
        );
    }
    // Idempotent.
    assert!(m.trolley_joined("t1").is_empty());
    assert!(m.server_joined("p1").is_empty());
    assert!(m.server_left("p9").is_empty());
    assert!(m.trolley_left("t9").is_empty());

    // A third planner joins: exactly the trolleys where it ranks first or second change.
    let changes = m.apply(MembershipEvent::ServerJoined("p3".into()));
    let expected: Vec<OwnershipChange> = trolleys
        .iter()
        .filter_map(|t| {
            let before = ranked_assignment(t, &["p1", "p2"]);
            let after = ranked_assignment(t, &["p1", "p2", "p3"]);
            (before != after).then(|| OwnershipChange {
                trolley: t.to_string(),
                before,
                after,
            })
        })
        .collect();
    assert_eq!(changes, expected);
    // With two planners every trolley had both; p3 must take a role wherever it ranks top two,
    // which with 6 trolleys and 3 planners is not nowhere.
    assert!(!changes.is_empty());
    for c in &changes {
        let after = c.after.as_ref().map(|a| a.role_of("p3"));
        assert!(matches!(after, Some(Some(_))), "{c:?}");
    }
    // Sorted by trolley.
    assert!(changes.windows(2).all(|w| w[0].trolley < w[1].trolley));

    // The owner of some trolley leaves: its trolleys move to their replica.
    let leaving = m.assignment("t1").map(|a| a.owner).unwrap_or_default();
    let before: BTreeMap<String, Assignment> = trolleys
        .iter()
        .filter_map(|t| m.assignment(t).map(|a| (t.to_string(), a)))
        .collect();
    let changes = m.server_left(leaving.clone());
    let rest: Vec<&str> = ["p1", "p2", "p3"]
        .into_iter()
        .filter(|p| *p != leaving)
        .collect();
    for c in &changes {
        let was = &before[&c.trolley];
        assert!(
            was.role_of(&leaving).is_some(),
            "{c:?} changed without {leaving} involved"
        );
        let now = c.after.as_ref().map(|a| a.owner.as_str());
        if was.owner == leaving {
            assert_eq!(now, was.replica.as_deref(), "replica promoted");
            assert!(c.owner_changed());
        } else {
            assert_eq!(now, Some(was.owner.as_str()), "owner kept");
            assert!(!c.owner_changed());
        }
        assert_eq!(c.after, ranked_assignment(&c.trolley, &rest));
    }
    // Every trolley in which the leaver had a role is reported.
    let involved = before
        .values()
        .filter(|a| a.role_of(&leaving).is_some())
        .count();
    assert_eq!(changes.len(), involved);
    assert!(m.roles_of(&leaving).is_empty());

    // A trolley leaving: one change to nothing.
    let was = m.assignment("t2");
    assert_eq!(
        m.trolley_left("t2"),
        vec![OwnershipChange {
            trolley: "t2".into(),
            before: was,
            after: None,
        }]
    );
    assert_eq!(m.assignment("t2"), None);

    // All planners leave: the last leave takes every trolley to nothing.
    for p in &rest[..1] {
        m.server_left(*p);
    }
    let last = m.server_left(rest[1]);
    assert_eq!(last.len(), 5);
    assert!(last.iter().all(|c| c.after.is_none() && c.before.is_some()));
}

#[test]
fn roles_of_partitions_the_fleet() {
    let mut m = Membership::new();
    for p in ["p1", "p2", "p3", "p4"] {
        m.server_joined(p);
    }
    for t in ids("t", 40) {
        m.trolley_joined(t);
    }
    let mut owners = 0;
    let mut replicas = 0;
    for p in ["p1", "p2", "p3", "p4"] {
        for (t, role) in m.roles_of(p) {
            let a = m.assignment(&t);
            assert_eq!(a.as_ref().and_then(|a| a.role_of(p)), Some(role));
            match role {
                Role::Owner => owners += 1,
                Role::Replica => replicas += 1,
            }
        }
    }
    assert_eq!(owners, 40);
    assert_eq!(replicas, 40);
    assert!(m.roles_of("p-none").is_empty());
}

#[test]
fn membership_does_not_depend_on_event_order() {
    let planners = ids("p", 5);
    let trolleys = ids("t", 30);
    let mut events: Vec<MembershipEvent> = planners
        .iter()
        .map(|p| MembershipEvent::ServerJoined(p.clone()))
        .chain(
            trolleys
                .iter()
                .map(|t| MembershipEvent::TrolleyJoined(t.clone())),
        )
        .collect();
    let mut reference = Membership::new();
    for e in events.clone() {
        reference.apply(e);
    }
    for seed in 0..5 {
        shuffle(&mut events, seed);
        let mut m = Membership::new();
        for e in events.clone() {
            m.apply(e);
        }
        assert_eq!(m, reference);
        for t in &trolleys {
            assert_eq!(m.assignment(t), reference.assignment(t));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// merge

fn fruit(trolley: &str, id: u32, centre: [f64; 3], confidence: f64) -> TrolleyFruit {
    let r = 0.03;
    let centre = Point3::from(centre);
    let half = Vector3::repeat(r);
    TrolleyFruit {
        trolley_id: trolley.to_owned(),
        fruit: FruitEstimate {
            volume_m3: 4.0 / 3.0 * std::f64::consts::PI * r * r * r,
            confidence,
            ..FruitEstimate::from_box(id, centre, centre - half, centre + half)
        },
    }
}

fn source(trolley: &str, id: u32) -> (String, u32) {
    (trolley.to_owned(), id)
}

#[test]
fn same_fruit_from_two_trolleys_merges() {
    let inputs = [
        fruit("t2", 7, [1.02, 0.0, 1.0], 0.9),
        fruit("t1", 3, [1.0, 0.0, 1.0], 0.6),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 1);
    let f = &r.fruits[0];
    assert_eq!(f.sources, [source("t1", 3), source("t2", 7)]);
    assert_eq!(f.fleet_id, "t1/3");
    // Highest confidence wins.
    assert_eq!(f.estimate_from, source("t2", 7));
    assert_eq!(f.fruit.centre, Point3::from([1.02, 0.0, 1.0]));
    assert_eq!(f.fruit.confidence, 0.9);
    assert_eq!(r.skipped_non_finite, 0);
}

#[test]
fn equal_confidence_keeps_the_smallest_source() {
    let inputs = [
        fruit("t2", 1, [1.02, 0.0, 1.0], 0.5),
        fruit("t1", 9, [1.0, 0.0, 1.0], 0.5),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 1);
    assert_eq!(r.fruits[0].estimate_from, source("t1", 9));
    assert_eq!(r.fruits[0].fruit.centre, Point3::from([1.0, 0.0, 1.0]));
}

#[test]
fn two_fruits_of_one_trolley_stay_two() {
    let inputs = [
        fruit("t1", 1, [1.0, 0.0, 1.0], 0.8),
        fruit("t1", 2, [1.02, 0.0, 1.0], 0.8),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    let fleet_ids: Vec<&str> = r.fruits.iter().map(|f| f.fleet_id.as_str()).collect();
    assert_eq!(fleet_ids, ["t1/1", "t1/2"]);
    assert!(r.fruits.iter().all(|f| f.sources.len() == 1));
}

#[test]
fn far_fruits_stay_apart() {
    let inputs = [
        fruit("t1", 1, [1.0, 0.0, 1.0], 0.8),
        fruit("t2", 1, [1.0, 0.2, 1.0], 0.8),
        fruit("t3", 1, [1.0, 0.0, 1.3], 0.8),
    ];
    assert_eq!(merge_fruits(&inputs, MERGE_DISTANCE_M).fruits.len(), 3);
}

#[test]
fn chain_of_three_trolleys_merges_into_one() {
    // A~B and B~C are 4 cm apart, A and C 8 cm: no direct match.
    let inputs = [
        fruit("tA", 1, [1.00, 0.0, 1.0], 0.5),
        fruit("tB", 1, [1.04, 0.0, 1.0], 0.7),
        fruit("tC", 1, [1.08, 0.0, 1.0], 0.6),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 1);
    let f = &r.fruits[0];
    assert_eq!(
        f.sources,
        [source("tA", 1), source("tB", 1), source("tC", 1)]
    );
    assert_eq!(f.fleet_id, "tA/1");
    assert_eq!(f.estimate_from, source("tB", 1));
}

#[test]
fn a_chain_never_joins_two_fruits_of_one_trolley() {
    // B (t2) sits between A and C (both t1): it joins the closer one only.
    let inputs = [
        fruit("t1", 1, [1.00, 0.0, 1.0], 0.5),
        fruit("t2", 5, [1.03, 0.0, 1.0], 0.5),
        fruit("t1", 2, [1.065, 0.0, 1.0], 0.5),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 2);
    assert_eq!(r.fruits[0].sources, [source("t1", 1), source("t2", 5)]);
    assert_eq!(r.fruits[1].sources, [source("t1", 2)]);
}

#[test]
fn overlapping_boxes_merge_even_with_distant_centres() {
    // Centres 8 cm apart (long fruit seen from two ends), boxes overlap by 75% of the smaller.
    let mut a = fruit("t1", 1, [1.0, 0.0, 1.0], 0.5);
    a.fruit.min = Point3::from([0.90, -0.03, 0.97]);
    a.fruit.max = Point3::from([1.10, 0.03, 1.03]);
    let mut b = fruit("t2", 1, [1.08, 0.0, 1.0], 0.5);
    b.fruit.min = Point3::from([1.04, -0.03, 0.97]);
    b.fruit.max = Point3::from([1.12, 0.03, 1.03]);
    let r = merge_fruits(&[a.clone(), b.clone()], MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 1);
    assert_eq!(r.fruits[0].sources, [source("t1", 1), source("t2", 1)]);
    // Overlap of less than half the smaller box (0.03 of 0.08 along x) is not enough.
    b.fruit.min[0] = 1.07;
    b.fruit.max[0] = 1.15;
    let r = merge_fruits(&[a, b], MERGE_DISTANCE_M);
    assert_eq!(r.fruits.len(), 2);
}

#[test]
fn non_finite_inputs_are_skipped_and_counted() {
    let mut nan_centre = fruit("t2", 1, [1.0, 0.0, 1.0], 0.9);
    nan_centre.fruit.centre[1] = f64::NAN;
    let mut inf_conf = fruit("t3", 1, [1.0, 0.0, 1.0], 0.9);
    inf_conf.fruit.confidence = f64::INFINITY;
    let mut nan_box = fruit("t4", 1, [1.0, 0.0, 1.0], 0.9);
    nan_box.fruit.max[2] = f64::NAN;
    let inputs = [
        fruit("t1", 1, [1.0, 0.0, 1.0], 0.5),
        nan_centre,
        inf_conf,
        nan_box,
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.skipped_non_finite, 3);
    assert_eq!(r.fruits.len(), 1);
    assert_eq!(r.fruits[0].sources, [source("t1", 1)]);
}

#[test]
fn duplicate_keys_count_once() {
    let inputs = [
        fruit("t1", 1, [1.0, 0.0, 1.0], 0.5),
        fruit("t1", 1, [1.5, 0.0, 1.0], 0.8),
    ];
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    assert_eq!(r.skipped_duplicate, 1);
    assert_eq!(r.fruits.len(), 1);
    assert_eq!(r.fruits[0].fruit.centre, Point3::from([1.5, 0.0, 1.0]));
}

/// A fleet of 4 trolleys in a row whose working ranges overlap: each sees some fruits of its
/// neighbours, with a little estimation noise.
fn overlapping_rows() -> Vec<TrolleyFruit> {
    let mut inputs = Vec::new();
    let mut state = 42u64;
    let mut noise = || {
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        (mix64(state) as f64 / u64::MAX as f64 - 0.5) * 0.01
    };
    for (t, trolley) in ["t0", "t1", "t2", "t3"].iter().enumerate() {
        let (lo, hi) = (t * 10, t * 10 + 14);
        for (id, k) in (lo..hi.min(40)).enumerate() {
            let centre = [
                k as f64 * 0.25 + noise(),
                noise(),
                1.0 + (k % 3) as f64 * 0.2,
            ];
            inputs.push(fruit(trolley, id as u32 + 1, centre, 0.5 + noise()));
        }
    }
    inputs
}

#[test]
fn fleet_ids_are_stable_under_shuffling() {
    let inputs = overlapping_rows();
    let reference = merge_fruits(&inputs, MERGE_DISTANCE_M);
    // 40 distinct fruits, the overlaps seen twice.
    assert_eq!(reference.fruits.len(), 40);
    assert_eq!(
        reference
            .fruits
            .iter()
            .filter(|f| f.sources.len() == 2)
            .count(),
        12
    );
    for seed in 0..20 {
        let mut shuffled = inputs.clone();
        shuffle(&mut shuffled, seed);
        assert_eq!(
            merge_fruits(&shuffled, MERGE_DISTANCE_M),
            reference,
            "seed {seed}"
        );
    }
}

#[test]
fn output_is_sorted_by_fleet_key_and_sources_are_sorted() {
    let mut inputs = overlapping_rows();
    inputs.push(fruit("t1", 100, [20.0, 0.0, 1.0], 0.5));
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    let keys: Vec<(String, u32)> = r.fruits.iter().map(|f| f.sources[0].clone()).collect();
    assert!(keys.windows(2).all(|w| w[0] < w[1]));
    for f in &r.fruits {
        assert!(f.sources.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(f.fleet_id, format!("{}/{}", f.sources[0].0, f.sources[0].1));
    }
    // Numeric fruit order: t1/14 before t1/100.
    let t1: Vec<&str> = r
        .fruits
        .iter()
        .filter(|f| f.sources[0].0 == "t1")
        .map(|f| f.fleet_id.as_str())
        .collect();
    assert_eq!(t1.last().copied(), Some("t1/100"));
}

#[test]
fn sweep_finds_the_same_matches_as_all_pairs() {
    // Brute force over all pairs must give the same groups as the x sweep.
    let inputs = overlapping_rows();
    let r = merge_fruits(&inputs, MERGE_DISTANCE_M);
    let mut brute_pairs = 0;
    for (i, a) in inputs.iter().enumerate() {
        for b in &inputs[i + 1..] {
            let close = a.trolley_id != b.trolley_id && {
                let d: f64 = (0..3)
                    .map(|k| (a.fruit.centre[k] - b.fruit.centre[k]).powi(2))
                    .sum();
                d.sqrt() <= MERGE_DISTANCE_M
            };
            if close {
                brute_pairs += 1;
                let together = r.fruits.iter().any(|f| {
                    f.sources.contains(&source(&a.trolley_id, a.fruit.id))
                        && f.sources.contains(&source(&b.trolley_id, b.fruit.id))
                });
                assert!(together, "{a:?} and {b:?} not merged");
            }
        }
    }
    assert_eq!(brute_pairs, 12);
}

// ---------------------------------------------------------------------------------------------
// epoch

use crate::epoch::{next_epoch, EpochFence, EpochVerdict, NO_EPOCH};

#[test]
fn a_new_term_is_later_than_every_epoch_seen_whatever_the_clock_says() {
    // The clock ahead of the newest epoch: its reading.
    assert_eq!(next_epoch(100, 5_000), 5_000);
    // The clock behind it (another planner's clock runs ahead): one more than the newest.
    assert_eq!(next_epoch(5_000, 100), 5_001);
    assert_eq!(next_epoch(5_000, 5_000), 5_001);
    assert_eq!(next_epoch(NO_EPOCH, 0), 1);
    // Never wraps around to an old epoch.
    assert_eq!(next_epoch(u64::MAX, 7), u64::MAX);
}

#[test]
fn the_fence_keeps_the_newest_epoch_per_trolley_and_judges_the_others() {
    let mut fence = EpochFence::new();
    assert_eq!(fence.newest("t1"), NO_EPOCH);
    assert_eq!(fence.observe("t1", 10), EpochVerdict::Newer { previous: 0 });
    assert_eq!(fence.observe("t1", 10), EpochVerdict::Current);
    assert_eq!(fence.observe("t1", 7), EpochVerdict::Stale { newest: 10 });
    // A stale epoch does not lower the newest; another trolley has its own.
    assert_eq!(fence.newest("t1"), 10);
    assert_eq!(fence.check("t2", 7), EpochVerdict::Newer { previous: 0 });
    assert_eq!(fence.newest("t2"), NO_EPOCH, "check records nothing");
    // A sender without fencing is older than any term.
    assert!(fence.check("t1", NO_EPOCH).is_stale());
}

#[test]
fn every_term_begun_on_a_trolley_is_later_than_the_one_before() {
    // Two planners begin terms on one trolley in turn, each knowing what the other published;
    // their clocks disagree by a second either way.
    let (mut a, mut b) = (EpochFence::new(), EpochFence::new());
    let mut last = NO_EPOCH;
    for (i, now_ns) in [
        5_000_000_000u64,
        4_000_000_000,
        4_000_000_100,
        6_000_000_000,
    ]
    .into_iter()
    .enumerate()
    {
        let (mine, other) = if i % 2 == 0 {
            (&mut a, &mut b)
        } else {
            (&mut b, &mut a)
        };
        let epoch = mine.begin_term("t1", now_ns);
        assert!(epoch > last, "term {i}: {epoch} after {last}");
        assert_eq!(
            other.observe("t1", epoch),
            EpochVerdict::Newer { previous: last }
        );
        last = epoch;
    }
}
