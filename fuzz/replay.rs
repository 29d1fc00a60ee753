// The corpus replay shared by `crates/{proto,roimap}/tests/fuzz_corpus.rs`, which include it after
// naming their crate's `target`, `TARGETS` and target-name `PREFIX`.

use std::path::{Path, PathBuf};

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz")
}

#[test]
fn every_corpus_file_decodes_or_is_a_typed_error() {
    let mut failures = Vec::new();
    for t in TARGETS {
        let dir = fuzz_dir().join("corpus").join(t.name);
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        let (mut files, mut decoded) = (0, 0);
        for entry in entries {
            let path = entry.expect("corpus entry").path();
            let bytes = std::fs::read(&path).expect("corpus file reads");
            files += 1;
            match std::panic::catch_unwind(|| (t.run)(&bytes)) {
                Ok(Ok(())) => decoded += 1,
                Ok(Err(_)) => {}
                Err(_) => failures.push(path.display().to_string()),
            }
        }
        assert!(files > 0, "{} is empty", dir.display());
        // The seeds are valid encodings: a corpus none of which decodes tests only the errors.
        assert!(decoded > 0, "no file of {} decodes", dir.display());
    }
    assert!(failures.is_empty(), "panicked on {failures:#?}");
}

#[test]
fn every_fuzz_target_of_this_crate_is_replayed() {
    let dir = fuzz_dir().join("fuzz_targets");
    let mut files = 0;
    for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.expect("fuzz_targets entry").path();
        let Some(name) = path.file_stem().and_then(|s| s.to_str()) else {
            continue;
        };
        if name.starts_with(PREFIX) {
            files += 1;
            assert!(target(name).is_some(), "{name} is not in fuzzing::TARGETS");
        }
    }
    assert_eq!(
        files,
        TARGETS.len(),
        "fuzz targets named {PREFIX}* vs fuzzing::TARGETS"
    );
}
