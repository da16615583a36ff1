"""Depth as image_transport compresses it (mabdi.sources.compressed_depth): the PNG of the `compressed` and
`compressedDepth` transports, millimetres and quantised inverse depth, and what is refused."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from mabdi.sources.compressed_depth import HEADER, decode_compressed_depth
from mabdi.sources.sequence_files import SequenceError

#: image_transport's compressedDepth quantisation of 32FC1 (its defaults: depth_quantization 100, depth_max 10 m).
QUANT_A = 100.0 * 101.0
QUANT_B = 1.0 - QUANT_A / 10.0


def _png(pixels: np.ndarray) -> bytes:
    stream = io.BytesIO()
    Image.fromarray(pixels.astype(np.uint16)).save(stream, format="PNG")
    return stream.getvalue()


def _depth() -> np.ndarray:
    """(6, 8) metres from 0.6 to 4.5 m with two pixels without a return."""
    depth = np.linspace(0.6, 4.5, 48, dtype=np.float32).reshape(6, 8)
    depth[1, 2] = depth[4, 7] = np.nan
    return depth


def test_millimetres_in_a_plain_png_and_behind_the_compressed_depth_header():
    depth = _depth()
    millimetres = np.nan_to_num(np.round(depth * 1000.0), nan=0.0)
    plain = decode_compressed_depth("16UC1; png compressed mono16", np.frombuffer(_png(millimetres), np.uint8), "m")
    headed = decode_compressed_depth("16UC1; compressedDepth png", HEADER.pack(0, 0.0, 0.0) + _png(millimetres), "m")
    for decoded in (plain, headed):
        assert decoded.dtype == np.float32 and decoded.shape == (6, 8)
        np.testing.assert_array_equal(np.isnan(decoded), np.isnan(depth))
        np.testing.assert_allclose(decoded, depth, atol=0.0005, equal_nan=True)


def test_metres_as_quantised_inverse_depth():
    depth = _depth()
    with np.errstate(invalid="ignore"):
        inverse = np.where(np.isfinite(depth), np.round(QUANT_A / depth + QUANT_B), 0.0)
    decoded = decode_compressed_depth("32FC1; compressedDepth", HEADER.pack(0, QUANT_A, QUANT_B) + _png(inverse), "m")
    np.testing.assert_array_equal(np.isnan(decoded), np.isnan(depth))
    # one step of v is z^2 / a: 2 mm at 4.5 m
    np.testing.assert_allclose(decoded, depth, atol=0.5 * 4.5**2 / QUANT_A + 1e-6, equal_nan=True)


@pytest.mark.parametrize(
    "format_text, data, words",
    [
        ("bgr8; jpeg compressed bgr8", b"\xff\xd8\xff", "is not depth"),
        ("16UC1; compressedDepth rvl", HEADER.pack(0, 0.0, 0.0) + b"RVL?", "the rvl codec and others are not read"),
        ("32FC1; png compressed", None, "no quantisation to undo"),
        ("16UC1; compressedDepth png", HEADER.pack(0, 0.0, 0.0) + b"\x89PNG\r\n\x1a\nbroken", "cannot decode its PNG"),
    ],
)
def test_what_is_not_read_is_an_error_naming_the_message(format_text, data, words):
    if data is None:
        data = _png(np.ones((2, 2)))
    with pytest.raises(SequenceError, match=f"^the image: .*{words}"):
        decode_compressed_depth(format_text, np.frombuffer(data, np.uint8), "the image")
