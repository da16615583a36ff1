"""Mesh and image files through VTK's readers and writers, written atomically.

Meshes: VTP (binary, compressed, every array kept), PLY (binary; triangles),
OBJ and STL. Images: VTI (field data kept). :func:`read_mesh_file` and
:func:`write_mesh_file` pick the format from the suffix.

Both directions are checked (:mod:`mabdi.io.checks`): a file is checked to
be whole before VTK reads it (a binary PLY cut short would crash VTK's
reader), and what a VTK writer wrote is checked before the temporary file
takes the target's name (VTK's writers report success on a full disk).
Either failure is a :class:`~mabdi.errors.MabdiError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkTriangleFilter
from vtkmodules.vtkIOGeometry import vtkOBJReader, vtkOBJWriter, vtkSTLReader, vtkSTLWriter
from vtkmodules.vtkIOPLY import vtkPLYReader, vtkPLYWriter
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter, vtkXMLPolyDataReader, vtkXMLPolyDataWriter

from mabdi.errors import AssetNotFoundError, ConfigError, DamagedFileError, WriteError
from mabdi.io.atomic import atomic_output
from mabdi.io.checks import check_mesh_file

MESH_FORMATS = (".vtp", ".ply", ".obj", ".stl")


def _write(writer, data, path, points: int | None = None, cells: int | None = None) -> Path:
    """Write ``data`` with a VTK ``writer`` to ``path`` atomically; check the file before renaming it.

    ``points``/``cells``: the counts the file must hold (PLY, OBJ, STL).
    """
    from mabdi.algorithm import vtk_messages_held

    path = Path(path)
    with atomic_output(path) as temporary:
        writer.SetFileName(str(temporary))
        writer.SetInputData(data)
        with vtk_messages_held() as messages:
            written = writer.Write()
            if written != 1 or writer.GetErrorCode() != 0:
                said = _first_line(messages())
                raise WriteError(f"cannot write {path}: the VTK writer failed (is the disk full?)" + (f": {said}" if said else ""))
        if not temporary.exists():
            raise WriteError(f"cannot write {path}: the VTK writer left no file (is the disk full?)")
        try:
            check_mesh_file(temporary, points=points, cells=cells)
        except DamagedFileError as error:
            what = str(error).split(": ", 1)[-1]
            raise WriteError(f"cannot write {path}: the file came out incomplete (is the disk full?): {what}") from None
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
    if mesh.GetNumberOfCells() == 0:
        return _write_empty_mesh(path, suffix)
    triangles = _triangles(mesh)
    return _write(writer, triangles, path, points=triangles.GetNumberOfPoints(), cells=triangles.GetNumberOfCells())


def _holds_no_mesh(path: Path) -> bool:
    """Whether a (checked) mesh file says it holds no triangles: 0 vertices in a PLY header, 0 STL triangles,
    an OBJ without vertices (as :func:`_write_empty_mesh` writes an empty map)."""
    suffix = path.suffix.lower()
    head = path.read_bytes()[:4096]
    if suffix == ".ply":
        return b"\nelement vertex 0\n" in head.split(b"end_header")[0]
    if suffix == ".stl":
        return len(head) == 84 and head[80:84] == b"\0\0\0\0"
    if suffix == ".obj":
        return not any(line.startswith(b"v ") for line in path.read_bytes().splitlines())
    if suffix == ".vtp":
        return b'NumberOfPoints="0"' in head and head.count(b"<Piece") == 1
    return False


def _write_empty_mesh(path: Path, suffix: str) -> Path:
    """A valid file holding no triangles (VTK's PLY and STL writers refuse to write one)."""
    if suffix == ".ply":
        content = b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n" \
            b"element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    elif suffix == ".stl":
        content = b"empty mesh written by mabdi".ljust(80, b" ") + (0).to_bytes(4, "little")
    else:
        content = b"# empty mesh written by mabdi\n"
    with atomic_output(path) as temporary:
        Path(temporary).write_bytes(content)
    return path


def read_mesh_file(path) -> vtkPolyData:
    """Read a VTP, PLY, OBJ or STL file as vtkPolyData (as stored: no cleaning).

    Raises :class:`ConfigError` for an unknown suffix, :class:`AssetNotFoundError`
    for a missing file and :class:`DamagedFileError` for a file that is empty,
    cut short or gives no mesh.
    """
    from mabdi.algorithm import vtk_messages_held

    path = Path(path)
    readers = {".vtp": vtkXMLPolyDataReader, ".ply": vtkPLYReader, ".obj": vtkOBJReader, ".stl": vtkSTLReader}
    reader_class = readers.get(path.suffix.lower())
    if reader_class is None:
        raise ConfigError(f"{path}: unknown mesh format '{path.suffix}' (known: {', '.join(MESH_FORMATS)})")
    if not path.is_file():
        raise AssetNotFoundError(f"mesh file not found: {path}")
    check_mesh_file(path)
    reader = reader_class()
    reader.SetFileName(str(path))
    with vtk_messages_held() as messages:
        reader.Update()
        mesh = vtkPolyData()
        mesh.ShallowCopy(reader.GetOutput())
        said = _first_line(messages())
        if mesh.GetNumberOfPoints() == 0 and not _holds_no_mesh(path):
            raise DamagedFileError(f"{path}: no mesh could be read from this file" + (f" (VTK: {said})" if said else ""))
        if reader.GetErrorCode() != 0:
            raise DamagedFileError(f"{path}: VTK's reader failed on this file" + (f" (VTK: {said})" if said else ""))
    return mesh


def _first_line(text: str) -> str:
    """VTK's first own message in ``text`` ("vtkX (0x...): message"), without the pipeline's dump."""
    import re

    text = re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", text)
    for match in re.finditer(r"(vtk\w+) \(0x[0-9a-fA-F]+\): ([^\n]+)", text):
        if "returned failure for request" not in match.group(2):
            return f"{match.group(1)}: {match.group(2).strip()}"
    return ""
