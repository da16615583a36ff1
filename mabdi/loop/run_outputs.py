"""What a run writes: the result of a run (:class:`RunResult`) and its files in the run folder.

The files of a finished run (each written to a temporary name, then renamed;
the folder follows :mod:`mabdi.io.run_folder`):

* ``config.toml``: the resolved config (every default filled in);
* ``world_mesh.vtp`` (cell data ``frame``) and ``world_mesh.ply`` (binary);
  with ``output.h5``, ``world_mesh.h5`` (:func:`annotated_map`);
* ``metrics.csv``: one row per frame, columns :data:`METRICS_COLUMNS` first;
* ``summary.json``: totals, timings, the source, the machine's render backend,
  and the metrics against the ground truth when the run was evaluated
  (written last, by :func:`finish_run`: a folder with a ``summary.json``
  holds a finished run);
* ``elements.png``: triangles in the map per frame (seed 001 Fig. 7);
* ``poses.npy``: the poses the frames were meshed with (registered to the
  map, :mod:`mabdi.filters.registration`; as given where registration is off
  or failed), the same as a TUM trajectory (``trajectory.txt``: timestamp
  tx ty tz qx qy qz qw), ``poses_given.npy`` (the poses the frames carried),
  ``path.vtp`` (the meshed poses' path) and, when the scene is known,
  ``scene.vtp`` (the ground truth at the last frame);
* ``poses_true.npy`` when the source knows the true poses (a simulation:
  they differ from ``poses.npy`` with ``[sensor.pose_noise]``);
* with ``output.depth_images``: ``depth/D_000000.vti``, ``E_...``, ``labels_...``
  (:class:`mabdi.loop.run_pipeline.DepthImages`);
* ``.mabdi-run.json``: the manifest of the files above (:mod:`mabdi.io.run_folder`);
* while running, with ``output.checkpoint_every``: ``checkpoint.npz``
  (:class:`mabdi.loop.run_pipeline.Checkpoints`).

``simulation`` below is the run's :class:`~mabdi.loop.runner.Simulation`
(its ``config``, ``source``, ``scene``, ``rig``, ``poses``, ``true_poses``,
``meshed_poses()``).
"""

from __future__ import annotations

import csv
import io
import json
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.config import RunConfig
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.checkpoint import VERSION as CHECKPOINT_FORMAT_VERSION
from mabdi.io.hdf5 import write_map
from mabdi.io.plots import write_elements_plot
from mabdi.io.run_folder import RunFolder
from mabdi.io.vtk_files import write_mesh_file, write_polydata
from mabdi.maps.colours import colours_by_normal
from mabdi.maps.labels import label_floor, planar_clusters
from mabdi.maps.layers import add_cost_layers
from mabdi.maps.mesh_map import MeshMap
from mabdi.polydata import polyline
from mabdi.loop.loop import FrameRecord
from mabdi.simulate.recording import TRUE_POSES  # in a run's folder too, when the source knows the true poses
from mabdi.sources.tum import write_tum_trajectory

#: The loop's state every ``output.checkpoint_every`` frames (data only: :mod:`mabdi.io.checkpoint`).
CHECKPOINT = "checkpoint.npz"
CHECKPOINT_VERSION = CHECKPOINT_FORMAT_VERSION
#: The pickled checkpoint of mabdi before format version 2: refused, never loaded.
OLD_CHECKPOINT = "checkpoint.pkl"

#: The first columns of metrics.csv, in this order (counts are triangles; times in ms).
METRICS_COLUMNS = (
    "frame",
    "novel_fraction",
    "cells_added",
    "cells_removed",
    "cells_total",
    "t_depth_ms",
    "t_expected_ms",
    "t_classify_ms",
    "t_remove_ms",
    "t_surface_ms",
    "t_append_ms",
    "t_total_ms",
)


@dataclass
class RunResult:
    """A finished run: its config, one record per frame, the map (one merged vtkPolyData), its scores.

    ``seconds``: time in the loop's steps (the observers' time, a movie's say, is not counted).
    """

    config: RunConfig
    #: One record per frame, in order (:class:`~mabdi.loop.frame_records.FrameRecords` from a run).
    records: Sequence[FrameRecord]
    mesh: vtkPolyData
    map_bytes: int
    seconds: float
    out_dir: Path | None = None
    backend: dict = field(default_factory=dict)
    source: str = ""
    folder: RunFolder | None = field(default=None, repr=False)
    #: ``noise = "auto"``: the calibrated sigma(z) (:meth:`mabdi.noise_calibration.NoiseCalibration.summary`)
    noise_calibration: dict | None = None
    #: The source's intrinsics (:class:`mabdi.camera.Intrinsics` as a dict): ``mabdi view --from-frame`` uses them.
    intrinsics: dict | None = None
    #: The scores against the ground truth (:class:`mabdi.evaluate.metrics.MapMetrics`) when the run was evaluated.
    scores: object = None
    #: Why there are no scores, when there are none (``summary.json``'s ``evaluation``).
    evaluation: str | None = None
    #: Seconds the evaluation took.
    evaluation_seconds: float = 0.0

    @property
    def cells(self) -> np.ndarray:
        """Triangles in the map after each frame."""
        return np.array([r.cells_total for r in self.records])

    def summary(self) -> dict:
        """Totals for ``summary.json`` and the command line."""
        records = self.records
        n = max(len(records), 1)
        stages = ("t_depth_ms", "t_register_ms", "t_expected_ms", "t_classify_ms", "t_refine_ms", "t_remove_ms", "t_surface_ms", "t_append_ms", "t_total_ms")
        return {
            "name": self.config.run.name,
            "source": self.source,
            "frames": len(records),
            "classifier": self.config.classifier.enabled,
            "removal": self.config.classifier.enabled and self.config.classifier.removal,
            "cells_removed": int(sum(r.cells_removed for r in records)),
            "surface": self.config.surface.method,
            "surface_parameters": asdict(self.config.surface.parameters_of()),
            "noise": self.config.sensor.noise,
            "seed": self.config.run.seed,
            "cells": int(self.mesh.GetNumberOfCells()),
            "points": int(self.mesh.GetNumberOfPoints()),
            "map_bytes": int(self.map_bytes),
            "seconds": self.seconds,
            "frames_per_second": len(records) / self.seconds if self.seconds > 0 else None,
            "mean_ms": {s: float(sum(getattr(r, s) for r in records) / n) for s in stages},
            "render": self.backend,
            "registration": registration_summary(records),
            "noise_calibration": self.noise_calibration,
            "intrinsics": self.intrinsics,
        }




def registration_summary(records: list[FrameRecord]) -> dict:
    """How many frames were registered to the map, why the others were not, and the corrections' medians."""
    statuses: dict[str, int] = {}
    for record in records:
        statuses[record.registration] = statuses.get(record.registration, 0) + 1
    registered = [r for r in records if r.registered]
    return {
        "registered": len(registered),
        "not_registered": len(records) - len(registered) - statuses.get("off", 0),
        "statuses": statuses,
        "median_correction_mm": float(np.median([r.correction_mm for r in registered])) if registered else None,
        "median_correction_deg": float(np.median([r.correction_deg for r in registered])) if registered else None,
        "median_residual_mm": float(np.median([r.residual_mm for r in registered])) if registered else None,
    }


def metrics_csv(records: list[FrameRecord]) -> str:
    """metrics.csv text: the :data:`METRICS_COLUMNS` first, then the remaining record fields."""
    names = [f.name for f in fields(FrameRecord)]
    columns = list(METRICS_COLUMNS) + [n for n in names if n not in METRICS_COLUMNS]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for record in records:
        values = asdict(record)
        writer.writerow([f"{values[c]:.3f}" if isinstance(values[c], float) else values[c] for c in columns])
    return buffer.getvalue()


def annotated_map(mesh: vtkPolyData, poses: np.ndarray, intrinsics) -> MeshMap:
    """The run's map as a MeshMap with cost layers, colours by normal, a floor label and planar clusters."""
    mesh_map = MeshMap.from_polydata(mesh)
    mesh_map.vertex_layers = {}  # the merged mesh's point data is not a map layer
    mesh_map.face_layers = {k: v for k, v in mesh_map.face_layers.items() if k == "frame"}
    if mesh_map.number_of_faces:
        add_cost_layers(mesh_map)
        mesh_map.vertex_layers["rgb_colors"] = colours_by_normal(mesh_map.vertex_layers["normals"])
        label_floor(mesh_map)
        planar_clusters(mesh_map, min_faces=10)
    mesh_map.poses = np.asarray(poses, dtype=np.float64)
    mesh_map.intrinsics = intrinsics.to_array()
    return mesh_map


def write_run_outputs(result: RunResult, simulation) -> None:
    """Write a finished run's files (all but ``summary.json``) into its folder, each atomically."""
    folder = result.folder
    config = result.config
    if result.mesh.GetNumberOfCells() == 0:
        # An empty map is a result, but rarely the one wanted: say so (the files stay valid and empty).
        warnings.warn(empty_map_reason(result, simulation), EmptyMapWarning, stacklevel=3)
    if config.output.vtp:
        write_mesh_file(result.mesh, folder.path("world_mesh.vtp"))
    if config.output.ply:
        write_mesh_file(result.mesh, folder.path("world_mesh.ply"))
    if config.output.h5:
        mesh_map = annotated_map(result.mesh, simulation.poses, simulation.source.intrinsics)
        write_map(mesh_map, folder.path("world_mesh.h5"))
    write_text(folder.path("metrics.csv"), metrics_csv(result.records))
    frames = np.array([r.frame for r in result.records])
    label = "mabdi" if config.classifier.enabled else "black box"
    write_elements_plot({label: (frames, result.cells)}, folder.path("elements.png"), title=config.run.name)
    meshed = simulation.meshed_poses()
    with atomic_output(folder.path("poses.npy")) as temporary:
        np.save(temporary, meshed)
    with atomic_output(folder.path("poses_given.npy")) as temporary:
        np.save(temporary, simulation.poses)
    write_tum_trajectory(folder.path("trajectory.txt"), simulation.source.timestamps, meshed, simulation.source.description)
    if getattr(simulation, "true_poses", None) is not None:
        with atomic_output(folder.path(TRUE_POSES)) as temporary:
            np.save(temporary, simulation.true_poses)
    write_polydata(polyline(meshed[:, :3, 3]), folder.path("path.vtp"))
    if simulation.scene is not None:
        write_polydata(simulation.scene.mesh_at(len(simulation.poses) - 1), folder.path("scene.vtp"))


def finish_run(result: RunResult, metrics: dict | None = None, evaluation: str | None = None) -> None:
    """Write ``summary.json`` (with ``metrics`` when the map was evaluated), drop the checkpoint and mark
    the run complete. ``evaluation`` says why there are no metrics, when there are none."""
    folder = result.folder
    summary = result.summary()
    if metrics is not None:
        summary["metrics"] = metrics
    else:
        summary["evaluation"] = evaluation or "not run (mabdi run evaluates unless --no-eval)"
    write_text(folder.path("summary.json"), json.dumps(summary, indent=2) + "\n")
    folder.forget(CHECKPOINT)
    folder.complete()


class EmptyMapWarning(UserWarning):
    """A run ended with a map of no triangles."""


def empty_map_reason(result: RunResult, simulation) -> str:
    """Why a run's map is empty, in words: no objects, nothing in view, or everything filtered."""
    config = result.config
    if simulation.rig is not None and not config.scene.objects:
        return "the map is empty: the scene has no objects ([[scene.objects]] in the config)"
    if not any(r.valid_pixels for r in result.records):
        far = simulation.source.intrinsics.far
        return (
            f"the map is empty: no frame had a depth return (nothing in view within the sensor's range, "
            f"{simulation.source.intrinsics.near:g}-{far:g} m); check the objects' positions, the path and the intrinsics"
        )
    return (
        "the map is empty: frames had depth returns, but the surface filter made no triangles of them "
        f"({config.surface.method}; e.g. too few points per voxel, or every pixel classified known)"
    )


