"""What a robot does with a mesh map: colours, cost layers, labels, picking, planning (seed 003)."""

from mabdi.mesh_maps.colours import colours_by_frame, colours_by_normal
from mabdi.mesh_maps.mesh_map import MeshMap

__all__ = ["MeshMap", "colours_by_frame", "colours_by_normal"]
