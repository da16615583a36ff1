"""Area-weighted random samples on a triangle mesh (fixed seed: the same surface gives the same samples, whatever
the order of its triangles and the corner each starts at, so a map stored in other blocks scores the same)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.polydata import polydata_arrays, triangle_normals

#: Seed of every evaluation's samples.
SAMPLE_SEED = 20261122


@dataclass
class SurfaceSamples:
    """Points on a mesh: (N, 3) positions, the triangle each lies on, and that triangle's unit normal."""

    points: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    area: float

    def __len__(self) -> int:
        return len(self.points)


def triangle_geometry(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(areas (M,), unit normals (M, 3)) of triangles; degenerate ones get area 0 and normal 0
    (:func:`mabdi.polydata.triangle_normals`)."""
    normals, areas = triangle_normals(points, triangles)
    return areas, normals


def sample_surface(mesh: vtkPolyData, count: int, seed: int = SAMPLE_SEED) -> SurfaceSamples:
    """``count`` points on ``mesh`` (triangulated if needed), uniform by area.

    Triangles are drawn with probability proportional to their area, points
    uniformly inside them (the square-root barycentric rule), in a canonical order (:func:`canonical_order`);
    ``faces`` are the mesh's own triangle indices.
    """
    if mesh.GetNumberOfCells() == 0 or count <= 0:
        return SurfaceSamples(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0.0)
    points, triangles = polydata_arrays(mesh)
    areas, normals = triangle_geometry(points, triangles)
    total = float(areas.sum())
    if total <= 0:
        return SurfaceSamples(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0.0)
    order, triangles = canonical_order(points, triangles)
    areas, normals = areas[order], normals[order]
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(areas)
    faces = np.searchsorted(cumulative, rng.random(count) * cumulative[-1], side="right")
    faces = np.minimum(faces, len(triangles) - 1)
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    a, b, c = (points[triangles[faces, k]] for k in range(3))
    samples = (1.0 - r1)[:, None] * a + (r1 * (1.0 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    return SurfaceSamples(samples, order[faces], normals[faces], total)


def canonical_order(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, triangles[order] with corners rotated): the triangles sorted by their corners' coordinates, each
    rotated (its winding kept) to start at its lexicographically smallest corner. The same set of triangles in
    any order and any starting corners gives the same result."""
    corners = points[triangles]  # (M, 3, 3)
    first = np.zeros(len(triangles), dtype=np.int64)  # the smallest corner by (x, y, z)
    for k in (1, 2):
        a, b = corners[np.arange(len(triangles)), first], corners[:, k]
        smaller = (b[:, 0] < a[:, 0]) | ((b[:, 0] == a[:, 0]) & ((b[:, 1] < a[:, 1]) | ((b[:, 1] == a[:, 1]) & (b[:, 2] < a[:, 2]))))
        first[smaller] = k
    rotated = triangles[np.arange(len(triangles))[:, None], (first[:, None] + np.arange(3)[None, :]) % 3]
    c = points[rotated].reshape(len(triangles), 9)
    order = np.lexsort(c.T[::-1])  # by the first corner's x, y, z, then the second's, then the third's
    return order, rotated[order]
