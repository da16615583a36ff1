"""The runner: a run config in, a map and its per-frame records out.

``MappingRun(config)`` is the simulated rig (:class:`~mabdi.simulate.rig.SimulatedRig`:
scene, sensor, helical path) feeding the MABDI loop
(:class:`~mabdi.loop.loop.MabdiLoop`: expected image, classifier,
surface, world mesh). ``MappingRun(config, source=...)`` runs the same loop
on any other :class:`~mabdi.sources.frames.FrameSource` (a recorded
sequence), with ``scene=`` the ground truth when it is known;
:func:`recorded_simulation` builds one over a recording on disk, its
frames read through :class:`RecordedFrames` (the first ``frames`` of them,
and per frame the pixels dropped as no return, nearer than near or beyond
far, for the run's summary and its warnings).

A run of it is a :class:`~mabdi.loop.run_pipeline.RunPipeline` (the
steps and the observers are listed there; the files a run writes in
:mod:`mabdi.loop.run_outputs`). ``simulation.run(out_dir)`` is that
pipeline without an evaluation; :func:`resume_run` is the pipeline of an
interrupted run, from its last checkpoint (:meth:`MappingRun.resume` runs
it). A resume refuses (an :class:`~mabdi.io.run_folder.OutputError` naming
it) a checkpoint of another format version, an old ``checkpoint.pkl``
(never unpickled), any input file that changed, went or appeared since the
run started (:mod:`mabdi.io.fingerprint`: config file, scene meshes, the
recording's files, by SHA-256), and a checkpoint that is past the source's
last frame.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics
from mabdi.config import RunConfig, run_config_from_dict, scene_digest, with_overrides
from mabdi.errors import ConfigError
from mabdi.io.checkpoint import CheckpointError, read_tree
from mabdi.io.fingerprint import changed_inputs, run_inputs
from mabdi.io.run_folder import OutputError, RunFolder
from mabdi.loop.frame_records import FrameRecords
from mabdi.loop.loop import FrameRecord, MabdiLoop
from mabdi.simulate.recording import TRUE_POSES
from mabdi.simulate.rig import SimulatedRig
from mabdi.loop.run_outputs import CHECKPOINT, OLD_CHECKPOINT, RunResult, depth_range_counts, depth_returns_summary
from mabdi.loop.run_pipeline import FrameCallback, ResumePoint, RunPipeline
from mabdi.sources.depth_range import DepthRange, learn_depth_range
from mabdi.sources.frames import FrameSource, FrameSubset
from mabdi.sources.scene import SourceScene
from mabdi.sources.sequences import FORMATS, READER_OPTIONS, metadata_path, open_sequence, read_sequence_metadata, sequence_format
from mabdi.stages.time_offset import AUTO, learn_recording_time_offset


class MappingRun:
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
        self._poses = source.poses if source.frames_known is not None else None
        self.true_poses = source.true_poses
        #: the pose clock's offset a recording's run learnt (:mod:`mabdi.stages.time_offset`), None when not learnt
        self.learnt_time_offset = None

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) world_from_camera as the frames give them (a stream's: those of the frames read so far)."""
        return self.source.poses if self._poses is None else self._poses

    @property
    def frames(self) -> int | None:
        """Number of frames a run steps through (the source's); None for a stream, whose end is not known yet."""
        return self.source.frames_known

    def step(self, i: int) -> FrameRecord:
        """Run frame ``i`` (see :meth:`MabdiLoop.step`)."""
        return self.loop.step(i)

    def meshed_poses(self) -> np.ndarray:
        """(N, 4, 4) the poses the frames were meshed with: registered to the map, else as given (frames not run too)."""
        trajectory, given = self.loop.trajectory(), self.poses
        if len(given) != len(trajectory):  # a stream's: the frames read so far, the frames run so far
            count = min(len(given), len(trajectory))
            trajectory, given = trajectory[:count], given[:count]
        run = np.isfinite(trajectory).all(axis=(1, 2))
        return np.where(run[:, None, None], trajectory, given)

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
        """Run every frame: ``RunPipeline(self, out_dir, ...).run()`` without an evaluation (see
        :class:`~mabdi.loop.run_pipeline.RunPipeline` for the arguments; ``progress(record)`` is
        called after each frame). Writes the files of :mod:`mabdi.loop.run_outputs` when ``out_dir``
        is given."""
        observers = [FrameCallback(progress)] if progress is not None else []
        pipeline = RunPipeline(
            self, out_dir, observers, overwrite=overwrite, recording=recording, run_options=run_options or {}, finish=finish
        )
        self.run_options = pipeline.run_options
        return pipeline.run()

    @classmethod
    def resume(cls, out_dir, progress=None, finish: bool = True) -> tuple[MappingRun, RunResult]:
        """Finish the interrupted run in ``out_dir`` from its last checkpoint (:func:`resume_run`, not
        evaluated); returns (simulation, result)."""
        pipeline = resume_run(out_dir, [FrameCallback(progress)] if progress is not None else [], finish=finish)
        return pipeline.simulation, pipeline.run()


def resume_run(out_dir, observers=(), **options) -> RunPipeline:
    """The pipeline of the interrupted run in ``out_dir``, set to go on from its last checkpoint.

    Runs are deterministic, so ``.run()`` gives the map an uninterrupted run gives. ``options`` go to
    :class:`RunPipeline` (``evaluate``, ``no_eval``, ``finish``); the recording and the run's options
    are the checkpoint's. Refused (an :class:`OutputError` naming the reason) when an input file changed
    since the run started, or the checkpoint is not one this mabdi reads (see the module docs).
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
        note = None
        if recording is None:
            simulation = MappingRun(config)
        else:
            simulation, note = recorded_simulation(
                config, recording["path"], frames=recording.get("frames"), **recording["options"]
            )
        first = int(checkpoint["next_frame"])
        if first > simulation.frames:
            raise OutputError(
                f"cannot resume {folder.folder}: its checkpoint is at frame {first}, "
                f"but the source has {simulation.frames} frames now"
            )
        try:
            records = FrameRecords.from_state(checkpoint["records"])
        except TypeError as exc:
            raise OutputError(f"cannot resume {folder.folder}: its checkpoint's frame records do not fit ({exc})") from None
        try:
            simulation.loop.set_state(checkpoint["loop"])
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise OutputError(
                f"cannot resume {folder.folder}: its checkpoint's loop state does not fit this run "
                f"({type(exc).__name__}: {exc})"
            ) from None
        counts = checkpoint.get("depth_returns")
        if counts is not None and hasattr(simulation.source, "set_counts_state"):
            simulation.source.set_counts_state(counts)
    except BaseException:
        folder.release()
        raise
    run_options = dict(checkpoint["run_options"] or {})
    simulation.run_options = run_options
    simulation.recording_note = note  # why the evaluation is skipped, if it is
    if run_options.get("no_eval"):
        options["no_eval"] = True  # a run started with --no-eval stays unevaluated
    resume_from = ResumePoint(first, records, float(checkpoint["seconds"]), saved_inputs)
    return RunPipeline(
        simulation, folder, list(observers), recording=recording, run_options=run_options, note=note,
        resume_from=resume_from, **options,
    )


def read_checkpoint(folder: Path) -> dict:
    """The checkpoint of an interrupted run (:meth:`MappingRun.run` with ``output.checkpoint_every``).

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


#: The noise model of a depth camera's recording whose run states none (no config file, or one whose ``[sensor]``
#: leaves ``noise`` out, and no ``--noise``): learnt from the run (:mod:`mabdi.noise_calibration`), since every
#: real camera has noise and its model is unknown; ``none`` would hold the thresholds at ``tau_min`` at every depth.
RECORDING_NOISE = "auto"
#: The noise model of a LiDAR's recording whose run states none: ``range``, at the config's ``range_sigma``
#: (0.02 m, the figure spinning LiDARs' datasheets give); ``none`` would take every range as exact and see
#: through the map wherever a real scan's 2-5 cm of noise meets it at grazing incidence.
RECORDING_LIDAR_NOISE = "range"

#: The fields of ``--camera fx,fy,cx,cy,width,height[,near,far]``, in order.
CAMERA_FIELDS = ("fx", "fy", "cx", "cy", "width", "height", "near", "far")


def camera_option(text: str) -> Intrinsics:
    """``--camera fx,fy,cx,cy,width,height[,near,far]`` as :class:`Intrinsics` (mabdi's pixel centres, metres):
    fx, fy positive, width and height positive whole numbers of pixels; a :class:`ConfigError` names the field."""
    fields = [field.strip() for field in text.split(",")]
    if len(fields) not in (6, 8):
        raise ConfigError(
            f"--camera {text}: expected 6 numbers fx,fy,cx,cy,width,height (or 8, with near,far in metres), got {len(fields)}"
        )
    values = {}
    for name, field in zip(CAMERA_FIELDS, fields):
        try:
            value = float(field)
        except ValueError:
            raise ConfigError(f"--camera {text}: {name} must be a number, got {field!r}") from None
        if not np.isfinite(value):
            raise ConfigError(f"--camera {text}: {name} must be finite, got {field!r}")
        if name in ("width", "height"):
            if not (value.is_integer() and value > 0):
                raise ConfigError(f"--camera {text}: {name} must be a positive whole number of pixels, got {field}")
            value = int(value)
        elif name in ("fx", "fy", "near", "far") and value <= 0:
            raise ConfigError(f"--camera {text}: {name} must be positive, got {field}")
        values[name] = value
    try:
        return Intrinsics(**values)
    except ConfigError as exc:
        raise ConfigError(f"--camera {text}: {str(exc).removeprefix('intrinsics: ')}") from None


class RecordedFrames(FrameSubset):
    """A recording's first ``frames`` frames (all when None, or when it has fewer), counting per frame the pixels
    its depth loses before the loop sees it: no return, nearer than near, beyond far (:meth:`depth_returns`).

    ``depth_range``: a near and far learnt from the frames (:mod:`mabdi.sources.depth_range`) that replace the
    camera's; None keeps them. Everything else is the recording's (``recording``: the reader). ``asked``: the
    frames asked for (None: all).
    """

    def __init__(self, recording: FrameSource, frames: int | None = None, path=None, depth_range: DepthRange | None = None) -> None:
        self.recording = recording
        self.depth_range = depth_range
        self.available = len(recording)
        self.asked = None if frames is None else int(frames)
        if self.asked is not None and self.asked < 1:
            raise ConfigError(f"{recording.description}: frames must be at least 1, got {self.asked}")
        self.count = self.available if self.asked is None else min(self.asked, self.available)
        super().__init__(recording, np.arange(self.count))
        self.description = recording.description
        if self.count < self.available:
            self.description += f", its first {self.count} frame{'s' if self.count != 1 else ''} run"
        if depth_range is not None:
            self.description += f", {depth_range.note()}"
        self.path = None if path is None else Path(path)
        self._counts: dict[int, np.ndarray] = {}

    def __getattr__(self, name):
        if name == "recording":  # not set yet: no recursion
            raise AttributeError(name)
        return getattr(self.recording, name)  # the reader's own (depth_scale, folder, skipped, ...)

    @property
    def intrinsics(self):
        geometry = self.recording.intrinsics
        if self.depth_range is None:
            return geometry
        return dataclasses.replace(geometry, near=self.depth_range.near, far=self.depth_range.far)

    def read_frame(self, index: int):
        frame = self.recording.read_frame(index)  # as the recording has it: the counts come before the near/far cut
        if self.depth_range is not None:
            frame.intrinsics = self.intrinsics
        geometry = frame.intrinsics
        self._counts[index] = depth_range_counts(frame.depth, geometry.near, geometry.far)
        return frame

    def depth_returns(self) -> dict | None:
        """The counts over the frames read so far (:func:`mabdi.loop.run_outputs.depth_returns_summary`); None before any."""
        if not self._counts:
            return None
        geometry = self.intrinsics
        return depth_returns_summary(np.stack(list(self._counts.values())), geometry.near, geometry.far)

    def counts_state(self) -> np.ndarray:
        """The per-frame counts as one (N, 7) array: frame index, then :func:`depth_range_counts`'s six (a checkpoint's)."""
        rows = [np.concatenate(([index], counts)) for index, counts in sorted(self._counts.items())]
        return np.array(rows, dtype=np.float64).reshape(-1, 7)

    def set_counts_state(self, state) -> None:
        """Take back :meth:`counts_state` (a resumed run counts its first frames too)."""
        state = np.asarray(state, dtype=np.float64).reshape(-1, 7)
        self._counts = {int(row[0]): row[1:].copy() for row in state}


def depth_range_stated(path, camera) -> bool:
    """Whether a depth camera's near and far are stated for the recording at ``path``: near or far in its
    ``mabdi.toml`` ``[camera]`` table (mabdi writes both with every recording), or ``camera`` given as
    ``"fx,fy,cx,cy,width,height,near,far"`` or as :class:`Intrinsics` (a preset's name states no range)."""
    table = read_sequence_metadata(path).get("camera", {})
    if isinstance(table, dict) and ("near" in table or "far" in table):
        return True
    if isinstance(camera, str):
        return camera.count(",") == len(CAMERA_FIELDS) - 1
    return isinstance(camera, Intrinsics)


def recorded_simulation(
    config: RunConfig, path, noise_stated: bool = True, frames: int | None = None, **options
) -> tuple[MappingRun, str | None]:
    """A MappingRun over the recording at ``path`` (``options`` go to the reader; ``camera`` may also be
    ``"fx,fy,cx,cy,width,height[,near,far]"``, :func:`camera_option`), and a note when the ground truth is
    unknown (the evaluation is then skipped). ``frames``: run the recording's first ``frames`` frames (None, or
    more than it has: all of them; :class:`RecordedFrames`). ``noise_stated`` False (no config file, or one that
    leaves ``[sensor] noise`` out, and no noise model given): a depth camera's recording runs with
    :data:`RECORDING_NOISE`, a LiDAR's with :data:`RECORDING_LIDAR_NOISE`. A reader that pairs depth with a pose
    stream of its own (TUM) takes ``time_offset`` (seconds, or ``"auto"``, the default: learnt over the frames
    run, :mod:`mabdi.stages.time_offset`; what was found is the run's ``learnt_time_offset``)."""
    kind = sequence_format(path)
    wanted = READER_OPTIONS[kind]
    for name, value in options.items():
        if value is not None and name not in wanted:
            flag = "--" + name.replace("_", "-")
            raise ConfigError(f"{path} is a {FORMATS[kind][0]}: {flag} does not apply to it")
    reader_options = {k: v for k, v in options.items() if v is not None and k in wanted}
    camera = reader_options.get("camera")
    if isinstance(camera, str) and "," in camera:
        reader_options["camera"] = camera_option(camera)
    learn_offset = "time_offset" in wanted and reader_options.get("time_offset", AUTO) == AUTO
    if learn_offset:
        reader_options.pop("time_offset", None)
    recording = open_sequence(path, **reader_options)
    time_offset = learn_recording_time_offset(recording, frames) if learn_offset else None
    if time_offset is not None and time_offset.applied:
        recording = recording.with_time_offset(time_offset.seconds)
    source = RecordedFrames(recording, frames, path=path)
    if isinstance(recording.intrinsics, Intrinsics) and not depth_range_stated(path, camera):
        depth_range = learn_depth_range(recording, source.count)  # from the frames the run takes
        if depth_range is not None:
            source = RecordedFrames(recording, frames, path=path, depth_range=depth_range)
    source.options = wanted  # the remedies a message may name (--camera, --depth-scale)
    if not noise_stated:
        if isinstance(source.intrinsics, Intrinsics):
            stated = {"sensor.noise": RECORDING_NOISE}
        else:
            stated = {"sensor.kind": "lidar", "sensor.noise": RECORDING_LIDAR_NOISE}
        config = with_overrides(config, stated, f"{path} (no noise model stated)")
    recorded = read_sequence_metadata(path).get("recorded", {})
    scene = None
    note = None
    if not config.scene.objects:
        note = f"{path}: no scene in the config, so no ground truth: the evaluation is skipped"
    elif recorded.get("scene_digest") != scene_digest(config.scene, recorded.get("frames", source.available)):
        note = (
            f"{path}: the recording does not say it came from this config's scene "
            "(its mabdi.toml [recorded] scene_digest differs or is absent): the evaluation is skipped"
        )
    else:
        base_dir = config.source.parent if config.source is not None else None
        scene = SourceScene(config.scene, frames=int(recorded["frames"]), base_dir=base_dir)
    simulation = MappingRun(config, source=source, scene=scene)
    simulation.learnt_time_offset = time_offset
    true_file = metadata_path(path).with_name(TRUE_POSES)  # beside the recording's mabdi.toml
    if scene is not None and true_file.is_file():
        true_poses = np.load(true_file, allow_pickle=False)
        if true_poses.shape == (source.available, 4, 4):
            simulation.true_poses = true_poses[: source.count]
    return simulation, note
