"""Pixel planes of a glasshouse RgbdFrame: the Python twin of `glasshouse_proto::pixels`.

Every Python reader of frame pixels goes through `rgbd_planes`, which handles each plane's
`ImageEncoding` (Raw, or LeftDeltaZstd: wrapping left delta per channel, the first column
predicted from the row above, little-endian, one zstd frame with a content checksum).
Needs numpy and zstandard (`pip install zstandard==0.25.0`).
"""

import numpy as np
import zstandard

from glasshouse.wire.ImageEncoding import ImageEncoding


class PixelDecodeError(ValueError):
    """A plane that is missing, corrupt, truncated or of the wrong size."""


def _undo_left_delta(residuals, height, width, channels):
    r = residuals.reshape(height, width, channels).copy()
    # The first column is predicted from the sample above, the rest from the left.
    r[:, 0, :] = np.cumsum(r[:, 0, :], axis=0, dtype=r.dtype)
    return np.cumsum(r, axis=1, dtype=r.dtype).reshape(-1)


def decode_plane(encoding, raw, encoded, height, width, channels, dtype):
    """One plane as a flat numpy array of `height * width * channels` samples of `dtype`.

    `raw` and `encoded` are callables returning the frame's raw vector (numpy) and encoded
    bytes (numpy uint8), or 0 when absent (flatc's `...AsNumpy` accessors).
    """
    samples = height * width * channels
    dtype = np.dtype(dtype).newbyteorder("<")
    if encoding == ImageEncoding.Raw:
        plane = raw()
        if isinstance(plane, int):
            raise PixelDecodeError("the raw plane is missing")
    elif encoding == ImageEncoding.LeftDeltaZstd:
        data = encoded()
        if isinstance(data, int):
            raise PixelDecodeError("the encoded plane is missing")
        try:
            out = zstandard.ZstdDecompressor().decompress(
                data.tobytes(), max_output_size=samples * dtype.itemsize
            )
        except zstandard.ZstdError as e:
            raise PixelDecodeError(f"zstd: {e}") from e
        if len(out) != samples * dtype.itemsize:
            raise PixelDecodeError(f"{len(out) // dtype.itemsize} samples, {samples} expected")
        plane = _undo_left_delta(np.frombuffer(out, dtype=dtype), height, width, channels)
    else:
        raise PixelDecodeError(f"unknown image encoding {encoding}")
    if plane.size != samples:
        raise PixelDecodeError(f"{plane.size} samples, {samples} expected")
    return plane


def rgbd_planes(frame):
    """(depth uint16 of shape (height, width), rgb uint8 of shape (height, width, 3)) of a
    `glasshouse.wire.RgbdFrame` table, whatever each plane's encoding."""
    k = frame.Intrinsics()
    h, w = k.Height(), k.Width()
    depth = decode_plane(frame.DepthEncoding(), frame.DepthAsNumpy, frame.DepthEncodedAsNumpy,
                         h, w, 1, np.uint16)
    rgb = decode_plane(frame.RgbEncoding(), frame.RgbAsNumpy, frame.RgbEncodedAsNumpy,
                       h, w, 3, np.uint8)
    return depth.reshape(h, w), rgb.reshape(h, w, 3)
