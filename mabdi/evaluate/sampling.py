"""Area-weighted random samples on a triangle mesh (fixed seed: the same mesh gives the same samples)."""

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
    uniformly inside them (the square-root barycentric rule).
    """
    if mesh.GetNumberOfCells() == 0 or count <= 0:
        return SurfaceSamples(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0.0)
    points, triangles = polydata_arrays(mesh)
    areas, normals = triangle_geometry(points, triangles)
    total = float(areas.sum())
    if total <= 0:
        return SurfaceSamples(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), np.zeros((0, 3)), 0.0)
    rng = np.random.default_rng(seed)
    cumulative = np.cumsum(areas)
    faces = np.searchsorted(cumulative, rng.random(count) * cumulative[-1], side="right")
    faces = np.minimum(faces, len(triangles) - 1)
    r1 = np.sqrt(rng.random(count))
    r2 = rng.random(count)
    a, b, c = (points[triangles[faces, k]] for k in range(3))
    samples = (1.0 - r1)[:, None] * a + (r1 * (1.0 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    return SurfaceSamples(samples, faces, normals[faces], total)
