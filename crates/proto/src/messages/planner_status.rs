//! PlannerStatus: a planner's health and ownership, planner → dashboard, other planners.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{payload, string_or_empty, strings, strings_from_fb};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlannerStatus {
    pub planner_id: String,
    pub owned_trolleys: Vec<String>,
    pub standby_trolleys: Vec<String>,
    pub clouds_integrated: u64,
    pub views_published: u64,
    pub last_planning_time_ms: f32,
    pub mean_planning_time_ms: f32,
    pub dropped_messages: u64,
    pub map_voxels: u64,
    /// RoiClouds refused: not from a live detector, or a frame id no honest trolley sends.
    pub refused_clouds: u64,
    /// Time in each stage of cloud handling, summed since the planner started.
    pub stage_totals: StageTimes,
    /// Time spent catching up trolleys taken over from a lost owner (snapshot decode and the
    /// clouds kept since; the replayed clouds also count in `stage_totals`).
    pub catch_up_ms: f64,
}

/// A planner's time per stage of its cloud handling, ms (see the schema's `StageTimes`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTimes {
    pub integrate_ms: f64,
    pub cluster_ms: f64,
    pub track_ms: f64,
    pub fit_ms: f64,
    pub plan_ms: f64,
    pub publish_ms: f64,
}

impl StageTimes {
    /// The stages by name, in pipeline order.
    pub fn named(&self) -> [(&'static str, f64); 6] {
        [
            ("integrate", self.integrate_ms),
            ("cluster", self.cluster_ms),
            ("track", self.track_ms),
            ("fit", self.fit_ms),
            ("plan", self.plan_ms),
            ("publish", self.publish_ms),
        ]
    }

    pub fn total_ms(&self) -> f64 {
        self.named().iter().map(|(_, ms)| ms).sum()
    }

    fn to_fb(self) -> fb::StageTimes {
        fb::StageTimes::new(
            self.integrate_ms,
            self.cluster_ms,
            self.track_ms,
            self.fit_ms,
            self.plan_ms,
            self.publish_ms,
        )
    }

    fn from_fb(t: &fb::StageTimes) -> Self {
        Self {
            integrate_ms: t.integrate_ms(),
            cluster_ms: t.cluster_ms(),
            track_ms: t.track_ms(),
            fit_ms: t.fit_ms(),
            plan_ms: t.plan_ms(),
            publish_ms: t.publish_ms(),
        }
    }
}

impl Wire for PlannerStatus {
    const KIND: MessageKind = MessageKind::PlannerStatus;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let pid = fbb.create_string(&self.planner_id);
        let owned = strings(fbb, &self.owned_trolleys);
        let standby = strings(fbb, &self.standby_trolleys);
        let stages = self.stage_totals.to_fb();
        fb::PlannerStatus::create(
            fbb,
            &fb::PlannerStatusArgs {
                planner_id: Some(pid),
                owned_trolleys: Some(owned),
                standby_trolleys: Some(standby),
                clouds_integrated: self.clouds_integrated,
                views_published: self.views_published,
                last_planning_time_ms: self.last_planning_time_ms,
                mean_planning_time_ms: self.mean_planning_time_ms,
                dropped_messages: self.dropped_messages,
                map_voxels: self.map_voxels,
                refused_clouds: self.refused_clouds,
                stage_totals: Some(&stages),
                catch_up_ms: self.catch_up_ms,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_planner_status())?;
        Ok(PlannerStatus {
            planner_id: string_or_empty(m.planner_id()),
            owned_trolleys: strings_from_fb(m.owned_trolleys()),
            standby_trolleys: strings_from_fb(m.standby_trolleys()),
            clouds_integrated: m.clouds_integrated(),
            views_published: m.views_published(),
            last_planning_time_ms: m.last_planning_time_ms(),
            mean_planning_time_ms: m.mean_planning_time_ms(),
            dropped_messages: m.dropped_messages(),
            map_voxels: m.map_voxels(),
            refused_clouds: m.refused_clouds(),
            stage_totals: m
                .stage_totals()
                .map(StageTimes::from_fb)
                .unwrap_or_default(),
            catch_up_ms: m.catch_up_ms(),
        })
    }
}
