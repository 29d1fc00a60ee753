//! Replays the committed fuzz corpus (`fuzz/corpus/<target>/`) through each fuzz target's own
//! decoding (`glasshouse_proto::fuzzing`), so the inputs the fuzzers found keep passing in a
//! plain `cargo test`: every file decodes or is a typed error, never a panic.

use glasshouse_proto::fuzzing::{target, TARGETS};

const PREFIX: &str = "proto_";

include!("../../../fuzz/replay.rs");
