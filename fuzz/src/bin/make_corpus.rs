//! Writes the seed corpus: `cargo run --manifest-path fuzz/Cargo.toml --bin make_corpus`.
//!
//! Every seed is a valid encoding made by the crates' own encoders (`fuzzing::seeds` of
//! glasshouse-proto and glasshouse-roimap), written as `fuzz/corpus/<target>/<name>`.

use std::path::Path;

fn main() -> std::io::Result<()> {
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("corpus");
    let seeds = glasshouse_proto::fuzzing::seeds()
        .into_iter()
        .chain(glasshouse_roimap::fuzzing::seeds());
    for (target, name, bytes) in seeds {
        let dir = corpus.join(target);
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join(&name), &bytes)?;
        println!("{target}/{name}: {} bytes", bytes.len());
    }
    Ok(())
}
