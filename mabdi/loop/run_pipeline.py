"""A run, assembled once: :class:`RunPipeline` and the observers that watch it.

Every way of running the loop goes through one object (``mabdi run`` and
``--resume``, the movie, the dynamic-scene metrics, the bench, a sweep's
cells, :meth:`MappingRun.run <mabdi.loop.mapping_run.MappingRun.run>`). Its steps,
in order (:data:`STEPS`; :meth:`RunPipeline.run` calls a method per step)::

    source      the frames: the MappingRun's source and its MabdiLoop
    outputs     the run folder opened (refused if another run holds it), config.toml (with
                [resolved], what the loop's "auto" settings became), the input files' fingerprint (for --resume)
    loop        frame by frame: MabdiLoop.step(i), then each observer's on_frame
    results     the RunResult and the run's files (mabdi.loop.run_outputs)
    evaluation  the map scored against the ground truth by the ``evaluate`` callable, or why not
    summary     summary.json written last, the checkpoint dropped, the folder complete

Observers watch without changing the map: objects with some of the hooks
``on_start``, ``on_frame``, ``on_loop_end``, ``on_finish``, ``on_abort``
(:class:`RunObserver` has them all), called in the order given. Here:
:class:`ProgressBar`, :class:`FrameCallback`, :class:`DepthImages` and
:class:`Checkpoints`.

Checkpoints (``.mabdi-partial/checkpoint.npz``, :mod:`mabdi.io.checkpoint`)
hold arrays and a JSON header, loaded without pickle; a resumed run
(:func:`mabdi.loop.mapping_run.resume_run`) is the same pipeline started at the
checkpoint's frame. More: docs/architecture.md (``mabdi.loop.run_pipeline``).
"""

from __future__ import annotations

import itertools
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field

from mabdi.config import dump_toml, run_config_toml
from mabdi.interrupts import raise_if_interrupted
from mabdi.io.atomic import write_text
from mabdi.io.checkpoint import write_tree
from mabdi.io.fingerprint import fingerprint, run_inputs
from mabdi.io.run_folder import RunFolder
from mabdi.io.vtk_files import write_image
from mabdi.loop.frame_records import FrameRecords
from mabdi.loop.run_outputs import CHECKPOINT, DepthRangeWarning, RunResult, dropped_depth_note, finish_run, write_run_outputs

#: The steps of a run, in order (see the module docs).
STEPS = ("source", "outputs", "loop", "results", "evaluation", "summary")


class RunObserver:
    """Watches a run (see the module docs); every hook does nothing unless overridden."""

    def on_start(self, pipeline: RunPipeline) -> None:
        pass

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        pass

    def on_loop_end(self, pipeline: RunPipeline, result: RunResult) -> None:
        pass

    def on_finish(self, pipeline: RunPipeline, result: RunResult) -> None:
        pass

    def on_abort(self, pipeline: RunPipeline, error: BaseException) -> None:
        pass


class FrameCallback(RunObserver):
    """A ``progress(record)`` function called after each frame."""

    def __init__(self, progress) -> None:
        self.progress = progress

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        self.progress(record)


class InterruptCheck(RunObserver):
    """Stops the run (KeyboardInterrupt) at its start and after each frame if a SIGINT came that something
    swallowed on its way out (:mod:`mabdi.interrupts`: the command line watches for them)."""

    def on_start(self, pipeline: RunPipeline) -> None:
        raise_if_interrupted()

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        raise_if_interrupted()


class ProgressBar(RunObserver):
    """A one-line progress bar on stderr (only when stderr is a terminal); ``total`` None: not known."""

    def __init__(self, total: int | None, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled and sys.stderr.isatty()

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        self(record)

    def __call__(self, record) -> None:
        if not self.enabled:
            return
        done = record.frame + 1
        if self.total is None:
            sys.stderr.write(f"\rframe {done}  map {record.cells_total:,} triangles ")
            sys.stderr.flush()
            return
        width = 30
        filled = int(width * done / self.total)
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r[{bar}] frame {done}/{self.total}  map {record.cells_total:,} triangles ")
        sys.stderr.flush()
        if done == self.total:
            sys.stderr.write("\n")


class DepthImages(RunObserver):
    """``output.depth_images``: D, and with the classifier E and the labels, of every frame as VTI in ``depth/``."""

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        loop, folder, i = pipeline.simulation.loop, pipeline.folder, record.frame
        write_image(loop.measured_image(), folder.path(f"depth/D_{i:06d}.vti"))
        if loop.classifier_enabled:
            write_image(loop.expected_image(), folder.path(f"depth/E_{i:06d}.vti"))
            write_image(loop.classified_image(), folder.path(f"depth/labels_{i:06d}.vti"))


#: ``output.checkpoint_every = "auto"``: a checkpoint every this many frames at the most often ...
AUTO_CHECKPOINT_FRAMES = 10
#: ... and no sooner than the loop has run this many times as long as the last checkpoint took to write.
AUTO_CHECKPOINT_SPACING = 20.0


class Checkpoints(RunObserver):
    """``output.checkpoint_every = N``: the run's state after every N frames (not after the last), atomically.
    ``"auto"``: after every :data:`AUTO_CHECKPOINT_FRAMES` frames while the map is small; once the last checkpoint
    took more than 1 / :data:`AUTO_CHECKPOINT_SPACING` of the loop's time since the one before, the next waits
    until the loop has run that much longer (writing a large map's state takes seconds, and a long run's
    map only grows). An interruption then loses at most about
    :data:`AUTO_CHECKPOINT_SPACING` times a checkpoint's writing time of work.
    None for a stream of frames (:class:`~mabdi.sources.frames.StreamedFrames`): it cannot be read again to resume."""

    def __init__(self, every: int | str) -> None:
        self.auto = every == "auto"
        self.every = AUTO_CHECKPOINT_FRAMES if self.auto else int(every)
        #: The loop's seconds when the last checkpoint was written, and how long writing it took.
        self._last_loop_seconds: float | None = None
        self._write_seconds = 0.0

    def due(self, done: int, loop_seconds: float) -> bool:
        """Whether a checkpoint is due after ``done`` frames, the loop having run ``loop_seconds`` in all."""
        if done % self.every:
            return False
        if not self.auto or self._last_loop_seconds is None:
            return True
        return loop_seconds - self._last_loop_seconds >= AUTO_CHECKPOINT_SPACING * self._write_seconds

    def on_frame(self, pipeline: RunPipeline, record) -> None:
        done = record.frame + 1
        if pipeline.frames is None:
            return
        if done < pipeline.frames and self.due(done, pipeline.loop_seconds):
            start = time.perf_counter()
            pipeline.write_checkpoint(done)
            self._write_seconds = time.perf_counter() - start
            self._last_loop_seconds = pipeline.loop_seconds


@dataclass
class ResumePoint:
    """Where an interrupted run goes on: its next frame, the records and loop seconds so far, the inputs' fingerprint."""

    next_frame: int
    records: FrameRecords
    seconds: float
    inputs: dict | None = None


@dataclass(eq=False)
class RunPipeline:
    """One run: ``simulation`` (source + loop) through the steps of the module docs, watched by ``observers``.

    ``out_dir``: the run folder (a path or a prepared
    :class:`~mabdi.io.run_folder.RunFolder`), None to write nothing.
    ``evaluate(simulation, result)``: scores the map against the ground truth
    (:func:`mabdi.evaluate.metrics.evaluate_run`); None: not evaluated. An
    empty map is not scored (``mabdi run`` says so) unless ``evaluate_empty``
    (a sweep's or the bench's row: F-score 0).
    ``overwrite``: write into a folder holding files mabdi did not write.
    ``recording``: a recorded source as ``{"path": ..., "options": {...}, "frames": N}``
    (kept in checkpoints, so a resume can reopen it; ``frames``, the first N
    frames run, None for all, defaults to the source's). ``run_options``: plain
    data kept in checkpoints for the resumed run (``{"no_eval": True}``: the
    run stays unevaluated). ``no_eval``: skip the evaluation (default: as
    ``run_options`` says). ``note``: why the ground truth is unknown (the
    evaluation is then skipped, saying so). ``finish``: write
    ``summary.json`` and complete the folder (False: the caller does, with
    :func:`mabdi.loop.run_outputs.finish_run`). ``resume_from``: go on
    from a checkpoint (:func:`mabdi.loop.mapping_run.resume_run`).
    """

    simulation: object
    out_dir: object = None
    observers: list = field(default_factory=list)
    evaluate: object = None
    evaluate_empty: bool = False
    overwrite: bool = False
    recording: dict | None = None
    run_options: dict = field(default_factory=dict)
    no_eval: bool | None = None
    note: str | None = None
    finish: bool = True
    resume_from: ResumePoint | None = None

    def __post_init__(self) -> None:
        self.observers = list(self.observers)
        self.run_options = dict(self.run_options or {})
        asked = getattr(getattr(self.simulation, "source", None), "asked", None)  # a recording's first N frames (RecordedFrames)
        if self.recording is not None and "frames" not in self.recording and asked is not None:
            self.recording = {**self.recording, "frames": asked}  # kept in checkpoints: a resume runs the same frames
        if self.no_eval is None:
            self.no_eval = bool(self.run_options.get("no_eval"))
        self.folder: RunFolder | None = None
        self.records = FrameRecords()
        self.loop_seconds = 0.0
        self.inputs: dict | None = None
        self.result: RunResult | None = None
        self.frames = 0

    @property
    def config(self):
        return self.simulation.config

    def run(self) -> RunResult:
        """The steps of :data:`STEPS` in order; returns the :class:`RunResult` (scores and all). A pipeline runs once."""
        if self.result is not None or self.records:
            raise RuntimeError("this RunPipeline has run: make a new one for another run")
        try:
            for step in STEPS:
                getattr(self, f"_{step}")()
        except BaseException as error:
            self._notify("on_abort", error)
            if self.folder is not None:
                self.folder.release()  # an interrupted run: its staged files stay for --resume, the folder is free
            raise
        self._notify("on_finish", self.result)
        return self.result

    # -- the steps ---------------------------------------------------------------------------------

    def _source(self) -> None:
        """The frames to run: the simulation's source (simulated, recorded or streamed), read by the loop frame by
        frame; ``frames`` is None while a stream's length is not known (it is set when the stream ends)."""
        self.frames = self.simulation.frames

    def _outputs(self) -> None:
        """The run folder, its config.toml and the input files' fingerprint; the built-in observers; ``on_start``."""
        out = self.out_dir
        if out is None:
            self._notify("on_start")
            return
        if isinstance(out, RunFolder):
            self.folder = out
        elif self.resume_from is not None:
            raise ValueError("a resumed run goes on in its own RunFolder (mabdi.loop.mapping_run.resume_run)")
        else:
            self.folder = RunFolder.prepare(out, self.overwrite, self.config.source)
        output = self.config.output
        if self.resume_from is None:
            settings = getattr(self.simulation.loop, "settings", None)  # what every "auto" became: [resolved]
            write_text(self.folder.path("config.toml"), run_config_toml(self.config, settings))
            if output.checkpoint_every:
                self.inputs = fingerprint(self._input_files())
        else:
            self.inputs = self.resume_from.inputs
        built_in = [DepthImages()] if output.depth_images else []
        if output.checkpoint_every:
            built_in.append(Checkpoints(output.checkpoint_every))
        self.observers = built_in + self.observers  # the run's own files first, as frames are made
        self._notify("on_start")

    def _loop(self) -> None:
        """Every frame from the first (or the checkpoint's), each observer told after it."""
        loop = self.simulation.loop
        first = 0
        if self.resume_from is None:
            loop.reset()
        else:
            first = self.resume_from.next_frame
            self.records = FrameRecords(self.resume_from.records)
            self.loop_seconds = float(self.resume_from.seconds)
        watching = self._hooks("on_frame")
        source = self.simulation.source
        for i in range(first, self.frames) if self.frames is not None else itertools.count(first):
            start = time.perf_counter()
            if self.frames is None and not source.has_frame(i):  # a stream: read until it ends
                self.loop_seconds += time.perf_counter() - start
                self.frames = i
                break
            record = loop.step(i)
            self.loop_seconds += time.perf_counter() - start
            self.records.append(record)
            for on_frame in watching:
                on_frame(self, record)
        loop.finish()

    def _results(self) -> None:
        """The RunResult, and the run's files when there is a folder; ``on_loop_end``."""
        simulation, loop = self.simulation, self.simulation.loop
        calibration = loop.noise.calibration
        result = RunResult(
            config=self.config,
            records=self.records,
            mesh=loop.mesh(),
            map_bytes=loop.memory_bytes(),
            seconds=self.loop_seconds,
            out_dir=self.folder.folder if self.folder is not None else None,
            backend=simulation.render_backend(),
            source=simulation.source.description,
            folder=self.folder,
            noise_calibration=calibration.summary() if calibration is not None else None,
            intrinsics=asdict(simulation.source.intrinsics),
            depth_returns=simulation.source.depth_returns() if hasattr(simulation.source, "depth_returns") else None,
        )
        if self.folder is not None:
            write_run_outputs(result, simulation)  # an empty map: EmptyMapWarning says why
        if result.mesh.GetNumberOfCells():
            note = dropped_depth_note(result.depth_returns, simulation.source)
            if note is not None:
                warnings.warn(note, DepthRangeWarning, stacklevel=2)
        self.result = result
        self._notify("on_loop_end", result)

    def _evaluation(self) -> None:
        """Score the map against the ground truth, or say why not (``result.evaluation``)."""
        result = self.result
        if self.no_eval:
            result.evaluation = "skipped (--no-eval)"
        elif self.evaluate is None:
            result.evaluation = None  # summary.json: "not run (mabdi run evaluates unless --no-eval)"
        elif self.note is not None:
            result.evaluation = f"skipped: {self.note}"
        elif self.simulation.scene is None:
            result.evaluation = "skipped: no ground-truth scene"
        elif result.mesh.GetNumberOfCells() == 0 and not self.evaluate_empty:
            result.evaluation = "skipped: the map is empty"
        else:
            start = time.perf_counter()
            result.scores = self.evaluate(self.simulation, result)
            result.evaluation_seconds = time.perf_counter() - start

    def _summary(self) -> None:
        """``summary.json`` last (the scores, or why there are none), the checkpoint dropped, the folder complete."""
        result = self.result
        if self.folder is not None and self.finish:
            finish_run(result, result.scores.as_dict() if result.scores is not None else None, result.evaluation)

    # -- what the steps share ----------------------------------------------------------------------

    def _hooks(self, hook: str) -> list:
        """The observers' ``hook`` methods, in the observers' order (an observer may leave any out)."""
        return [method for method in (getattr(observer, hook, None) for observer in self.observers) if method is not None]

    def _notify(self, hook: str, *args) -> None:
        for method in self._hooks(hook):
            method(self, *args)

    def _input_files(self) -> dict[str, str]:
        """The files this run reads (:func:`mabdi.io.fingerprint.run_inputs`)."""
        recording = self.recording["path"] if self.recording else None
        simulation = self.simulation
        return run_inputs(self.config, recording, scene=simulation.scene is not None or simulation.rig is not None)

    def write_checkpoint(self, next_frame: int) -> None:
        """Save the run's state after ``next_frame`` frames (atomically; the previous checkpoint is replaced)."""
        if self.inputs is None:
            self.inputs = fingerprint(self._input_files())
        config = self.config
        state = {
            "config": dump_toml(config),
            "config_source": str(config.source) if config.source is not None else "",
            "recording": self.recording,
            "run_options": self.run_options,
            "next_frame": next_frame,
            "seconds": float(self.loop_seconds),
            "records": self.records.state(),
            "inputs": self.inputs,
            "loop": self.simulation.loop.state(),
        }
        if hasattr(self.simulation.source, "counts_state"):  # a recording's dropped depth so far (a resume counts it too)
            state["depth_returns"] = self.simulation.source.counts_state()
        write_tree(self.folder.path(CHECKPOINT), state)
