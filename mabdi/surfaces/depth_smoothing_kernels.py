"""Compiled (numba) depth smoothing (:func:`mabdi.surfaces.depth_smoothing.smooth_depth`): one pass over the
image with no image-sized temporaries, the same arithmetic in the same order as the array formulation the
tests compare it with."""

from __future__ import annotations

import numpy as np
from numba import njit

#: The 4 opposite-neighbour pairs of the 3 x 3 window, as (du, dv) of one side (the other side is (-du, -dv)).
PAIR_DIRECTIONS = np.array([(1, 0), (0, 1), (1, 1), (1, -1)], dtype=np.int64)


def pair_directions(radius: int) -> np.ndarray:
    """The opposite-neighbour pairs of the (2 radius + 1)^2 window, as (du, dv) of one side ((2 r + 1)^2 - 1) / 2
    pairs; radius 1 is :data:`PAIR_DIRECTIONS`."""
    if radius == 1:
        return PAIR_DIRECTIONS
    pairs = [(du, dv) for du in range(radius + 1) for dv in range(-radius, radius + 1) if du > 0 or dv > 0]
    return np.array(pairs, dtype=np.int64)


@njit(cache=True, error_model="numpy")  # a depth of 0 divides as numpy does (inf), not raising
def smooth_depth_kernel(z, sigma, gate_scale, directions):
    """(H, W) float32: each pixel's harmonic mean with the opposite-neighbour pairs (``directions`` (P, 2) of
    (du, dv)) whose both members lie within ``gate_scale`` times its ``sigma`` (H, W, metres) of it; ``z``
    (H, W) metres, NaN = no return (a pair with a NaN or outside the image is left out; a NaN pixel stays
    NaN). Arithmetic in float64."""
    height, width = z.shape
    out = np.empty((height, width), dtype=np.float32)
    for row in range(height):
        for col in range(width):
            centre = np.float64(z[row, col])
            if not np.isfinite(centre):  # no return (or only the pixels being meshed were given): stays as it is
                out[row, col] = np.float32(centre)
                continue
            inverse_sum = 1.0 / centre
            count = 1.0
            limit = gate_scale * np.float64(sigma[row, col])
            for pair in range(directions.shape[0]):
                du, dv = directions[pair, 0], directions[pair, 1]
                r1, c1, r2, c2 = row + dv, col + du, row - dv, col - du
                if r1 < 0 or r1 >= height or c1 < 0 or c1 >= width or r2 < 0 or r2 >= height or c2 < 0 or c2 >= width:
                    continue
                ahead, behind = np.float64(z[r1, c1]), np.float64(z[r2, c2])
                if abs(ahead - centre) <= limit and abs(behind - centre) <= limit:
                    inverse_sum += 1.0 / ahead + 1.0 / behind
                    count += 2.0
            out[row, col] = np.float32(count / inverse_sum)
    return out
