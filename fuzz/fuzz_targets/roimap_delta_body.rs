#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // Errors are the expected outcome; panics (including failed checks) are the findings.
    let _ = glasshouse_roimap::fuzzing::delta_body(data);
});
