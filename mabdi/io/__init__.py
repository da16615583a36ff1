"""Files: atomic writes, VTK mesh and image files, plots."""

from mabdi.io.atomic import atomic_output
from mabdi.io.vtk_files import read_mesh_file, write_image, write_mesh_file, write_polydata

__all__ = ["atomic_output", "read_mesh_file", "write_image", "write_mesh_file", "write_polydata"]
