"""Record a run as a movie: the dashboard of every frame streamed to MP4, PNG snapshots at chosen frames.

:class:`MovieObserver` watches a run (an observer of
:class:`~mabdi.loop.run_pipeline.RunPipeline`, which ``mabdi run
--movie`` adds) and writes ``movie.mp4`` (or ``movie.gif`` without ffmpeg)
into the run's folder, and ``dashboard_<frame>.png`` for each frame in
``snapshots`` (default: the first, the middle and the last). Frames go to
the encoder as they are rendered; nothing is kept per frame. The movie is
closed before ``summary.json`` is written, so it takes its place with the
run's other files. :func:`run_with_movie` runs a MappingRun with one.
"""

from __future__ import annotations

import time
from pathlib import Path

from mabdi.io.atomic import atomic_output
from mabdi.loop.run_pipeline import FrameCallback, RunObserver, RunPipeline
from mabdi.viz.dashboard import SIZE, Dashboard
from mabdi.viz.movie import MovieWriter


def default_snapshots(frames: int) -> list[int]:
    return sorted({0, frames // 2, frames - 1})


class MovieObserver(RunObserver):
    """The dashboard of every frame to the run folder's movie, and PNG snapshots of the chosen frames.

    After the run: ``path`` (the movie, in the finished folder), ``mean_ms``
    (dashboard milliseconds per frame). Needs a run that writes a folder.
    """

    def __init__(self, snapshots=None, fps: float = 5.0, size=SIZE) -> None:
        self.snapshots = snapshots
        self.fps = fps
        self.size = size
        self.path: Path | None = None
        self._chosen: set[int] = set()
        self._dashboard = None
        self._writer = None
        self._ms: list[float] = []

    @property
    def mean_ms(self) -> float:
        return sum(self._ms) / len(self._ms) if self._ms else 0.0

    def on_start(self, pipeline) -> None:
        if pipeline.folder is None:
            raise ValueError("a movie is written into the run's folder: give the run an output folder")
        frames = pipeline.simulation.frames
        self._chosen = set(default_snapshots(frames) if self.snapshots is None else [int(s) % frames for s in self.snapshots])

    def on_frame(self, pipeline, record) -> None:
        from PIL import Image

        folder = pipeline.folder
        if self._dashboard is None:
            self._dashboard = Dashboard(pipeline.simulation, self.size)
            # The writer picks movie.mp4 or, without ffmpeg, movie.gif: list both names.
            self._writer = MovieWriter(folder.path("movie.mp4", "movie.gif"), self.size, self.fps)
        start = time.perf_counter()
        picture = self._dashboard.render(record.frame)
        self._ms.append(1000.0 * (time.perf_counter() - start))
        self._writer.write(picture)
        if record.frame in self._chosen:
            with atomic_output(folder.path(f"dashboard_{record.frame:04d}.png")) as temporary:
                Image.fromarray(picture).save(temporary, format="PNG")

    def on_loop_end(self, pipeline, result) -> None:
        self.path = self._writer.close() if self._writer is not None else None
        self._writer = None
        self._close_dashboard()

    def on_finish(self, pipeline, result) -> None:
        if self.path is not None and pipeline.folder.is_complete:
            self.path = pipeline.folder.folder / Path(self.path).name  # moved from the staging folder

    def on_abort(self, pipeline, error) -> None:
        if self._writer is not None:
            self._writer.abort()
            self._writer = None
        self._close_dashboard()

    def _close_dashboard(self) -> None:
        if self._dashboard is not None:
            self._dashboard.close()
            self._dashboard = None


def run_with_movie(
    simulation, out_dir, snapshots=None, fps: float = 5.0, progress=None, size=SIZE, overwrite: bool = False, finish: bool = True
):
    """Run the simulation into ``out_dir`` with a :class:`MovieObserver`; returns (RunResult, movie path,
    dashboard ms per frame). ``progress(record)`` after each frame; ``overwrite`` and ``finish`` as in
    :class:`~mabdi.loop.run_pipeline.RunPipeline`."""
    movie = MovieObserver(snapshots, fps, size)
    observers = [movie] + ([FrameCallback(progress)] if progress is not None else [])
    result = RunPipeline(simulation, out_dir, observers, overwrite=overwrite, finish=finish).run()
    return result, movie.path, movie.mean_ms
