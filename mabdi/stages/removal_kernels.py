"""Compiled (numba) per-point work of object removal (:mod:`mabdi.stages.object_removal`).

:func:`points_in_boxes`: which of a block's points lie in any of the boxes
around the faces a frame contradicted (where the map was seen through).
:func:`window_extremes_at`: E's farthest and D's nearest depth, and whether a
silhouette of E lies, within a window around each of a few pixels (the
contradicted ones) instead of over the whole image.
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


#: :func:`window_extremes_at` reads each window whole while that reads the image at most this many times over.
DIRECT_READS_PER_PIXEL = 4


@njit(cache=True)
def _windows_read_whole(
    expected, measured, silhouettes, rows, cols, margin, margin_columns, silhouette_margin, farthest, nearest, near_silhouette
):
    """:func:`window_extremes_at` by reading each window whole, into ``farthest``, ``nearest``, ``near_silhouette``."""
    height, width = expected.shape
    for k in range(rows.shape[0]):
        row, col = rows[k], cols[k]
        for r in range(max(row - margin, 0), min(row + margin + 1, height)):
            for c in range(max(col - margin_columns, 0), min(col + margin_columns + 1, width)):
                e = expected[r, c]
                if np.isfinite(e) and e > farthest[k]:
                    farthest[k] = e
                d = measured[r, c]
                if np.isfinite(d) and d < nearest[k]:
                    nearest[k] = d
        for r in range(max(row - silhouette_margin, 0), min(row + silhouette_margin + 1, height)):
            for c in range(max(col - silhouette_margin, 0), min(col + silhouette_margin + 1, width)):
                if silhouettes[r, c]:
                    near_silhouette[k] = True
                    break
            if near_silhouette[k]:
                break


@njit(cache=True)
def window_extremes_at(expected, measured, silhouettes, rows, cols, margin, silhouette_margin, margin_columns=-1):
    """At the pixels (``rows[k]``, ``cols[k]``): the farthest finite depth of ``expected`` and the nearest finite
    depth of ``measured`` within ``margin`` rows and ``margin_columns`` columns (-1: ``margin``; a
    (2 margin + 1) x (2 margin_columns + 1) window clipped to the image; -inf / inf where it holds none), and
    whether ``silhouettes`` holds a True within ``silhouette_margin`` pixels (a square, outside the image
    False). The values of a full-image maximum / minimum filter with edge padding and of a square dilation, at
    those pixels only.

    Few pixels: each window read whole. Many (their windows would read the image over
    :data:`DIRECT_READS_PER_PIXEL` times): separably, each window's rows reduced across first (at the pixels
    within a window's height above or below a given pixel, in its column: computed once however many windows
    share them), then down the window's rows; where the given pixels lie together (a region seen through)
    that is a few reads a pixel."""
    height, width = expected.shape
    count = rows.shape[0]
    if margin_columns < 0:
        margin_columns = margin
    farthest = np.full(count, -np.inf, dtype=np.float32)
    nearest = np.full(count, np.inf, dtype=np.float32)
    near_silhouette = np.zeros(count, dtype=np.bool_)
    reach = max(margin, silhouette_margin)
    across = max(margin_columns, silhouette_margin)
    if count * (2 * reach + 1) * (2 * across + 1) <= DIRECT_READS_PER_PIXEL * height * width:
        _windows_read_whole(
            expected, measured, silhouettes, rows, cols, margin, margin_columns, silhouette_margin, farthest, nearest, near_silhouette
        )
        return farthest, nearest, near_silhouette
    # the pixels whose row-wise extremes some window needs: each given pixel's column, reach rows up and down
    needed = np.zeros((height, width), dtype=np.bool_)
    for k in range(count):
        for r in range(max(rows[k] - reach, 0), min(rows[k] + reach + 1, height)):
            needed[r, cols[k]] = True
    across_far = np.full((height, width), -np.inf, dtype=np.float32)
    across_near = np.full((height, width), np.inf, dtype=np.float32)
    across_silhouette = np.zeros((height, width), dtype=np.bool_)
    for r in range(height):
        for c in range(width):
            if not needed[r, c]:
                continue
            far = np.float32(-np.inf)
            near = np.float32(np.inf)
            for cc in range(max(c - margin_columns, 0), min(c + margin_columns + 1, width)):
                e = expected[r, cc]
                if np.isfinite(e) and e > far:
                    far = e
                d = measured[r, cc]
                if np.isfinite(d) and d < near:
                    near = d
            across_far[r, c] = far
            across_near[r, c] = near
            for cc in range(max(c - silhouette_margin, 0), min(c + silhouette_margin + 1, width)):
                if silhouettes[r, cc]:
                    across_silhouette[r, c] = True
                    break
    for k in range(count):
        row, col = rows[k], cols[k]
        for r in range(max(row - margin, 0), min(row + margin + 1, height)):
            if across_far[r, col] > farthest[k]:
                farthest[k] = across_far[r, col]
            if across_near[r, col] < nearest[k]:
                nearest[k] = across_near[r, col]
        for r in range(max(row - silhouette_margin, 0), min(row + silhouette_margin + 1, height)):
            if across_silhouette[r, col]:
                near_silhouette[k] = True
                break
    return farthest, nearest, near_silhouette
