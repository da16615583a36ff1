"""Filters: one module per VTK algorithm of the MABDI pipeline, and beside them what only they use: their
numba kernels, the surface registry, the rules of removal and refinement (the loop runs those stages,
:mod:`mabdi.loop`) and the map's anchor of registration. The voxel planes' storage is
:mod:`mabdi.voxels`; the sensor's noise model, which every depth image carries, is
:mod:`mabdi.sensor_noise` (its online calibration :mod:`mabdi.noise_calibration`)."""

from mabdi.filters.classifier import ClassifierParameters, FilterClassifier
from mabdi.filters.depth_image import DepthRenderer, FilterDepthImage
from mabdi.filters.pixel_grid import FilterPixelGrid, PixelGridParameters
from mabdi.filters.map_anchor import MapAnchor
from mabdi.filters.quadtree import FilterQuadTree, QuadTreeParameters
from mabdi.filters.registration import FilterRegistration, RegistrationParameters
from mabdi.voxels.voxel_map import VoxelMap
from mabdi.filters.voxel_planes import FilterVoxelPlanes, VoxelPlanesParameters
from mabdi.filters.world_mesh import FilterWorldMesh
from mabdi.filters.registry import make_surface_filter, register_surface_filter, surface_filter, surface_filter_names

__all__ = [
    "ClassifierParameters",
    "DepthRenderer",
    "FilterClassifier",
    "FilterDepthImage",
    "FilterPixelGrid",
    "PixelGridParameters",
    "make_surface_filter",
    "register_surface_filter",
    "surface_filter",
    "surface_filter_names",
    "FilterQuadTree",
    "FilterRegistration",
    "FilterVoxelPlanes",
    "FilterWorldMesh",
    "MapAnchor",
    "QuadTreeParameters",
    "RegistrationParameters",
    "VoxelMap",
    "VoxelPlanesParameters",
]
