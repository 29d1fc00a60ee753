//! Writes one encoded sample of every message kind to a folder (`<Kind>.ghw`), for readers in
//! other languages to check against (see `scripts/check-python-proto`), and the RgbdFrame with
//! compressed planes as `compressed/RgbdFrame.ghw`.

use glasshouse_proto::{encode, encode_any, samples, ImageEncoding, MessageKind};

fn main() -> std::io::Result<()> {
    let dir = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "proto-samples".into());
    std::fs::create_dir_all(&dir)?;
    for kind in MessageKind::ALL {
        let bytes = encode_any(&samples::header(7), &samples::message(kind));
        std::fs::write(format!("{dir}/{kind}.ghw"), bytes)?;
    }
    std::fs::create_dir_all(format!("{dir}/compressed"))?;
    let compressed = samples::rgbd_frame().encoded_as(ImageEncoding::LeftDeltaZstd);
    let bytes = encode(&samples::header(7), &compressed);
    std::fs::write(format!("{dir}/compressed/RgbdFrame.ghw"), bytes)?;
    println!("wrote {} samples to {dir}", MessageKind::ALL.len());
    Ok(())
}
