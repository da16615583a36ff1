"""mabdi: a triangle-mesh map of the world from a moving depth sensor (MABDI, VTK pipeline filters).

Importing mabdi selects VTK's EGL render window (``VTK_DEFAULT_OPENGL_WINDOW``)
unless the user chose another one, so off-screen rendering never tries an X
server. This must happen before VTK is imported, hence first.
"""

import os as _os

_os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

# a Ctrl-C during the imports below is noted, should a library swallow it (mabdi/interrupts.py)
from mabdi import interrupts as _interrupts  # noqa: E402

_interrupts.watch()

from mabdi.algorithm import MabdiAlgorithm, raise_pipeline_errors  # noqa: E402
from mabdi.camera import Intrinsics, backproject, check_pose, look_at, project  # noqa: E402
from mabdi.config import RunConfig, load_run_config  # noqa: E402
from mabdi.depth import DepthFrame, depth_image  # noqa: E402
from mabdi.errors import AssetNotFoundError, ConfigError, MabdiError, PoseError  # noqa: E402
from mabdi.render.depth_image import FilterDepthImage  # noqa: E402
from mabdi.stages.classifier import ClassifierParameters, FilterClassifier  # noqa: E402
from mabdi.stages.registration import FilterRegistration, RegistrationParameters  # noqa: E402
from mabdi.stages.world_mesh import FilterWorldMesh  # noqa: E402
from mabdi.surfaces.pixel_grid import FilterPixelGrid  # noqa: E402
from mabdi.surfaces.quadtree import FilterQuadTree  # noqa: E402
from mabdi.surfaces.voxel_planes import FilterVoxelPlanes  # noqa: E402
from mabdi.mesh_maps import MeshMap  # noqa: E402
from mabdi.sensor_noise import SensorNoise  # noqa: E402
from mabdi.stages.expected_image import FilterExpectedImage  # noqa: E402
from mabdi.surfaces.registry import register_surface_filter  # noqa: E402
from mabdi.loop import FrameStep, MabdiLoop, Mapper, RunObserver, RunPipeline, MappingRun, map_frames  # noqa: E402
from mabdi.simulate import SimulatedRig, helical_path  # noqa: E402
from mabdi.sources import FrameSource, SourceDepthFrames, SourceScene, StreamedFrames  # noqa: E402

_interrupts.unwatch()  # Python's own handler again, for programs that import mabdi

__version__ = "0.1.0"

__all__ = [
    "AssetNotFoundError",
    "ConfigError",
    "DepthFrame",
    "ClassifierParameters",
    "FilterClassifier",
    "FilterDepthImage",
    "FilterExpectedImage",
    "FilterPixelGrid",
    "FrameSource",
    "FrameStep",
    "MabdiLoop",
    "Mapper",
    "SimulatedRig",
    "SourceDepthFrames",
    "register_surface_filter",
    "FilterQuadTree",
    "FilterRegistration",
    "FilterVoxelPlanes",
    "FilterWorldMesh",
    "MeshMap",
    "Intrinsics",
    "MabdiAlgorithm",
    "MabdiError",
    "PoseError",
    "RegistrationParameters",
    "RunObserver",
    "RunPipeline",
    "RunConfig",
    "SensorNoise",
    "MappingRun",
    "SourceScene",
    "StreamedFrames",
    "backproject",
    "check_pose",
    "depth_image",
    "helical_path",
    "load_run_config",
    "look_at",
    "map_frames",
    "project",
    "raise_pipeline_errors",
]
