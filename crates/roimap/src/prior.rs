//! A revisit's prior: the map a trolley starts a new visit of its row with, made from the map
//! the previous visit ended with ([`RoiMap::prior`]).
//!
//! What a revisit is for is the fruit: they swell, new ones set, ripe ones are picked. So the
//! prior keeps the previous visit's fruit voxels as *hints*: known, free by the occupancy rule,
//! their ROI log-odds [`PriorRules::fruit_below_threshold_logodds`] under the ROI threshold.
//! One observation of fruit there makes them fruit again (a new map needs two), one of
//! anything else clears them, and without an observation this visit no fruit is reported on the
//! prior's word (a picked fruit is not counted). The planner's ROI-targeted sampling then has
//! its targets as soon as the first scan touches a fruit where it was.
//!
//! Free space is not kept by default ([`PriorRules::free_share`] 0): with the unobserved-voxel
//! gains, a map that already knows the air between the plants leaves unknown mostly what the
//! previous visit could not see, and the planner spends its first views there; measured on the
//! tuning seeds (docs/seasons.md), a revisit on such a prior reached the previous visit's
//! level of fruit later than one from an empty map, one on fruit hints alone much earlier.

use crate::{Occupancy, RoiMap, Voxel, VoxelKey};

/// How a revisit's prior is made from the previous visit's map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PriorRules {
    /// The previous visit's ROI voxels start this far below the ROI threshold (> 0).
    pub fruit_below_threshold_logodds: f32,
    /// Share of the log-odds of the previous visit's free voxels the prior keeps (0: none,
    /// at most 1); the free voxels beside a fruit voxel are never kept (a fruit grows into them).
    pub free_share: f32,
}

impl Default for PriorRules {
    fn default() -> Self {
        Self {
            fruit_below_threshold_logodds: 0.05,
            free_share: 0.0,
        }
    }
}

impl PriorRules {
    pub fn validate(&self) -> Result<(), String> {
        let below = self.fruit_below_threshold_logodds;
        if !(below.is_finite() && below > 0.0) {
            return Err(format!(
                "fruit_below_threshold_logodds must be finite and > 0, got {below}"
            ));
        }
        if !(self.free_share.is_finite() && (0.0..=1.0).contains(&self.free_share)) {
            return Err(format!(
                "free_share must be within [0, 1], got {}",
                self.free_share
            ));
        }
        Ok(())
    }
}

impl RoiMap {
    /// The prior of a new visit (see the module docs): a new map with this map's configuration
    /// and no scans inserted, holding this map's ROI voxels as hints and, with a `free_share`,
    /// its free voxels away from them, weakened. Invalid `rules`
    /// ([`PriorRules::validate`]) give the default rules' prior.
    pub fn prior(&self, rules: &PriorRules) -> RoiMap {
        let rules = match rules.validate() {
            Ok(()) => *rules,
            Err(_) => PriorRules::default(),
        };
        let hint = Voxel {
            occupancy_logodds: 0.0,
            roi_logodds: self.config.roi_threshold_logodds - rules.fruit_below_threshold_logodds,
        };
        let mut voxels: Vec<(VoxelKey, Voxel)> =
            self.roi_voxels().iter().map(|&k| (k, hint)).collect();
        if rules.free_share > 0.0 {
            let beside_fruit = |k: VoxelKey| {
                k.neighbours(crate::Neighbourhood::TwentySix)
                    .any(|n| self.is_roi(n))
            };
            voxels.extend(
                self.iter()
                    .filter(|(k, v)| v.occupancy_logodds <= 0.0 && !self.is_roi(*k))
                    .filter(|(k, _)| !beside_fruit(*k))
                    .map(|(k, v)| {
                        let weakened = Voxel {
                            occupancy_logodds: v.occupancy_logodds * rules.free_share,
                            roi_logodds: v.roi_logodds.min(0.0) * rules.free_share,
                        };
                        (k, weakened)
                    }),
            );
        }
        let mut prior = RoiMap::new(self.config).expect("this map's configuration was validated");
        prior.apply_voxels(&voxels);
        // The prior is where the visit starts, not something to publish as changed.
        prior.drain_changes(|_, _, _| {});
        prior
    }
}

impl RoiMap {
    /// Whether `key` is a prior's fruit hint no scan of this visit has touched: known, its
    /// occupancy log-odds still exactly the prior's 0 (any hit or miss moves it), its ROI
    /// log-odds above 0 and under the threshold.
    pub fn is_unobserved_hint(&self, key: VoxelKey) -> bool {
        self.get(key).is_some_and(|v| {
            v.occupancy_logodds == 0.0
                && v.roi_logodds > 0.0
                && v.roi_logodds < self.config.roi_threshold_logodds
        })
    }

    /// The occupancy this visit's scans gave `key`: [`RoiMap::occupancy`], except that an
    /// unobserved hint ([`RoiMap::is_unobserved_hint`]) is unknown. The map holds a hint as a
    /// known voxel (free by the occupancy rule), but no ray of this visit has seen it: a grown
    /// fruit hides the last visit's skin inside its own, where a fit or an inside test that
    /// took it for free space would shrink the fruit or call it a sheet.
    pub fn observed_occupancy(&self, key: VoxelKey) -> Occupancy {
        match self.occupancy(key) {
            Occupancy::Free if self.is_unobserved_hint(key) => Occupancy::Unknown,
            seen => seen,
        }
    }

    /// Every [`RoiMap::is_unobserved_hint`] voxel, sorted: where the previous visit's fruit
    /// were and this visit has not looked yet (a walk over the whole map).
    pub fn unobserved_hints(&self) -> Vec<VoxelKey> {
        let mut hints: Vec<VoxelKey> = self
            .iter()
            .map(|(k, _)| k)
            .filter(|&k| self.is_unobserved_hint(k))
            .collect();
        hints.sort_unstable();
        hints
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::MapConfig;
    use nalgebra::Point3;

    /// Points of a wall at x = 1 m, (y, z) on a 1 cm grid within `half` cm of the middle.
    fn wall(half: i32) -> Vec<Point3<f32>> {
        let mut points = Vec::new();
        for iy in -half..=half {
            for iz in -half..=half {
                let (y, z) = (iy as f32 * 0.01 + 0.005, iz as f32 * 0.01 + 0.005);
                points.push(Point3::new(1.005, y, z));
            }
        }
        points
    }

    /// The wall seen three times from the origin, its middle 5 x 5 cm labelled fruit.
    fn seen_map() -> RoiMap {
        let mut map = RoiMap::new(MapConfig::default()).unwrap();
        let points = wall(10);
        let roi: Vec<bool> = points
            .iter()
            .map(|p| p.y.abs() < 0.03 && p.z.abs() < 0.03)
            .collect();
        for _ in 0..3 {
            map.insert_scan(&Point3::origin(), &points, &roi).unwrap();
        }
        map
    }

    #[test]
    fn the_prior_holds_the_fruit_as_hints_below_the_threshold() {
        let map = seen_map();
        assert_eq!(map.roi_voxels().len(), 36);
        let prior = map.prior(&PriorRules::default());
        assert_eq!(prior.scans_inserted(), 0);
        assert_eq!(prior.len(), 36, "the fruit voxels and nothing else");
        assert!(
            prior.roi_voxels().is_empty(),
            "no fruit on the prior's word"
        );
        let fruit = map.key_of(&Point3::new(1.005, 0.005, 0.005));
        assert_eq!(prior.occupancy(fruit), Occupancy::Free);
        assert_eq!(prior.observed_occupancy(fruit), Occupancy::Unknown);
        assert_eq!(prior.roi_logodds(fruit), Some(1.0 - 0.05));
        let leaf = map.key_of(&Point3::new(1.005, 0.095, 0.095));
        assert_eq!(prior.occupancy(leaf), Occupancy::Unknown);
        assert!(prior.clone().take_changes().is_empty());
    }

    #[test]
    fn with_a_free_share_the_free_space_away_from_the_fruit_is_kept_weakened() {
        let map = seen_map();
        let rules = PriorRules {
            free_share: 0.5,
            ..PriorRules::default()
        };
        let prior = map.prior(&rules);
        let air = map.key_of(&Point3::new(0.5, 0.0, 0.0));
        assert_eq!(prior.occupancy(air), Occupancy::Free);
        assert_eq!(
            prior.occupancy_logodds(air),
            map.occupancy_logodds(air).map(|l| l * 0.5)
        );
        let before_fruit = map.key_of(&Point3::new(0.995, 0.005, 0.005));
        assert_eq!(map.occupancy(before_fruit), Occupancy::Free);
        assert_eq!(prior.occupancy(before_fruit), Occupancy::Unknown);
        let leaf = map.key_of(&Point3::new(1.005, 0.095, 0.095));
        assert_eq!(prior.occupancy(leaf), Occupancy::Unknown);
    }

    #[test]
    fn one_observation_makes_a_hint_fruit_again_and_one_of_something_else_clears_it() {
        let map = seen_map();
        let mut prior = map.prior(&PriorRules::default());
        let middle = wall(2);
        prior
            .insert_scan(&Point3::origin(), &middle, &vec![true; middle.len()])
            .unwrap();
        assert_eq!(prior.roi_voxels().len(), 25, "one hit on a hint is fruit");
        // Seen, a hint is what the scan made it; the hints the scan missed stay unseen.
        let seen = map.key_of(&Point3::new(1.005, 0.005, 0.005));
        assert_eq!(prior.observed_occupancy(seen), Occupancy::Occupied);
        let unseen = map.key_of(&Point3::new(1.005, -0.025, -0.025));
        assert_eq!(prior.observed_occupancy(unseen), Occupancy::Unknown);
        assert_eq!(prior.occupancy(unseen), Occupancy::Free);
        let mut cleared = map.prior(&PriorRules::default());
        cleared
            .insert_scan(&Point3::origin(), &middle, &vec![false; middle.len()])
            .unwrap();
        let fruit = map.key_of(&Point3::new(1.005, 0.005, 0.005));
        assert!(cleared.roi_logodds(fruit).unwrap() < 1.0 - 0.05);
        assert!(cleared.roi_voxels().is_empty());
        // A new map needs two.
        let mut fresh = RoiMap::new(MapConfig::default()).unwrap();
        fresh
            .insert_scan(&Point3::origin(), &middle, &vec![true; middle.len()])
            .unwrap();
        assert!(fresh.roi_voxels().is_empty());
    }

    #[test]
    fn a_hint_stays_unobserved_until_a_scan_touches_it() {
        let map = seen_map();
        let mut prior = map.prior(&PriorRules::default());
        assert_eq!(prior.unobserved_hints().len(), 36);
        assert!(
            map.unobserved_hints().is_empty(),
            "a visit's own map has none"
        );
        let middle = wall(1);
        prior
            .insert_scan(&Point3::origin(), &middle, &vec![false; middle.len()])
            .unwrap();
        let seen = map.key_of(&Point3::new(1.005, 0.005, 0.005));
        assert!(!prior.is_unobserved_hint(seen));
        assert_eq!(prior.unobserved_hints().len(), 36 - 9);
    }

    #[test]
    fn bad_rules_are_refused() {
        for below in [0.0, -0.5, f32::NAN] {
            let rules = PriorRules {
                fruit_below_threshold_logodds: below,
                ..PriorRules::default()
            };
            assert!(rules.validate().is_err(), "{below}");
        }
        for share in [-0.1, 1.5, f32::INFINITY] {
            let rules = PriorRules {
                free_share: share,
                ..PriorRules::default()
            };
            assert!(rules.validate().is_err(), "{share}");
        }
    }
}
