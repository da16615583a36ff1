"""Fixed-radius neighbourhood statistics of a point set, by a uniform grid hash compiled with numba.

For every point, over all points within ``radius`` of it (itself included):
the mean of 1 - |n_i . n_j| (normal variation) and the largest and smallest
z. Points are sorted into cubic cells of side ``radius`` (only the occupied
cells are stored, sorted by key, so a map's extent costs nothing); a
point's neighbours lie in its cell and the 26 around it, found by binary
search. One pass over the points, in parallel threads, no neighbour lists
in memory.
"""

from __future__ import annotations

import os

import numpy as np
from numba import config, njit, prange

if "NUMBA_THREADING_LAYER" not in os.environ:
    # numba's own thread pool: always there, and no warning about an old TBB that another package
    # (Open3D) may have installed; a user's NUMBA_THREADING_LAYER wins
    config.THREADING_LAYER = "workqueue"


@njit(cache=True, parallel=True)
def _statistics(points, normals, heights, order, keys, starts, cells, dims, radius):
    n = points.shape[0]
    roughness = np.zeros(n)
    high = np.empty(n)
    low = np.empty(n)
    r2 = radius * radius
    for i in prange(n):
        total = 0.0
        count = 0
        top = -np.inf
        bottom = np.inf
        for dx in range(-1, 2):
            x = cells[i, 0] + dx
            if x < 0 or x >= dims[0]:
                continue
            for dy in range(-1, 2):
                y = cells[i, 1] + dy
                if y < 0 or y >= dims[1]:
                    continue
                for dz in range(-1, 2):
                    z = cells[i, 2] + dz
                    if z < 0 or z >= dims[2]:
                        continue
                    key = (x * dims[1] + y) * dims[2] + z
                    slot = np.searchsorted(keys, key)
                    if slot >= keys.shape[0] or keys[slot] != key:
                        continue
                    for k in range(starts[slot], starts[slot + 1]):
                        j = order[k]
                        ddx = points[j, 0] - points[i, 0]
                        ddy = points[j, 1] - points[i, 1]
                        ddz = points[j, 2] - points[i, 2]
                        if ddx * ddx + ddy * ddy + ddz * ddz > r2:
                            continue
                        dot = normals[i, 0] * normals[j, 0] + normals[i, 1] * normals[j, 1] + normals[i, 2] * normals[j, 2]
                        total += 1.0 - abs(dot)
                        count += 1
                        if heights[j] > top:
                            top = heights[j]
                        if heights[j] < bottom:
                            bottom = heights[j]
        roughness[i] = total / count
        high[i] = top
        low[i] = bottom
    return roughness, high, low


def radius_statistics(points: np.ndarray, normals: np.ndarray, heights: np.ndarray, radius: float):
    """(roughness, max height, min height) per point over the points within ``radius`` (see the module docs)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) == 0:
        empty = np.zeros(0)
        return empty, empty, empty
    low = points.min(axis=0)
    cells = np.floor((points - low) / radius).astype(np.int64)
    dims = cells.max(axis=0) + 1
    cell_key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(cell_key, kind="stable")
    sorted_keys = cell_key[order]
    first = np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]])
    keys = sorted_keys[first]
    starts = np.concatenate([np.flatnonzero(first), [len(points)]])
    return _statistics(
        points,
        np.ascontiguousarray(normals, dtype=np.float64),
        np.ascontiguousarray(heights, dtype=np.float64),
        order,
        keys,
        starts,
        cells,
        dims.astype(np.int64),
        float(radius),
    )
