"""The runner: a run config in, a map and its per-frame records out.

``Simulation(config)`` is the simulated rig (:class:`~mabdi.simulate.rig.SimulatedRig`:
scene, sensor, helical path) feeding the MABDI loop
(:class:`~mabdi.simulate.loop.MabdiLoop`: expected image, classifier,
surface, world mesh), plus the outputs. ``Simulation(config, source=...)``
runs the same loop on any other :class:`~mabdi.sources.frames.FrameSource`
(a recorded sequence), with ``scene=`` the ground truth when it is known;
:func:`recorded_simulation` builds one over a recording on disk (and
:meth:`Simulation.resume` reopens it so).

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
* ``poses.npy``: the poses the frames were meshed with (registered to the
  map, :mod:`mabdi.filters.registration`; as given where registration is off
  or failed), the same as a TUM trajectory (``trajectory.txt``: timestamp
  tx ty tz qx qy qz qw), ``poses_given.npy`` (the poses the frames carried),
  ``path.vtp`` (the meshed poses' path) and, when the scene is known,
  ``scene.vtp`` (the ground truth at the last frame);
* ``poses_true.npy`` when the source knows the true poses (a simulation:
  they differ from ``poses.npy`` with ``[sensor.pose_noise]``);
* with ``output.depth_images``: ``depth/D_000000.vti``, ``E_...``, ``labels_...``;
* ``.mabdi-run.json``: the manifest of the files above (:mod:`mabdi.io.run_folder`);
* while running, with ``output.checkpoint_every``: ``checkpoint.npz``.

**Checkpoints** (``.mabdi-partial/checkpoint.npz``, :mod:`mabdi.io.checkpoint`
format version 2: arrays and a JSON header, loaded without pickle, so a
checkpoint from elsewhere runs no code). They hold the resolved config, the
recording and its options, the run's own options (``run_options``: whether
it is evaluated), the next frame, the seconds run so far, the frame records,
:meth:`MabdiLoop.state` and the fingerprint of every input file
(:mod:`mabdi.io.fingerprint`: config file, scene meshes, the recording's
files, by SHA-256). :meth:`Simulation.resume` refuses (an
:class:`~mabdi.io.run_folder.OutputError` naming it) a checkpoint of another
format version, an old ``checkpoint.pkl`` (never unpickled), any input file
that changed, went or appeared since the run started, and a checkpoint that
is past the source's last frame.
"""

from __future__ import annotations

import csv
import io
import json
import time
import tomllib
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.config import RunConfig, dump_toml, run_config_from_dict, scene_digest
from mabdi.errors import ConfigError
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.checkpoint import VERSION as CHECKPOINT_FORMAT_VERSION
from mabdi.io.checkpoint import CheckpointError, read_tree, write_tree
from mabdi.io.fingerprint import changed_inputs, fingerprint, run_inputs
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
from mabdi.sources.sequences import FORMATS, READER_OPTIONS, metadata_path, open_sequence, read_sequence_metadata, sequence_format
from mabdi.sources.tum import write_tum_trajectory

#: The loop's state every ``output.checkpoint_every`` frames (data only: :mod:`mabdi.io.checkpoint`).
#: The true poses, (N, 4, 4): in a run's folder (when the source knows them), and beside a recording made by
#: :func:`mabdi.simulate.recorded.record` (read back by :func:`recorded_simulation`).
TRUE_POSES = "poses_true.npy"
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
    #: ``noise = "auto"``: the calibrated sigma(z) (:meth:`mabdi.filters.noise_calibration.NoiseCalibration.summary`)
    noise_calibration: dict | None = None
    #: The source's intrinsics (:class:`mabdi.camera.Intrinsics` as a dict): ``mabdi view --from-frame`` uses them.
    intrinsics: dict | None = None

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


class Simulation:
    """A source of depth frames + the MABDI loop + the outputs (see the module docs).

    Attributes: ``config``; ``source`` (the frames); ``rig`` (the
    :class:`SimulatedRig` when the frames are simulated, else None);
    ``scene`` (the ground truth :class:`SourceScene`, None when unknown);
    ``loop`` (:class:`MabdiLoop`); ``poses`` ((N, 4, 4) world_from_camera, as
    the frames give them); ``true_poses`` (the poses the sensor really had,
    when known, else None: :attr:`FrameSource.true_poses`).
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
        self.true_poses = source.true_poses

    @property
    def frames(self) -> int:
        """Number of frames a run steps through (the source's)."""
        return len(self.source)

    def step(self, i: int) -> FrameRecord:
        """Run frame ``i`` (see :meth:`MabdiLoop.step`)."""
        return self.loop.step(i)

    def meshed_poses(self) -> np.ndarray:
        """(N, 4, 4) the poses the frames were meshed with: registered to the map, else as given (frames not run too)."""
        trajectory = self.loop.trajectory()
        run = np.isfinite(trajectory).all(axis=(1, 2))
        return np.where(run[:, None, None], trajectory, self.poses)

    def render_backend(self) -> dict:
        """The backend that rendered (the sensor's for simulated frames, else E's)."""
        renderer = self.rig.sensor.renderer if self.rig is not None else self.loop.expected.renderer
        return renderer.describe()

    def run(
        self,
        out_dir=None,
        progress=None,
        *,
        overwrite: bool = False,
        finish: bool = True,
        recording: dict | None = None,
        run_options: dict | None = None,
    ) -> RunResult:
        """Run every frame; write the outputs of the module docs when ``out_dir`` is given.

        ``progress(record)`` is called after each frame. The output folder
        follows :mod:`mabdi.io.run_folder` (a previous run's files are
        replaced whole; a folder with other files is refused unless
        ``overwrite``; a folder another run is writing is refused). With
        ``output.checkpoint_every = N`` the loop's state is saved every N
        frames (``checkpoint.npz``) so that :meth:`resume` can finish an
        interrupted run. ``finish=False`` leaves ``summary.json`` and the
        completion mark to the caller (who evaluates first, then calls
        :func:`finish_run`). ``recording`` describes a recorded source so a
        resume can reopen it (``{"path": ..., "options": {...}}``);
        ``run_options`` (plain data, e.g. ``{"no_eval": True}``) is kept in
        the checkpoint for the resumed run (:attr:`run_options`).
        """
        folder = None
        self._recording = recording
        self.run_options = dict(run_options or {})
        self._inputs = None
        if out_dir is not None:
            folder = out_dir if isinstance(out_dir, RunFolder) else RunFolder.prepare(out_dir, overwrite, self.config.source)
            write_text(folder.path("config.toml"), dump_toml(self.config))
            if self.config.output.checkpoint_every:
                self._inputs = fingerprint(self._input_files())
        self.loop.reset()
        return self._run_frames(folder, 0, [], progress, finish)

    def _input_files(self) -> dict[str, str]:
        """The files this run reads (:func:`mabdi.io.fingerprint.run_inputs`)."""
        recording = self._recording["path"] if getattr(self, "_recording", None) else None
        return run_inputs(self.config, recording, scene=self.scene is not None or self.rig is not None)

    @classmethod
    def resume(cls, out_dir, progress=None, finish: bool = True) -> tuple[Simulation, RunResult]:
        """Finish the interrupted run in ``out_dir`` from its last checkpoint; returns (simulation, result).

        Runs are deterministic, so the map equals the one an uninterrupted run gives. Refused (an
        :class:`OutputError` naming the reason) when an input file changed since the run started, or the
        checkpoint is not one this mabdi reads (see the module docs).
        """
        folder = RunFolder.resume(out_dir)
        try:
            checkpoint = read_checkpoint(folder.staging)
            config = run_config_from_dict(tomllib.loads(checkpoint["config"]), where=str(folder.folder / "config.toml"))
            config.source = Path(checkpoint["config_source"]) if checkpoint["config_source"] else None
            recording = checkpoint["recording"]
            saved_inputs = checkpoint["inputs"]
            changes = changed_inputs(saved_inputs, run_inputs(config, recording["path"] if recording else None, scene=False))
            if changes:
                shown = "; ".join(changes[:3]) + (f"; and {len(changes) - 3} more" if len(changes) > 3 else "")
                raise OutputError(
                    f"cannot resume {folder.folder}: an input changed since the run started ({shown}); "
                    "run it again without --resume"
                )
            if recording is None:
                simulation = cls(config)
            else:
                simulation, simulation_note = recorded_simulation(config, recording["path"], **recording["options"])
                simulation.recording_note = simulation_note  # why the evaluation is skipped, if it is
            first = int(checkpoint["next_frame"])
            if first > simulation.frames:
                raise OutputError(
                    f"cannot resume {folder.folder}: its checkpoint is at frame {first}, "
                    f"but the source has {simulation.frames} frames now"
                )
            try:
                records = [FrameRecord(**record) for record in checkpoint["records"]]
            except TypeError as exc:
                raise OutputError(f"cannot resume {folder.folder}: its checkpoint's frame records do not fit ({exc})") from None
            simulation._recording = recording
            simulation.run_options = dict(checkpoint["run_options"] or {})
            simulation._inputs = saved_inputs
            try:
                simulation.loop.set_state(checkpoint["loop"])
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                raise OutputError(
                    f"cannot resume {folder.folder}: its checkpoint's loop state does not fit this run "
                    f"({type(exc).__name__}: {exc})"
                ) from None
        except BaseException:
            folder.release()
            raise
        result = simulation._run_frames(folder, first, records, progress, finish, float(checkpoint["seconds"]))
        return simulation, result

    def _run_frames(self, folder, first: int, records: list, progress, finish: bool, seconds_before: float = 0.0) -> RunResult:
        """Frames ``first``.. of the source; ``seconds_before``: the time an interrupted run spent on the earlier ones."""
        every = self.config.output.checkpoint_every
        start = time.perf_counter()
        try:
            for i in range(first, self.frames):
                records.append(self.step(i))
                if folder is not None and self.config.output.depth_images:
                    self._write_depth_images(folder, i)
                if folder is not None and every and (i + 1) % every == 0 and i + 1 < self.frames:
                    self._write_checkpoint(folder, i + 1, records, seconds_before + time.perf_counter() - start)
                if progress is not None:
                    progress(records[-1])
        except BaseException:
            if folder is not None:
                folder.release()  # an interrupted run: its staged files stay for --resume, the folder is free
            raise
        seconds = seconds_before + time.perf_counter() - start
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
            noise_calibration=self.loop.noise.calibration.summary() if self.loop.noise.calibration is not None else None,
            intrinsics=asdict(self.source.intrinsics),
        )
        if folder is not None:
            try:
                write_run_outputs(result, self)
                if finish:
                    finish_run(result)
            except BaseException:
                folder.release()
                raise
        return result

    def _write_checkpoint(self, folder: RunFolder, next_frame: int, records: list, seconds: float) -> None:
        """Save the loop's state after ``next_frame`` frames (atomically; the previous checkpoint is replaced)."""
        if getattr(self, "_inputs", None) is None:
            self._inputs = fingerprint(self._input_files())
        state = {
            "config": dump_toml(self.config),
            "config_source": str(self.config.source) if self.config.source is not None else "",
            "recording": getattr(self, "_recording", None),
            "run_options": getattr(self, "run_options", {}),
            "next_frame": next_frame,
            "seconds": float(seconds),
            "records": [asdict(record) for record in records],
            "inputs": self._inputs,
            "loop": self.loop.state(),
        }
        write_tree(folder.path(CHECKPOINT), state)

    def _write_depth_images(self, folder: RunFolder, i: int) -> None:
        write_image(self.loop.measured_image(), folder.path(f"depth/D_{i:06d}.vti"))
        if self.loop.classifier_enabled:
            write_image(self.loop.expected_image(), folder.path(f"depth/E_{i:06d}.vti"))
            write_image(self.loop.classified_image(), folder.path(f"depth/labels_{i:06d}.vti"))


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
    """The checkpoint of an interrupted run (:meth:`Simulation.run` with ``output.checkpoint_every``).

    Data only: nothing in it is executed (an old pickled ``checkpoint.pkl`` is refused unread).
    """
    folder = Path(folder)
    path = folder / CHECKPOINT
    if not path.is_file():
        if (folder / OLD_CHECKPOINT).is_file():
            raise OutputError(
                f"cannot resume {folder.parent}: its checkpoint {folder / OLD_CHECKPOINT} is a pickle from an older mabdi, "
                "which is not loaded (loading a pickle can run code); run it again without --resume"
            )
        raise OutputError(f"cannot resume {folder.parent}: no {CHECKPOINT} (the run stopped before its first checkpoint)")
    try:
        state = read_tree(path)
    except CheckpointError as exc:
        raise OutputError(f"cannot resume {folder.parent}: {exc}") from None
    needed = ("config", "config_source", "recording", "run_options", "next_frame", "seconds", "records", "inputs", "loop")
    missing = [key for key in needed if not isinstance(state, dict) or key not in state]
    if missing:
        raise OutputError(f"cannot resume {folder.parent}: {path} lacks {', '.join(missing)}")
    return state


def recorded_simulation(config: RunConfig, path, **options) -> tuple[Simulation, str | None]:
    """A Simulation over the recording at ``path`` (``options`` go to the reader), and a note when
    the ground truth is unknown (the evaluation is then skipped)."""
    kind = sequence_format(path)
    wanted = READER_OPTIONS[kind]
    for name, value in options.items():
        if value is not None and name not in wanted:
            flag = "--" + name.replace("_", "-")
            raise ConfigError(f"{path} is a {FORMATS[kind][0]}: {flag} does not apply to it")
    source = open_sequence(path, **{k: v for k, v in options.items() if v is not None and k in wanted})
    recorded = read_sequence_metadata(path).get("recorded", {})
    scene = None
    note = None
    if not config.scene.objects:
        note = f"{path}: no scene in the config, so no ground truth: the evaluation is skipped"
    elif recorded.get("scene_digest") != scene_digest(config.scene, recorded.get("frames", len(source))):
        note = (
            f"{path}: the recording does not say it came from this config's scene "
            "(its mabdi.toml [recorded] scene_digest differs or is absent): the evaluation is skipped"
        )
    else:
        base_dir = config.source.parent if config.source is not None else None
        scene = SourceScene(config.scene, frames=int(recorded["frames"]), base_dir=base_dir)
    simulation = Simulation(config, source=source, scene=scene)
    true_file = metadata_path(path).with_name(TRUE_POSES)  # beside the recording's mabdi.toml
    if scene is not None and true_file.is_file():
        true_poses = np.load(true_file, allow_pickle=False)
        if true_poses.shape == simulation.poses.shape:
            simulation.true_poses = true_poses
    return simulation, note
