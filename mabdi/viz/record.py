"""Record a run as a movie: the dashboard of every frame streamed to MP4, PNG snapshots at chosen frames.

:func:`run_with_movie` runs a :class:`~mabdi.simulate.Simulation` like
``simulation.run(out_dir)`` and also writes ``movie.mp4`` (or ``movie.gif``
without ffmpeg) and ``dashboard_<frame>.png`` for each frame in
``snapshots`` (default: the first, the middle and the last). Frames go to
the encoder as they are rendered; nothing is kept per frame.
"""

from __future__ import annotations

import time
from pathlib import Path
from mabdi.io.atomic import atomic_output
from mabdi.io.run_folder import RunFolder
from mabdi.viz.dashboard import SIZE, Dashboard
from mabdi.viz.movie import MovieWriter


def default_snapshots(frames: int) -> list[int]:
    return sorted({0, frames // 2, frames - 1})


def run_with_movie(
    simulation, out_dir, snapshots=None, fps: float = 5.0, progress=None, size=SIZE, overwrite: bool = False, finish: bool = True
):
    """Run the simulation into ``out_dir`` with a dashboard movie; returns (RunResult, movie path, dashboard ms per frame).

    ``overwrite`` and ``finish`` as in :meth:`mabdi.simulate.Simulation.run`.
    """
    from PIL import Image

    frames = len(simulation.poses)
    chosen = set(default_snapshots(frames) if snapshots is None else [int(s) % frames for s in snapshots])
    state = {"writer": None, "dashboard": None, "ms": []}
    folder = RunFolder.prepare(out_dir, overwrite, simulation.config.source)

    def on_frame(record) -> None:
        if state["dashboard"] is None:
            state["dashboard"] = Dashboard(simulation, size)
            # The writer picks movie.mp4 or, without ffmpeg, movie.gif: list both names.
            state["writer"] = MovieWriter(folder.path("movie.mp4", "movie.gif"), size, fps)
        start = time.perf_counter()
        picture = state["dashboard"].render(record.frame)
        state["ms"].append(1000.0 * (time.perf_counter() - start))
        state["writer"].write(picture)
        if record.frame in chosen:
            with atomic_output(folder.path(f"dashboard_{record.frame:04d}.png")) as temporary:
                Image.fromarray(picture).save(temporary, format="PNG")
        if progress is not None:
            progress(record)

    try:
        result = simulation.run(folder, progress=on_frame, finish=False)
        movie = state["writer"].close() if state["writer"] is not None else None
        if finish:  # the movie is written: now the run's files take their places
            from mabdi.simulate.runner import finish_run

            finish_run(result)
        if movie is not None and folder.is_complete:
            movie = folder.folder / Path(movie).name
    except BaseException:
        if state["writer"] is not None:
            state["writer"].abort()
        raise
    finally:
        if state["dashboard"] is not None:
            state["dashboard"].close()
    ms = sum(state["ms"]) / len(state["ms"]) if state["ms"] else 0.0
    return result, movie, ms
