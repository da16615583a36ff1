"""Mesh and image files through VTK's readers and writers, written atomically.

Meshes: VTP (binary, compressed, every array kept), PLY (binary; triangles),
OBJ and STL. Images: VTI (field data kept). :func:`read_mesh_file` and
:func:`write_mesh_file` pick the format from the suffix.
"""

from __future__ import annotations

from pathlib import Path

from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkTriangleFilter
from vtkmodules.vtkIOGeometry import vtkOBJReader, vtkOBJWriter, vtkSTLReader, vtkSTLWriter
from vtkmodules.vtkIOPLY import vtkPLYReader, vtkPLYWriter
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter, vtkXMLPolyDataReader, vtkXMLPolyDataWriter

from mabdi.errors import AssetNotFoundError, ConfigError
from mabdi.io.atomic import atomic_output

MESH_FORMATS = (".vtp", ".ply", ".obj", ".stl")


def _write(writer, data, path) -> Path:
    path = Path(path)
    with atomic_output(path) as temporary:
        writer.SetFileName(str(temporary))
        writer.SetInputData(data)
        if writer.Write() != 1:
            raise OSError(f"could not write {path} (VTK writer failed; is the disk full?)")
    return path


def write_polydata(mesh, path) -> Path:
    """Write a vtkPolyData as binary, compressed VTP (with all its arrays)."""
    writer = vtkXMLPolyDataWriter()
    writer.SetDataModeToAppended()
    writer.SetCompressorTypeToZLib()
    return _write(writer, mesh, path)


def write_image(image, path) -> Path:
    """Write a vtkImageData (e.g. a depth image, field data included) as VTI."""
    writer = vtkXMLImageDataWriter()
    writer.SetDataModeToAppended()
    writer.SetCompressorTypeToZLib()
    return _write(writer, image, path)


def _triangles(mesh: vtkPolyData) -> vtkPolyData:
    triangles = vtkTriangleFilter()
    triangles.SetInputData(mesh)
    triangles.PassVertsOff()
    triangles.PassLinesOff()
    triangles.Update()
    return triangles.GetOutput()


def write_mesh_file(mesh: vtkPolyData, path) -> Path:
    """Write ``mesh`` as VTP, PLY (binary), OBJ or STL (binary) by the suffix of ``path``.

    PLY, OBJ and STL hold triangles (polygons are triangulated) and no cell
    arrays; VTP keeps everything.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".vtp":
        return write_polydata(mesh, path)
    if suffix == ".ply":
        writer = vtkPLYWriter()
        writer.SetFileTypeToBinary()
    elif suffix == ".obj":
        writer = vtkOBJWriter()
    elif suffix == ".stl":
        writer = vtkSTLWriter()
        writer.SetFileTypeToBinary()
    else:
        raise ConfigError(f"{path}: unknown mesh format '{path.suffix}' (known: {', '.join(MESH_FORMATS)})")
    return _write(writer, _triangles(mesh), path)


def read_mesh_file(path) -> vtkPolyData:
    """Read a VTP, PLY, OBJ or STL file as vtkPolyData (as stored: no cleaning)."""
    path = Path(path)
    readers = {".vtp": vtkXMLPolyDataReader, ".ply": vtkPLYReader, ".obj": vtkOBJReader, ".stl": vtkSTLReader}
    reader_class = readers.get(path.suffix.lower())
    if reader_class is None:
        raise ConfigError(f"{path}: unknown mesh format '{path.suffix}' (known: {', '.join(MESH_FORMATS)})")
    if not path.is_file():
        raise AssetNotFoundError(f"mesh file not found: {path}")
    reader = reader_class()
    reader.SetFileName(str(path))
    reader.Update()
    mesh = vtkPolyData()
    mesh.ShallowCopy(reader.GetOutput())
    if mesh.GetNumberOfPoints() == 0:
        raise ConfigError(f"{path}: no mesh could be read from this file")
    return mesh
