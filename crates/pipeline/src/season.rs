//! A trolley's visits of its row on the planner's copy: the visit it is on, the fruits of the
//! visits before it ([`SeasonTracker`]: each fruit's id from visit to visit and its history), and
//! the step from one visit to the next ([`TrolleyPlanner::start_visit`]: the previous visit's
//! map made into a prior, [`glasshouse_roimap::RoiMap::prior`]).

use glasshouse_geom::FruitEstimate;
use glasshouse_nbv::season::{SeasonFruit, SeasonRules, SeasonTracker, VisitRecord};
use glasshouse_proto::{FruitHistory, FruitVisit};
use glasshouse_roimap::PriorRules;

use crate::published::PublishedSolid;
use crate::{PlanningError, TrolleyPlanner};

impl TrolleyPlanner {
    /// The trolley's visit of its row this copy is on (0: the first).
    pub fn visit(&self) -> u32 {
        self.visit
    }

    /// Closes the current visit (its fruits go into their histories) and starts visit `visit`
    /// from the current map made into a prior: no fruit ids, no frame yet; the trolley's info,
    /// reach filter, registration counts and what was published are kept. Returns false, and
    /// changes nothing, when `visit` is not later than the current one.
    pub fn start_visit(&mut self, visit: u32, rules: &PriorRules) -> Result<bool, PlanningError> {
        if visit <= self.visit {
            return Ok(false);
        }
        rules.validate().map_err(PlanningError::Settings)?;
        let fruits = self.fruits();
        let ids: Vec<u32> = fruits.iter().map(|f| f.id).collect();
        let surfaces = self.fruit_voxel_centres(&ids);
        self.season
            .observe_visit_measured(self.visit as usize, &fruits, &surfaces);
        let prior = self.map.prior(rules);
        let mut next = Self::on_prior(self.settings.clone(), prior)?;
        next.info = self.info.take();
        next.reach = self.reach.take();
        next.alignment_counts = self.alignment_counts;
        next.hand_eye = self.hand_eye.for_next_visit();
        // A prior holds no solid voxel (its fruit hints and kept free space are free by the
        // occupancy rule), so the visit's first update, every voxel solid since, is its whole
        // map: sent as `full`, it clears the last visit's voxels from the dashboards.
        next.published_solid = PublishedSolid::default();
        next.publish_full = true;
        next.season = std::mem::take(&mut self.season);
        next.visit = visit;
        *self = next;
        Ok(true)
    }

    /// Every fruit of the season as FruitEstimates carries it: the fruits of the earlier visits
    /// and `current` (this visit's estimates, matched to them as a visit's end would match
    /// them, new ones numbered after them), each with its estimate's id on this visit (0: not
    /// seen on it). Nothing is committed: the visit's end decides, and measures each fruit's
    /// growth since its last visit then (a record of the current visit has no volume ratio
    /// yet). No surfaces: FruitEstimates leave them out.
    pub fn season_histories(&self, current: &[FruitEstimate]) -> Vec<FruitHistory> {
        let mut season = self.season.clone();
        let ids = season.observe_visit(self.visit as usize, current);
        season
            .fruits()
            .iter()
            .map(|f| FruitHistory {
                season_id: f.id,
                fruit_id: ids
                    .iter()
                    .position(|&id| id == f.id)
                    .map_or(0, |i| current[i].id),
                visits: f.history.iter().map(wire_record).collect(),
                last_surface: None,
            })
            .collect()
    }

    /// The fruits of the visits before this one as a snapshot or the store keeps them: their
    /// histories and the last surface of each, against which the next visit's growth is
    /// measured.
    pub fn committed_season(&self) -> Vec<FruitHistory> {
        self.season
            .fruits()
            .iter()
            .map(|f| FruitHistory {
                season_id: f.id,
                fruit_id: 0,
                visits: f.history.iter().map(wire_record).collect(),
                last_surface: f.last_surface.clone(),
            })
            .collect()
    }

    /// Takes the visit and the earlier visits' fruits a snapshot or store carried.
    pub(crate) fn set_season(&mut self, visit: u32, fruits: &[FruitHistory]) {
        let fruits = fruits
            .iter()
            .map(|h| SeasonFruit {
                id: h.season_id,
                history: h.visits.iter().map(tracker_record).collect(),
                last_surface: h.last_surface.clone(),
            })
            .collect();
        self.visit = visit;
        self.season = SeasonTracker::from_fruits(SeasonRules::default(), fruits, visit as usize);
    }
}

fn wire_record(r: &VisitRecord) -> FruitVisit {
    FruitVisit {
        visit: u32::try_from(r.visit).unwrap_or(u32::MAX),
        centre: r.centre,
        size_m: r.size_m,
        volume_m3: r.volume_m3,
        colour: r.colour,
        volume_ratio: r.volume_ratio,
    }
}

fn tracker_record(r: &FruitVisit) -> VisitRecord {
    VisitRecord {
        visit: r.visit as usize,
        centre: r.centre,
        size_m: r.size_m,
        volume_m3: r.volume_m3,
        visit_fruit_id: 0,
        colour: r.colour,
        volume_ratio: r.volume_ratio,
    }
}
