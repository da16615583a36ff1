"""Compiled (numba) per-face work on a polydata's arrays (:mod:`mabdi.world_map`).

:func:`triangle_centres` gives the corner-average centre and the radius
(farthest corner) of triangles straight from the polygons' connectivity, in
float64, without the (M, 3, 3) temporaries of an array formulation.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def triangle_centres(points, connectivity, starts):
    """((M, 3) centres, (M,) radii) of the triangles whose corners are ``connectivity[starts[m] .. starts[m] + 2]``
    into ``points`` (N, 3); metres, float64."""
    count = starts.shape[0]
    centres = np.empty((count, 3), dtype=np.float64)
    radii = np.empty(count, dtype=np.float64)
    for m in range(count):
        a = connectivity[starts[m]]
        b = connectivity[starts[m] + 1]
        c = connectivity[starts[m] + 2]
        for axis in range(3):
            centres[m, axis] = (np.float64(points[a, axis]) + np.float64(points[b, axis]) + np.float64(points[c, axis])) / 3.0
        reach = 0.0
        for corner in (a, b, c):
            dx = np.float64(points[corner, 0]) - centres[m, 0]
            dy = np.float64(points[corner, 1]) - centres[m, 1]
            dz = np.float64(points[corner, 2]) - centres[m, 2]
            reach = max(reach, np.sqrt(dx * dx + dy * dy + dz * dz))
        radii[m] = reach
    return centres, radii


@njit(cache=True)
def corners_marked(triangles, points, gone):
    """(M,) int8: how many corners of each triangle of ``triangles`` (M, 3) into ``points`` vertices belong to a
    triangle of the mask ``gone`` (M,), in one pass without temporaries."""
    marked = np.zeros(points, dtype=np.bool_)
    for m in range(triangles.shape[0]):
        if gone[m]:
            marked[triangles[m, 0]] = True
            marked[triangles[m, 1]] = True
            marked[triangles[m, 2]] = True
    counts = np.empty(triangles.shape[0], dtype=np.int8)
    for m in range(triangles.shape[0]):
        counts[m] = np.int8(marked[triangles[m, 0]]) + np.int8(marked[triangles[m, 1]]) + np.int8(marked[triangles[m, 2]])
    return counts


@njit(cache=True)
def triangles_touching(triangles, points, vertex_ids):
    """(K,) int64 ascending: the triangles of ``triangles`` (M, 3) into ``points`` vertices with a corner among
    ``vertex_ids``, in one pass without temporaries."""
    marked = np.zeros(points, dtype=np.bool_)
    for v in vertex_ids:
        marked[v] = True
    out = np.empty(triangles.shape[0], dtype=np.int64)
    count = 0
    for m in range(triangles.shape[0]):
        if marked[triangles[m, 0]] or marked[triangles[m, 1]] or marked[triangles[m, 2]]:
            out[count] = m
            count += 1
    return out[:count]
