"""Held-out LiDAR scans: recall, precision and F-score of a map against scans it was never given.

* recall at t (5, 10 cm): share of the held-out points (scans pooled) within t
  of the map (point to nearest triangle);
* precision at 10 cm: share of the map's area (uniform samples, one per
  25 cm^2, at most 3 million) within 10 cm of a held-out point, counting only
  samples some held-out scan could see (:func:`seen_from_scans`: within its
  range limits and vertical field of view, and the ray from its sensor meets
  no map triangle more than 3 cm before the sample);
* F: their harmonic mean at 10 cm; both also by range band, since a scan
  samples far surfaces sparsely (a 1 degree beam spacing is 17 cm at 10 m);
* supported: given the integrated scans' points, the share of the seen area
  that misses precision (no held-out point within 10 cm) but lies within
  10 cm of an integrated point: surface the map's own returns put there
  where the held-out rings are too sparse to say (also by band).

Units: metres (areas m^2, field of view degrees). Frames: compared in the
world frame; scan points come in the sensor frame (x forward, y left, z up),
are returns when ``range_min < r < range_max`` (the reader's rule), and are
moved by the given ``world_from_sensor`` poses (:func:`scan_in_world`).
Distances and rays: Open3D's RaycastingScene (float32, so about an origin
near the map: :class:`MapScene`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.evaluate import metrics
from mabdi.evaluate.sampling import SAMPLE_SEED, SurfaceSamples, sample_surface
from mabdi.polydata import polydata_area, polydata_arrays

#: Recall thresholds (m): the share of held-out points within each of the map.
RECALL_THRESHOLDS_M = (0.05, 0.10)
#: Precision threshold (m): the share of the map's seen area within it of a held-out point; F is at this threshold.
PRECISION_THRESHOLD_M = 0.10
#: Map area per precision sample (m^2): one sample per 25 cm^2.
SAMPLE_AREA_M2 = 0.0025
#: The most precision samples a map gets.
MAX_SAMPLES = 3_000_000
#: A sample is seen from a sensor when no triangle lies on the ray to it more than this (m) before it.
SEEN_TOLERANCE_M = 0.03
#: Edges (m) of the range bands recall and precision are also given in.
RANGE_BANDS_M = (0.0, 5.0, 10.0, 20.0, math.inf)
#: Points (or rays) handed to Open3D in one call.
CHUNK = 1_000_000


def scan_in_world(points, world_from_sensor, range_min: float, range_max: float) -> np.ndarray:
    """(M, 3) float64 world positions of the returns among sensor-frame ``points`` (N, 3+; x y z first):
    finite, with range r in ``range_min < r < range_max`` (m), moved by the 4x4 ``world_from_sensor``."""
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    pose = np.asarray(world_from_sensor, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        r = np.linalg.norm(xyz, axis=1)
        keep = np.isfinite(xyz).all(axis=1) & (r > range_min) & (r < range_max)
    return xyz[keep] @ pose[:3, :3].T + pose[:3, 3]


@dataclass
class HeldOutScans:
    """The held-out scans' returns in the world frame, pooled, and where each scan was taken.

    ``points`` (N, 3) world (m); ``scan`` (N,) the position in ``poses`` of the scan each point came from;
    ``poses`` (S, 4, 4) world_from_sensor; ``range_min``, ``range_max`` (m) the sensor's range limits;
    ``elevation_limits`` (fov_down, fov_up) degrees in the sensor frame, or None: every elevation.
    """

    points: np.ndarray
    scan: np.ndarray
    poses: np.ndarray
    range_min: float
    range_max: float
    elevation_limits: tuple[float, float] | None = None

    @classmethod
    def from_scans(cls, scans, poses, range_min: float, range_max: float, elevation_limits=None) -> HeldOutScans:
        """From sensor-frame scans (a list of (N_i, 3+) arrays) and their world_from_sensor ``poses``."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        scans = list(scans)
        if len(scans) != len(poses):
            raise ValueError(f"HeldOutScans: {len(scans)} scans but {len(poses)} poses")
        world = [scan_in_world(points, pose, range_min, range_max) for points, pose in zip(scans, poses)]
        counts = np.array([len(w) for w in world], dtype=np.int64)
        points = np.concatenate(world) if world else np.zeros((0, 3))
        limits = None if elevation_limits is None else (float(elevation_limits[0]), float(elevation_limits[1]))
        return cls(points, np.repeat(np.arange(len(world)), counts), poses, float(range_min), float(range_max), limits)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def sensor_positions(self) -> np.ndarray:
        """(S, 3) world positions of the scans' sensors."""
        return self.poses[:, :3, 3].copy()


class MapScene:
    """A map's triangles (a vtkPolyData; polygons triangulated) in an Open3D RaycastingScene.

    Open3D works in float32, so the triangles, points and rays are moved by ``-origin`` (the centre of the
    map's bounding box) before they are handed over: a map tens of metres from the world's origin keeps
    sub-millimetre precision.
    """

    def __init__(self, mesh: vtkPolyData) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        if mesh.GetNumberOfCells() == 0 or mesh.GetNumberOfPoints() == 0:
            self.origin = np.zeros(3)
            self.triangles = 0
            return
        vertices, triangles = polydata_arrays(mesh)
        self.origin = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        self.triangles = len(triangles)
        if self.triangles:
            self.scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(vertices - self.origin, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
            )

    def _tensor(self, values: np.ndarray):
        return self._o3d.core.Tensor(np.ascontiguousarray(values, dtype=np.float32))

    def distances(self, points) -> np.ndarray:
        """(N,) float64 distance (m) from each world point (N, 3) to the nearest triangle; +inf for an empty map."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.triangles == 0:
            return np.full(len(points), np.inf)
        out = np.empty(len(points))
        for start in range(0, len(points), CHUNK):
            chunk = points[start : start + CHUNK] - self.origin
            out[start : start + CHUNK] = self.scene.compute_distance(self._tensor(chunk)).numpy()
        return out

    def occluded(self, origins, targets, tolerance: float = SEEN_TOLERANCE_M) -> np.ndarray:
        """(N,) bool: whether the segment from each world ``origins`` (N, 3) to ``targets`` (N, 3) meets a
        triangle more than ``tolerance`` (m) before the target (a target nearer than ``tolerance``: never)."""
        origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), np.shape(targets)).reshape(-1, 3)
        targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(targets), dtype=bool)
        if self.triangles == 0 or len(targets) == 0:
            return out
        offset = targets - origins
        length = np.linalg.norm(offset, axis=1)
        reach = length - tolerance
        test = np.flatnonzero(reach > 0)
        for start in range(0, len(test), CHUNK):
            rows = test[start : start + CHUNK]
            # the direction is scaled so that t = 1 lies ``tolerance`` before the target: one tfar for every ray
            direction = offset[rows] * (reach[rows] / length[rows])[:, None]
            rays = np.concatenate([origins[rows] - self.origin, direction], axis=1)
            out[rows] = self.scene.test_occlusions(self._tensor(rays), tnear=0.0, tfar=1.0).numpy().astype(bool)
        return out


def recall(scene: MapScene, points, thresholds=RECALL_THRESHOLDS_M) -> tuple[dict[float, float], np.ndarray]:
    """({threshold: share of ``points`` within it of the map}, (N,) distances (m)); shares are NaN with no point."""
    distances = scene.distances(points)
    shares = {float(t): float(np.mean(distances <= t)) if len(distances) else math.nan for t in thresholds}
    return shares, distances


def precision_samples(
    mesh: vtkPolyData, sample_area: float = SAMPLE_AREA_M2, max_samples: int = MAX_SAMPLES, seed: int = SAMPLE_SEED
) -> SurfaceSamples:
    """Area-uniform samples on ``mesh``: ceil(area / ``sample_area``) of them, at most ``max_samples``."""
    area = polydata_area(mesh)
    count = min(int(max_samples), int(math.ceil(area / sample_area))) if area > 0 else 0
    return sample_surface(mesh, count, seed)


def seen_from_scans(scene: MapScene, samples, scans: HeldOutScans, tolerance: float = SEEN_TOLERANCE_M) -> np.ndarray:
    """(N,) bool: which world ``samples`` (N, 3) on the map some scan of ``scans`` could see (module docs):
    within its range limits (``range_min < r < range_max``) and elevation limits (in its sensor frame), and not
    hidden behind the map's own triangles (:meth:`MapScene.occluded`)."""
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    seen = np.zeros(len(samples), dtype=bool)
    for pose in scans.poses:
        rest = np.flatnonzero(~seen)
        if len(rest) == 0:
            break
        offset = samples[rest] - pose[:3, 3]
        r = np.linalg.norm(offset, axis=1)
        candidate = (r > scans.range_min) & (r < scans.range_max)
        if scans.elevation_limits is not None:
            up = offset @ pose[:3, 2]  # the sensor's z axis in the world
            with np.errstate(invalid="ignore", divide="ignore"):
                elevation = np.degrees(np.arcsin(np.clip(up / r, -1.0, 1.0)))
            low, high = scans.elevation_limits
            candidate &= (elevation >= low) & (elevation <= high)
        rows = rest[candidate]
        if len(rows):
            seen[rows] = ~scene.occluded(pose[:3, 3], samples[rows], tolerance)
    return seen


def near_points(samples, points, threshold: float) -> np.ndarray:
    """(N,) bool: whether each of ``samples`` (N, 3) has one of ``points`` (M, 3) within ``threshold`` (m)."""
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(samples) == 0 or len(points) == 0:
        return np.zeros(len(samples), dtype=bool)
    distance, _ = cKDTree(points).query(samples, k=1, distance_upper_bound=threshold, workers=-1)
    return distance <= threshold


def nearest_sensor_distances(points, sensors) -> np.ndarray:
    """(N,) distance (m) from each of ``points`` (N, 3) to the nearest of ``sensors`` (S, 3); +inf with none."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(points), np.inf)
    for sensor in np.asarray(sensors, dtype=np.float64).reshape(-1, 3):
        np.minimum(out, np.linalg.norm(points - sensor, axis=1), out=out)
    return out


def by_band(ranges, hits, bands=RANGE_BANDS_M) -> list[tuple[float, float, int, float]]:
    """(from, to, count, share of ``hits``) of the values whose ``ranges`` fall in each band [from, to); ``hits``
    bool, or float (the band's mean: NaN where not measured)."""
    ranges = np.asarray(ranges, dtype=np.float64)
    hits = np.asarray(hits, dtype=np.float64)
    out = []
    for low, high in zip(bands[:-1], bands[1:]):
        inside = (ranges >= low) & (ranges < high)
        count = int(inside.sum())
        out.append((float(low), float(high), count, float(hits[inside].mean()) if count else math.nan))
    return out


def fscore(precision: float, recall_: float) -> float:
    """2 P R / (P + R) (:func:`mabdi.evaluate.metrics.fscore`); NaN when either is NaN."""
    if math.isnan(precision) or math.isnan(recall_):
        return math.nan
    return metrics.fscore(precision, recall_)


@dataclass
class HeldOutScansScore:
    """A map scored against held-out scans (module docs). Shares in [0, 1] (NaN: nothing to count); m, m^2."""

    recall: dict[float, float]
    precision: float
    fscore: float
    precision_threshold_m: float
    points: int
    samples: int
    samples_seen: int
    area_m2: float
    area_seen_m2: float
    triangles: int
    per_scan_recall: list[float] = field(default_factory=list)
    #: One entry per range band (module docs): ``from_m``, ``to_m``, ``points``, ``recall`` (at the precision
    #: threshold), ``samples_seen``, ``precision``, ``supported``.
    by_range: list[dict] = field(default_factory=list)
    #: Share of the seen samples with no held-out point but an integrated one within the precision threshold
    #: (module docs); NaN when no integrated points were given.
    supported: float = math.nan

    def as_dict(self) -> dict:
        out = asdict(self)
        out["recall"] = {f"{t * 100:g}cm": share for t, share in self.recall.items()}
        for band in out["by_range"]:
            band["to_m"] = None if math.isinf(band["to_m"]) else band["to_m"]  # JSON has no infinity
        return out


def score_map(
    mesh: vtkPolyData,
    scans: HeldOutScans,
    recall_thresholds=RECALL_THRESHOLDS_M,
    precision_threshold: float = PRECISION_THRESHOLD_M,
    sample_area: float = SAMPLE_AREA_M2,
    max_samples: int = MAX_SAMPLES,
    tolerance: float = SEEN_TOLERANCE_M,
    integrated_points=None,
) -> HeldOutScansScore:
    """Recall at each of ``recall_thresholds`` and at ``precision_threshold``, precision at
    ``precision_threshold`` over the seen samples, and their F-score, of ``mesh`` against ``scans``.
    ``per_scan_recall``: each scan's recall at ``precision_threshold``. ``integrated_points`` (N, 3) world: the
    points the map was built from, for ``supported`` (module docs); None: not measured."""
    scene = MapScene(mesh)
    thresholds = tuple(dict.fromkeys([*map(float, recall_thresholds), float(precision_threshold)]))
    shares, distances = recall(scene, scans.points, thresholds)
    within = distances <= precision_threshold
    hits = np.bincount(scans.scan, weights=within, minlength=len(scans.poses))
    counts = np.bincount(scans.scan, minlength=len(scans.poses))
    with np.errstate(invalid="ignore", divide="ignore"):
        per_scan = np.where(counts > 0, hits / np.maximum(counts, 1), np.nan)
    samples = precision_samples(mesh, sample_area, max_samples)
    seen = seen_from_scans(scene, samples.points, scans, tolerance)
    close = near_points(samples.points[seen], scans.points, precision_threshold)
    precision = float(close.mean()) if len(close) else math.nan
    supported = np.full(len(close), np.nan)
    if integrated_points is not None:
        supported = (~close & near_points(samples.points[seen], integrated_points, precision_threshold)).astype(np.float64)
    share_seen = float(seen.mean()) if len(seen) else 0.0
    point_ranges = np.linalg.norm(scans.points - scans.poses[scans.scan, :3, 3], axis=1)
    sample_ranges = nearest_sensor_distances(samples.points[seen], scans.sensor_positions)
    bands = [
        {"from_m": low, "to_m": high, "points": points, "recall": point_share, "samples_seen": seen_count, "precision": sample_share,
         "supported": band_supported}  # fmt: skip
        for (low, high, points, point_share), (_, _, seen_count, sample_share), (_, _, _, band_supported) in zip(
            by_band(point_ranges, within), by_band(sample_ranges, close), by_band(sample_ranges, supported)
        )
    ]
    return HeldOutScansScore(
        recall=shares,
        precision=precision,
        fscore=fscore(precision, shares[float(precision_threshold)]),
        precision_threshold_m=float(precision_threshold),
        points=len(scans.points),
        samples=len(samples),
        samples_seen=int(seen.sum()),
        area_m2=float(samples.area),
        area_seen_m2=float(samples.area) * share_seen,
        triangles=scene.triangles,
        per_scan_recall=[float(x) for x in per_scan],
        by_range=bands,
        supported=float(supported.mean()) if len(supported) else math.nan,
    )


__all__ = [
    "HeldOutScans",
    "HeldOutScansScore",
    "MapScene",
    "by_band",
    "near_points",
    "nearest_sensor_distances",
    "precision_samples",
    "recall",
    "scan_in_world",
    "score_map",
    "seen_from_scans",
]
