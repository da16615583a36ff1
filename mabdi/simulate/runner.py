"""The runner: a run config in, a map and its per-frame records out.

``Simulation(config)`` is the simulated rig (:class:`~mabdi.simulate.rig.SimulatedRig`:
scene, sensor, helical path) feeding the MABDI loop
(:class:`~mabdi.simulate.loop.MabdiLoop`: expected image, classifier,
surface, world mesh), plus the outputs. ``Simulation(config, source=...)``
runs the same loop on any other :class:`~mabdi.sources.frames.FrameSource`
(a recorded sequence), with ``scene=`` the ground truth when it is known.

``run(out_dir)`` steps through every frame of the source and returns a
:class:`RunResult`; with an output folder it writes (each file to a
temporary name, then renamed):

* ``config.toml``: the resolved config (every default filled in);
* ``world_mesh.vtp`` (cell data ``frame``) and ``world_mesh.ply`` (binary);
* ``metrics.csv``: one row per frame, columns :data:`METRICS_COLUMNS`;
* ``summary.json``: totals, timings, the source, the machine's render backend,
  and the metrics against the ground truth when the run was evaluated
  (written last: a folder with a ``summary.json`` holds a finished run);
* ``elements.png``: triangles in the map per frame (seed 001 Fig. 7);
* ``poses.npy``, ``path.vtp`` and, when the scene is known, ``scene.vtp``
  (the ground truth at the last frame);
* with ``output.depth_images``: ``depth/D_000000.vti``, ``E_...``, ``labels_...``;
* ``.mabdi-run.json``: the manifest of the files above (:mod:`mabdi.io.run_folder`);
* while running, with ``output.checkpoint_every``: ``checkpoint.pkl``.
"""

from __future__ import annotations

import csv
import io
import json
import pickle
import time
import tomllib
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.config import RunConfig, dump_toml, run_config_from_dict
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.hdf5 import write_map
from mabdi.io.plots import write_elements_plot
from mabdi.io.run_folder import OutputError, RunFolder
from mabdi.io.vtk_files import write_image, write_mesh_file, write_polydata
from mabdi.maps.colours import colours_by_normal
from mabdi.maps.labels import label_floor, planar_clusters
from mabdi.maps.layers import add_cost_layers
from mabdi.maps.mesh_map import MeshMap
from mabdi.polydata import polyline
from mabdi.simulate.loop import FrameRecord, MabdiLoop
from mabdi.simulate.rig import SimulatedRig
from mabdi.sources.frames import FrameSource
from mabdi.sources.scene import SourceScene

#: The loop's state every ``output.checkpoint_every`` frames (pickled; read only by the same mabdi version).
CHECKPOINT = "checkpoint.pkl"
CHECKPOINT_VERSION = 1

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
    """A finished run: its config, one record per frame, the map (one merged vtkPolyData)."""

    config: RunConfig
    records: list[FrameRecord]
    mesh: vtkPolyData
    map_bytes: int
    seconds: float
    out_dir: Path | None = None
    backend: dict = field(default_factory=dict)
    source: str = ""
    folder: RunFolder | None = field(default=None, repr=False)

    @property
    def cells(self) -> np.ndarray:
        """Triangles in the map after each frame."""
        return np.array([r.cells_total for r in self.records])

    def summary(self) -> dict:
        """Totals for ``summary.json`` and the command line."""
        records = self.records
        n = max(len(records), 1)
        stages = ("t_depth_ms", "t_expected_ms", "t_classify_ms", "t_refine_ms", "t_remove_ms", "t_surface_ms", "t_append_ms", "t_total_ms")
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
        }


class Simulation:
    """A source of depth frames + the MABDI loop + the outputs (see the module docs).

    Attributes: ``config``; ``source`` (the frames); ``rig`` (the
    :class:`SimulatedRig` when the frames are simulated, else None);
    ``scene`` (the ground truth :class:`SourceScene`, None when unknown);
    ``loop`` (:class:`MabdiLoop`); ``poses`` ((N, 4, 4) world_from_camera).
    """

    def __init__(self, config: RunConfig, source: FrameSource | None = None, scene: SourceScene | None = None) -> None:
        self.config = config
        self.rig: SimulatedRig | None = None
        if source is None:
            self.rig = SimulatedRig.from_config(config)
            source = self.rig
            scene = self.rig.scene if scene is None else scene
        self.source = source
        self.scene = scene
        self.loop = MabdiLoop.from_config(config, source)
        self.poses = source.poses

    @property
    def frames(self) -> int:
        """Number of frames a run steps through (the source's)."""
        return len(self.source)

    def step(self, i: int) -> FrameRecord:
        """Run frame ``i`` (see :meth:`MabdiLoop.step`)."""
        return self.loop.step(i)

    def render_backend(self) -> dict:
        """The backend that rendered (the sensor's for simulated frames, else E's)."""
        renderer = self.rig.sensor.renderer if self.rig is not None else self.loop.expected.renderer
        return renderer.describe()

    def run(
        self, out_dir=None, progress=None, *, overwrite: bool = False, finish: bool = True, recording: dict | None = None
    ) -> RunResult:
        """Run every frame; write the outputs of the module docs when ``out_dir`` is given.

        ``progress(record)`` is called after each frame. The output folder
        follows :mod:`mabdi.io.run_folder` (a previous run's files are
        replaced whole; a folder with other files is refused unless
        ``overwrite``). With ``output.checkpoint_every = N`` the loop's state
        is saved every N frames (``checkpoint.pkl``) so that :meth:`resume`
        can finish an interrupted run. ``finish=False`` leaves
        ``summary.json`` and the completion mark to the caller (who
        evaluates first, then calls :func:`finish_run`). ``recording``
        describes a recorded source so a resume can reopen it.
        """
        folder = None
        if out_dir is not None:
            folder = out_dir if isinstance(out_dir, RunFolder) else RunFolder.prepare(out_dir, overwrite, self.config.source)
            write_text(folder.path("config.toml"), dump_toml(self.config))
        self.loop.reset()
        self._recording = recording
        return self._run_frames(folder, 0, [], progress, finish)

    @classmethod
    def resume(cls, out_dir, progress=None, finish: bool = True) -> tuple[Simulation, RunResult]:
        """Finish the interrupted run in ``out_dir`` from its last checkpoint; returns (simulation, result).

        Runs are deterministic, so the map equals the one an uninterrupted run gives.
        """
        folder = RunFolder.resume(out_dir)
        checkpoint = read_checkpoint(folder.staging)
        config = run_config_from_dict(tomllib.loads(checkpoint["config"]), where=str(folder.folder / "config.toml"))
        config.source = Path(checkpoint["config_source"]) if checkpoint["config_source"] else None
        recording = checkpoint["recording"]
        if recording is None:
            simulation = cls(config)
        else:
            from mabdi.simulate.recorded import recorded_simulation  # above this module: imported when needed

            simulation, _ = recorded_simulation(config, recording["path"], **recording["options"])
        simulation._recording = recording
        simulation.loop.set_state(checkpoint["loop"])
        result = simulation._run_frames(folder, checkpoint["next_frame"], checkpoint["records"], progress, finish)
        return simulation, result

    def _run_frames(self, folder, first: int, records: list, progress, finish: bool) -> RunResult:
        every = self.config.output.checkpoint_every
        start = time.perf_counter()
        for i in range(first, self.frames):
            records.append(self.step(i))
            if folder is not None and self.config.output.depth_images:
                self._write_depth_images(folder, i)
            if folder is not None and every and (i + 1) % every == 0 and i + 1 < self.frames:
                self._write_checkpoint(folder, i + 1, records)
            if progress is not None:
                progress(records[-1])
        seconds = time.perf_counter() - start
        result = RunResult(
            config=self.config,
            records=records,
            mesh=self.loop.mesh(),
            map_bytes=self.loop.memory_bytes(),
            seconds=seconds,
            out_dir=folder.folder if folder is not None else None,
            backend=self.render_backend(),
            source=self.source.description,
            folder=folder,
        )
        if folder is not None:
            write_run_outputs(result, self)
            if finish:
                finish_run(result)
        return result

    def _write_checkpoint(self, folder: RunFolder, next_frame: int, records: list) -> None:
        """Save the loop's state after ``next_frame`` frames (atomically; the previous checkpoint is replaced)."""
        state = {
            "version": CHECKPOINT_VERSION,
            "config": dump_toml(self.config),
            "config_source": str(self.config.source) if self.config.source is not None else "",
            "recording": getattr(self, "_recording", None),
            "next_frame": next_frame,
            "records": records,
            "loop": self.loop.state(),
        }
        with atomic_output(folder.path(CHECKPOINT)) as temporary, open(temporary, "wb") as stream:
            pickle.dump(state, stream, protocol=pickle.HIGHEST_PROTOCOL)

    def _write_depth_images(self, folder: RunFolder, i: int) -> None:
        write_image(self.loop.measured_image(), folder.path(f"depth/D_{i:06d}.vti"))
        if self.loop.classifier_enabled:
            write_image(self.loop.expected_image(), folder.path(f"depth/E_{i:06d}.vti"))
            write_image(self.loop.classified_image(), folder.path(f"depth/labels_{i:06d}.vti"))


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


def write_run_outputs(result: RunResult, simulation: Simulation) -> None:
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
    with atomic_output(folder.path("poses.npy")) as temporary:
        np.save(temporary, simulation.poses)
    write_polydata(polyline(simulation.poses[:, :3, 3]), folder.path("path.vtp"))
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


def empty_map_reason(result: RunResult, simulation: Simulation) -> str:
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


def read_checkpoint(folder: Path) -> dict:
    """The checkpoint of an interrupted run (:meth:`Simulation.run` with ``output.checkpoint_every``)."""
    path = Path(folder) / CHECKPOINT
    if not path.is_file():
        raise OutputError(f"cannot resume {folder.parent}: no {CHECKPOINT} (the run stopped before its first checkpoint)")
    try:
        with open(path, "rb") as stream:
            state = pickle.load(stream)
    except Exception as exc:  # a damaged checkpoint: say which file
        raise OutputError(f"cannot resume {folder}: {path} is damaged ({type(exc).__name__}: {exc})") from None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION:
        raise OutputError(f"cannot resume {folder}: {path} was written by another version of mabdi")
    return state
