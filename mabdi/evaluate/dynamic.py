"""Metrics of a map in a changing world: ghosts, how fast they clear, static surface lost.

When an object leaves the scene, the map still holds its surface until the
loop removes it: a **ghost**. These metrics judge a map against the scene as
it stands at each frame (:meth:`mabdi.sources.scene.SourceScene.mesh_at`):

* **ghost share** (:func:`ghost_share`): the share of the map's area more
  than ``threshold`` (3 cm) from the scene as it is, on area-weighted
  samples with exact point-to-mesh distances; per departed object,
  ``GhostRun.by_object``;
* **first seen** (:func:`first_seen`): the first frame after a departure
  from which at least ``min_pixels`` pixels of the object's former surface
  are in view and not hidden;
* **frames to clear** (:func:`frames_to_clear`): frames from then until the
  object's ghost falls below ``clear_below`` (1 %) of the map's area;
* **static loss** (:class:`StaticCoverage`, :func:`static_loss`): area (m^2)
  of surfaces present all run that the map covered (within ``tau`` = 2 cm)
  earlier and no longer covers at the end;
* **static and dynamic accuracy** (the KTH DynamicMap benchmark's SA, DA
  and AA, :mod:`mabdi.evaluate.removal_accuracy`; ``GhostRun.removal``).

:class:`GhostObserver` measures all of this as a run goes (an observer of
:class:`mabdi.loop.run_pipeline.RunPipeline`; :func:`run_with_ghosts` runs a
MappingRun with one); :class:`GhostTracker` measures any map handed to it.
Details and caveats: docs/architecture.md (``mabdi.evaluate.dynamic``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics
from mabdi.evaluate.distance import distances_within
from mabdi.evaluate.removal_accuracy import MapHistory, RemovalAccuracy, removal_accuracy
from mabdi.evaluate.sampling import SAMPLE_SEED, sample_surface
from mabdi.render.depth_image import SensorRenderer
from mabdi.polydata import triangles_polydata
from mabdi.loop.run_pipeline import RunObserver, RunPipeline

#: A map point this far (m) from the scene as it is is a ghost.
GHOST_THRESHOLD = 0.03
#: A map point this close (m) to a departed object's former surface belongs to it.
OBJECT_NEAR = 0.03
#: A ghost below this share of the map's area is cleared.
CLEAR_BELOW = 0.01
#: A static sample is covered when the map comes this close (m).
COVER_TAU = 0.02
#: Pixels of a departed object's former surface a frame must see to count as seeing its place.
MIN_PIXELS = 200
#: Map samples per ghost measurement; static-surface samples.
GHOST_SAMPLES = 20_000
STATIC_SAMPLES = 20_000
#: Depth slack of the "not hidden" test (metres, fraction of depth), as in visibility.py.
_SLACK_M = 0.005
_SLACK_RELATIVE = 0.005


# ---------------------------------------------------------------------------
# Ghost share


def _map_samples(mesh: vtkPolyData, samples: int, seed: int):
    drawn = sample_surface(mesh, samples, seed)
    return drawn.points, drawn.area


def ghost_mask(points: np.ndarray, scene_mesh: vtkPolyData, threshold: float = GHOST_THRESHOLD) -> np.ndarray:
    """Which (N, 3) ``points`` lie more than ``threshold`` from ``scene_mesh`` (all, for an empty scene)."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    if scene_mesh.GetNumberOfCells() == 0:
        return np.ones(len(points), dtype=bool)
    return distances_within(points, scene_mesh, cap=2.0 * threshold) > threshold


def ghost_share(
    mesh: vtkPolyData,
    scene_mesh: vtkPolyData,
    threshold: float = GHOST_THRESHOLD,
    samples: int = GHOST_SAMPLES,
    seed: int = SAMPLE_SEED,
) -> float:
    """Share of ``mesh``'s area farther than ``threshold`` (m) from ``scene_mesh`` (0 for an empty map).

    Estimated from ``samples`` area-weighted samples of the map (see the module docs).
    """
    points, _ = _map_samples(mesh, samples, seed)
    if len(points) == 0:
        return 0.0
    return float(ghost_mask(points, scene_mesh, threshold).mean())


# ---------------------------------------------------------------------------
# Departures and when their place is seen


@dataclass
class Departure:
    """An object that leaves the scene during the run: its name, index, the first frame without it,
    its former surface, and (once known) the first frame that sees its place."""

    name: str
    index: int
    frame: int
    mesh: vtkPolyData
    seen_at: int | None = None


def departures(scene, frames: int) -> list[Departure]:
    """The objects of ``scene`` (a :class:`~mabdi.sources.scene.SourceScene`) that leave within ``frames`` frames."""
    found = []
    for i, obj in enumerate(scene.objects):
        if obj.disappear is not None and max(obj.appear, 1) <= obj.disappear < frames:
            found.append(Departure(obj.name, i, int(obj.disappear), triangles_polydata(obj.points, obj.triangles)))
    return found


def static_mesh(scene, frames: int) -> vtkPolyData:
    """The surfaces of ``scene`` that exist at every one of ``frames`` frames, as one mesh."""
    keep = [o for o in scene.objects if o.appear <= 0 and (o.disappear is None or o.disappear >= frames)]
    if not keep:
        return vtkPolyData()
    offsets = np.cumsum([0] + [len(o.points) for o in keep[:-1]])
    points = np.concatenate([o.points for o in keep])
    triangles = np.concatenate([o.triangles + off for o, off in zip(keep, offsets, strict=True)])
    return triangles_polydata(points, triangles)


def seen_pixels(object_depth: np.ndarray, scene_depth: np.ndarray) -> int:
    """Pixels where a former surface (``object_depth``, NaN = not there) is in view and not behind the scene."""
    slack = np.maximum(_SLACK_M, _SLACK_RELATIVE * np.nan_to_num(object_depth, nan=0.0))
    hidden = np.isfinite(scene_depth) & (scene_depth < object_depth - slack)
    return int(np.count_nonzero(np.isfinite(object_depth) & ~hidden))


def first_seen(
    departure: Departure,
    scene,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    min_pixels: int = MIN_PIXELS,
    backend: str = "egl",
) -> int | None:
    """First frame >= the departure that sees at least ``min_pixels`` pixels of the object's former place.

    None when no later pose does (see the module docs for the test).
    """
    poses = np.asarray(poses)
    object_view, scene_view = SensorRenderer(backend), SensorRenderer(backend)
    cache: dict[tuple, vtkPolyData] = {}
    try:
        for f in range(departure.frame, len(poses)):
            key = scene.active_objects(f)
            if key not in cache:
                cache[key] = scene.mesh_at(f)
            object_depth = object_view.render(departure.mesh, intrinsics, poses[f])
            if np.count_nonzero(np.isfinite(object_depth)) < min_pixels:
                continue
            scene_depth = scene_view.render(cache[key], intrinsics, poses[f])
            if seen_pixels(object_depth, scene_depth) >= min_pixels:
                return f
    finally:
        object_view.close()
        scene_view.close()
    return None


def frames_to_clear(
    shares,
    departures_,
    poses=None,
    intrinsics: Intrinsics | None = None,
    scene=None,
    *,
    clear_below: float = CLEAR_BELOW,
    min_pixels: int = MIN_PIXELS,
    backend: str = "egl",
) -> dict[str, int | None]:
    """Frames from first sight of each departed object's place until its ghost falls below ``clear_below``.

    ``shares``: the ghost series, a list of (frame, share), or a dict from
    departure name to such a list (each object's own ghost,
    ``GhostRun.by_object``). ``departures_``: :class:`Departure` objects (their
    ``seen_at`` is found with :func:`first_seen` from ``scene``, ``poses``,
    ``intrinsics`` when not set), or (name, frame) pairs whose place counts as
    seen at the departure frame itself. Returns name -> frames (the first
    measured frame at or after the first sight with a share below
    ``clear_below``, minus that first sight), None when never cleared or
    never seen.
    """
    result: dict[str, int | None] = {}
    for item in departures_:
        if isinstance(item, Departure):
            name, seen = item.name, item.seen_at
            if seen is None and scene is not None and poses is not None and intrinsics is not None:
                seen = item.seen_at = first_seen(item, scene, poses, intrinsics, min_pixels, backend)
        else:
            name, seen = item[0], int(item[1])
        series = shares[name] if isinstance(shares, dict) else shares
        if seen is None:
            result[name] = None
            continue
        cleared = next((int(f) for f, s in series if f >= seen and s < clear_below), None)
        result[name] = None if cleared is None else cleared - seen
    return result


# ---------------------------------------------------------------------------
# Static loss


@dataclass
class StaticLoss:
    """Static surface lost (m^2), that as a share of what the map ever covered, and the covered areas (m^2)."""

    area_m2: float
    share: float
    covered_ever_m2: float
    covered_end_m2: float

    def as_dict(self) -> dict:
        return {k: float(v) for k, v in self.__dict__.items()}


class StaticCoverage:
    """Which samples of the static surfaces the map covers, frame after frame (see the module docs).

    ``update(mesh)`` after each measured frame (the last call is "the end");
    :meth:`loss` gives the static loss.
    """

    def __init__(self, static: vtkPolyData, samples: int = STATIC_SAMPLES, tau: float = COVER_TAU, seed: int = SAMPLE_SEED):
        drawn = sample_surface(static, samples, seed)
        self.points = drawn.points
        self.area = drawn.area
        self.tau = tau
        self.ever = np.zeros(len(self.points), dtype=bool)  # covered at some update before the last
        self.last = np.zeros(len(self.points), dtype=bool)

    def covered(self, mesh: vtkPolyData) -> np.ndarray:
        if len(self.points) == 0 or mesh.GetNumberOfCells() == 0:
            return np.zeros(len(self.points), dtype=bool)
        return distances_within(self.points, mesh, cap=2.0 * self.tau) <= self.tau

    def update(self, mesh: vtkPolyData) -> None:
        self.ever |= self.last
        self.last = self.covered(mesh)

    def loss(self) -> StaticLoss:
        n = max(len(self.points), 1)
        ever = self.ever | self.last
        lost = self.ever & ~self.last
        covered = float(ever.sum())
        return StaticLoss(
            area_m2=self.area * float(lost.sum()) / n,
            share=float(lost.sum()) / covered if covered else 0.0,
            covered_ever_m2=self.area * covered / n,
            covered_end_m2=self.area * float(self.last.sum()) / n,
        )


def static_loss(meshes, static: vtkPolyData, tau: float = COVER_TAU, samples: int = STATIC_SAMPLES) -> StaticLoss:
    """Static loss of a sequence of maps (earlier frames first, the last is the end) over ``static`` surfaces."""
    coverage = StaticCoverage(static, samples, tau)
    for mesh in meshes:
        coverage.update(mesh)
    return coverage.loss()


# ---------------------------------------------------------------------------
# Tracking a run


@dataclass
class GhostRun:
    """What :func:`run_with_ghosts` (or a :class:`GhostTracker`) measured.

    Unpacks as ``records, shares = run_with_ghosts(...)``. ``shares``: (frame,
    ghost share) after each measured frame; ``by_object``: departure name ->
    (frame, share of the map's area that is that object's ghost);
    ``departures`` with their ``seen_at``; ``result``: the
    :class:`~mabdi.loop.run_outputs.RunResult` (None for a map not made by the loop).
    ``loop_seconds``: time in the loop's steps alone (not the measuring).
    ``removal``: static and dynamic accuracy of the final map
    (:mod:`mabdi.evaluate.removal_accuracy`), None when no map was measured.
    """

    records: list
    shares: list[tuple[int, float]]
    by_object: dict[str, list[tuple[int, float]]]
    departures: list[Departure]
    static: StaticLoss
    result: object = None
    loop_seconds: float = 0.0
    measure_seconds: float = 0.0
    areas: list[tuple[int, float]] = field(default_factory=list)
    removal: RemovalAccuracy | None = None

    def __iter__(self):
        return iter((self.records, self.shares))

    @property
    def final_share(self) -> float:
        return self.shares[-1][1] if self.shares else 0.0

    def frames_to_clear(self, clear_below: float = CLEAR_BELOW) -> dict[str, int | None]:
        return frames_to_clear(self.by_object, self.departures, clear_below=clear_below)


class GhostTracker:
    """Measures maps of a run against its scene frame by frame (ghost share, departed objects, static coverage).

    ``measure(i, mesh)``: the map as it stands after frame ``i``. The static
    coverage is updated every ``static_every`` measurements and always at
    the one :meth:`finish` is given (the end).
    """

    def __init__(
        self,
        scene,
        frames: int,
        poses=None,
        intrinsics: Intrinsics | None = None,
        threshold: float = GHOST_THRESHOLD,
        samples: int = GHOST_SAMPLES,
        static_every: int = 1,
        min_pixels: int = MIN_PIXELS,
        backend: str = "egl",
        seed: int = SAMPLE_SEED,
    ) -> None:
        self.scene = scene
        self.frames = int(frames)
        self.threshold = threshold
        self.samples = samples
        self.seed = seed
        self.static_every = max(1, int(static_every))
        self.departures = departures(scene, self.frames)
        if poses is not None and intrinsics is not None:
            for d in self.departures:
                d.seen_at = first_seen(d, scene, poses, intrinsics, min_pixels, backend)
        self.coverage = StaticCoverage(static_mesh(scene, self.frames))
        self.shares: list[tuple[int, float]] = []
        self.areas: list[tuple[int, float]] = []
        self.by_object: dict[str, list[tuple[int, float]]] = {d.name: [] for d in self.departures}
        self._scenes: dict[tuple, vtkPolyData] = {}
        self._count = 0
        self.seconds = 0.0
        #: The vertices of every measured map (the raw map of the static and dynamic accuracy).
        self.history = MapHistory()
        self._last: tuple[int, vtkPolyData] | None = None

    def scene_at(self, frame: int) -> vtkPolyData:
        key = self.scene.active_objects(frame)
        if key not in self._scenes:
            self._scenes[key] = self.scene.mesh_at(frame)
        return self._scenes[key]

    def measure(self, frame: int, mesh: vtkPolyData, final: bool = False) -> float:
        """Ghost share of ``mesh`` after ``frame`` (recorded with the per-object ghosts); returns it."""
        start = time.perf_counter()
        points, area = _map_samples(mesh, self.samples, self.seed)
        ghost = ghost_mask(points, self.scene_at(frame), self.threshold)
        share = float(ghost.mean()) if len(points) else 0.0
        self.shares.append((int(frame), share))
        self.areas.append((int(frame), float(area)))
        for d in self.departures:
            if frame < d.frame or not ghost.any():
                self.by_object[d.name].append((int(frame), 0.0))
                continue
            near = np.zeros(len(points), dtype=bool)
            near[ghost] = distances_within(points[ghost], d.mesh, cap=2.0 * OBJECT_NEAR) <= OBJECT_NEAR
            self.by_object[d.name].append((int(frame), float((ghost & near).mean())))
        if final or self._count % self.static_every == 0:
            self.coverage.update(mesh)
        self.history.add(mesh)
        self._last = (int(frame), mesh)
        self._count += 1
        self.seconds += time.perf_counter() - start
        return share

    def removal(self) -> RemovalAccuracy | None:
        """Static and dynamic accuracy of the last measured map on the vertices of all of them (None before any)."""
        if self._last is None:
            return None
        frame, mesh = self._last
        return removal_accuracy(self.history.points, mesh, self.scene_at(frame), [d.mesh for d in self.departures])

    def finish(self, records=None, result=None, loop_seconds: float = 0.0) -> GhostRun:
        start = time.perf_counter()
        removal = self.removal()
        self.seconds += time.perf_counter() - start
        return GhostRun(
            records=list(records or []),
            shares=list(self.shares),
            by_object={k: list(v) for k, v in self.by_object.items()},
            departures=self.departures,
            static=self.coverage.loss(),
            result=result,
            loop_seconds=loop_seconds,
            measure_seconds=self.seconds,
            areas=list(self.areas),
            removal=removal,
        )


class GhostObserver(RunObserver):
    """Watches a run (:class:`~mabdi.loop.run_pipeline.RunPipeline`) and measures its map every ``every``
    frames and after the last, against the scene as it stands at that frame (a :class:`GhostTracker`).

    The scene is the simulation's (or its rig's); the first sight of each
    departed object is judged from the poses the sensor really had. After the
    run, ``ghosts`` is the :class:`GhostRun` (its ``result`` the run's
    :class:`~mabdi.loop.run_outputs.RunResult`, ``loop_seconds`` the
    loop's steps alone). ``progress(frame, share)`` is called after each
    measurement.
    """

    def __init__(
        self,
        every: int = 1,
        threshold: float = GHOST_THRESHOLD,
        samples: int = GHOST_SAMPLES,
        static_every: int = 1,
        min_pixels: int = MIN_PIXELS,
        progress=None,
    ) -> None:
        self.every = max(1, int(every))
        self.threshold = threshold
        self.samples = samples
        self.static_every = static_every
        self.min_pixels = min_pixels
        self.progress = progress
        self.tracker: GhostTracker | None = None
        self.ghosts: GhostRun | None = None

    def on_start(self, pipeline) -> None:
        simulation = pipeline.simulation
        scene = simulation.scene if simulation.scene is not None else simulation.rig.scene
        true_poses = getattr(simulation, "true_poses", None)
        self.tracker = GhostTracker(
            scene,
            simulation.frames,
            simulation.poses if true_poses is None else true_poses,  # what the sensor saw
            simulation.source.intrinsics,
            threshold=self.threshold,
            samples=self.samples,
            static_every=self.static_every,
            min_pixels=self.min_pixels,
            backend=simulation.config.sensor.backend,
        )

    def on_frame(self, pipeline, record) -> None:
        i = record.frame
        last = i == pipeline.simulation.frames - 1
        if i % self.every == 0 or last:
            share = self.tracker.measure(i, pipeline.simulation.loop.mesh(), final=last)
            if self.progress is not None:
                self.progress(i, share)

    def on_loop_end(self, pipeline, result) -> None:
        self.ghosts = self.tracker.finish(result.records, result, result.seconds)


def run_with_ghosts(
    simulation,
    every: int = 1,
    threshold: float = GHOST_THRESHOLD,
    samples: int = GHOST_SAMPLES,
    static_every: int = 1,
    min_pixels: int = MIN_PIXELS,
    progress=None,
) -> GhostRun:
    """Run ``simulation`` (a :class:`~mabdi.loop.run_pipeline.RunPipeline`, nothing written) with a
    :class:`GhostObserver` measuring the map every ``every`` frames and after the last.

    Returns a :class:`GhostRun` (``records, shares = run_with_ghosts(sim)``) whose ``result`` is the
    run's :class:`~mabdi.loop.run_outputs.RunResult`.
    """
    observer = GhostObserver(every, threshold, samples, static_every, min_pixels, progress)
    RunPipeline(simulation, observers=[observer]).run()
    return observer.ghosts
