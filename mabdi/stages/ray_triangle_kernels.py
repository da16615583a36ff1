"""Compiled (numba) ray casting against a small set of triangles: the nearest hit of each ray.

Used where an expected image's face codes no longer name the faces of a block
(a keyed patch re-meshed after E was drawn, :mod:`mabdi.stages.object_removal`):
the pixels that showed the block are cast against its new triangles.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def nearest_hits_in_boxes_kernel(origin, directions, slots, boxes, corner, edge1, edge2, tolerance):
    """(N,) int64 the triangle each ray ``directions`` (N, 3, world frame, unit) from ``origin`` (3,) meets
    first (-1: none), and (N,) float64 the distance along the ray (metres; inf: none). Triangle ``i`` is
    ``corner[i]`` + a ``edge1[i]`` + b ``edge2[i]`` (a, b >= -tolerance, a + b <= 1 + tolerance: a ray through
    the edge two triangles share meets one of them when ``tolerance`` > 0), met from either side
    (Moller-Trumbore), and tested only against the rays of the pixels in its box:

    ``slots`` (H, W) int64: the ray (row of ``directions``) of each pixel, -1 for pixels not cast;
    ``boxes`` (M, 4) int64: the pixel columns u0..u1 and rows v0..v1 (inclusive) a triangle may cover
    (u0 > u1: none).
    """
    n = directions.shape[0]
    m = corner.shape[0]
    hits = np.full(n, -1, dtype=np.int64)
    distances = np.full(n, np.inf)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for j in range(m):
        e1x, e1y, e1z = edge1[j, 0], edge1[j, 1], edge1[j, 2]
        e2x, e2y, e2z = edge2[j, 0], edge2[j, 1], edge2[j, 2]
        sx, sy, sz = ox - corner[j, 0], oy - corner[j, 1], oz - corner[j, 2]
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
        t_num = e2x * qx + e2y * qy + e2z * qz
        for v in range(boxes[j, 2], boxes[j, 3] + 1):
            for u in range(boxes[j, 0], boxes[j, 1] + 1):
                i = slots[v, u]
                if i < 0:
                    continue
                dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
                px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
                det = e1x * px + e1y * py + e1z * pz
                if abs(det) < 1e-15:
                    continue
                inv = 1.0 / det
                a = (sx * px + sy * py + sz * pz) * inv
                if a < -tolerance or a > 1.0 + tolerance:
                    continue
                b = (dx * qx + dy * qy + dz * qz) * inv
                if b < -tolerance or a + b > 1.0 + tolerance:
                    continue
                t = t_num * inv
                if 0.0 < t < distances[i]:
                    distances[i] = t
                    hits[i] = j
    return hits, distances
