"""What a run writes: the result of a run (:class:`RunResult`) and its files in the run folder.

The files of a finished run (each written to a temporary name, then renamed;
the folder follows :mod:`mabdi.io.run_folder`):

* ``config.toml``: the resolved config (every default filled in), then ``[resolved]``, what the loop's
  "auto" settings became (:func:`mabdi.config.run_config_toml`; not read back);
* ``world_mesh.vtp`` (cell data ``frame``) and ``world_mesh.ply`` (binary);
  with ``output.h5``, ``world_mesh.h5`` (:func:`annotated_map`);
* ``metrics.csv``: one row per frame, columns :data:`METRICS_COLUMNS` first;
* ``summary.json``: totals, timings, the source, the machine's render backend,
  for a recording ``depth_returns`` (pixels dropped as no return, nearer than
  near, beyond far: :func:`depth_returns_summary`),
  and the metrics against the ground truth when the run was evaluated
  (written last, by :func:`finish_run`: a folder with a ``summary.json``
  holds a finished run);
* ``elements.png``: triangles in the map per frame (seed 001 Fig. 7);
* ``poses.npy``: the poses the frames were meshed with (registered to the
  map, :mod:`mabdi.stages.registration`; as given where registration is off
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

``simulation`` below is the run's :class:`~mabdi.loop.mapping_run.MappingRun`
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

from mabdi.camera import Intrinsics
from mabdi.config import RunConfig
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.checkpoint import VERSION as CHECKPOINT_FORMAT_VERSION
from mabdi.io.hdf5 import write_map
from mabdi.io.plots import write_elements_plot
from mabdi.io.run_folder import RunFolder
from mabdi.io.vtk_files import write_mesh_file, write_polydata
from mabdi.mesh_maps.colours import colours_by_normal
from mabdi.mesh_maps.labels import label_floor, planar_clusters
from mabdi.mesh_maps.layers import add_cost_layers
from mabdi.mesh_maps.mesh_map import MeshMap
from mabdi.polydata import polyline
from mabdi.loop.loop import FrameRecord
from mabdi.simulate.recording import TRUE_POSES  # in a run's folder too, when the source knows the true poses
from mabdi.sources.depth_range import DROPPED_SHARE
from mabdi.sources.tum import write_tum_trajectory

#: The loop's state every ``output.checkpoint_every`` frames (data only: :mod:`mabdi.io.checkpoint`).
CHECKPOINT = "checkpoint.npz"
CHECKPOINT_VERSION = CHECKPOINT_FORMAT_VERSION
#: The pickled checkpoint of mabdi before format version 2: refused, never loaded. Kept because run folders
#: written then may still hold one: resuming such a run says why it cannot (:func:`mabdi.loop.mapping_run.read_checkpoint`).
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
    #: A recording's depth before the loop saw it: pixels, and those dropped as no return, nearer than near,
    #: beyond far (:func:`depth_returns_summary`); None for a simulated run.
    depth_returns: dict | None = None

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
            "removal": self.config.classifier.enabled and self.config.removal.enabled,
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
            "registration": {**registration_summary(records), "device": self.config.registration.device},
            "pixel_holes_filled": {
                "frames": sum(1 for r in records if r.filled_pixels),
                "pixels": int(sum(r.filled_pixels for r in records)),
            },
            "noise_calibration": self.noise_calibration,
            "intrinsics": self.intrinsics,
            **({"depth_returns": self.depth_returns} if self.depth_returns is not None else {}),
        }




def registration_summary(records: list[FrameRecord]) -> dict:
    """How many frames were registered to the map, why the others were not, and the corrections' medians."""
    statuses: dict[str, int] = {}
    for record in records:
        statuses[record.registration] = statuses.get(record.registration, 0) + 1
    registered = [r for r in records if r.registered]
    return {
        "registered": len(registered),
        "not_registered": len(records) - len(registered) - statuses.get("off", 0) - statuses.get("exact", 0),
        "statuses": statuses,
        "median_correction_mm": float(np.median([r.correction_mm for r in registered])) if registered else None,
        "median_correction_deg": float(np.median([r.correction_deg for r in registered])) if registered else None,
        "median_residual_mm": float(np.median([r.residual_mm for r in registered])) if registered else None,
        "poor_fit": sum(1 for r in records if r.poor_fit),
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


class DepthRangeWarning(UserWarning):
    """A recording's frames lost more than :data:`DROPPED_SHARE` of their depth values to near and far."""


def depth_range_counts(depth, near: float, far: float) -> np.ndarray:
    """float64[6] of a depth image as read (metres, before :func:`mabdi.depth.only_returns`): pixels, no return
    (not finite, or <= 0), nearer than near (0 < z <= near), beyond far (z >= far), and the smallest and largest
    depth value (NaN when there is none): the rule of :func:`mabdi.depth.returns`, counted by cause."""
    depth = np.asarray(depth)
    with np.errstate(invalid="ignore"):
        values = depth[np.isfinite(depth) & (depth > 0)]
    nearer = np.count_nonzero(values <= near)
    beyond = np.count_nonzero(values >= far)
    low, high = (float(values.min()), float(values.max())) if values.size else (np.nan, np.nan)
    return np.array([depth.size, depth.size - values.size, nearer, beyond, low, high], dtype=np.float64)


def depth_returns_summary(rows, near: float, far: float) -> dict:
    """The frames' :func:`depth_range_counts` rows summed: ``frames``, ``pixels``, ``no_return``,
    ``nearer_than_near``, ``beyond_far``, ``returns`` (what the loop kept), the ``near`` and ``far`` used
    (m), and ``depth_min``, ``depth_max`` of the depth values (m; None when no pixel had one)."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 6)
    pixels, no_return, nearer, beyond = (int(v) for v in rows[:, :4].sum(axis=0))
    lows, highs = rows[:, 4][np.isfinite(rows[:, 4])], rows[:, 5][np.isfinite(rows[:, 5])]
    return {
        "frames": len(rows),
        "pixels": pixels,
        "no_return": no_return,
        "nearer_than_near": nearer,
        "beyond_far": beyond,
        "returns": pixels - no_return - nearer - beyond,
        "near": float(near),
        "far": float(far),
        "depth_min": float(lows.min()) if lows.size else None,
        "depth_max": float(highs.max()) if highs.size else None,
    }


def dropped_share(counts: dict) -> float:
    """The share of the depth values (pixels that had one) dropped as nearer than near or beyond far."""
    valued = counts["pixels"] - counts["no_return"]
    return (counts["nearer_than_near"] + counts["beyond_far"]) / valued if valued else 0.0


def _dropped_words(counts: dict) -> str:
    """What the frames' depth lost, in words and numbers (near and far as shares of the depth values)."""
    pixels = counts["pixels"]
    valued = pixels - counts["no_return"]
    frames = f"{counts['frames']} frame{'s' if counts['frames'] != 1 else ''}"
    if not valued:
        return f"none of the {pixels:,} pixels of {frames} had a depth value"

    def share(n: int) -> str:
        return f"{100.0 * n / valued:.1f}%"

    return (
        f"of the {valued:,} depth values of {frames} ({100.0 * valued / max(pixels, 1):.1f}% of the pixels had one), "
        f"{share(counts['nearer_than_near'])} were nearer than near ({counts['near']:g} m) and "
        f"{share(counts['beyond_far'])} beyond far ({counts['far']:g} m); the depth values run "
        f"{counts['depth_min']:.3g} .. {counts['depth_max']:.3g} m"
    )


def _range_remedy(counts: dict, source) -> str:
    """How to keep the dropped depth of a recording: its near and far, or its depth unit, by the options it takes."""
    from mabdi.sources.sequences import metadata_path

    path = getattr(source, "path", None)
    options = getattr(source, "options", ())
    file = metadata_path(path) if path is not None else "mabdi.toml"
    lidar = not isinstance(getattr(source, "intrinsics", None), Intrinsics)  # a range image: [lidar] range_min, range_max
    near, far, sensor, table = ("range_min", "range_max", "LiDAR", "lidar") if lidar else ("near", "far", "camera", "camera")
    change = [
        words
        for words, count in ((f"a lower {near}", counts["nearer_than_near"]), (f"a higher {far}", counts["beyond_far"]))
        if count
    ]
    text = f"to keep them, give the {sensor} {' and '.join(change) or f'another {near} and {far}'}: {near} and {far} in the [{table}] table of {file}"
    if "camera" in options and not lidar:
        text += " or --camera fx,fy,cx,cy,width,height,near,far"
    valued = counts["pixels"] - counts["no_return"]
    one_side = max(counts["nearer_than_near"], counts["beyond_far"])
    if "depth_scale" in options and valued and one_side >= valued / 2:
        scale = getattr(source, "depth_scale", None)
        used = f" ({scale:g} units per metre here)" if isinstance(scale, (int, float)) else ""
        unit = f"if the depth is in another unit than the reader takes{used}, give --depth-scale (units per metre)"
        # every value on one side: a wrong unit is the likelier cause (a near or far moved to fit it makes a map of the wrong size)
        return f"{unit[0].upper()}{unit[1:]}. Otherwise, {text}." if one_side == valued else f"{text[0].upper()}{text[1:]}; {unit}."
    return f"{text[0].upper()}{text[1:]}."


def dropped_depth_note(counts: dict | None, source) -> str | None:
    """A line on the depth values a recording's frames lost to near and far, when more than
    :data:`DROPPED_SHARE` of them; None otherwise."""
    if counts is None or dropped_share(counts) <= DROPPED_SHARE:
        return None
    return (
        f"{100.0 * dropped_share(counts):.1f}% of the depth values were dropped as outside near..far: "
        f"{_dropped_words(counts)}. {_range_remedy(counts, source)}"
    )


def empty_map_reason(result: RunResult, simulation) -> str:
    """Why a run's map is empty, in words: no objects, nothing in view, depth dropped by near and far
    (with the counts, for a recording), or everything filtered."""
    config = result.config
    if simulation.rig is not None and not config.scene.objects:
        return "the map is empty: the scene has no objects ([[scene.objects]] in the config)"
    counts = result.depth_returns
    no_returns = not any(r.valid_pixels for r in result.records)
    if counts is not None and counts["pixels"]:
        if no_returns:
            if counts["nearer_than_near"] + counts["beyond_far"] == 0:
                return f"the map is empty: {_dropped_words(counts)}"
            return (
                f"the map is empty: no frame kept a depth return between near and far: {_dropped_words(counts)}. "
                f"{_range_remedy(counts, simulation.source)}"
            )
        if dropped_share(counts) >= 0.5:
            return (
                f"the map is empty: most depth values were dropped as outside near..far, and the surface filter "
                f"({config.surface.method}) made no triangles of the rest: {_dropped_words(counts)}. "
                f"{_range_remedy(counts, simulation.source)}"
            )
    if no_returns:
        intrinsics = simulation.source.intrinsics
        reach = f"{intrinsics.near:g}-{intrinsics.far:g} m"
        if simulation.rig is not None:
            return (
                f"the map is empty: no frame had a depth return (nothing in view within the sensor's range, "
                f"{reach}); check the objects' positions, the path and the intrinsics"
            )
        return (
            f"the map is empty: no frame had a depth return within the camera's range ({reach}); "
            "check its near and far, and the depth's unit (--depth-scale)"
        )
    reason = (
        "the map is empty: frames had depth returns, but the surface filter made no triangles of them "
        f"({config.surface.method}; e.g. too few points per voxel, or every pixel classified known)"
    )
    note = dropped_depth_note(counts, simulation.source)
    return reason + (f". Also, {note}" if note else "")
