"""Simulation: the helical sensor path and the runner that drives the pipeline along it."""

from mabdi.simulate.path import helical_path, path_from_config
from mabdi.simulate.runner import RunSummary, Simulation

__all__ = ["RunSummary", "Simulation", "helical_path", "path_from_config"]
