"""Simulation: the simulated rig (scene, sensor, helical path), the MABDI loop and the runner."""

from mabdi.simulate.loop import FrameRecord, MabdiLoop
from mabdi.simulate.path import helical_path, path_from_config
from mabdi.simulate.rig import SimulatedRig
from mabdi.simulate.runner import RunResult, Simulation

__all__ = ["FrameRecord", "MabdiLoop", "RunResult", "Simulation", "SimulatedRig", "helical_path", "path_from_config"]
