"""PNG decoding for the sequence readers: 16-bit greyscale (depth), 8-bit greyscale and RGB (colour), by hand.

Depth and colour PNGs are read on every frame of a recorded sequence. For the
two kinds the datasets use (non-interlaced 16-bit grey, 8-bit RGB) the chunks
are walked here, the image data inflated at once (ISA-L's inflate when
installed) and unfiltered by a compiled loop; any other PNG gives None, and
the caller reads it with Pillow. What it saves against Pillow and zlib:
docs/benchmarks.md, section "Sources of depth frames: recorded sequences in
the loop".
"""

from __future__ import annotations

import struct
import zlib

import numba
import numpy as np

try:  # ISA-L's inflate, faster than zlib's on depth PNGs, when installed
    from isal.isal_zlib import decompress as _inflate
except ImportError:  # pragma: no cover (depends on the environment)
    _inflate = zlib.decompress

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@numba.njit(cache=True, nogil=True)
def _unfilter_rows(filtered: np.ndarray, height: int, stride: int, bpp: int, out: np.ndarray) -> bool:
    """Undo PNG's per-row filters (None, Sub, Up, Average, Paeth) into ``out`` (height, stride) bytes; False on a bad filter type."""
    previous = np.zeros(stride, dtype=np.uint8)  # the row above the first is zeros
    for y in range(height):
        start = y * (stride + 1) + 1
        kind = filtered[start - 1]
        row = filtered[start : start + stride]
        current = out[y]
        if y > 0:
            previous = out[y - 1]
        if kind == 0:
            current[:] = row
        elif kind == 1:
            for x in range(bpp):
                current[x] = row[x]
            for x in range(bpp, stride):
                current[x] = (row[x] + current[x - bpp]) & 0xFF
        elif kind == 2:
            for x in range(stride):
                current[x] = (row[x] + previous[x]) & 0xFF
        elif kind == 3:
            for x in range(bpp):
                current[x] = (row[x] + (previous[x] >> 1)) & 0xFF
            for x in range(bpp, stride):
                current[x] = (np.int32(row[x]) + ((np.int32(current[x - bpp]) + np.int32(previous[x])) >> 1)) & 0xFF
        elif kind == 4:
            for x in range(bpp):
                current[x] = (row[x] + previous[x]) & 0xFF  # Paeth with a = c = 0 predicts b
            for x in range(bpp, stride):
                a, b, c = np.int32(current[x - bpp]), np.int32(previous[x]), np.int32(previous[x - bpp])
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                predictor = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                current[x] = (np.int32(row[x]) + predictor) & 0xFF
        else:
            return False
    return True


def _decode_png(data: bytes, bit_depth: int, colour_type: int, channels: int) -> np.ndarray | None:
    """The pixels of a non-interlaced PNG of ``bit_depth`` and ``colour_type`` (0 grey, 2 RGB) as (H, W * channels *
    bytes) uint8 rows; None for any other PNG (Pillow reads those).

    Chunks are walked by hand, the image data inflated at once (ISA-L when
    installed) and unfiltered by a compiled loop, faster than Pillow (the
    figures: docs/benchmarks.md, "Sources of depth frames"). CRCs are not
    checked; a truncated or inconsistent stream raises ValueError.
    """
    if data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
        return None
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if depth != bit_depth or colour != colour_type or interlace != 0:
        return None
    parts, position = [], 8
    while position + 8 <= len(data):
        (length,) = struct.unpack(">I", data[position : position + 4])
        kind = data[position + 4 : position + 8]
        if kind == b"IDAT":
            parts.append(data[position + 8 : position + 8 + length])
        elif kind == b"IEND":
            break
        position += 12 + length
    bpp = channels * bit_depth // 8
    stride = bpp * width
    try:
        filtered = np.frombuffer(_inflate(b"".join(parts)), dtype=np.uint8)
    except Exception as exc:  # noqa: BLE001 (zlib.error, isal's IsalError)
        raise ValueError(f"corrupt image data: {exc}") from None
    if filtered.size < height * (stride + 1):
        raise ValueError(f"image data holds {filtered.size} bytes, a {width}x{height} image needs {height * (stride + 1)}")
    out = np.empty((height, stride), dtype=np.uint8)
    if not _unfilter_rows(filtered, height, stride, bpp, out):
        raise ValueError("unknown PNG row filter")
    return out


def decode_gray16_png(data: bytes) -> np.ndarray | None:
    """uint16 (H, W) of a non-interlaced 16-bit greyscale PNG's bytes; None for any other PNG (Pillow reads those)."""
    rows = _decode_png(data, 16, 0, 1)
    return None if rows is None else rows.view(">u2")


def decode_gray8_png(data: bytes) -> np.ndarray | None:
    """uint8 (H, W) of a non-interlaced 8-bit greyscale PNG's bytes; None for any other PNG (Pillow reads those)."""
    return _decode_png(data, 8, 0, 1)


def decode_rgb8_png(data: bytes) -> np.ndarray | None:
    """uint8 (H, W, 3) of a non-interlaced 8-bit RGB PNG's bytes; None for any other PNG (Pillow reads those)."""
    rows = _decode_png(data, 8, 2, 3)
    return None if rows is None else rows.reshape(rows.shape[0], -1, 3)
