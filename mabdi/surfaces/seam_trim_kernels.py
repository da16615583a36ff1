"""Compiled (numba) pixel-box test of :func:`mabdi.surfaces.seam_trim.over_a_hole`: whether each of many small
boxes of an image holds a pixel of a mask, read box by box with no image-sized temporary. The tests compare it
with its array-slice formulation."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def boxes_hold_kernel(mask, boxes):
    """(N,) bool: whether box ``boxes[i]`` = (u0, u1, v0, v1) (columns u0..u1 and rows v0..v1, inclusive, within
    the image) holds a True pixel of ``mask`` (H, W) bool; u0 > u1 or v0 > v1: an empty box, False."""
    out = np.zeros(boxes.shape[0], dtype=np.bool_)
    for i in range(boxes.shape[0]):
        for v in range(boxes[i, 2], boxes[i, 3] + 1):
            for u in range(boxes[i, 0], boxes[i, 1] + 1):
                if mask[v, u]:
                    out[i] = True
                    break
            if out[i]:
                break
    return out
