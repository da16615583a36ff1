"""Surfaces: a frame's novel pixels made into triangles for the map. The pixel grid (seed 001), the
quad-tree (seed 002) and voxel planes (seed 000), the depth smoothing they share, and the registry that
finds a surface by the name a run config gives (:mod:`.registry`)."""
