"""Refinement of known faces: a map that gets better with every look.

Without it the first look at a surface wins: a wall first seen from far
keeps that look's noise although the robot later sees it from near. Once a
frame, after the world mesh has appended the frame's novel surface,
:class:`MapRefinement` reads D, E (with the face each pixel shows), the
labels and the pose, and:

* **refines**: every vertex keeps a running estimate of the surface along
  its normal, an offset t_v (metres) from its original position: a prior of
  weight sigma(z_create)^-2, and each pixel that shows one of its faces and
  lies on that face's surface within ``gate_k`` sigma (3; 5 for a real
  camera's learnt noise, whose looks differ by more) adds an observation
  weighted cos(incidence) / sigma(D)^2, near the corner only
  (``radius_px``). A vertex moves to its estimate once the observations
  weigh ``confidence`` times its prior and the move is at least ``min_step``;
* **replaces** (``replace``, off by default): a face made from a much
  noisier look (``replace_ratio``) is removed, and its pixels are meshed
  again from the better look in the next frame.

It runs where the noise model says neighbouring pixels err together
(``[classifier] refinement = "auto"``). Only pixel-grid and quad-tree
triangles (``frame_<i>`` blocks) are refined; voxel-plane patches average
their own statistics. The per-pixel work is a numba kernel
(:mod:`mabdi.stages.refinement_kernels`).

The reasoning behind each rule: docs/architecture.md
(``mabdi.stages.refinement``); measured figures: docs/benchmarks.md.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import unit_rays
from mabdi.errors import ConfigError, check_switch
from mabdi.stages.classifier import NO_RETURN
from mabdi.frame_values import Expected, Measured
from mabdi.polydata import vertex_normals
from mabdi.world_map import FRAME_CELL_ARRAY, patch_triangles

from mabdi.stages import refinement_kernels as kernels

#: ``radius_px = "auto"``: footprints around a corner where pixels err independently, and per correlation
#: length of the noise where they err together (see the module docs).
RADIUS_PX_INDEPENDENT = 2.5
RADIUS_PER_CORRELATION = 4.0

#: ``gate_k = "auto"``: a look observes a face within this many sigma of it where the sensor's noise model is its
#: own (the simulator's), and within :data:`REAL_CAMERA_GATE_K` where the model is learnt from a real camera's
#: frames, whose looks at one surface differ by more than their per-pixel noise (see the module docs).
GATE_K = 3.0
REAL_CAMERA_GATE_K = 5.0

#: Blocks of these key prefixes are refined (pixel grid and quad-tree patches, and the world map's merges of
#: them); voxel planes use ``patch_``.
REFINED_PREFIX = ("frame_", "merged_")


@dataclass(frozen=True)
class RefinementParameters:
    """The refinement and replacement rules (see the module docs). Metres, degrees, pixels.

    ``stride``: pixels sampled every ``stride`` in u and v; ``grazing_deg``: pixels whose ray is more than this
    angle off the face's normal neither observe nor vote (75);
    ``radius_px``: a pixel observes a vertex only if its measured point lies within this many pixel footprints
    (its depth / focal length) of the vertex across the vertex's normal ("auto": by the noise's correlation,
    :meth:`radius_for`);
    ``confidence``: a vertex moves once its observations' weight is at least this times its prior's;
    ``min_step``: nor unless its estimate is at least this far from where it is; ``min_sigma``: floor on
    sigma(z); ``replace_ratio``: a face is replaced when its sigma is at least this times the pixel's;
    ``gate_k``: same surface when |D - E| <= gate_k sqrt(sigma_D^2 + sigma_f^2) ("auto": :meth:`gate_k_for`);
    ``replace_share``: share
    of a face's pixels that must prefer the better look; ``replace``: False refines only.

    ``enabled``: the ``[refinement]`` section's switch (refinement runs only with the classifier on and a noisy
    sensor); "auto" (the default) turns it on where the noise model says neighbouring pixels err together
    (:attr:`~mabdi.sensor_noise.SensorNoise.correlated`: a structured-light or stereo camera, a real camera
    under ``noise = "auto"``): smoothing cannot take such errors out of one look, so later looks are averaged
    in; with independent noise the smoothed first look is nearly as good (docs/benchmarks.md, "Depth
    smoothing before meshing"). True or False decide outright.
    """

    enabled: bool | str = "auto"
    stride: int = 2
    grazing_deg: float = 75.0
    radius_px: float | str = "auto"
    confidence: float = 1.0
    min_step: float = 2e-4
    min_sigma: float = 1e-4
    replace: bool = False
    replace_ratio: float = 2.0
    gate_k: float | str = "auto"
    replace_share: float = 0.5

    def __post_init__(self) -> None:
        check_switch("refinement: enabled", self.enabled)
        if not (isinstance(self.stride, int) and self.stride >= 1):
            raise ConfigError(f"refinement: stride must be an integer >= 1 (pixels), got {self.stride!r}")
        if not 0 < self.grazing_deg < 90:
            raise ConfigError(f"refinement: need 0 < grazing_deg < 90, got {self.grazing_deg}")
        if self.radius_px != "auto" and not (
            isinstance(self.radius_px, (int, float)) and not isinstance(self.radius_px, bool) and self.radius_px > 0
        ):
            raise ConfigError(f"refinement: radius_px must be > 0 pixels or \"auto\", got {self.radius_px!r}")
        if not (self.confidence >= 0 and self.min_step >= 0 and self.min_sigma > 0):
            raise ConfigError("refinement: need confidence >= 0, min_step >= 0 and min_sigma > 0")
        if self.gate_k != "auto" and not (
            isinstance(self.gate_k, (int, float)) and not isinstance(self.gate_k, bool) and self.gate_k > 0
        ):
            raise ConfigError(f'refinement: gate_k must be > 0 (sigmas) or "auto", got {self.gate_k!r}')
        if not (self.replace_ratio > 1 and 0 < self.replace_share <= 1):
            raise ConfigError("refinement: need replace_ratio > 1 and 0 < replace_share <= 1")

    def gate_k_for(self, noise) -> float:
        """The gate in sigmas for depth of noise ``noise`` (a SensorNoise): ``gate_k``, or for "auto"
        :data:`REAL_CAMERA_GATE_K` where the model is learnt from a real camera's frames (model ``auto``) and
        :data:`GATE_K` for a model of the simulator's."""
        if self.gate_k != "auto":
            return float(self.gate_k)
        return REAL_CAMERA_GATE_K if noise.learnt else GATE_K

    def radius_for(self, noise) -> float:
        """The radius (pixel footprints) for a depth image of noise ``noise`` (a SensorNoise): ``radius_px``, or
        for "auto" max(RADIUS_PX_INDEPENDENT, RADIUS_PER_CORRELATION x its correlation length)."""
        if self.radius_px != "auto":
            return float(self.radius_px)
        return max(RADIUS_PX_INDEPENDENT, RADIUS_PER_CORRELATION * noise.correlation_px)


@dataclass
class RefinementResult:
    """What one frame's refinement found, for the map's owner to apply: the vertices to move (``moves``:
    (block key, vertex ids, their new points in the map frame, metres), for ``world.move_points``), faces to
    replace (E's face codes, with E's :class:`~mabdi.face_identity.FaceIdTable`: for ``world.remove_faces``),
    pixels that observed, and the time it took (ms)."""

    moved_vertices: int = 0
    replaced: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    moves: list = field(default_factory=list)
    observed_pixels: int = 0
    t_ms: float = 0.0


@dataclass
class _BlockState:
    """Per-vertex state of one block (see the module docs)."""

    patch: vtkPolyData  # the block object this state belongs to (a rebuilt block is a new object)
    triangles: np.ndarray | None  # (M, 3) vertex ids; None when the block has non-triangle faces
    original: np.ndarray  # (N, 3) float64 positions when first met
    normal: np.ndarray  # (N, 3) float64 unit vertex normals (original)
    prior: np.ndarray  # (N,) W0 = sigma(z_create)^-2
    weight: np.ndarray  # (N,) W: sum of observation weights
    total: np.ndarray  # (N,) S: weighted sum of observed offsets
    offset: np.ndarray  # (N,) t: the offset the vertex is at now


#: The per-vertex arrays of a block's state, carried over when the block is rebuilt.
_STATE = ("original", "normal", "prior", "weight", "total", "offset")


def _points(patch: vtkPolyData) -> np.ndarray:
    return vtk_to_numpy(patch.GetPoints().GetData())


def _match_rows(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """For each row of ``new``, the index of an identical row of ``old`` (-1 where none): how a block's
    vertices carry their state over when the block is rebuilt with some faces taken out."""
    old = np.ascontiguousarray(old)
    new = np.ascontiguousarray(new, dtype=old.dtype)
    row = np.dtype((np.void, old.dtype.itemsize * 3))
    keys = np.concatenate([old.view(row).ravel(), new.view(row).ravel()])
    _, inverse = np.unique(keys, return_inverse=True)
    inverse = inverse.ravel()
    where = np.full(inverse.max() + 1 if len(inverse) else 0, -1, dtype=np.int64)
    where[inverse[: len(old)]] = np.arange(len(old))
    return where[inverse[len(old):]]


@dataclass(frozen=True)
class _FrameView:
    """The frame a refinement step works on: D, the sensor's intrinsics, and ``pose_of(frame)``: the pose an
    older frame was meshed with (None: unknown)."""

    measured: Measured
    intrinsics: object
    pose_of: object


class MapRefinement:
    """Refines the map's known faces and picks faces to replace, once per frame (see the module docs).

    Keep one per loop; call :meth:`step` after the world mesh appended the frame's surface and before any
    face of that frame is removed (E's face codes must still name the faces E drew).
    """

    def __init__(self, parameters: RefinementParameters | None = None) -> None:
        self.parameters = parameters if parameters is not None else RefinementParameters()
        self._blocks: dict[str, _BlockState] = {}

    def reset(self) -> None:
        """Forget every block (after the map was emptied or replaced)."""
        self._blocks.clear()

    def state(self, world) -> dict:
        """The per-block memory as plain data, for checkpoints (``world``: the loop's world mesh).

        Per block: its state arrays, its triangles (-1 rows stand for None), the points of the block object
        the state belongs to, and whether that object is the world's current block (then :meth:`set_state`
        binds the state to the restored block, else to a copy of those points, as an uninterrupted run has it).
        """
        blocks = {}
        in_map = set(world.patch_keys)
        for key, block in self._blocks.items():
            current = key in in_map and world.block(key) is block.patch
            blocks[key] = {
                "current": bool(current),
                "points": _points(block.patch).copy(),
                "triangles": np.zeros((0, 3), dtype=np.int64) if block.triangles is None else block.triangles.copy(),
                "has_triangles": block.triangles is not None,
                **{name: getattr(block, name).copy() for name in _STATE},
            }
        return {"blocks": blocks}

    def set_state(self, state: dict, world) -> None:
        """Go on from :meth:`state` (after ``world`` was restored from the same checkpoint)."""
        self.reset()
        in_map = set(world.patch_keys)
        for key, block in state["blocks"].items():
            if block["current"] and key in in_map:
                patch = world.block(key)
            else:
                patch = vtkPolyData()
                points = vtkPoints()
                points.SetData(numpy_to_vtk(np.ascontiguousarray(block["points"]), deep=True))
                patch.SetPoints(points)
            triangles = np.asarray(block["triangles"], dtype=np.int64) if block["has_triangles"] else None
            self._blocks[key] = _BlockState(patch, triangles, *(np.array(block[name]) for name in _STATE))

    # -- helpers -------------------------------------------------------------
    def _unit_rays(self, intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) unit rays and (M,) their lengths per metre of depth at every ``stride``-th pixel (the
        pipeline's ray cache, :func:`mabdi.camera.unit_rays`)."""
        stride = self.parameters.stride
        rays, length = unit_rays(intrinsics)
        return rays[::stride, ::stride].reshape(-1, 3), length[::stride, ::stride].ravel()

    def _sigma(self, view: _FrameView, depth: np.ndarray) -> np.ndarray:
        """The sensor's sigma(z) (the noise model D carries), floored at ``min_sigma``."""
        intrinsics = view.intrinsics
        sigma = view.measured.noise.sigma(depth, intrinsics.near, intrinsics.far)
        return np.maximum(sigma, sigma.dtype.type(self.parameters.min_sigma))

    def _match_points(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """For each point of a rebuilt block, its index in the old block (-1: none): the compiled in-order walk,
        or where the block gained points or changed their order, :func:`_match_rows`."""
        where = kernels.match_kept_points_kernel(old, np.ascontiguousarray(new, dtype=old.dtype))
        if where is not None:
            return where
        return _match_rows(old, new)

    def _merge_states(self, key: str, patch: vtkPolyData, parts: list[tuple[str, int]], view: _FrameView, pose: np.ndarray) -> None:
        """The state of a block merged from ``parts`` ((key, points) in the order of its points): each part's
        vertices keep the state they had, the others start fresh. A part rebuilt (faces removed, points
        compacted) after its state was last taken hands on the state of the points it kept."""
        merged = self._register(key, patch, view, pose)
        merged_points = _points(patch)
        start = 0
        for part, points in parts:
            state = self._blocks.get(part)
            if state is not None and start + points <= len(merged.original):
                if len(state.original) == points:
                    for name in _STATE:
                        getattr(merged, name)[start : start + points] = getattr(state, name)
                else:
                    source = self._match_points(_points(state.patch), merged_points[start : start + points])
                    found = np.flatnonzero(source >= 0)
                    for name in _STATE:
                        getattr(merged, name)[start + found] = getattr(state, name)[source[found]]
            start += points

    def _register(self, key: str, patch: vtkPolyData, view: _FrameView, pose: np.ndarray) -> _BlockState:
        """The state of block ``key``: new, carried over from a rebuilt block, or as it was."""
        state = self._blocks.get(key)
        if state is not None and state.patch is patch:
            return state
        triangles = patch_triangles(patch)
        if triangles is not None:
            triangles = triangles.astype(np.int64, copy=False)
        n = patch.GetNumberOfPoints()
        source = np.full(n, -1, dtype=np.int64)
        if state is not None and n and len(_points(state.patch)):
            # a rebuilt block (faces removed, points compacted): vertices found in the old block keep their state
            source = self._match_points(_points(state.patch), _points(patch))
            if np.all(source >= 0):  # no new vertex (the usual case): the state is the old one's, compacted
                self._blocks[key] = _BlockState(patch, triangles, *(getattr(state, name)[source] for name in _STATE))
                return self._blocks[key]
        points = _points(patch).astype(np.float64)
        if triangles is not None and len(triangles):
            normal = vertex_normals(points, triangles)
        else:
            normal = np.zeros((n, 3))
        # prior from the creating frame: each vertex's depth in the camera of the frame that made it
        frames = patch.GetCellData().GetArray(FRAME_CELL_ARRAY)
        vertex_frame = np.full(n, -1, dtype=np.int64)
        if frames is not None and triangles is not None and len(triangles):
            vertex_frame[triangles.ravel()] = np.repeat(vtk_to_numpy(frames).astype(np.int64), 3)
        z = np.full(n, np.nan)
        order = np.argsort(vertex_frame, kind="stable")  # each frame's vertices together, in their order
        starts = np.flatnonzero(np.diff(vertex_frame[order], prepend=-2))  # -1 (no frame) is the lowest
        for start, end in zip(starts, np.append(starts[1:], n)):
            chosen = order[start:end]
            creator = view.pose_of(int(vertex_frame[chosen[0]]))
            creator = pose if creator is None else creator
            z[chosen] = (points[chosen] - creator[:3, 3]) @ creator[:3, 2]
        z = np.where(np.isfinite(z) & (z > 0), z, np.linalg.norm(points - pose[:3, 3], axis=1))
        prior = 1.0 / self._sigma(view, z) ** 2
        fresh = _BlockState(patch, triangles, points, normal, prior, np.zeros(n), np.zeros(n), np.zeros(n))
        kept = source >= 0
        if kept.any():
            for name in _STATE:
                getattr(fresh, name)[kept] = getattr(state, name)[source[kept]]
        self._blocks[key] = fresh
        return fresh

    # -- one frame -----------------------------------------------------------
    def step(self, measured: Measured, expected: Expected | None, labels, world, pose_of) -> RefinementResult:
        """One frame's refinement: D (``measured``, registered to the map), E with face identity (None or
        without it: nothing refined), the classifier's ``labels`` (None: classifier off, nothing refined), the
        map (``world``, a :class:`~mabdi.stages.world_mesh.FilterWorldMesh` after it appended the frame; read
        only) and ``pose_of(frame)``: the pose each frame that made a face was meshed with
        (the loop's record; None where unknown: this frame's pose stands in).
        Returns what it found: the moves and the faces to replace, for the map's owner to apply."""
        start = time.perf_counter()
        p = self.parameters
        result = RefinementResult()
        noise, intrinsics = measured.noise, measured.geometry
        if labels is None or not noise.noisy:
            return result
        if expected is None or expected.face_ids is None:
            return result  # E drawn without face identity: nothing to attribute pixels to
        view = _FrameView(measured, intrinsics, pose_of)
        pose = measured.pose
        in_map = world.patch_keys
        for key in in_map:  # blocks merged since the last frame carry their parts' states
            parts = world.store.merged_parts(key)
            if parts and key not in self._blocks and any(part in self._blocks for part, _ in parts):
                self._merge_states(key, world.block(key), parts, view, pose)
        in_map = set(in_map)
        for key in [k for k in self._blocks if k not in in_map]:
            del self._blocks[key]

        s = p.stride
        face_ids = expected.face_ids[::s, ::s].ravel()
        labels = labels[::s, ::s].ravel()
        candidates = np.flatnonzero((face_ids > 0) & (labels != NO_RETURN))
        if not len(candidates):
            result.t_ms = 1000.0 * (time.perf_counter() - start)
            return result
        ids = face_ids[candidates].astype(np.int64)
        block, local, keys = world.face_lookup(ids, expected.table)
        expected_depth = expected.depth[::s, ::s].ravel()[candidates]
        measured = measured.depth[::s, ::s].ravel()[candidates]
        expected = expected_depth
        rays, length = self._unit_rays(intrinsics)
        rays = rays[candidates] @ pose[:3, :3].T  # world
        length = length[candidates]
        sigma_d = self._sigma(view, measured).astype(np.float64)
        centre = pose[:3, 3]
        focal = 0.5 * (intrinsics.fx + intrinsics.fy)
        cos_grazing = np.cos(np.radians(p.grazing_deg))
        radius = p.radius_for(noise)
        gate_k = p.gate_k_for(noise)

        replaced = []
        touched = []
        observed = 0
        order = np.argsort(block, kind="stable")  # the pixels of each block together
        bounds = np.searchsorted(block[order], np.arange(len(keys) + 1), side="left")
        for b in np.flatnonzero(np.diff(bounds) > 0):
            key = keys[b]
            if not key.startswith(REFINED_PREFIX):
                continue
            state = self._register(key, world.block(key), view, pose)
            if state.triangles is None:
                continue
            chosen = order[bounds[b] : bounds[b + 1]]
            arguments = (
                state.triangles, _points(state.patch), state.original, state.normal, state.prior, state.weight,
                state.total, local[chosen], rays[chosen], measured[chosen], expected[chosen], length[chosen],
                sigma_d[chosen], centre, focal, cos_grazing, gate_k, p.replace, p.replace_ratio,
                p.replace_share, radius,
            )  # fmt: skip
            gone, count, vertices = kernels.observe_block_kernel(*arguments)
            if gone.any():
                replaced.append(ids[chosen][gone])
            observed += int(count)
            if len(vertices):
                touched.append((key, state, vertices))

        moved = 0
        for key, state, vertices in touched:
            # the weighted mean of the prior and the looks the gate took in, wherever that lies: a first look off
            # by more than its own noise (a real camera's view-dependent bias, its pose's error) is averaged away
            estimate = state.total[vertices] / (state.prior[vertices] + state.weight[vertices])
            move = (state.weight[vertices] >= p.confidence * state.prior[vertices]) & (
                np.abs(estimate - state.offset[vertices]) >= p.min_step
            )
            if not move.any():
                continue
            moving = vertices[move]
            state.offset[moving] = estimate[move]
            result.moves.append((key, moving, state.original[moving] + estimate[move][:, None] * state.normal[moving]))
            moved += int(move.sum())
        result.moved_vertices = moved
        result.observed_pixels = observed
        if replaced:
            result.replaced = np.unique(np.concatenate(replaced))
        result.t_ms = 1000.0 * (time.perf_counter() - start)
        return result
