"""Compiled (numba) beam casting for :mod:`mabdi.filters.range_rendering`: each beam against the few
triangles the perspective renders show around its direction."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def cast_beams_kernel(origin, directions, candidates, corner, edge1, edge2, longest, small_footprint, tolerance):
    """(N,) float64 range along each unit world-frame beam ``directions`` (N, 3) from ``origin`` (3,) (NaN:
    no hit), and (N,) int64 the identity of the triangle hit (0: none).

    ``candidates`` (N, K) are triangle identities (0: none; the middle one, K // 2, is the face drawn at
    the beam's own render pixel); triangle ``i`` is ``corner[i]`` + a ``edge1[i]`` + b ``edge2[i]``. A beam
    takes the nearest candidate it hits inside (barycentric tolerance ``tolerance``; Moller-Trumbore).
    When none is hit inside, it takes the middle candidate's plane, but only if that triangle is small
    (``longest[i]`` below ``small_footprint`` times the hit's range): a triangle smaller than a render pixel
    may be missing from the candidates, and its neighbour's plane is then a sub-pixel extrapolation. A
    large face the beam misses (a silhouette) gives no return there.
    """
    n, k = candidates.shape
    ranges = np.full(n, np.nan)
    hits = np.zeros(n, dtype=np.int64)
    middle = k // 2
    for i in range(n):
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        best = np.inf
        best_id = 0
        for j in range(k):
            t_id = candidates[i, j]
            if t_id <= 0:
                continue
            already = False
            for m in range(j):
                if candidates[i, m] == t_id:
                    already = True
                    break
            if already:
                continue
            e1x, e1y, e1z = edge1[t_id, 0], edge1[t_id, 1], edge1[t_id, 2]
            e2x, e2y, e2z = edge2[t_id, 0], edge2[t_id, 1], edge2[t_id, 2]
            px = dy * e2z - dz * e2y
            py = dz * e2x - dx * e2z
            pz = dx * e2y - dy * e2x
            det = e1x * px + e1y * py + e1z * pz
            if det == 0.0:
                continue
            inv = 1.0 / det
            sx = origin[0] - corner[t_id, 0]
            sy = origin[1] - corner[t_id, 1]
            sz = origin[2] - corner[t_id, 2]
            a = (sx * px + sy * py + sz * pz) * inv
            if a < -tolerance or a > 1.0 + tolerance:
                continue
            qx = sy * e1z - sz * e1y
            qy = sz * e1x - sx * e1z
            qz = sx * e1y - sy * e1x
            b = (dx * qx + dy * qy + dz * qz) * inv
            if b < -tolerance or a + b > 1.0 + tolerance:
                continue
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
            if t > 0.0 and t < best:
                best = t
                best_id = t_id
        if best_id == 0:
            t_id = candidates[i, middle]
            if t_id > 0:
                e1x, e1y, e1z = edge1[t_id, 0], edge1[t_id, 1], edge1[t_id, 2]
                e2x, e2y, e2z = edge2[t_id, 0], edge2[t_id, 1], edge2[t_id, 2]
                nx = e1y * e2z - e1z * e2y
                ny = e1z * e2x - e1x * e2z
                nz = e1x * e2y - e1y * e2x
                facing = nx * dx + ny * dy + nz * dz
                if facing != 0.0:
                    t = (nx * (corner[t_id, 0] - origin[0]) + ny * (corner[t_id, 1] - origin[1])
                         + nz * (corner[t_id, 2] - origin[2])) / facing
                    if t > 0.0 and longest[t_id] < small_footprint * t:
                        best = t
                        best_id = t_id
        if best_id > 0:
            ranges[i] = best
            hits[i] = best_id
    return ranges, hits
