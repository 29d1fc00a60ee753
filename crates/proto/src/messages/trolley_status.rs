//! TrolleyStatus: the edge's loop state and counters, edge → dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{payload, string_or_empty, unknown_enum};
use crate::{fb, MessageKind, Result, Wire};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrolleyState {
    Starting,
    Capturing,
    WaitingForViews,
    Moving,
    Done,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrolleyStatus {
    pub state: TrolleyState,
    pub views_done: u32,
    pub frames_published: u64,
    pub unreachable_views: u32,
    pub reannounces: u32,
    pub dropped_messages: u64,
    pub last_views_seq: u64,
    pub message: String,
    /// RankedViews refused because they did not come from the planner owning the trolley.
    pub refused_views: u64,
    /// RankedViews refused because their ownership epoch was older than the newest taken.
    pub stale_views: u64,
    /// The newest ownership epoch views were taken under (0: none yet).
    pub owner_epoch: u64,
    /// Views executed per ownership term, oldest first (the last [`OWNER_TERMS`] terms).
    pub owner_terms: Vec<OwnerTerm>,
}

/// Ownership terms a [`TrolleyStatus`] lists at most (the newest).
pub const OWNER_TERMS: usize = 16;

/// Views a trolley executed during one ownership term.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct OwnerTerm {
    pub planner_id: String,
    pub owner_epoch: u64,
    pub views_executed: u32,
}

fn state_to_fb(state: TrolleyState) -> fb::TrolleyState {
    match state {
        TrolleyState::Starting => fb::TrolleyState::Starting,
        TrolleyState::Capturing => fb::TrolleyState::Capturing,
        TrolleyState::WaitingForViews => fb::TrolleyState::WaitingForViews,
        TrolleyState::Moving => fb::TrolleyState::Moving,
        TrolleyState::Done => fb::TrolleyState::Done,
    }
}

fn state_from_fb(state: fb::TrolleyState) -> Result<TrolleyState> {
    match state {
        fb::TrolleyState::Starting => Ok(TrolleyState::Starting),
        fb::TrolleyState::Capturing => Ok(TrolleyState::Capturing),
        fb::TrolleyState::WaitingForViews => Ok(TrolleyState::WaitingForViews),
        fb::TrolleyState::Moving => Ok(TrolleyState::Moving),
        fb::TrolleyState::Done => Ok(TrolleyState::Done),
        other => Err(unknown_enum(MessageKind::TrolleyStatus, "trolley state", other.0)),
    }
}

impl Wire for TrolleyStatus {
    const KIND: MessageKind = MessageKind::TrolleyStatus;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let message = fbb.create_string(&self.message);
        let terms: Vec<_> = self
            .owner_terms
            .iter()
            .map(|t| {
                let planner_id = fbb.create_string(&t.planner_id);
                fb::OwnerTerm::create(
                    fbb,
                    &fb::OwnerTermArgs {
                        planner_id: Some(planner_id),
                        owner_epoch: t.owner_epoch,
                        views_executed: t.views_executed,
                    },
                )
            })
            .collect();
        let terms = fbb.create_vector(&terms);
        fb::TrolleyStatus::create(
            fbb,
            &fb::TrolleyStatusArgs {
                state: state_to_fb(self.state),
                views_done: self.views_done,
                frames_published: self.frames_published,
                unreachable_views: self.unreachable_views,
                reannounces: self.reannounces,
                dropped_messages: self.dropped_messages,
                last_views_seq: self.last_views_seq,
                message: Some(message),
                refused_views: self.refused_views,
                stale_views: self.stale_views,
                owner_epoch: self.owner_epoch,
                owner_terms: Some(terms),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_trolley_status())?;
        Ok(TrolleyStatus {
            state: state_from_fb(m.state())?,
            views_done: m.views_done(),
            frames_published: m.frames_published(),
            unreachable_views: m.unreachable_views(),
            reannounces: m.reannounces(),
            dropped_messages: m.dropped_messages(),
            last_views_seq: m.last_views_seq(),
            message: string_or_empty(m.message()),
            refused_views: m.refused_views(),
            stale_views: m.stale_views(),
            owner_epoch: m.owner_epoch(),
            owner_terms: m
                .owner_terms()
                .map(|ts| {
                    ts.iter()
                        .map(|t| OwnerTerm {
                            planner_id: string_or_empty(t.planner_id()),
                            owner_epoch: t.owner_epoch(),
                            views_executed: t.views_executed(),
                        })
                        .collect()
                })
                .unwrap_or_default(),
        })
    }
}
