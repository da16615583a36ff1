"""Filters: one module per VTK algorithm of the MABDI pipeline."""

from mabdi.filters.classifier import ClassifierParameters, FilterClassifier
from mabdi.filters.depth_image import DepthRenderer, FilterDepthImage, SensorNoise
from mabdi.filters.depth_to_surface import FilterDepthImageToSurface
from mabdi.filters.quadtree import FilterQuadTree, QuadTreeParameters
from mabdi.filters.voxel_map import VoxelMap
from mabdi.filters.voxel_planes import FilterVoxelPlanes, VoxelPlanesParameters
from mabdi.filters.world_mesh import FilterWorldMesh

__all__ = [
    "ClassifierParameters",
    "DepthRenderer",
    "FilterClassifier",
    "FilterDepthImage",
    "FilterDepthImageToSurface",
    "FilterQuadTree",
    "FilterVoxelPlanes",
    "FilterWorldMesh",
    "QuadTreeParameters",
    "VoxelMap",
    "VoxelPlanesParameters",
    "SensorNoise",
]
