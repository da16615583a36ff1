"""Depth images as ROS's image_transport compresses them (``sensor_msgs/CompressedImage``), decoded.

Robots record depth compressed more often than raw: the ``compressedDepth``
transport (a 12-byte header, then a PNG) or the ``compressed`` one (a PNG).
The message's ``format`` starts with the raw image's encoding
(``"16UC1; compressedDepth png"``, ``"32FC1; compressedDepth"``,
``"16UC1; png compressed mono16"``):

* ``16UC1`` (or ``mono16``): the PNG holds the millimetres as they were
  (0 = no return);
* ``32FC1``, ``compressedDepth`` only: the PNG holds quantised inverse depth
  v, and depth = a / (v - b) metres with (a, b) the header's two floats
  (after its int32 format code); v = 0 is no return.

The header is told by where the PNG signature starts (byte 0 or byte 12).
Other payloads (the ``rvl`` codec, JPEG, a colour PNG) are a
:class:`~mabdi.sources.sequence_files.SequenceError` naming the format.
Pillow is imported on first use.
"""

from __future__ import annotations

import io
import struct

import numpy as np

from mabdi.sources.sequence_files import SequenceError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: compressedDepth's header: int32 format code, float32 depth quantisation a, float32 b.
HEADER = struct.Struct("<iff")
#: The raw encodings a compressed depth image may carry, as the first word of its ``format``.
MILLIMETRE_ENCODINGS = ("16UC1", "mono16")
METRE_ENCODINGS = ("32FC1",)


def depth_encoding(format_text: str) -> str | None:
    """The raw encoding a CompressedImage's ``format`` names (its first word), when it is a depth one; else None."""
    word = format_text.split(";")[0].strip()
    return word if word in MILLIMETRE_ENCODINGS + METRE_ENCODINGS else None


def _png_pixels(data: bytes, where: str) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            if image.mode not in ("I;16", "I;16B", "I;16L", "I"):
                raise SequenceError(f"{where}: the PNG holds {image.mode} pixels, not 16-bit depth")
            return np.asarray(image, dtype=np.uint32)
    except SequenceError:
        raise
    except Exception as exc:  # noqa: BLE001 (Pillow raises several kinds for a damaged image)
        raise SequenceError(f"{where}: cannot decode its PNG: {exc}") from None


def decode_compressed_depth(format_text: str, data, where: str) -> np.ndarray:
    """(H, W) float32 metres (NaN = no return) of a CompressedImage's ``format`` and ``data`` (module docs);
    ``where`` names the message in errors."""
    data = data if isinstance(data, bytes) else np.asarray(data, dtype=np.uint8).tobytes()  # a message's uint8 array
    encoding = depth_encoding(format_text)
    if encoding is None:
        raise SequenceError(f"{where}: compressed image of format {format_text!r} is not depth (16UC1, mono16 or 32FC1)")
    if data.startswith(PNG_SIGNATURE):
        header = None
        pixels = _png_pixels(data, where)
    elif len(data) > HEADER.size and data[HEADER.size:].startswith(PNG_SIGNATURE):
        header = HEADER.unpack_from(data)
        pixels = _png_pixels(data[HEADER.size:], where)
    else:
        raise SequenceError(
            f"{where}: compressed depth of format {format_text!r} is not a PNG (the rvl codec and others are not read): "
            "republish it raw (image_transport republish)"
        )
    valid = pixels > 0
    if encoding in MILLIMETRE_ENCODINGS:
        return np.where(valid, pixels.astype(np.float32) * np.float32(1e-3), np.float32(np.nan)).astype(np.float32)
    if header is None:
        raise SequenceError(f"{where}: 32FC1 depth compressed as a plain PNG has no quantisation to undo")
    _, a, b = header
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(a) / (pixels.astype(np.float32) - np.float32(b))
    return np.where(valid & np.isfinite(depth) & (depth > 0), depth, np.float32(np.nan)).astype(np.float32)
