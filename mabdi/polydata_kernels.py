"""Compiled (numba) per-face work on a polydata's arrays (:mod:`mabdi.world_map`).

:func:`triangle_centres` gives the corner-average centre and the radius
(farthest corner) of triangles straight from the polygons' connectivity, in
float64, without the (M, 3, 3) temporaries of an array formulation;
:func:`triangle_normals_kernel` the unit normals and areas of triangles in the
points' own dtype, the same numbers as numpy's cross product and norm.
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


@njit(cache=True)
def triangle_normals_kernel(points, triangles):
    """((M, 3) unit normals, (M,) areas) of ``triangles`` (M, 3) into ``points`` (N, 3, float32 or float64), in the
    points' dtype, right-hand rule; a degenerate triangle has normal 0 and area 0. The sums run in the order
    numpy's ``cross`` and ``linalg.norm`` take, so the numbers are theirs to the bit."""
    count = triangles.shape[0]
    normals = np.empty((count, 3), dtype=points.dtype)
    areas = np.empty(count, dtype=points.dtype)
    one = points.dtype.type(1.0)
    half = points.dtype.type(0.5)
    for m in range(count):
        a, b, c = triangles[m, 0], triangles[m, 1], triangles[m, 2]
        ux, uy, uz = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        vx, vy, vz = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        length = np.sqrt((nx * nx + ny * ny) + nz * nz)
        divisor = length if length > 0 else one
        normals[m, 0], normals[m, 1], normals[m, 2] = nx / divisor, ny / divisor, nz / divisor
        areas[m] = half * length
    return normals, areas
