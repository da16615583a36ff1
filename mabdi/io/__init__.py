"""Files: atomic writes and VTK exports."""

from mabdi.io.atomic import atomic_output
from mabdi.io.vtk_files import write_image, write_polydata

__all__ = ["atomic_output", "write_image", "write_polydata"]
