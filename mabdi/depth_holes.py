"""One-pixel holes in a depth image: filled where the pixels on either side agree, on fragmented frames.

A camera whose depth is registered to its colour camera (reprojected to the
colour camera's pixels, as RealSense and Kinect drivers offer) leaves a
regular pattern of one-pixel holes: where two depth pixels map to one
colour pixel, the pixel beside them gets none. On such frames most valid
pixels lack a valid neighbour, so the surfaces (a quad of four returns, a
block of them) and the speck filter drop nearly everything.

**The rule** (:func:`fill_pixel_holes`): a pixel without a return is given
the mean of the pairs of opposite neighbours (left-right, up-down, the two
diagonals) that both have returns and agree within ``k`` times the noise of
their difference (sqrt(2) sigma(z)) plus 1% of their depth (a slanted
surface's step across two pixels); a pair across a depth edge disagrees
and fills nothing, so no hole is bridged across a discontinuity, and a hole
wider than a pixel stays.

**When** (:func:`is_fragmented`): only on a frame whose returns are
fragmented, fewer than :data:`FRAGMENTED_SHARE` of them with all four
neighbours returning. A raw depth camera's frames and the simulator's have
nearly all of them surrounded, their holes being real no-returns (black or
shiny surfaces, depth edges), and are left as they are.
"""

from __future__ import annotations

import numpy as np

#: A frame is fragmented when fewer than this share of its returns have all four neighbours returning.
FRAGMENTED_SHARE = 0.5
#: Opposite neighbours must agree within this many standard deviations of their difference.
AGREEMENT_SIGMAS = 3.0
#: ... plus this share of their depth (a slanted surface's step across two pixels).
AGREEMENT_SLOPE = 0.01
#: The pairs of opposite neighbours, as (row, column) offsets of one of them.
PAIRS = ((0, 1), (1, 0), (1, 1), (1, -1))


def _shifted(padded: np.ndarray, dy: int, dx: int, shape: tuple[int, int]) -> np.ndarray:
    height, width = shape
    return padded[1 + dy : 1 + dy + height, 1 + dx : 1 + dx + width]


def is_fragmented(depth: np.ndarray) -> bool:
    """Whether fewer than :data:`FRAGMENTED_SHARE` of the image's returns (finite depths) have all four neighbours
    returning (the image's border pixels not counted)."""
    valid = np.isfinite(depth)
    inner = valid[1:-1, 1:-1]
    returns = int(inner.sum())
    if returns == 0:
        return False
    surrounded = inner & valid[:-2, 1:-1] & valid[2:, 1:-1] & valid[1:-1, :-2] & valid[1:-1, 2:]
    return int(surrounded.sum()) < FRAGMENTED_SHARE * returns


def fill_pixel_holes(depth: np.ndarray, sigma=None) -> tuple[np.ndarray, int]:
    """(depth with its one-pixel holes filled, how many were filled): the rule of the module docs.

    ``depth``: (H, W) metres, NaN for no return. ``sigma``: a function of depth (m) giving the sensor's standard
    deviation (m), None for a noise-free sensor.
    """
    depth = np.asarray(depth)
    shape = depth.shape
    padded = np.pad(depth.astype(np.float64), 1, constant_values=np.nan)
    total = np.zeros(shape)
    count = np.zeros(shape)
    hole = ~np.isfinite(depth)
    with np.errstate(invalid="ignore"):
        for dy, dx in PAIRS:
            a = _shifted(padded, dy, dx, shape)
            b = _shifted(padded, -dy, -dx, shape)
            both = hole & np.isfinite(a) & np.isfinite(b)
            if not both.any():
                continue
            mean = 0.5 * (a + b)
            allowed = AGREEMENT_SLOPE * mean
            if sigma is not None:
                allowed = allowed + AGREEMENT_SIGMAS * np.sqrt(2.0) * np.where(both, sigma(np.where(both, mean, 1.0)), 0.0)
            agree = both & (np.abs(a - b) <= allowed)
            total += np.where(agree, a + b, 0.0)
            count += 2.0 * agree
    filled = count > 0
    out = depth.copy()
    out[filled] = (total[filled] / count[filled]).astype(depth.dtype)
    return out, int(filled.sum())
