//! Compressed versioned binary snapshot of a map.
//!
//! Layout (little endian):
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `GHRM` |
//! | 2 | format version (4) |
//! | 2 | kind: 0 snapshot |
//! | 8 | length of the compressed body in bytes |
//! | body | the LZ4 block (`lz4_flex`, uncompressed size as a u32 first) of the body below |
//! | 4 | CRC-32 (IEEE) of everything before it |
//!
//! Body: the configuration (`resolution_m` f64, hit, miss, clamp min, clamp max, ROI threshold,
//! ROI hit, ROI miss as f32, `max_range_m` f64 with −1 for none, the rule flags as a u8: bit 0
//! whether an ROI target needs an ROI neighbour, bit 1 whether far rays are merged), `scans_inserted` u64, the block count u32, then per
//! block its coordinate (3 × i32), its known mask (8 × u64, bit `z*64 + y*8 + x`) and the
//! occupancy, then the ROI log-odds of its known voxels: tag 0 and one f32 (all equal), tag 1, the
//! palette size − 1 (u8), the palette (f32 each) and each known voxel's index in bit order packed
//! LSB first in ⌈log2 size⌉ bits (padded to a byte), or tag 2 and one f32 per known voxel. Well
//! under one byte per known voxel on the glasshouse scans.
//!
//! A short file is [`SnapshotError::Truncated`]; any flipped bit is
//! [`SnapshotError::ChecksumMismatch`]; content that passes the checksum but is inconsistent is
//! [`SnapshotError::Corrupt`].

use std::io::{Read, Write};

use crate::grid::{for_each_bit, mask_count, Mask, BLOCK_VOXELS};
use crate::values::Values;
use crate::{ChangeLog, MapConfig, MapError, RoiMap, VoxelKey};

const MAGIC: &[u8; 4] = b"GHRM";
/// Current format version.
pub const FORMAT_VERSION: u16 = 4;
pub(crate) const KIND_SNAPSHOT: u16 = 0;
pub(crate) const KIND_DELTA: u16 = 1;
pub(crate) const HEADER_BYTES: usize = 16;

/// Errors reading or writing snapshots and deltas.
#[derive(thiserror::Error, Debug)]
pub enum SnapshotError {
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    #[error("not a Glasshouse map file (bad magic)")]
    BadMagic,
    #[error("unsupported map file version {0} (this build reads version {FORMAT_VERSION})")]
    UnsupportedVersion(u16),
    #[error("expected a map {expected}, found a {found}")]
    WrongKind {
        expected: &'static str,
        found: &'static str,
    },
    #[error("map file truncated: {expected} bytes expected, {actual} present")]
    Truncated { expected: u64, actual: u64 },
    #[error("map file corrupt: checksum {stored:#010x} stored, {computed:#010x} computed")]
    ChecksumMismatch { stored: u32, computed: u32 },
    #[error("map file corrupt: {0}")]
    Corrupt(String),
    #[error("map file has an invalid configuration: {0}")]
    Config(#[from] MapError),
    #[error("a delta on the map after {base} scans does not apply to a map after {scans}")]
    DeltaBase { base: u64, scans: u64 },
}

/// CRC-32 (IEEE 802.3, as zlib and PNG).
/// `crc32fast` picks the carry-less multiply (PCLMULQDQ) path where the CPU has it: the
/// byte-at-a-time table it replaced was a tenth of a snapshot's decode.
pub fn crc32(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

fn kind_name(kind: u16) -> &'static str {
    match kind {
        KIND_SNAPSHOT => "snapshot",
        KIND_DELTA => "delta",
        _ => "unknown kind",
    }
}

pub(crate) fn frame(kind: u16, body: &[u8], w: &mut impl Write) -> Result<(), SnapshotError> {
    let mut out = Vec::with_capacity(HEADER_BYTES + body.len() + 4);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    out.extend_from_slice(body);
    let crc = crc32(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    w.write_all(&out)?;
    Ok(())
}

/// Reads a whole framed file and returns its verified body.
pub(crate) fn unframe(expected_kind: u16, bytes: &[u8]) -> Result<&[u8], SnapshotError> {
    if bytes.len() < 4 || &bytes[..4] != MAGIC {
        if bytes.len() < 4 && MAGIC.starts_with(bytes) {
            return Err(SnapshotError::Truncated {
                expected: HEADER_BYTES as u64 + 4,
                actual: bytes.len() as u64,
            });
        }
        return Err(SnapshotError::BadMagic);
    }
    if bytes.len() < HEADER_BYTES {
        return Err(SnapshotError::Truncated {
            expected: HEADER_BYTES as u64 + 4,
            actual: bytes.len() as u64,
        });
    }
    let mut c = Cursor::new(&bytes[4..HEADER_BYTES]);
    let version = c.u16()?;
    if version != FORMAT_VERSION {
        return Err(SnapshotError::UnsupportedVersion(version));
    }
    let kind = c.u16()?;
    if kind != expected_kind {
        return Err(SnapshotError::WrongKind {
            expected: kind_name(expected_kind),
            found: kind_name(kind),
        });
    }
    let body_len = c.u64()?;
    let expected = (HEADER_BYTES as u64)
        .checked_add(body_len)
        .and_then(|v| v.checked_add(4))
        .ok_or_else(|| SnapshotError::Corrupt("body length overflows".into()))?;
    let actual = bytes.len() as u64;
    if actual < expected {
        return Err(SnapshotError::Truncated { expected, actual });
    }
    if actual > expected {
        return Err(SnapshotError::Corrupt(format!(
            "{} bytes after the checksum",
            actual - expected
        )));
    }
    let crc_at = bytes.len() - 4;
    let stored = u32::from_le_bytes([
        bytes[crc_at],
        bytes[crc_at + 1],
        bytes[crc_at + 2],
        bytes[crc_at + 3],
    ]);
    let computed = crc32(&bytes[..crc_at]);
    if stored != computed {
        return Err(SnapshotError::ChecksumMismatch { stored, computed });
    }
    Ok(&bytes[HEADER_BYTES..crc_at])
}

/// Little-endian reader over a verified body.
pub(crate) struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, at: 0 }
    }

    fn take<const N: usize>(&mut self) -> Result<[u8; N], SnapshotError> {
        let end = self.at + N;
        let slice = self
            .bytes
            .get(self.at..end)
            .ok_or_else(|| SnapshotError::Corrupt("body ends early".into()))?;
        self.at = end;
        let mut out = [0u8; N];
        out.copy_from_slice(slice);
        Ok(out)
    }

    fn slice(&mut self, n: usize) -> Result<&'a [u8], SnapshotError> {
        let end = self.at.saturating_add(n);
        let slice = self
            .bytes
            .get(self.at..end)
            .ok_or_else(|| SnapshotError::Corrupt("body ends early".into()))?;
        self.at = end;
        Ok(slice)
    }

    fn u8(&mut self) -> Result<u8, SnapshotError> {
        Ok(self.take::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, SnapshotError> {
        Ok(u16::from_le_bytes(self.take()?))
    }
    pub(crate) fn u32(&mut self) -> Result<u32, SnapshotError> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    pub(crate) fn u64(&mut self) -> Result<u64, SnapshotError> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn i32(&mut self) -> Result<i32, SnapshotError> {
        Ok(i32::from_le_bytes(self.take()?))
    }
    fn f32(&mut self) -> Result<f32, SnapshotError> {
        Ok(f32::from_le_bytes(self.take()?))
    }
    fn f64(&mut self) -> Result<f64, SnapshotError> {
        Ok(f64::from_le_bytes(self.take()?))
    }
    pub(crate) fn finished(&self) -> Result<(), SnapshotError> {
        if self.at == self.bytes.len() {
            Ok(())
        } else {
            Err(SnapshotError::Corrupt(format!(
                "{} unread bytes in the body",
                self.bytes.len() - self.at
            )))
        }
    }
}

/// Bits per palette index for a palette of `n` values (0 for a single value).
fn index_bits(n: usize) -> u32 {
    usize::BITS - (n.max(1) - 1).leading_zeros()
}

/// Appends one block's values: tag 0 = one value, 1 = palette (count − 1 as u8, the values,
/// then each known voxel's index in bit order, packed LSB first), 2 = each known voxel's value.
fn write_values(body: &mut Vec<u8>, values: &Values, known: &Mask) {
    match values.palette() {
        Some((pal, idx)) => {
            let (Some(idx), true) = (idx, pal.len() > 1) else {
                body.push(0);
                body.extend_from_slice(&pal[0].to_le_bytes());
                return;
            };
            body.push(1);
            body.push((pal.len() - 1) as u8);
            for v in pal {
                body.extend_from_slice(&v.to_le_bytes());
            }
            let bits = index_bits(pal.len());
            let (mut acc, mut filled) = (0u64, 0u32);
            for_each_bit(known, |l| {
                acc |= u64::from(idx[l]) << filled;
                filled += bits;
                if filled >= 32 {
                    body.extend_from_slice(&(acc as u32).to_le_bytes());
                    acc >>= 32;
                    filled -= 32;
                }
            });
            let tail = filled.div_ceil(8) as usize;
            body.extend_from_slice(&acc.to_le_bytes()[..tail]);
        }
        None => {
            body.push(2);
            for_each_bit(known, |l| {
                body.extend_from_slice(&values.get(l).to_le_bytes());
            });
        }
    }
}

/// Unpacks `out.len()` (at most 512) palette indices of `bits` (at most 8) bits each, packed
/// LSB first. The bytes are copied once into a zero-padded buffer so that each index is one
/// unaligned 16-bit read with no carried state: the loop runs at about a nanosecond an index.
fn unpack_indices(bytes: &[u8], bits: u32, out: &mut [u8]) {
    let mut padded = [0u8; 512 + 2];
    let n = bytes.len().min(512);
    padded[..n].copy_from_slice(&bytes[..n]);
    let mask = (1u16 << bits.min(8)) - 1;
    for (i, o) in out.iter_mut().take(512).enumerate() {
        let at = i * bits as usize;
        let byte = (at >> 3).min(512);
        let pair = u16::from_le_bytes([padded[byte], padded[byte + 1]]);
        *o = ((pair >> (at & 7)) & mask) as u8;
    }
}

/// Reads what [`write_values`] wrote.
fn read_values(c: &mut Cursor, known: &Mask) -> Result<Values, SnapshotError> {
    let finite = |v: f32| {
        v.is_finite()
            .then_some(v)
            .ok_or_else(|| SnapshotError::Corrupt("non-finite log-odds".into()))
    };
    match c.u8()? {
        0 => {
            let v = finite(c.f32()?)?;
            Ok(Values::uniform_on(v, known))
        }
        1 => {
            let n = usize::from(c.u8()?) + 1;
            let mut pal = Vec::with_capacity(n + 1);
            for _ in 0..n {
                pal.push(finite(c.f32()?)?);
            }
            let bits = index_bits(n);
            let packed = (mask_count(known) * bits as usize).div_ceil(8);
            let mut indices = [0u8; BLOCK_VOXELS];
            let indices = &mut indices[..mask_count(known)];
            unpack_indices(c.slice(packed)?, bits, indices);
            Values::from_palette(pal, known, indices)
                .ok_or_else(|| SnapshotError::Corrupt("palette index out of range".into()))
        }
        2 => {
            let mut err = None;
            let v = Values::from_known(known, || match c.f32().and_then(finite) {
                Ok(v) => v,
                Err(e) => {
                    err.get_or_insert(e);
                    0.0
                }
            });
            err.map_or(Ok(v), Err)
        }
        t => Err(SnapshotError::Corrupt(format!("unknown value tag {t}"))),
    }
}

impl RoiMap {
    /// Writes the whole map (configuration and voxels) as a compressed snapshot.
    pub fn write_snapshot(&self, mut w: impl Write) -> Result<(), SnapshotError> {
        let mut body = Vec::with_capacity(64 + self.known_count + self.store.blocks.len() * 100);
        self.write_header(&mut body);
        let blocks: Vec<usize> = (0..self.store.blocks.len())
            .filter(|&i| mask_count(&self.store.blocks[i].known) > 0)
            .collect();
        body.extend_from_slice(&(blocks.len() as u32).to_le_bytes());
        for i in blocks {
            self.write_block(i, &mut body);
        }
        let packed = lz4_flex::block::compress_prepend_size(&body);
        frame(KIND_SNAPSHOT, &packed, &mut w)
    }

    /// Checks a snapshot's framing (magic, version, kind, length) and checksum without decoding
    /// its body: a truncated or damaged snapshot fails here as it would in
    /// [`RoiMap::read_snapshot`].
    pub fn check_snapshot(bytes: &[u8]) -> Result<(), SnapshotError> {
        unframe(KIND_SNAPSHOT, bytes).map(|_| ())
    }

    /// Reads a snapshot written by [`RoiMap::write_snapshot`]. The restored map has no pending
    /// changes.
    pub fn read_snapshot(mut r: impl Read) -> Result<RoiMap, SnapshotError> {
        let mut bytes = Vec::new();
        r.read_to_end(&mut bytes)?;
        let body = unpack(unframe(KIND_SNAPSHOT, &bytes)?)?;
        drop(bytes);
        let mut c = Cursor::new(&body);
        let mut map = Self::read_header(&mut c)?;
        let n_blocks = c.u32()?;
        // A block takes more than 64 bytes (its coordinates and known mask alone take 76): a
        // damaged count cannot reserve more than the body holds.
        let room = (n_blocks as usize).min(body.len() / 64);
        let mut log = ChangeLog::with_capacity(room);
        map.store.reserve(room);
        for _ in 0..n_blocks {
            map.read_block(&mut c, &mut log)?;
        }
        c.finished()?;
        map.refresh_derived(&log);
        Ok(map)
    }

    /// Appends the configuration and the scan count (the body's first fields).
    pub(crate) fn write_header(&self, body: &mut Vec<u8>) {
        let c = &self.config;
        body.extend_from_slice(&c.resolution_m.to_le_bytes());
        for v in [
            c.hit_logodds,
            c.miss_logodds,
            c.clamp_min_logodds,
            c.clamp_max_logodds,
            c.roi_threshold_logodds,
            c.roi_hit_logodds,
            c.roi_miss_logodds,
        ] {
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&c.max_range_m.unwrap_or(-1.0).to_le_bytes());
        body.push(u8::from(c.roi_target_needs_neighbour) | u8::from(c.merge_far_rays) << 1);
        body.extend_from_slice(&self.scans_inserted.to_le_bytes());
    }

    /// Appends block `i`: its coordinate, known mask and values.
    pub(crate) fn write_block(&self, i: usize, body: &mut Vec<u8>) {
        let b = &self.store.blocks[i];
        let bk = self.store.coords[i];
        for v in [bk.x, bk.y, bk.z] {
            body.extend_from_slice(&v.to_le_bytes());
        }
        for w in b.known {
            body.extend_from_slice(&w.to_le_bytes());
        }
        write_values(body, &b.occ, &b.known);
        write_values(body, &b.roi, &b.known);
    }

    /// An empty map with the configuration and scan count [`RoiMap::write_header`] wrote.
    pub(crate) fn read_header(c: &mut Cursor) -> Result<RoiMap, SnapshotError> {
        let resolution_m = c.f64()?;
        let hit_logodds = c.f32()?;
        let miss_logodds = c.f32()?;
        let clamp_min_logodds = c.f32()?;
        let clamp_max_logodds = c.f32()?;
        let roi_threshold_logodds = c.f32()?;
        let roi_hit_logodds = c.f32()?;
        let roi_miss_logodds = c.f32()?;
        let max_range = c.f64()?;
        let flags = c.u8()?;
        if flags > 0b11 {
            return Err(SnapshotError::Corrupt(format!("rule flags {flags:#b}")));
        }
        let (roi_target_needs_neighbour, merge_far_rays) = (flags & 1 != 0, flags & 2 != 0);
        let config = MapConfig {
            resolution_m,
            hit_logodds,
            miss_logodds,
            clamp_min_logodds,
            clamp_max_logodds,
            roi_threshold_logodds,
            roi_hit_logodds,
            roi_miss_logodds,
            roi_target_needs_neighbour,
            max_range_m: (max_range >= 0.0).then_some(max_range),
            merge_far_rays,
        };
        let mut map = RoiMap::new(config)?;
        map.scans_inserted = c.u64()?;
        Ok(map)
    }

    /// Reads one block of a snapshot into a new block of the map.
    pub(crate) fn read_block(
        &mut self,
        c: &mut Cursor,
        log: &mut ChangeLog,
    ) -> Result<(), SnapshotError> {
        let record = BlockRecord::read(c)?;
        let bk = record.key;
        if self.store.index.contains_key(&bk) {
            return Err(SnapshotError::Corrupt(format!("block {bk:?} twice")));
        }
        let thr = self.config.roi_threshold_logodds;
        let bi = self.store.get_or_create(bk);
        let b = &mut self.store.blocks[bi];
        let known = record.known;
        b.occupied = record.occ.mask_where(&known, |v| v > 0.0);
        b.roi_mask = record.roi.mask_where(&known, |v| v >= thr);
        b.known = known;
        b.occ = record.occ;
        b.roi = record.roi;
        self.known_count += mask_count(&known);
        self.occupied_count += mask_count(&b.occupied);
        log.note(bi as u32, &known, &b.roi_mask);
        Ok(())
    }
}

/// One block as a snapshot or a delta writes it ([`RoiMap::write_block`]), read and checked.
pub(crate) struct BlockRecord {
    pub key: VoxelKey,
    pub known: Mask,
    pub occ: Values,
    pub roi: Values,
}

impl BlockRecord {
    pub(crate) fn read(c: &mut Cursor) -> Result<Self, SnapshotError> {
        let key = VoxelKey::new(c.i32()?, c.i32()?, c.i32()?);
        let key_ok = |v: i32| (-(1 << 17)..(1 << 17)).contains(&v);
        if !(key_ok(key.x) && key_ok(key.y) && key_ok(key.z)) {
            return Err(SnapshotError::Corrupt(format!(
                "block {key:?} out of range"
            )));
        }
        let mut known: Mask = [0; 8];
        for w in &mut known {
            *w = c.u64()?;
        }
        let occ = read_values(c, &known)?;
        let roi = read_values(c, &known)?;
        Ok(Self {
            key,
            known,
            occ,
            roi,
        })
    }
}

/// Decompresses a verified body, refusing a stated size no LZ4 block could expand to.
pub(crate) fn unpack(packed: &[u8]) -> Result<Vec<u8>, SnapshotError> {
    let corrupt = |m: &str| SnapshotError::Corrupt(m.into());
    let size = packed
        .get(..4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
        .ok_or_else(|| corrupt("body ends early"))?;
    // LZ4 expands at most about 255 times.
    if size > packed.len().saturating_mul(256) + 64 {
        return Err(corrupt("stated size does not fit the compressed body"));
    }
    lz4_flex::block::decompress(&packed[4..], size).map_err(|e| corrupt(&e.to_string()))
}
