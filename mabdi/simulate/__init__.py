"""Simulation: the simulated rig (scene, sensor, helical path), the MABDI loop, the runner and a run's pipeline."""

from mabdi.simulate.loop import FrameRecord, MabdiLoop
from mabdi.simulate.path import helical_path, path_from_config
from mabdi.simulate.rig import SimulatedRig
from mabdi.simulate.run_pipeline import RunObserver, RunPipeline
from mabdi.simulate.runner import RunResult, Simulation

__all__ = [
    "FrameRecord",
    "MabdiLoop",
    "RunObserver",
    "RunPipeline",
    "RunResult",
    "Simulation",
    "SimulatedRig",
    "helical_path",
    "path_from_config",
]
