//! Writes one encoded sample of every message kind to a folder (`<Kind>.ghw`), for readers in
//! other languages to check against (see `scripts/check-python-proto`).

use glasshouse_proto::{encode_any, samples, MessageKind};

fn main() -> std::io::Result<()> {
    let dir = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "proto-samples".into());
    std::fs::create_dir_all(&dir)?;
    for kind in MessageKind::ALL {
        let bytes = encode_any(&samples::header(7), &samples::message(kind));
        std::fs::write(format!("{dir}/{kind}.ghw"), bytes)?;
    }
    println!("wrote {} samples to {dir}", MessageKind::ALL.len());
    Ok(())
}
