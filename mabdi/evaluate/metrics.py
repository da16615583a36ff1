"""Map quality against the ground truth: accuracy, completeness, F-score, redundancy, size, growth.

Definitions (distances in metres, reported in mm where named so):

* **accuracy**: distances from area-weighted samples of the map to the
  ground-truth surface: mean, median, 95th percentile.
* **precision at tau**: share of the map's samples within tau of the ground truth.
* **recall (completeness) at tau**: share of the *observed* ground-truth
  samples within tau of the map. Observed = seen by some pose of the run
  (:mod:`mabdi.evaluate.visibility`), so surfaces never in view do not count
  as missed. The poses are the true ones where the source knows them
  (:func:`sensor_poses`: with pose noise the sensor saw from its true
  poses, not from the ones the frames carry).
* **F-score at tau**: 2 P R / (P + R) (Tanks and Temples).
* **redundancy**: share of the map's area stacked over a surface made at
  another frame (:mod:`mabdi.evaluate.redundancy`), from the first 50,000
  map samples; None for a map without cell data ``frame`` (a fused TSDF
  surface).
* **size**: triangles, points, bytes in memory (VTK's actual size of the
  merged mesh) and as binary PLY (written to a temporary file and measured).
* **growth**: net triangles added in each circle of the helical path.

tau = 1 cm and 2 cm. Samples: 100,000 on each side by default, fixed seed.
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics
from mabdi.errors import MabdiError
from mabdi.evaluate.distance import distances_to_mesh, distances_within
from mabdi.evaluate.redundancy import DELTA_MIN, redundancy
from mabdi.evaluate.sampling import SurfaceSamples, sample_surface
from mabdi.evaluate.visibility import observed_mask
from mabdi.sensor_noise import SensorNoise
from mabdi.io.vtk_files import write_mesh_file
from mabdi.simulate.path import circle_index

TAUS = (0.01, 0.02)
RECALL_CAP = 0.05
SAMPLES = 100_000
#: Map samples tested for redundancy (the first of the accuracy samples).
REDUNDANCY_SAMPLES = 50_000


@dataclass
class MapMetrics:
    """The numbers of one map against one ground truth (see the module docs)."""

    accuracy_mean_mm: float
    accuracy_median_mm: float
    accuracy_p95_mm: float
    precision_1cm: float
    recall_1cm: float
    fscore_1cm: float
    precision_2cm: float
    recall_2cm: float
    fscore_2cm: float
    redundancy: float | None
    triangles: int
    points: int
    memory_bytes: int
    ply_bytes: int
    observed_samples: int
    growth_per_circle: list[int] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def fscore(precision: float, recall: float) -> float:
    """2 P R / (P + R), 0 when both are 0."""
    return 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0


def observed_ground_truth(
    ground_truth: vtkPolyData,
    scenes,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    count: int = SAMPLES,
    backend: str = "egl",
) -> SurfaceSamples:
    """Area-weighted samples of ``ground_truth`` that some pose saw (``scenes``: one mesh or one per pose)."""
    samples = sample_surface(ground_truth, count)
    seen = observed_mask(samples.points, scenes, poses, intrinsics, backend)
    return SurfaceSamples(samples.points[seen], samples.faces[seen], samples.normals[seen], samples.area)


def redundancy_delta(samples: SurfaceSamples, mesh: vtkPolyData, poses, noise: SensorNoise | None, intrinsics) -> np.ndarray:
    """delta = max(1 cm, 3 sigma(z)) per sample, z its depth from the pose of the frame that made it."""
    frames = mesh.GetCellData().GetArray("frame")
    if noise is None or poses is None or frames is None or not noise.noisy or len(samples) == 0:
        return np.full(len(samples), DELTA_MIN)
    frame_of = vtk_to_numpy(frames).astype(np.int64)[samples.faces]
    poses = np.asarray(poses)
    frame_of = np.clip(frame_of, 0, len(poses) - 1)
    rotation = poses[frame_of, :3, :3]
    offset = samples.points - poses[frame_of, :3, 3]
    z = intrinsics.sensor_values(np.einsum("nij,ni->nj", rotation, offset))  # depth or range from that pose
    sigma = noise.sigma(np.maximum(z, intrinsics.near), intrinsics.near, intrinsics.far)
    return np.maximum(DELTA_MIN, 3.0 * sigma)


def ply_size(mesh: vtkPolyData) -> int:
    """Bytes of ``mesh`` as binary PLY (written to a temporary file)."""
    if mesh.GetNumberOfPoints() == 0:
        return 0
    with tempfile.TemporaryDirectory(prefix="mabdi-ply-") as folder:
        path = write_mesh_file(mesh, Path(folder) / "map.ply")
        return path.stat().st_size


def growth_per_circle(cells_added, turns: float) -> list[int]:
    """Net triangles added in each circle of a helix of ``turns`` circles (frame i at t = i / (N - 1))."""
    added = np.asarray(cells_added, dtype=np.int64)
    circles = max(1, int(round(turns)))
    index = circle_index(len(added), turns)
    return [int(added[index == k].sum()) for k in range(circles)]


def evaluate_map(
    mesh: vtkPolyData,
    ground_truth: vtkPolyData,
    observed: SurfaceSamples,
    delta=DELTA_MIN,
    samples: int = SAMPLES,
    cells_added=None,
    turns: float = 2.0,
) -> MapMetrics:
    """All metrics of ``mesh`` against ``ground_truth`` and its ``observed`` samples."""
    map_samples = sample_surface(mesh, samples)
    if len(map_samples):
        to_truth = distances_to_mesh(map_samples.points, ground_truth)
    else:
        to_truth = np.zeros(0)
    # recall only asks "within tau?": distances beyond RECALL_CAP need not be exact
    to_map = distances_within(observed.points, mesh, cap=RECALL_CAP) if len(observed) else np.zeros(0)
    overlap_samples = SurfaceSamples(
        map_samples.points[:REDUNDANCY_SAMPLES],
        map_samples.faces[:REDUNDANCY_SAMPLES],
        map_samples.normals[:REDUNDANCY_SAMPLES],
        map_samples.area,
    )
    if callable(delta):
        delta = delta(overlap_samples)
    values = {}
    for tau in TAUS:
        name = f"{int(round(tau * 100))}cm"
        precision = float((to_truth <= tau).mean()) if len(to_truth) else 0.0
        recall = float((to_map <= tau).mean()) if len(to_map) else 0.0
        values[f"precision_{name}"] = precision
        values[f"recall_{name}"] = recall
        values[f"fscore_{name}"] = fscore(precision, recall)
    has_samples = len(to_truth) > 0
    return MapMetrics(
        accuracy_mean_mm=1000.0 * float(to_truth.mean()) if has_samples else float("nan"),
        accuracy_median_mm=1000.0 * float(np.median(to_truth)) if has_samples else float("nan"),
        accuracy_p95_mm=1000.0 * float(np.percentile(to_truth, 95)) if has_samples else float("nan"),
        redundancy=redundancy(mesh, overlap_samples, delta),
        triangles=int(mesh.GetNumberOfCells()),
        points=int(mesh.GetNumberOfPoints()),
        memory_bytes=1024 * int(mesh.GetActualMemorySize()),
        ply_bytes=ply_size(mesh),
        observed_samples=len(observed),
        growth_per_circle=growth_per_circle(cells_added, turns) if cells_added is not None else [],
        **values,
    )


def scenes_per_pose(scene, frames: int) -> list[vtkPolyData]:
    """The ground truth as it stood at each frame of a run (one mesh object per distinct object set)."""
    cache: dict[tuple, vtkPolyData] = {}
    meshes = []
    for i in range(frames):
        key = scene.active_objects(i)
        if key not in cache:
            cache[key] = scene.mesh_at(i)
        meshes.append(cache[key])
    return meshes


def sensor_poses(simulation) -> np.ndarray:
    """The poses the sensor really saw from: the source's true poses when known, else the given ones."""
    true_poses = getattr(simulation, "true_poses", None)
    return simulation.poses if true_poses is None else true_poses


def evaluate_run(simulation, result, samples: int = SAMPLES, observed: SurfaceSamples | None = None) -> MapMetrics:
    """Metrics of a finished :class:`mabdi.loop.MappingRun` run against its own scene (``simulation.scene``)."""
    config = simulation.config
    if simulation.scene is None:
        raise MabdiError(f"{simulation.source.description}: no ground-truth scene is known, so the map cannot be evaluated")
    frames = len(simulation.poses)
    intrinsics = simulation.source.intrinsics
    ground_truth = simulation.scene.mesh_at(frames - 1)
    if observed is None:
        observed = observed_ground_truth(
            ground_truth, scenes_per_pose(simulation.scene, frames), sensor_poses(simulation), intrinsics, samples, config.sensor.backend
        )
    noise = config.sensor.sensor_noise()

    meshed = simulation.meshed_poses() if hasattr(simulation, "meshed_poses") else simulation.poses

    def delta(map_samples):  # depth from the poses the frames were meshed with: where the map put the samples
        return redundancy_delta(map_samples, result.mesh, meshed, noise, intrinsics)

    return evaluate_map(
        result.mesh,
        ground_truth,
        observed,
        delta=delta,
        samples=samples,
        cells_added=[r.cells_added for r in result.records],
        turns=config.path.turns,
    )
