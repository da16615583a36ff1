"""The TSDF baseline: Open3D's VoxelBlockGrid (tensor API) fed the same depth frames as MABDI, at its best.

Open3D is an optional extra (``pip install "mabdi[compare]"``; on Debian its
import also needs ``apt-get install libusb-1.0-0``); :func:`open3d_status`
says whether it can be used, and why not.

* **Settings** (:class:`TsdfSettings`): voxel size (metres), truncation in
  voxels, the extraction's weight threshold (Open3D keeps a voxel whose
  weight is *above* it), ``depth_max``, the pixel convention
  (``pixel_centre``) and ``smooth_depth`` (the depth smoothed by the
  sensor's noise model, as MABDI's surfaces mesh it).
* **Range images** (a spinning LiDAR's) are fused point-wise along each beam
  into the same grid, as LiDAR TSDF mappers do (VDBFusion's scheme).
* **Runs**: :func:`run_tsdf` integrates every frame of a
  :class:`mabdi.sources.frames.FrameSource`, extracting the mesh at the end
  and every ``mesh_every`` frames.
* **Tuning**: :func:`tune_tsdf` searches truncation, weight threshold, depth
  range, pixel convention and smoothing at one voxel size against a score
  the caller gives.

Why these choices: docs/architecture.md (``mabdi.evaluate.tsdf``); what the
tuned TSDF scores: docs/benchmarks.md.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics, unit_rays
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.sensor_noise import SensorNoise
from mabdi.surfaces.depth_smoothing import smooth_depth_by_noise
from mabdi.polydata import triangles_polydata
from mabdi.simulate.path import circle_index
from mabdi.spherical import SphericalGeometry
from mabdi.sources.frames import FrameList, FrameSource

OPEN3D_HELP = (
    'Open3D is not available: pip install "mabdi[compare]" '
    "(on Debian its import also needs: apt-get install libusb-1.0-0)"
)

PIXEL_CENTRES = ("half", "integer")
TRUNC_VOXELS_RANGE = (2.0, 12.0)
WEIGHT_THRESHOLD_RANGE = (0.5, 3.0)


def open3d_status() -> tuple[bool, str]:
    """(usable, reason): whether ``import open3d`` works here, and the error if not."""
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError) as exc:
        return False, f"{OPEN3D_HELP}; import failed with: {exc}"
    return True, ""


# ---------------------------------------------------------------------------
# Settings


@dataclass(frozen=True)
class TsdfSettings:
    """How the TSDF is built and meshed (see the module docs). Every check is here.

    * ``voxel_size``: metres, > 0.
    * ``trunc_voxels``: truncation distance in voxels, 2-12 (the camera grid tries 2-6; a LiDAR's sparse rings want more).
    * ``weight_threshold``: extraction keeps voxels whose weight (frames fused) is above it, 0.5-3
      (0.5: every voxel a frame reached; 1, the plain setting: seen by two frames or more).
    * ``depth_max``: metres; depths beyond it are not fused (>= the sensor's far plane = all returns).
    * ``pixel_centre``: ``"half"`` (Open3D gets cx, cy) or ``"integer"`` (cx - 0.5, cy - 0.5).
    * ``smooth_depth``: integrate the depth smoothed by the sensor's noise model (see the module docs).
    * ``block_resolution``: voxels per block edge (Open3D's default 16); ``block_count``: the hash map's
      initial capacity in blocks. Open3D grows it as needed; what it allocates up front is zeroed at
      once (40,000 blocks = 1.3 GB, 8-16 s on the 2-core machine), so the default 4,000 (131 MB) is
      about the bench scenes' need at 1 cm (2,100-2,900 blocks).
    """

    voxel_size: float = 0.01
    trunc_voxels: float = 4.0
    weight_threshold: float = 1.0
    depth_max: float = 5.0
    pixel_centre: str = "half"
    smooth_depth: bool = False
    block_resolution: int = 16
    block_count: int = 4000

    @classmethod
    def tuned(cls, voxel_size: float, noisy: bool = True) -> TsdfSettings:
        """The settings tuned on the bench scenes (docs/benchmarks.md, "The peer at its best"): truncation 4
        voxels, weight above 0.5, half-pixel centres, the depth smoothed as the surfaces smooth it where it is
        ``noisy``. What a comparison runs the TSDF with."""
        return cls(voxel_size=voxel_size, trunc_voxels=4.0, weight_threshold=0.5, smooth_depth=noisy)

    def __post_init__(self) -> None:
        def number(name: str) -> float:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ConfigError(f"tsdf: {name} must be a number, got {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise ConfigError(f"tsdf: {name} must be finite, got {value!r}")
            object.__setattr__(self, name, value)
            return value

        if number("voxel_size") <= 0:
            raise ConfigError(f"tsdf: voxel_size must be > 0 (metres), got {self.voxel_size!r}")
        lo, hi = TRUNC_VOXELS_RANGE
        if not lo <= number("trunc_voxels") <= hi:
            raise ConfigError(f"tsdf: trunc_voxels must be in [{lo:g}, {hi:g}] voxels, got {self.trunc_voxels!r}")
        lo, hi = WEIGHT_THRESHOLD_RANGE
        if not lo <= number("weight_threshold") <= hi:
            raise ConfigError(f"tsdf: weight_threshold must be in [{lo:g}, {hi:g}], got {self.weight_threshold!r}")
        if number("depth_max") <= 0:
            raise ConfigError(f"tsdf: depth_max must be > 0 (metres), got {self.depth_max!r}")
        if self.pixel_centre not in PIXEL_CENTRES:
            raise ConfigError(
                f"tsdf: pixel_centre must be one of {', '.join(PIXEL_CENTRES)}, got {self.pixel_centre!r}"
            )
        if not isinstance(self.smooth_depth, (bool, np.bool_)):
            raise ConfigError(f"tsdf: smooth_depth must be true or false, got {self.smooth_depth!r}")
        object.__setattr__(self, "smooth_depth", bool(self.smooth_depth))
        for name in ("block_resolution", "block_count"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ConfigError(f"tsdf: {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))

    def replace(self, **changes) -> TsdfSettings:
        """A copy with ``changes`` (checked again)."""
        return replace(self, **changes)

    def open3d_intrinsic(self, intrinsics: Intrinsics) -> np.ndarray:
        """The 3x3 camera matrix handed to Open3D under this pixel convention."""
        shift = 0.0 if self.pixel_centre == "half" else 0.5
        return np.array(
            [[intrinsics.fx, 0.0, intrinsics.cx - shift], [0.0, intrinsics.fy, intrinsics.cy - shift], [0.0, 0.0, 1.0]]
        )

    def integration_key(self) -> tuple:
        """What the volume depends on (everything but the extraction's weight threshold)."""
        return (self.voxel_size, self.trunc_voxels, self.depth_max, self.pixel_centre, self.smooth_depth, self.block_resolution)

    def as_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------
# The volume


class TsdfMapper:
    """A VoxelBlockGrid TSDF volume built with ``settings``, integrating metric depth images.

    ``TsdfMapper(voxel_size, intrinsics)`` (the old form) still works: the
    other settings are :class:`TsdfSettings`' defaults. ``noise``: the sensor's
    noise model (a :class:`~mabdi.sensor_noise.SensorNoise` or its name),
    which ``settings.smooth_depth`` follows.
    """

    def __init__(
        self,
        settings: TsdfSettings | float,
        intrinsics: Intrinsics | SphericalGeometry,
        block_count: int | None = None,
        noise: SensorNoise | str | None = None,
    ):
        import open3d as o3d
        import open3d.core as o3c

        if not isinstance(settings, TsdfSettings):
            settings = TsdfSettings(voxel_size=float(settings))
        if block_count is not None:
            settings = settings.replace(block_count=block_count)
        self._o3d, self._o3c = o3d, o3c
        self.settings = settings
        self.noise = SensorNoise.of(noise or "none")
        self.voxel_size = settings.voxel_size
        self.intrinsics = intrinsics
        self.device = o3c.Device("CPU:0")
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)),
            voxel_size=settings.voxel_size,
            block_resolution=settings.block_resolution,
            block_count=settings.block_count,
            device=self.device,
        )
        self.beams = intrinsics.range_image
        if not self.beams:
            self._intrinsic = o3c.Tensor(settings.open3d_intrinsic(intrinsics), dtype=o3c.float64)

    def integrate(self, depth: np.ndarray, world_from_camera: np.ndarray) -> None:
        """Fuse a (H, W) metric depth image (NaN = no return) taken from ``world_from_camera``
        (a range image, for a spherical sensor: fused along each beam, see the module docs)."""
        o3d, o3c = self._o3d, self._o3c
        s = self.settings
        if s.smooth_depth:
            depth = smooth_depth_by_noise(depth, self.noise, self.intrinsics)
        if self.beams:
            self._integrate_beams(np.asarray(depth, dtype=np.float64), np.asarray(world_from_camera, dtype=np.float64))
            return
        image = o3d.t.geometry.Image(o3c.Tensor(np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0)))
        extrinsic = o3c.Tensor(np.linalg.inv(world_from_camera), dtype=o3c.float64)
        blocks = self.grid.compute_unique_block_coordinates(
            image,
            self._intrinsic,
            extrinsic,
            depth_scale=1.0,
            depth_max=s.depth_max,
            trunc_voxel_multiplier=s.trunc_voxels,
        )
        self.grid.integrate(
            blocks,
            image,
            self._intrinsic,
            extrinsic,
            depth_scale=1.0,
            depth_max=s.depth_max,
            trunc_voxel_multiplier=s.trunc_voxels,
        )

    def _integrate_beams(self, ranges: np.ndarray, world_from_sensor: np.ndarray) -> None:
        """Fuse a range image beam by beam: the voxels each ray crosses within the truncation distance of its hit."""
        o3c = self._o3c
        s = self.settings
        voxel, res = s.voxel_size, s.block_resolution
        trunc = s.trunc_voxels * voxel
        hit = np.isfinite(ranges) & (ranges <= s.depth_max)
        if not hit.any():
            return
        rotation, origin = world_from_sensor[:3, :3], world_from_sensor[:3, 3]
        directions = unit_rays(self.intrinsics)[0][hit] @ rotation.T  # unit rays, world frame
        points = origin + directions * ranges[hit][:, None]
        steps = np.arange(-trunc, trunc + 0.25 * voxel, 0.5 * voxel)
        samples = points[:, None, :] + steps[None, :, None] * directions[:, None, :]  # (beams, steps, 3)
        keys = np.rint(samples / voxel).astype(np.int64)  # the nearest grid point (voxel k sits at k * voxel)
        # a straight ray enters a grid point's cell once: a repeat is always the sample just before
        first = np.ones(keys.shape[:2], dtype=bool)
        first[:, 1:] = np.any(keys[:, 1:] != keys[:, :-1], axis=2)
        beam = np.broadcast_to(np.arange(len(points))[:, None], first.shape)[first]
        keys = keys[first]
        sdf = np.einsum("ij,ij->i", points[beam] - keys * voxel, directions[beam])  # along the beam, + in front
        inside = np.abs(sdf) <= trunc
        keys, sdf = keys[inside], sdf[inside] / trunc
        packed = ((keys[:, 0] + (1 << 20)) << 42) | ((keys[:, 1] + (1 << 20)) << 21) | (keys[:, 2] + (1 << 20))
        packed, inverse = np.unique(packed, return_inverse=True)
        count = np.bincount(inverse)
        total = np.bincount(inverse, weights=sdf)
        keys = np.stack([(packed >> 42) & 0x1FFFFF, (packed >> 21) & 0x1FFFFF, packed & 0x1FFFFF], axis=1) - (1 << 20)
        blocks = np.floor_divide(keys, res)
        local = keys - blocks * res
        blocks, block_of = np.unique(blocks, axis=0, return_inverse=True)
        block_tensor = o3c.Tensor(blocks.astype(np.int32))
        hashmap = self.grid.hashmap()
        buffers, new = hashmap.activate(block_tensor)
        buffers, new = buffers.numpy(), new.numpy()
        tsdf = self.grid.attribute("tsdf").numpy()  # views of the grid's buffers (after any growth)
        weight = self.grid.attribute("weight").numpy()
        if new.any():
            tsdf[buffers[new]] = 0.0
            weight[buffers[new]] = 0.0
        buffers, _ = hashmap.find(block_tensor)
        flat = buffers.numpy().astype(np.int64)[block_of.ravel()] * res**3 + local[:, 0] + res * local[:, 1] + res * res * local[:, 2]
        tsdf, weight = tsdf.reshape(-1), weight.reshape(-1)
        w = weight[flat]
        tsdf[flat] = (tsdf[flat] * w + total) / (w + count)
        weight[flat] = w + count

    def extract(self, weight_threshold: float | None = None) -> vtkPolyData:
        """The zero crossing as a triangle mesh (marching cubes over the blocks).

        Voxels whose weight (frames fused) is not above ``weight_threshold``
        (default: the settings') are left out. An empty volume gives an empty mesh.
        """
        if weight_threshold is None:
            weight_threshold = self.settings.weight_threshold
        try:
            mesh = self.grid.extract_triangle_mesh(weight_threshold=float(weight_threshold)).to_legacy()
        except RuntimeError:  # Open3D raises on a volume with no surface yet
            return vtkPolyData()
        vertices = np.asarray(mesh.vertices)
        triangles = np.asarray(mesh.triangles)
        if len(triangles) == 0:
            return vtkPolyData()
        return triangles_polydata(vertices, triangles, dtype=np.float32)

    def memory_bytes(self) -> int:
        """Bytes of the voxel blocks in use (tsdf + weight, float32 each)."""
        active = int(self.grid.hashmap().size())
        return active * self.settings.block_resolution**3 * 2 * 4


# ---------------------------------------------------------------------------
# A run


@dataclass
class TsdfRun:
    """A TSDF run: the final mesh, per-frame timings, the triangles curve and the volume's memory.

    ``t_depth_ms`` is the time to read each frame from the source (rendering,
    for a simulated source). ``meshes`` holds the final mesh at every weight
    threshold asked for (``mesh`` is the one at ``settings.weight_threshold``).
    """

    voxel_size: float
    mesh: vtkPolyData
    t_depth_ms: list[float]
    t_integrate_ms: list[float]
    extractions: list[tuple[int, int, float]] = field(default_factory=list)  # (frame, triangles, ms)
    seconds: float = 0.0
    volume_bytes: int = 0
    settings: TsdfSettings | None = None
    meshes: dict[float, vtkPolyData] = field(default_factory=dict)
    t_final_extract_ms: dict[float, float] = field(default_factory=dict)

    def growth_per_circle(self, frames: int, turns: float) -> list[int]:
        """Net triangles added in each circle, from the extractions at the circles' ends."""
        index = circle_index(frames, turns)
        ends = [int(np.flatnonzero(index == c).max()) for c in np.unique(index)]
        at = {frame: triangles for frame, triangles, _ in self.extractions}
        counts = [at.get(end, 0) for end in ends]
        return [counts[0]] + [counts[i] - counts[i - 1] for i in range(1, len(counts))]


def _settings_of(settings: TsdfSettings | float | None) -> TsdfSettings:
    if settings is None:
        return TsdfSettings()
    if isinstance(settings, TsdfSettings):
        return settings
    return TsdfSettings(voxel_size=float(settings))


def run_tsdf(
    frames: FrameSource,
    settings: TsdfSettings | float | None = None,
    mesh_every: int | None = 5,
    turns: float | None = None,
    weight_thresholds: Iterable[float] | None = None,
    noise: SensorNoise | str | None = None,
) -> TsdfRun:
    """Integrate every frame of ``frames`` into a TSDF built with ``settings`` and mesh it.

    ``settings`` may be a voxel size (m), the other settings being the
    defaults. The mesh is extracted at the end, also every ``mesh_every``
    frames (None or 0: only at the end) and, with ``turns`` (the helix's
    circles), at the last frame of each circle, for :meth:`TsdfRun.growth_per_circle`.
    The final mesh is extracted at ``settings.weight_threshold`` and at each
    of ``weight_thresholds`` (one integration, several meshes: ``run.meshes``).
    ``noise``: the sensor's noise model, for ``settings.smooth_depth``.
    """
    settings = _settings_of(settings)
    thresholds = [
        settings.replace(weight_threshold=float(w)).weight_threshold for w in weight_thresholds or ()
    ]  # checked
    count = len(frames)
    if count == 0:
        raise ValueError(f"{frames.description}: no frames to integrate")
    mapper = TsdfMapper(settings, frames.intrinsics, noise=noise)
    extract_at: set[int] = set()
    if mesh_every:
        extract_at |= {i for i in range(count) if (i + 1) % mesh_every == 0}
    if turns is not None:
        circle = circle_index(count, turns)
        extract_at |= {int(np.flatnonzero(circle == c).max()) for c in np.unique(circle)}
    run = TsdfRun(settings.voxel_size, vtkPolyData(), [], [], settings=settings)
    start = time.perf_counter()
    for i in range(count):
        t0 = time.perf_counter()
        frame = frames.read(i)
        t1 = time.perf_counter()
        mapper.integrate(frame.depth, frame.world_from_camera)
        t2 = time.perf_counter()
        run.t_depth_ms.append(1000.0 * (t1 - t0))
        run.t_integrate_ms.append(1000.0 * (t2 - t1))
        if i in extract_at or i == count - 1:
            mesh = mapper.extract(settings.weight_threshold)
            ms = 1000.0 * (time.perf_counter() - t2)
            run.extractions.append((i, mesh.GetNumberOfCells(), ms))
            if i == count - 1:
                run.mesh = mesh
                run.meshes[settings.weight_threshold] = mesh
                run.t_final_extract_ms[settings.weight_threshold] = ms
    for threshold in thresholds:
        if threshold in run.meshes:
            continue
        t0 = time.perf_counter()
        run.meshes[threshold] = mapper.extract(threshold)
        run.t_final_extract_ms[threshold] = 1000.0 * (time.perf_counter() - t0)
    run.seconds = time.perf_counter() - start
    run.volume_bytes = mapper.memory_bytes()
    return run


# ---------------------------------------------------------------------------
# Tuning

#: The axes :func:`tune_tsdf` searches, in the order the coordinate search visits them.
TUNED_AXES = ("pixel_centre", "trunc_voxels", "weight_threshold", "depth_max", "smooth_depth")


def default_grid(intrinsics: Intrinsics, noise: SensorNoise | str | None = None) -> dict[str, tuple]:
    """The search grid for ``intrinsics``: truncation 2-6 voxels, weight threshold 0.5-3, both pixel
    conventions, depth range 0.75 far (drops the noisiest far returns) or far (every return;
    anything beyond far, 5 m say, fuses the same), and depth smoothing off and on when ``noise``
    names a noise model (off only without one: there is nothing to smooth)."""
    noisy = SensorNoise.of(noise or "none").noisy
    return {
        "pixel_centre": PIXEL_CENTRES,
        "trunc_voxels": (2.0, 3.0, 4.0, 5.0, 6.0),
        "weight_threshold": (0.5, 1.0, 2.0, 3.0),
        "depth_max": (round(0.75 * intrinsics.far, 3), float(intrinsics.far)),
        "smooth_depth": (False, True) if noisy else (False,),
    }


@dataclass
class TsdfTuning:
    """What :func:`tune_tsdf` found: the best settings, its mesh and score, and every point tried.

    ``table`` has one dict per point scored: the settings' fields, the score's
    entries, ``score_s`` (seconds the score took) and ``best`` (bool).
    ``integrations`` counts the volumes built; ``seconds`` is the whole search,
    of which ``integrate_s``, ``extract_s`` and ``score_s`` are the parts.
    """

    best: TsdfSettings
    mesh: vtkPolyData
    score: dict
    table: list[dict]
    search: str
    grid: dict[str, tuple]
    integrations: int = 0
    seconds: float = 0.0
    integrate_s: float = 0.0
    extract_s: float = 0.0
    score_s: float = 0.0


def _rank(score: dict) -> tuple:
    """Sort key, smaller is better: the highest F@1cm, then the fewest triangles."""
    return (-float(score["fscore_1cm"]), int(score["triangles"]))


def tune_tsdf(
    frames: FrameSource,
    voxel_size: float,
    score: Callable[[vtkPolyData], dict],
    grid: dict[str, Iterable] | None = None,
    search: str = "coordinate",
    start: TsdfSettings | None = None,
    max_rounds: int = 3,
    progress: Callable[[str], None] | None = None,
    noise: SensorNoise | str | None = None,
) -> TsdfTuning:
    """The TSDF settings at ``voxel_size`` that score best on ``frames``.

    ``score(mesh)`` returns a dict with at least ``fscore_1cm``,
    ``precision_1cm``, ``recall_1cm`` and ``triangles``; the best point has the
    highest ``fscore_1cm`` (ties: fewer triangles). ``grid`` maps the axes
    ``pixel_centre``, ``trunc_voxels``, ``weight_threshold``, ``depth_max``,
    ``smooth_depth`` to the values to try (a missing axis: :func:`default_grid`'s
    values for ``noise``, the sensor's noise model; one value fixes it).

    The frames are read once and kept in memory. The weight threshold is an
    extraction parameter, so one volume serves every threshold. Searches:

    * ``"coordinate"`` (default): from ``start`` (default: the plain
      settings, truncation 4, threshold 1, every return, half-pixel centres,
      moved into the grid), try every value of one axis with the others
      held, keep the best, go on to the next axis (pixel convention,
      truncation, threshold, depth range, smoothing); repeat the sweep until a
      whole sweep changes nothing (at most ``max_rounds``). With the default
      grid and no noise that is 11 points and 7 volumes in the first sweep
      (one more of each with a noise model).
    * ``"full"``: every point of the grid (with the default grid 80 points, 20 volumes; twice
      that with a noise model).
    """
    if search not in ("coordinate", "full"):
        raise ValueError(f"tune_tsdf: search must be 'coordinate' or 'full', got {search!r}")
    say = progress or (lambda message: None)
    began = time.perf_counter()
    cached = (
        frames
        if isinstance(frames, FrameList)
        else FrameList([frames.read(i) for i in range(len(frames))], frames.description)
    )
    intrinsics = cached.intrinsics
    axes = default_grid(intrinsics, noise)
    for name, values in (grid or {}).items():
        if name not in axes:
            raise ValueError(f"tune_tsdf: unknown axis {name!r} (known: {', '.join(TUNED_AXES)})")
        values = tuple(values)
        if not values:
            raise ValueError(f"tune_tsdf: axis {name!r} has no values")
        axes[name] = values
    base = (start or TsdfSettings()).replace(voxel_size=voxel_size)
    for name in TUNED_AXES:  # every grid value must make valid settings, checked before any work
        for value in axes[name]:
            base.replace(**{name: value})
    if search == "coordinate":
        held = {name: getattr(base, name) for name in TUNED_AXES}
        for name in TUNED_AXES:
            if held[name] not in axes[name]:  # the nearest grid value (the first, for a name)
                numeric = [v for v in axes[name] if not isinstance(v, str)]
                if numeric and not isinstance(held[name], str):
                    held[name] = min(numeric, key=lambda v: abs(float(v) - float(held[name])))
                else:
                    held[name] = axes[name][0]
        base = base.replace(**held)

    tuning = TsdfTuning(base, vtkPolyData(), {}, [], search, {k: tuple(v) for k, v in axes.items()})
    volumes: OrderedDict[tuple, TsdfMapper] = OrderedDict()  # the last two volumes built
    results: dict[TsdfSettings, tuple[dict, vtkPolyData | None]] = {}
    best: list = [None, None, None]  # settings, score, mesh

    def volume(settings: TsdfSettings) -> TsdfMapper:
        key = settings.integration_key()
        if key in volumes:
            volumes.move_to_end(key)
            return volumes[key]
        t0 = time.perf_counter()
        mapper = TsdfMapper(settings, intrinsics, noise=noise)
        for frame in cached:
            mapper.integrate(frame.depth, frame.world_from_camera)
        tuning.integrate_s += time.perf_counter() - t0
        tuning.integrations += 1
        volumes[key] = mapper
        while len(volumes) > 2:
            volumes.popitem(last=False)
        return mapper

    def evaluate(settings: TsdfSettings) -> dict:
        if settings in results:
            return results[settings][0]
        mapper = volume(settings)
        t0 = time.perf_counter()
        mesh = mapper.extract(settings.weight_threshold)
        t1 = time.perf_counter()
        values = dict(score(mesh))
        t2 = time.perf_counter()
        tuning.extract_s += t1 - t0
        tuning.score_s += t2 - t1
        missing = {"fscore_1cm", "precision_1cm", "recall_1cm", "triangles"} - set(values)
        if missing:
            raise ValueError(f"tune_tsdf: score() must return {', '.join(sorted(missing))}")
        row = {name: getattr(settings, name) for name in ("voxel_size", *TUNED_AXES)}
        row.update(values)
        row["extract_s"], row["score_s"] = t1 - t0, t2 - t1
        tuning.table.append(row)
        if best[0] is None or _rank(values) < _rank(best[1]):
            best[:] = [settings, values, mesh]
        results[settings] = (values, None)
        say(
            f"tsdf {settings.voxel_size * 100:g} cm: trunc {settings.trunc_voxels:g}, weight > {settings.weight_threshold:g}, "
            f"depth_max {settings.depth_max:g}, {settings.pixel_centre}{', smoothed' if settings.smooth_depth else ''}: F@1cm {values['fscore_1cm']:.4f}, "
            f"{int(values['triangles']):,} triangles"
        )
        return values

    if search == "full":
        import itertools

        volumes_grid = itertools.product(
            axes["pixel_centre"], axes["trunc_voxels"], axes["depth_max"], axes["smooth_depth"]
        )
        for pixel, trunc, depth, smooth in volumes_grid:
            for weight in axes["weight_threshold"]:  # one volume, every threshold
                evaluate(
                    base.replace(
                        pixel_centre=pixel, trunc_voxels=trunc, depth_max=depth, smooth_depth=smooth, weight_threshold=weight
                    )
                )
    else:
        current = base
        evaluate(current)
        for _ in range(max_rounds):
            changed = False
            for name in TUNED_AXES:
                candidates = [current.replace(**{name: value}) for value in axes[name]]
                # the current volume's values first, so a threshold sweep reuses it
                candidates.sort(key=lambda s: s.integration_key() != current.integration_key())
                scored = [(evaluate(s), s) for s in candidates]
                winner = min(scored, key=lambda pair: _rank(pair[0]))[1]
                if _rank(results[winner][0]) < _rank(results[current][0]):
                    current, changed = winner, True
            if not changed:
                break

    tuning.best, tuning.score, tuning.mesh = best[0], best[1], best[2]
    for row in tuning.table:
        row["best"] = all(row[name] == getattr(tuning.best, name) for name in ("voxel_size", *TUNED_AXES))
    tuning.seconds = time.perf_counter() - began
    return tuning


def tuning_markdown(tuning: TsdfTuning) -> str:
    """The table of points tried, best first, as markdown."""
    lines = [
        "| pixel centre | trunc (voxels) | weight > | depth max (m) | smoothed | F@1cm | P@1cm | R@1cm | F@2cm | triangles |",
        "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for row in sorted(tuning.table, key=_rank):
        f2 = f"{row['fscore_2cm']:.4f}" if "fscore_2cm" in row else "-"
        mark = " **best**" if row.get("best") else ""
        lines.append(
            f"| {row['pixel_centre']}{mark} | {row['trunc_voxels']:g} | {row['weight_threshold']:g} | {row['depth_max']:g} "
            f"| {'yes' if row.get('smooth_depth') else 'no'} "
            f"| {row['fscore_1cm']:.4f} | {row['precision_1cm']:.4f} | {row['recall_1cm']:.4f} | {f2} | {int(row['triangles']):,} |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------
# Alignment check


def alignment_error(
    frame: DepthFrame, ground_truth: vtkPolyData, voxel_size: float = 0.01, settings: TsdfSettings | None = None
) -> float:
    """Median distance (m) from the TSDF surface of one noise-free ``frame`` to ``ground_truth``.

    A fraction of a millimetre means intrinsics and poses reach Open3D as
    intended; a half-pixel or frame mix-up shows as millimetres to
    centimetres. The frame is fused alone and every voxel it reached is meshed
    (weight threshold 0.5: one frame gives weight 1). ``settings`` (default: the defaults at ``voxel_size``) choose
    the truncation and the pixel convention.
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from mabdi.evaluate.distance import distances_to_mesh

    settings = (settings or TsdfSettings()).replace(voxel_size=voxel_size)
    mapper = TsdfMapper(settings, frame.intrinsics)
    mapper.integrate(frame.depth, frame.world_from_camera)
    mesh = mapper.extract(weight_threshold=0.5)
    if mesh.GetNumberOfPoints() == 0:
        return float("inf")
    vertices = vtk_to_numpy(mesh.GetPoints().GetData())
    return float(np.median(distances_to_mesh(vertices[:: max(1, len(vertices) // 50000)], ground_truth)))


__all__ = [
    "PIXEL_CENTRES",
    "TUNED_AXES",
    "TsdfMapper",
    "TsdfRun",
    "TsdfSettings",
    "TsdfTuning",
    "alignment_error",
    "default_grid",
    "open3d_status",
    "run_tsdf",
    "tune_tsdf",
    "tuning_markdown",
]
