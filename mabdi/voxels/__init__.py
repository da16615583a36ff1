"""Voxel storage for the voxel-plane surface (:class:`~mabdi.surfaces.voxel_planes.FilterVoxelPlanes`): the
semi-sparse blockwise grid of per-voxel statistics (:mod:`mabdi.voxels.voxel_map`) and the traversal of
rays through it (:mod:`mabdi.voxels.traversal`)."""

from mabdi.voxels.voxel_map import VoxelMap

__all__ = ["VoxelMap"]
