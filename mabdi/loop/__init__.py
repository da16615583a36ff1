"""The MABDI loop and the runs that drive it.

* :mod:`mabdi.loop.loop`: :class:`MabdiLoop`, one frame at a time (D, registration, E, classifier,
  surface, world mesh, refinement, removal) over any source of depth frames;
* :mod:`mabdi.stages.object_removal`: the removal stage (its rules are :mod:`mabdi.stages.removal`);
* :mod:`mabdi.loop.mapping_run`: :class:`MappingRun`, a run config's rig (or recording) and loop;
* :mod:`mabdi.loop.run_pipeline`: :class:`RunPipeline`, a run from the first frame to its files, with
  observers; :mod:`mabdi.loop.run_outputs` writes those files;
"""

from mabdi.loop.loop import FrameRecord, MabdiLoop
from mabdi.loop.mapper import FrameStep, Mapper, map_frames
from mabdi.loop.run_pipeline import RunObserver, RunPipeline
from mabdi.loop.run_outputs import RunResult
from mabdi.loop.mapping_run import MappingRun

__all__ = [
    "FrameRecord", "FrameStep", "MabdiLoop", "Mapper", "RunObserver", "RunPipeline", "RunResult", "MappingRun",
    "map_frames",
]
