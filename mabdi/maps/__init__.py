"""What a robot does with a mesh map: colours, cost layers, labels, picking, planning (seed 003)."""

from mabdi.maps.colours import colours_by_frame, colours_by_normal

__all__ = ["colours_by_frame", "colours_by_normal"]
