"""Distances from points to a triangle mesh, vectorised through VTK."""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkDoubleArray
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance


def distances_to_mesh(points, mesh: vtkPolyData) -> np.ndarray:
    """Unsigned distance (m) from each of (N, 3) ``points`` to the nearest point of ``mesh``'s triangles.

    One VTK call over all points (a static cell locator inside
    vtkImplicitPolyDataDistance); an empty mesh gives +inf everywhere.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if mesh.GetNumberOfCells() == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    distance = vtkImplicitPolyDataDistance()
    distance.SetInput(mesh)
    values = vtkDoubleArray()
    distance.FunctionValue(numpy_to_vtk(points, deep=True), values)
    return np.abs(vtk_to_numpy(values))
