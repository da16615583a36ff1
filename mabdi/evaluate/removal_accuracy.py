"""Dynamic-removal accuracy of a map: the static and dynamic accuracy of the KTH DynamicMap benchmark.

The benchmark (Zhang, Jensfelt et al., "A Dynamic Points Removal Benchmark in
Point Cloud Maps", ITSC 2023) labels every point of the raw map (all scans
accumulated) static or dynamic, and scores a cleaned map by

* **static accuracy** SA = static points kept / static points,
* **dynamic accuracy** DA = dynamic points removed / dynamic points,
* and their geometric mean AA = sqrt(SA DA) (its "associated accuracy").

For a mesh map, here:

* **The points** are the vertices of every map the run held (the raw map:
  :class:`MapHistory` gathers the vertices of the maps it is given, one
  point per distinct position), so a vertex the loop removed still counts.
* **Labels**, against the scene as it stands at the end (the objects present
  at the last frame, :meth:`~mabdi.sources.scene.SourceScene.mesh_at`) and the
  former surfaces of the objects that left during the run: a point within
  ``near`` (3 cm) of the scene as it stands is **static**; a point within
  ``near`` of a departed object's former surface and farther than ``near``
  from the scene as it stands is **dynamic**; any other point (noise farther
  than ``near`` from every surface) has no label and is not scored (counted
  in ``unlabelled``). A point of a departed object within ``near`` of a
  static surface (a wheel on the road) is static: no map can tell them apart.
* **Kept**: the final map's surface passes within ``keep`` (1 cm) of the
  point (distance to its triangles, so a vertex still in the map is at 0,
  and a static vertex whose face the loop replaced by another over the same
  surface is kept); otherwise the point is removed.

SA or DA is NaN when there is no point of that label (no object left, or the
map never held one), and AA then too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.evaluate.distance import distances_within
from mabdi.polydata import polydata_arrays

#: A point this close (m) to a surface takes its label (the ghost threshold of :mod:`mabdi.evaluate.dynamic`).
LABEL_NEAR = 0.03
#: A point this close (m) to the final map is kept.
KEEP_DISTANCE = 0.01
#: Point labels.
UNLABELLED, STATIC, DYNAMIC = 0, 1, 2


@dataclass(frozen=True)
class RemovalAccuracy:
    """Static and dynamic accuracy of a map (module docs); counts of the points scored."""

    static_accuracy: float
    dynamic_accuracy: float
    static_points: int
    dynamic_points: int
    unlabelled: int

    @property
    def associated_accuracy(self) -> float:
        """sqrt(SA DA), the benchmark's AA (NaN when either is)."""
        return math.sqrt(self.static_accuracy * self.dynamic_accuracy)

    def as_dict(self) -> dict:
        return {
            "static_accuracy": self.static_accuracy,
            "dynamic_accuracy": self.dynamic_accuracy,
            "associated_accuracy": self.associated_accuracy,
            "static_points": self.static_points,
            "dynamic_points": self.dynamic_points,
            "unlabelled": self.unlabelled,
        }


class MapHistory:
    """The raw map of a run: every distinct vertex position (m) of the maps given to :meth:`add`."""

    def __init__(self) -> None:
        self._points = np.zeros((0, 3))

    def add(self, mesh: vtkPolyData) -> None:
        """Gather the vertices of ``mesh``'s triangles (points no triangle uses are left out)."""
        if mesh.GetNumberOfCells() == 0:
            return
        vertices, triangles = polydata_arrays(mesh)
        used = vertices[np.unique(triangles)]
        self._points = np.unique(np.concatenate([self._points, used]), axis=0)

    @property
    def points(self) -> np.ndarray:
        """(N, 3) float64 the distinct vertex positions gathered so far."""
        return self._points.copy()

    def __len__(self) -> int:
        return len(self._points)


def _near(points: np.ndarray, meshes, distance: float) -> np.ndarray:
    near = np.zeros(len(points), dtype=bool)
    for mesh in meshes:
        if mesh is not None and mesh.GetNumberOfCells() and len(points):
            near |= distances_within(points, mesh, cap=2.0 * distance) <= distance
    return near


def label_points(points, scene: vtkPolyData, departed=(), near: float = LABEL_NEAR) -> np.ndarray:
    """(N,) int8 labels of ``points`` (N, 3): :data:`STATIC`, :data:`DYNAMIC` or :data:`UNLABELLED` (module docs).

    ``scene``: the scene as it stands at the end; ``departed``: the former surfaces of the objects that left
    (meshes).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    static = _near(points, [scene], near)
    dynamic = ~static & _near(points, list(departed), near)
    labels = np.full(len(points), UNLABELLED, dtype=np.int8)
    labels[static] = STATIC
    labels[dynamic] = DYNAMIC
    return labels


def removal_accuracy(
    points, final_map: vtkPolyData, scene: vtkPolyData, departed=(), near: float = LABEL_NEAR, keep: float = KEEP_DISTANCE
) -> RemovalAccuracy:
    """SA, DA (and AA) of ``final_map`` on the raw map's ``points`` (N, 3) (e.g. :attr:`MapHistory.points`),
    labelled against ``scene`` (as it stands at the end) and the ``departed`` objects' former surfaces."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    labels = label_points(points, scene, departed, near)
    kept = _near(points, [final_map], keep)
    static, dynamic = labels == STATIC, labels == DYNAMIC
    sa = float(kept[static].mean()) if static.any() else math.nan
    da = float((~kept[dynamic]).mean()) if dynamic.any() else math.nan
    return RemovalAccuracy(sa, da, int(static.sum()), int(dynamic.sum()), int((labels == UNLABELLED).sum()))


__all__ = [
    "DYNAMIC",
    "KEEP_DISTANCE",
    "LABEL_NEAR",
    "STATIC",
    "UNLABELLED",
    "MapHistory",
    "RemovalAccuracy",
    "label_points",
    "removal_accuracy",
]
