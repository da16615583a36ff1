"""Picking on a mesh map: the first face a ray hits, and a goal pose on it (seed 003's Mesh Goal tool).

:class:`MapPicker` builds a ``vtkStaticCellLocator`` once per map; each
:meth:`MapPicker.pick` is one ``IntersectWithLine`` call, which returns the
hit nearest the ray's origin. The face normal is turned to face the ray's
origin (the side the user looks from).

:func:`goal_pose` is seed 003's two-step goal: a picked point and a
direction (the drag) projected into the face's plane give a full pose,
position plus an orientation whose x axis is the direction and whose z axis
is the face normal; as a 4x4 matrix and as a quaternion (x, y, z, w).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.vtkCommonCore import reference
from vtkmodules.vtkCommonDataModel import vtkGenericCell, vtkPolyData, vtkStaticCellLocator

from mabdi.camera import quaternions_from_rotations
from mabdi.mesh_maps.layers import face_normals
from mabdi.mesh_maps.mesh_map import MeshMap


@dataclass(frozen=True)
class Pick:
    """A ray's first hit: the face id, the point (m, world) and the face's unit normal (towards the ray origin)."""

    face: int
    point: np.ndarray
    normal: np.ndarray
    distance: float


class MapPicker:
    """Ray picking on one map (the locator is built in the constructor)."""

    def __init__(self, mesh_map: MeshMap) -> None:
        self._map = mesh_map
        self._mesh: vtkPolyData = mesh_map.to_polydata()
        self._locator = vtkStaticCellLocator()
        self._locator.SetDataSet(self._mesh)
        self._locator.BuildLocator()
        self._normals, _ = face_normals(mesh_map.vertices, mesh_map.faces)
        low, high = mesh_map.bounds()
        self._low = low
        self._reach = 2.0 * float(np.linalg.norm(high - low)) + 1.0
        self._cell = vtkGenericCell()

    def pick(self, origin, direction, max_distance: float | None = None) -> Pick | None:
        """The first face along the ray ``origin + t * direction`` (t >= 0), or None if it hits nothing."""
        origin = np.asarray(origin, dtype=np.float64)
        direction = np.asarray(direction, dtype=np.float64)
        length = np.linalg.norm(direction)
        if origin.shape != (3,) or direction.shape != (3,) or not length > 0:
            raise ValueError("pick: origin and direction must be 3-vectors, the direction non-zero")
        direction = direction / length
        reach = self._reach + float(np.linalg.norm(origin - self._low)) if max_distance is None else max_distance
        end = origin + reach * direction
        t, x, pcoords = reference(0.0), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        sub_id, cell_id = reference(0), reference(-1)
        hit = self._locator.IntersectWithLine(origin, end, 0.0, t, x, pcoords, sub_id, cell_id, self._cell)
        if not hit or cell_id.get() < 0:
            return None
        face = int(cell_id.get())
        normal = self._normals[face].copy()
        if normal @ direction > 0:
            normal = -normal
        return Pick(face, np.array(x), normal, float(t.get()) * reach)


def goal_pose(point, normal, direction) -> tuple[np.ndarray, np.ndarray]:
    """A goal at ``point`` facing ``direction`` (projected into the plane of ``normal``): 4x4 pose and quaternion (x, y, z, w)."""
    z = np.asarray(normal, dtype=np.float64)
    z = z / np.linalg.norm(z)
    d = np.asarray(direction, dtype=np.float64)
    x = d - (d @ z) * z
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("goal_pose: the direction is along the face normal; it has no direction in the face's plane")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = point
    return pose, rotation_to_quaternion(pose[:3, :3])


def rotation_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix (:func:`mabdi.camera.quaternions_from_rotations`)."""
    return quaternions_from_rotations(rotation)[0]
