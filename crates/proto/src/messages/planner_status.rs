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
    /// Registrations of the clouds of the trolleys it owns now (made as their owner, or as
    /// their replica before), by verdict.
    pub registrations: RegistrationTotals,
    /// Messages dropped because they came under an older ownership epoch than the newest this
    /// planner had seen for their trolley (fruit estimates, map snapshots).
    pub stale_epoch: u64,
    /// Times it stopped owning a trolley on seeing a newer ownership epoch than its own term,
    /// and caught up from a snapshot before planning again.
    pub stepped_down: u64,
    /// RoiClouds refused because the detector that sent them (the id its key ends in) does not
    /// serve their trolley by the detectors' ranking, or their header names another source.
    pub unassigned_clouds: u64,
    /// RoiClouds integrated without colour: their `roi_rgb` was not 3 bytes per ROI point
    /// ([`crate::RoiColours::WrongLength`]).
    pub colourless_clouds: u64,
    /// Standby copies decoded ahead of a takeover (on an idle-class thread) and kept.
    pub standby_decodes_ahead: u64,
    /// Takeovers that adopted a copy decoded ahead instead of decoding the snapshot then.
    pub decoded_ahead_adopted: u64,
}

/// Clouds registered to their maps, by verdict (see [`crate::RegistrationVerdict`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RegistrationTotals {
    /// Inserted with the correction applied.
    pub applied: u64,
    /// Inserted as sent: the estimate was too small to tell, or failed a check the scan as
    /// sent passes.
    pub kept_as_sent: u64,
    /// Not inserted.
    pub rejected: u64,
    /// Not checked (registration off included), inserted as sent.
    pub skipped: u64,
}

impl RegistrationTotals {
    pub fn total(&self) -> u64 {
        self.applied + self.kept_as_sent + self.rejected + self.skipped
    }
}

impl std::ops::AddAssign for RegistrationTotals {
    fn add_assign(&mut self, other: Self) {
        self.applied += other.applied;
        self.kept_as_sent += other.kept_as_sent;
        self.rejected += other.rejected;
        self.skipped += other.skipped;
    }
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

    /// The time each stage took since `before`, an earlier reading of the same running totals.
    pub fn since(&self, before: &StageTimes) -> StageTimes {
        StageTimes {
            integrate_ms: self.integrate_ms - before.integrate_ms,
            cluster_ms: self.cluster_ms - before.cluster_ms,
            track_ms: self.track_ms - before.track_ms,
            fit_ms: self.fit_ms - before.fit_ms,
            plan_ms: self.plan_ms - before.plan_ms,
            publish_ms: self.publish_ms - before.publish_ms,
        }
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
                registration_applied: self.registrations.applied,
                registration_kept_as_sent: self.registrations.kept_as_sent,
                registration_rejected: self.registrations.rejected,
                registration_skipped: self.registrations.skipped,
                stale_epoch: self.stale_epoch,
                stepped_down: self.stepped_down,
                unassigned_clouds: self.unassigned_clouds,
                colourless_clouds: self.colourless_clouds,
                standby_decodes_ahead: self.standby_decodes_ahead,
                decoded_ahead_adopted: self.decoded_ahead_adopted,
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
            registrations: RegistrationTotals {
                applied: m.registration_applied(),
                kept_as_sent: m.registration_kept_as_sent(),
                rejected: m.registration_rejected(),
                skipped: m.registration_skipped(),
            },
            stale_epoch: m.stale_epoch(),
            stepped_down: m.stepped_down(),
            unassigned_clouds: m.unassigned_clouds(),
            colourless_clouds: m.colourless_clouds(),
            standby_decodes_ahead: m.standby_decodes_ahead(),
            decoded_ahead_adopted: m.decoded_ahead_adopted(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{decode_typed, encode, samples, Message};

    #[test]
    fn the_stages_since_an_earlier_reading_are_the_differences() {
        let earlier = StageTimes {
            integrate_ms: 10.0,
            fit_ms: 2.0,
            ..StageTimes::default()
        };
        let later = StageTimes {
            integrate_ms: 25.0,
            cluster_ms: 1.0,
            fit_ms: 2.5,
            publish_ms: 4.0,
            ..StageTimes::default()
        };
        let lap = later.since(&earlier);
        assert_eq!(
            lap.named().map(|(_, ms)| ms),
            [15.0, 1.0, 0.0, 0.5, 0.0, 4.0]
        );
        assert_eq!(later.since(&later).total_ms(), 0.0);
    }

    /// A PlannerStatus as a planner from before the registration totals writes it.
    #[derive(Clone, Debug)]
    struct OldSender(PlannerStatus);

    impl From<OldSender> for Message {
        fn from(old: OldSender) -> Self {
            Message::PlannerStatus(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::PlannerStatus;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let s = &self.0;
            let pid = fbb.create_string(&s.planner_id);
            let owned = strings(fbb, &s.owned_trolleys);
            let standby = strings(fbb, &s.standby_trolleys);
            let stages = s.stage_totals.to_fb();
            // In the order flatc's `create` of the table without the totals added them.
            let mut table = fb::PlannerStatusBuilder::new(fbb);
            table.add_catch_up_ms(s.catch_up_ms);
            table.add_refused_clouds(s.refused_clouds);
            table.add_map_voxels(s.map_voxels);
            table.add_dropped_messages(s.dropped_messages);
            table.add_views_published(s.views_published);
            table.add_clouds_integrated(s.clouds_integrated);
            table.add_stage_totals(&stages);
            table.add_mean_planning_time_ms(s.mean_planning_time_ms);
            table.add_last_planning_time_ms(s.last_planning_time_ms);
            table.add_standby_trolleys(standby);
            table.add_owned_trolleys(owned);
            table.add_planner_id(pid);
            table.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            PlannerStatus::read_payload(envelope).map(OldSender)
        }
    }

    #[test]
    fn the_registration_totals_round_trip() {
        let sample = samples::planner_status();
        assert_eq!(sample.registrations.total(), 10);
        let bytes = encode(&samples::header(2), &sample);
        assert_eq!(
            decode_typed::<PlannerStatus>(&bytes).expect("decodes").1,
            sample
        );
    }

    #[test]
    fn a_status_from_a_sender_without_registration_totals_reads_zero() {
        // Nor the fencing counts, the unassigned and the colourless clouds, the decodes
        // ahead, which came later.
        let sample = PlannerStatus {
            stale_epoch: 0,
            stepped_down: 0,
            unassigned_clouds: 0,
            colourless_clouds: 0,
            standby_decodes_ahead: 0,
            decoded_ahead_adopted: 0,
            ..samples::planner_status()
        };
        let old = encode(&samples::header(2), &OldSender(sample.clone()));
        let (_, read) =
            decode_typed::<PlannerStatus>(&old).expect("an old sender's status decodes");
        let without = PlannerStatus {
            registrations: RegistrationTotals::default(),
            ..sample
        };
        assert_eq!(read, without);
        // A status with no registrations is byte for byte what the older planner sent.
        assert_eq!(encode(&samples::header(2), &without), old);
    }

    #[test]
    fn totals_add_verdict_by_verdict() {
        let mut sum = samples::planner_status().registrations;
        sum += RegistrationTotals {
            applied: 1,
            kept_as_sent: 2,
            rejected: 3,
            skipped: 4,
        };
        let expected = RegistrationTotals {
            applied: 7,
            kept_as_sent: 4,
            rejected: 4,
            skipped: 5,
        };
        assert_eq!((sum, sum.total()), (expected, 20));
    }
}
