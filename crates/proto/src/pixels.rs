//! Pixel planes of an RgbdFrame on the wire: raw, or a left-delta predictor and zstd (lossless).
//!
//! The simulator's colour is flat-shaded (long runs of equal pixels) and its depth carries noise
//! that grows with distance, so a byte-level LZ coder alone gains little on depth: the left delta
//! turns smooth surfaces into small residuals and zstd's entropy stage packs them (figures in the
//! crate's README). [`decode_plane`] is the one decoder every reader goes through (the
//! RgbdFrame decoder calls it); `glasshouse_pixels.py` beside the Python code is its Python twin.

/// How one pixel plane travels (`ImageEncoding` of the schema).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ImageEncoding {
    /// The samples as they are.
    #[default]
    Raw,
    /// Each sample minus its left neighbour of the same channel (first column: minus the sample
    /// above), wrapping, little-endian, in one zstd frame.
    LeftDeltaZstd,
}

/// zstd level of [`ImageEncoding::LeftDeltaZstd`]: level 3 saves ~4 % more on depth at about
/// twice the encoding time.
const ZSTD_LEVEL: i32 = 1;

/// Why an encoded plane could not be decoded.
#[derive(thiserror::Error, Debug, Clone, PartialEq, Eq)]
pub enum PixelCodecError {
    #[error("unknown image encoding {0}")]
    UnknownEncoding(u8),
    #[error("the encoded plane is missing")]
    Missing,
    #[error("zstd: {0}")]
    Zstd(String),
    #[error("{found} samples, {expected} expected")]
    Length { expected: usize, found: usize },
}

/// One sample type of a plane: depth is `u16`, colour `u8`.
pub trait Sample: Copy + Default {
    const BYTES: usize;
    fn wrapping_sub(self, other: Self) -> Self;
    fn wrapping_add(self, other: Self) -> Self;
    fn put_le(self, out: &mut Vec<u8>);
    /// `bytes` holds exactly [`Self::BYTES`] bytes.
    fn from_le(bytes: &[u8]) -> Self;
}

macro_rules! impl_sample {
    ($($t:ty),+) => {$(
        impl Sample for $t {
            const BYTES: usize = std::mem::size_of::<$t>();
            fn wrapping_sub(self, other: Self) -> Self {
                <$t>::wrapping_sub(self, other)
            }
            fn wrapping_add(self, other: Self) -> Self {
                <$t>::wrapping_add(self, other)
            }
            fn put_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn from_le(bytes: &[u8]) -> Self {
                bytes.try_into().map_or(0, <$t>::from_le_bytes)
            }
        }
    )+};
}

impl_sample!(u8, u16);

/// The shape of a plane: `channels` interleaved samples per pixel, `width` pixels per row.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlaneShape {
    pub width: usize,
    pub channels: usize,
}

/// Encodes a plane as [`ImageEncoding::LeftDeltaZstd`]; `None` when zstd cannot allocate its
/// context (the writer then sends the plane raw).
pub fn encode_plane<T: Sample>(samples: &[T], shape: PlaneShape) -> Option<Vec<u8>> {
    let mut residuals = Vec::with_capacity(samples.len() * T::BYTES);
    let row_len = (shape.width * shape.channels).max(1);
    let mut above: &[T] = &[];
    for row in samples.chunks(row_len) {
        for (x, &s) in row.iter().enumerate() {
            let predicted = if x >= shape.channels {
                row[x - shape.channels]
            } else {
                above.get(x).copied().unwrap_or_default()
            };
            s.wrapping_sub(predicted).put_le(&mut residuals);
        }
        above = row;
    }
    compress(&residuals).ok()
}

/// One zstd frame with its content checksum, so a corrupted plane fails to decode instead of
/// decoding to other pixels. Fails only when zstd cannot allocate its context.
fn compress(bytes: &[u8]) -> std::io::Result<Vec<u8>> {
    let mut compressor = zstd::bulk::Compressor::new(ZSTD_LEVEL)?;
    compressor.set_parameter(zstd::zstd_safe::CParameter::ChecksumFlag(true))?;
    compressor.compress(bytes)
}

/// Decodes a plane of `samples` samples stored as `encoding` (the raw plane, when `Raw`, is
/// read by the caller). Corrupt, truncated or oversized input is an error, never a panic, and
/// never allocates more than the expected plane.
pub fn decode_plane<T: Sample>(
    encoded: &[u8],
    shape: PlaneShape,
    samples: usize,
) -> Result<Vec<T>, PixelCodecError> {
    if shape.width == 0 || shape.channels == 0 {
        return Err(PixelCodecError::Length {
            expected: samples,
            found: 0,
        });
    }
    let residuals = zstd::bulk::decompress(encoded, samples * T::BYTES)
        .map_err(|e| PixelCodecError::Zstd(e.to_string()))?;
    if residuals.len() != samples * T::BYTES {
        return Err(PixelCodecError::Length {
            expected: samples,
            found: residuals.len() / T::BYTES,
        });
    }
    let mut plane: Vec<T> = residuals.chunks_exact(T::BYTES).map(T::from_le).collect();
    let row_len = shape.width * shape.channels;
    for start in (0..plane.len()).step_by(row_len) {
        let end = (start + row_len).min(plane.len());
        if start >= row_len {
            let (done, row) = plane.split_at_mut(start);
            let above = &done[start - row_len..];
            for x in 0..shape.channels.min(end - start) {
                row[x] = row[x].wrapping_add(above[x]);
            }
        }
        let row = &mut plane[start..end];
        for x in shape.channels..row.len() {
            row[x] = row[x].wrapping_add(row[x - shape.channels]);
        }
    }
    Ok(plane)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    const DEPTH: PlaneShape = PlaneShape {
        width: 4,
        channels: 1,
    };
    const RGB: PlaneShape = PlaneShape {
        width: 4,
        channels: 3,
    };

    fn depth() -> Vec<u16> {
        vec![0, 1200, 1201, 65535, 3, 0, 7, 7, 500, 499, 0, 65535]
    }

    #[test]
    fn planes_round_trip_bit_for_bit() {
        let d = depth();
        let back: Vec<u16> =
            decode_plane(&encode_plane(&d, DEPTH).unwrap(), DEPTH, d.len()).unwrap();
        assert_eq!(back, d);
        let rgb: Vec<u8> = (0..36).map(|i| (i * 37 % 256) as u8).collect();
        let back: Vec<u8> =
            decode_plane(&encode_plane(&rgb, RGB).unwrap(), RGB, rgb.len()).unwrap();
        assert_eq!(back, rgb);
    }

    /// Index of the sample that predicts sample `i` (the format's definition): the same channel
    /// of the pixel to the left, in the first column the one above; `None` for the first pixel.
    fn predictor(shape: PlaneShape, i: usize) -> Option<usize> {
        let row_len = shape.width * shape.channels;
        if i % row_len >= shape.channels {
            Some(i - shape.channels)
        } else {
            i.checked_sub(row_len)
        }
    }

    #[test]
    fn the_residuals_follow_the_definition() {
        let rgb: Vec<u8> = (0..36).map(|i| (i * 53 % 256) as u8).collect();
        let encoded = encode_plane(&rgb, RGB).unwrap();
        let residuals = zstd::bulk::decompress(&encoded, rgb.len()).unwrap();
        for (i, r) in residuals.iter().enumerate() {
            let predicted = predictor(RGB, i).map_or(0, |p| rgb[p]);
            assert_eq!(*r, rgb[i].wrapping_sub(predicted), "sample {i}");
        }
    }

    #[test]
    fn predictor_is_left_then_above() {
        assert_eq!(predictor(RGB, 0), None);
        assert_eq!(predictor(RGB, 2), None);
        assert_eq!(predictor(RGB, 3), Some(0));
        assert_eq!(predictor(RGB, 12), Some(0));
        assert_eq!(predictor(RGB, 14), Some(2));
        assert_eq!(predictor(DEPTH, 5), Some(4));
        assert_eq!(predictor(DEPTH, 4), Some(0));
    }

    #[test]
    fn every_truncation_is_an_error() {
        let d = depth();
        let encoded = encode_plane(&d, DEPTH).unwrap();
        for len in 0..encoded.len() {
            assert!(
                decode_plane::<u16>(&encoded[..len], DEPTH, d.len()).is_err(),
                "{len}"
            );
        }
    }

    #[test]
    fn corrupt_input_is_an_error() {
        let d = depth();
        let encoded = encode_plane(&d, DEPTH).unwrap();
        for i in 0..encoded.len() {
            for flip in [1u8, 0x80, 0xff] {
                let mut bad = encoded.clone();
                bad[i] ^= flip;
                assert!(
                    decode_plane::<u16>(&bad, DEPTH, d.len()).is_err(),
                    "byte {i}"
                );
            }
        }
        assert!(matches!(
            decode_plane::<u16>(b"not zstd at all", DEPTH, d.len()),
            Err(PixelCodecError::Zstd(_))
        ));
    }

    #[test]
    fn a_plane_of_another_size_is_a_length_error() {
        let d = depth();
        let encoded = encode_plane(&d, DEPTH).unwrap();
        assert!(matches!(
            decode_plane::<u16>(&encoded, DEPTH, d.len() + 1),
            Err(PixelCodecError::Length { .. })
        ));
        // More data than expected must not be decoded into a larger buffer.
        assert!(decode_plane::<u16>(&encoded, DEPTH, d.len() - 1).is_err());
        assert!(decode_plane::<u16>(
            &encoded,
            PlaneShape {
                width: 0,
                channels: 1
            },
            12
        )
        .is_err());
    }
}
