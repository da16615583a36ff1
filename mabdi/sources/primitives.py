"""Primitive shapes as triangle meshes in their own frame (metres, centred at the origin, z up).

Each returns ``(points (N, 3) float64, triangles (M, 3) int64)``: the scene
places and concatenates them with numpy.
"""

from __future__ import annotations

import numpy as np
from vtkmodules.vtkFiltersCore import vtkTriangleFilter
from vtkmodules.vtkFiltersSources import vtkCubeSource, vtkCylinderSource, vtkSphereSource

from mabdi.polydata import polydata_arrays


def _from_source(source) -> tuple[np.ndarray, np.ndarray]:
    tri = vtkTriangleFilter()
    tri.SetInputConnection(source.GetOutputPort())
    tri.Update()
    return polydata_arrays(tri.GetOutput())


def box(size) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of ``size`` (x, y, z) metres: 12 triangles."""
    cube = vtkCubeSource()
    cube.SetXLength(size[0])
    cube.SetYLength(size[1])
    cube.SetZLength(size[2])
    return _from_source(cube)


def plane(size) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal rectangle of ``size`` (x, y) metres at z = 0: 2 triangles."""
    sx, sy = 0.5 * size[0], 0.5 * size[1]
    points = np.array([[-sx, -sy, 0.0], [sx, -sy, 0.0], [sx, sy, 0.0], [-sx, sy, 0.0]])
    return points, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def sphere(radius: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere: ``resolution`` segments around, ``resolution`` // 2 + 1 rings."""
    source = vtkSphereSource()
    source.SetRadius(radius)
    source.SetThetaResolution(resolution)
    source.SetPhiResolution(max(3, resolution // 2 + 1))
    source.LatLongTessellationOn()
    return _from_source(source)


def cylinder(radius: float, height: float, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """A capped cylinder with its axis along z."""
    source = vtkCylinderSource()
    source.SetRadius(radius)
    source.SetHeight(height)
    source.SetResolution(resolution)
    source.CappingOn()
    points, triangles = _from_source(source)
    # vtkCylinderSource's axis is y: turn it to z (y -> z, z -> -y).
    points = points[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    return points, triangles
