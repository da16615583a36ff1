"""SourceScene: the simulated world as a vtkPolyData, frame by frame.

A scene is a list of objects (:class:`mabdi.config.ObjectConfig`): primitives
or mesh assets, placed in the world (metres, z up) and switched on and off by
their schedule. ``set_frame(i)`` selects the objects that exist at frame i;
the output is their triangles, with cell data ``object_id`` (the object's
index in the config's list). The scene at frame i is the ground truth of an
evaluation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.config import DEFAULT_COLOUR, ObjectConfig, SceneConfig, load_run_config, schedule_frame
from mabdi.sources import primitives
from mabdi.polydata import polydata_arrays, triangles_polydata
from mabdi.sources.assets import read_mesh, resolve_mesh

OBJECT_ID_ARRAY = "object_id"
#: Cell data: each triangle's object colour (uint8 RGB), what the simulated sensor's colour image shows.
OBJECT_COLOUR_ARRAY = "object_colour"


@dataclass
class SceneObject:
    """One placed object: world-frame triangles and the frames it exists in (``appear <= i < disappear``)."""

    name: str
    points: np.ndarray
    triangles: np.ndarray
    appear: int
    disappear: int | None

    def exists_at(self, frame: int) -> bool:
        return self.appear <= frame and (self.disappear is None or frame < self.disappear)


def axis_to_z_rotation(axis: str) -> np.ndarray:
    """3x3 rotation that turns the model axis ``axis`` ("x", "-y", "+z", ...) onto world +z."""
    sign = -1.0 if axis.startswith("-") else 1.0
    a = np.zeros(3)
    a["xyz".index(axis[-1])] = sign
    z = np.array([0.0, 0.0, 1.0])
    if np.allclose(a, z):
        return np.eye(3)
    if np.allclose(a, -z):
        return np.diag([1.0, -1.0, -1.0])  # half turn about x
    k = np.cross(a, z)
    k /= np.linalg.norm(k)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = math.acos(float(np.clip(a @ z, -1.0, 1.0)))
    return np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * (kx @ kx)


def yaw_rotation(degrees: float) -> np.ndarray:
    """3x3 rotation about world z by ``degrees`` (counter-clockwise seen from above)."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def object_geometry(obj: ObjectConfig, base_dir: Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The object's triangles in its own frame, before placement."""
    if obj.type == "box":
        return primitives.box(obj.size)
    if obj.type == "plane":
        return primitives.plane(obj.size)
    if obj.type == "sphere":
        return primitives.sphere(obj.radius, obj.resolution)
    if obj.type == "cylinder":
        return primitives.cylinder(obj.radius, obj.height, obj.resolution)
    return polydata_arrays(read_mesh(resolve_mesh(obj.mesh, base_dir)))


def place(points: np.ndarray, obj: ObjectConfig) -> np.ndarray:
    """Scale, turn and move model points into the world as :class:`ObjectConfig` documents."""
    pts = np.asarray(points, dtype=np.float64) * (obj.scale if obj.type == "mesh" else 1.0)
    rotation = np.array(obj.rotation) if obj.rotation is not None else axis_to_z_rotation(obj.up)
    pts = pts @ rotation.T
    if obj.type == "mesh" and obj.height is not None:
        extent = pts[:, 2].max() - pts[:, 2].min()
        pts = pts * (obj.height / extent)
    pts = pts @ yaw_rotation(obj.yaw).T
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if obj.anchor == "bottom":
        anchor = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    elif obj.anchor == "center":
        anchor = 0.5 * (lo + hi)
    else:
        anchor = np.zeros(3)
    return pts - anchor + np.asarray(obj.position, dtype=np.float64)


def build_objects(scene: SceneConfig, frames: int, base_dir: Path | None = None) -> list[SceneObject]:
    """Place every object of ``scene`` and resolve its schedule for a run of ``frames`` frames."""
    objects = []
    for i, obj in enumerate(scene.objects):
        points, triangles = object_geometry(obj, base_dir)
        objects.append(
            SceneObject(
                name=obj.name or f"{obj.type}_{i}",
                points=place(points, obj),
                triangles=triangles,
                appear=schedule_frame(obj.appear_at, frames) or 0,
                disappear=schedule_frame(obj.disappear_at, frames),
            )
        )
    return objects


class SourceScene(MabdiAlgorithm):
    """The simulated world (0 inputs -> vtkPolyData with cell data ``object_id`` and ``object_colour``, the
    object's ``colour`` from the config, uint8 RGB).

    ``SourceScene(scene_config, frames=N)`` or ``SourceScene.from_file(path)``.
    ``frames`` is the run length, needed to resolve schedules given as
    fractions of the run.
    """

    def __init__(self, scene: SceneConfig | None = None, frames: int = 1, base_dir: Path | None = None) -> None:
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkPolyData")
        self._config = scene if scene is not None else SceneConfig()
        self._frames = int(frames)
        self.objects: list[SceneObject] = build_objects(self._config, self._frames, base_dir)
        #: (objects, 3) uint8: each object's colour (``colour`` in the config, else DEFAULT_COLOUR).
        self.colours = np.array(
            [obj.colour if obj.colour is not None else DEFAULT_COLOUR for obj in self._config.objects], dtype=np.uint8
        ).reshape(-1, 3)
        self._frame = 0
        self._active = self.active_objects(0)

    @classmethod
    def from_file(cls, path) -> SourceScene:
        """The scene of a run config file (its ``[scene]``, with ``run.frames`` for schedules)."""
        config = load_run_config(path)
        return cls(config.scene, frames=config.run.frames, base_dir=Path(path).parent)

    @property
    def frame(self) -> int:
        return self._frame

    def set_frame(self, frame: int) -> None:
        """Select the objects that exist at ``frame``; Modified() only when that set changes."""
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or frame < 0:
            raise ValueError(f"frame must be an integer >= 0, got {frame!r}")
        self._frame = int(frame)
        active = self.active_objects(self._frame)
        if active != self._active:
            self._active = active
            self.Modified()

    def active_objects(self, frame: int) -> tuple[int, ...]:
        """Indices of the objects that exist at ``frame``."""
        return tuple(i for i, obj in enumerate(self.objects) if obj.exists_at(frame))

    def mesh_at(self, frame: int) -> vtkPolyData:
        """The scene as it stands at ``frame`` (a new vtkPolyData; the pipeline state is untouched)."""
        chosen = [self.objects[i] for i in self.active_objects(frame)]
        ids = [i for i in self.active_objects(frame)]
        if not chosen:
            points = np.zeros((0, 3))
            triangles = np.zeros((0, 3), dtype=np.int64)
            object_id = np.zeros(0, dtype=np.int32)
        else:
            offsets = np.cumsum([0] + [len(o.points) for o in chosen[:-1]])
            points = np.concatenate([o.points for o in chosen])
            triangles = np.concatenate([o.triangles + off for o, off in zip(chosen, offsets, strict=True)])
            object_id = np.concatenate(
                [np.full(len(o.triangles), i, dtype=np.int32) for o, i in zip(chosen, ids, strict=True)]
            )
        mesh = triangles_polydata(points, triangles)
        array = numpy_to_vtk(object_id, deep=True)
        array.SetName(OBJECT_ID_ARRAY)
        mesh.GetCellData().AddArray(array)
        colour = numpy_to_vtk(np.ascontiguousarray(self.colours[object_id]).reshape(-1, 3), deep=True)
        colour.SetName(OBJECT_COLOUR_ARRAY)
        mesh.GetCellData().AddArray(colour)
        return mesh

    @property
    def coloured(self) -> bool:
        """Whether any object has a ``colour`` in the config."""
        return any(obj.colour is not None for obj in self._config.objects)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds (min, max) of all objects over the whole run, metres."""
        if not self.objects:
            return np.zeros((2, 3))
        points = np.concatenate([o.points for o in self.objects])
        return np.stack([points.min(axis=0), points.max(axis=0)])

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        output = vtkPolyData.GetData(outInfo)
        output.ShallowCopy(self.mesh_at(self._frame))
        return 1
