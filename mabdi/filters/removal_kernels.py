"""Compiled (numba) per-point work of object removal (:mod:`mabdi.loop.object_removal`).

:func:`points_in_boxes`: which of a block's points lie in any of the boxes
around the faces a frame contradicted (where the map was seen through).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def points_in_boxes(points, lows, highs):
    """(N,) bool: which of ``points`` (N, 3) lie in any box ``lows[k] .. highs[k]`` ((K, 3) each, inclusive)."""
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        for k in range(lows.shape[0]):
            if (
                lows[k, 0] <= x <= highs[k, 0]
                and lows[k, 1] <= y <= highs[k, 1]
                and lows[k, 2] <= z <= highs[k, 2]
            ):
                out[i] = True
                break
    return out
