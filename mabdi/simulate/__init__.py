"""Simulation: the helical sensor path and the runner that drives the MABDI loop along it."""

from mabdi.simulate.path import helical_path, path_from_config
from mabdi.simulate.runner import FrameRecord, RunResult, Simulation

__all__ = ["FrameRecord", "RunResult", "Simulation", "helical_path", "path_from_config"]
