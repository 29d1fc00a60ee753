//! Replays the committed fuzz corpus (`fuzz/corpus/<target>/`) through each fuzz target's own
//! decoding (`glasshouse_roimap::fuzzing`), so the inputs the fuzzers found keep passing in a
//! plain `cargo test`: every file decodes or is a typed error, never a panic.

use glasshouse_roimap::fuzzing::{target, TARGETS};

const PREFIX: &str = "roimap_";

include!("../../../fuzz/replay.rs");
