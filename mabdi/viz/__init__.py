"""Seeing a run: the six-panel dashboard, movies streamed to disk, the map viewer."""

from mabdi.viz.dashboard import Dashboard
from mabdi.viz.movie import MovieWriter
from mabdi.viz.record import MovieObserver, run_with_movie
from mabdi.viz.viewer import view

__all__ = ["Dashboard", "MovieObserver", "MovieWriter", "run_with_movie", "view"]
