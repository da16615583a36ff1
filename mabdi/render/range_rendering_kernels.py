"""Compiled (numba) beam casting for :mod:`mabdi.render.range_rendering`: each beam against the few
triangles the perspective renders show around its direction."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _segment_distance(px, py, pz, ax, ay, az, ex, ey, ez):
    """Distance from point p to the segment a .. a + e."""
    length2 = ex * ex + ey * ey + ez * ez
    s = 0.0
    if length2 > 0.0:
        s = min(1.0, max(0.0, ((px - ax) * ex + (py - ay) * ey + (pz - az) * ez) / length2))
    dx, dy, dz = px - ax - s * ex, py - ay - s * ey, pz - az - s * ez
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True)
def _distance_to_edges(px, py, pz, a, e1, e2):
    """Distance from a point in a triangle's plane, outside it, to the triangle (a, a + e1, a + e2)."""
    d1 = _segment_distance(px, py, pz, a[0], a[1], a[2], e1[0], e1[1], e1[2])
    d2 = _segment_distance(px, py, pz, a[0], a[1], a[2], e2[0], e2[1], e2[2])
    d3 = _segment_distance(px, py, pz, a[0] + e1[0], a[1] + e1[1], a[2] + e1[2], e2[0] - e1[0], e2[1] - e1[1], e2[2] - e1[2])
    return min(d1, d2, d3)


@njit(cache=True)
def cast_beams_kernel(
    origin, directions, ids, centres, offsets, inner, corner, edge1, edge2, width, footprint, tolerance
):
    """(N,) float64 range along each unit world-frame beam ``directions`` (N, 3) from ``origin`` (3,) (NaN:
    no hit), (N,) int64 the identity of the triangle hit (0: none), and (N,) bool whether any of the beam's
    ``inner`` first candidates is a triangle (the map drawn within its footprint).

    A beam's candidates are ``ids[centres[i] + offsets]`` (``ids``: the renders' triangle identities, flat, 0:
    none; ``centres`` (N,): the render pixel of the beam's direction; ``offsets`` (K,): to the render pixels
    around it), the ``inner`` first of them the nearest to the beam's direction; triangle ``i`` is
    ``corner[i]`` + a ``edge1[i]`` + b ``edge2[i]``, ``width[i]`` its height over its longest edge (metres). A
    beam takes the nearest of the inner candidates it hits inside (barycentric tolerance ``tolerance``;
    Moller-Trumbore), else the nearest of the others. Only when it
    hits none inside does it take the plane of a *thin* candidate (narrower than ``footprint`` radians
    times its range, so that its neighbour, which the beam may hit, can be thinner than a render pixel and
    not drawn) that it misses by less than ``footprint`` times the range: the nearest such.
    """
    n, k = len(centres), len(offsets)
    ranges = np.full(n, np.nan)
    hits = np.zeros(n, dtype=np.int64)
    covered = np.zeros(n, dtype=np.bool_)
    candidates = np.empty(k, dtype=np.int64)
    for i in range(n):
        for j in range(k):
            candidates[j] = ids[centres[i] + offsets[j]]
            if j < inner and candidates[j] != 0:
                covered[i] = True
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        best = np.inf
        best_id = 0
        thin = np.inf
        thin_id = 0
        for j in range(k):
            if j == inner and best_id > 0:
                break
            t_id = candidates[j]
            if t_id <= 0:
                continue
            already = False
            for m in range(j):
                if candidates[m] == t_id:
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
            qx = sy * e1z - sz * e1y
            qy = sz * e1x - sx * e1z
            qz = sx * e1y - sy * e1x
            b = (dx * qx + dy * qy + dz * qz) * inv
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
            if not t > 0.0:
                continue
            outside = max(0.0, -a, -b, a + b - 1.0)
            if outside <= tolerance:
                if t < best:
                    best = t
                    best_id = t_id
            elif t < thin and width[t_id] < footprint * t and _distance_to_edges(
                origin[0] + t * dx, origin[1] + t * dy, origin[2] + t * dz, corner[t_id], edge1[t_id], edge2[t_id]
            ) < footprint * t:
                thin = t
                thin_id = t_id
        if best_id == 0 and thin_id > 0:
            best = thin
            best_id = thin_id
        if best_id > 0:
            ranges[i] = best
            hits[i] = best_id
    return ranges, hits, covered
