"""Shared fixtures. Importing mabdi first selects the EGL render window (no X server)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mabdi  # noqa: F401  (sets VTK_DEFAULT_OPENGL_WINDOW before VTK loads)
from mabdi.polydata import triangles_polydata

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO / "scenes"


def plane_mesh(point, normal, size: float = 40.0, subdivisions: int = 1):
    """A square plane (vtkPolyData) through ``point`` with ``normal``, ``size`` metres on a side."""
    normal = np.asarray(normal, dtype=np.float64)
    normal /= np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    s = np.linspace(-0.5 * size, 0.5 * size, subdivisions + 1)
    grid_a, grid_b = np.meshgrid(s, s, indexing="ij")
    points = np.asarray(point) + grid_a.reshape(-1, 1) * a + grid_b.reshape(-1, 1) * b
    n = subdivisions + 1
    i, j = np.meshgrid(np.arange(subdivisions), np.arange(subdivisions), indexing="ij")
    v0 = (i * n + j).ravel()
    v1, v2, v3 = v0 + n, v0 + n + 1, v0 + 1
    triangles = np.concatenate([np.stack([v0, v1, v2], 1), np.stack([v0, v2, v3], 1)])
    return triangles_polydata(points, triangles)


@pytest.fixture(scope="session")
def scenes_dir() -> Path:
    return SCENES
