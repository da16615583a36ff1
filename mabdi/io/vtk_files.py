"""Mesh and image files through VTK's readers and writers, written atomically.

Meshes: VTP (binary, compressed, every array kept), PLY (binary; triangles),
OBJ and STL. Images: VTI (field data kept). :func:`read_mesh_file` and
:func:`write_mesh_file` pick the format from the suffix.

Vertex colours (point array :data:`~mabdi.mesh_maps.mesh_map.COLOUR_LAYER`,
uint8 RGB) go into PLY as the ``red``, ``green``, ``blue`` uchar vertex
properties and into OBJ as ``v x y z r g b`` (colours 0-1, the extension
MeshLab, Open3D, trimesh and VTK's own reader take); read back from either,
they are that point array again. STL has no place for them.

Both directions are checked (:mod:`mabdi.io.checks`): a file is checked to
be whole before VTK reads it (a binary PLY cut short would crash VTK's
reader), and what a VTK writer wrote is checked before the temporary file
takes the target's name (VTK's writers report success on a full disk).
Either failure is a :class:`~mabdi.errors.MabdiError` naming the file.

VTK's IO modules (vtkIOXML, vtkIOPLY, vtkIOGeometry: about 4 MB resident)
are imported inside the functions that read or write, not with the module (a
start-up memory choice: ``import mabdi`` loads this module).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkTriangleFilter

from mabdi.errors import AssetNotFoundError, ConfigError, DamagedFileError, WriteError
from mabdi.io.atomic import atomic_output
from mabdi.io.checks import check_mesh_file
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER

MESH_FORMATS = (".vtp", ".ply", ".obj", ".stl")


def _write(writer, data, path, points: int | None = None, cells: int | None = None, finish=None) -> Path:
    """Write ``data`` with a VTK ``writer`` to ``path`` atomically; check the file before renaming it.

    ``points``/``cells``: the counts the file must hold (PLY, OBJ, STL); ``finish(temporary)`` amends the
    written file before the check.
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
        if finish is not None:
            finish(temporary)
        try:
            check_mesh_file(temporary, points=points, cells=cells)
        except DamagedFileError as error:
            what = str(error).split(": ", 1)[-1]
            raise WriteError(f"cannot write {path}: the file came out incomplete (is the disk full?): {what}") from None
    return path


def write_polydata(mesh, path) -> Path:
    """Write a vtkPolyData as binary, compressed VTP (with all its arrays)."""
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    writer = vtkXMLPolyDataWriter()
    writer.SetDataModeToAppended()
    writer.SetCompressorTypeToZLib()
    return _write(writer, mesh, path)


def write_image(image, path) -> Path:
    """Write a vtkImageData (e.g. a depth image, field data included) as VTI."""
    from vtkmodules.vtkIOXML import vtkXMLImageDataWriter

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
        from vtkmodules.vtkIOPLY import vtkPLYWriter

        writer = vtkPLYWriter()
        writer.SetFileTypeToBinary()
    elif suffix == ".obj":
        from vtkmodules.vtkIOGeometry import vtkOBJWriter

        writer = vtkOBJWriter()
    elif suffix == ".stl":
        from vtkmodules.vtkIOGeometry import vtkSTLWriter

        writer = vtkSTLWriter()
        writer.SetFileTypeToBinary()
    else:
        raise ConfigError(f"{path}: unknown mesh format '{path.suffix}' (known: {', '.join(MESH_FORMATS)})")
    if mesh.GetNumberOfCells() == 0:
        return _write_empty_mesh(path, suffix)
    triangles = _triangles(mesh)
    colours = triangles.GetPointData().GetArray(COLOUR_LAYER)
    finish = None
    if colours is not None and suffix == ".ply":
        writer.SetArrayName(COLOUR_LAYER)
        writer.SetColorModeToDefault()
    elif colours is not None and suffix == ".obj":

        def finish(temporary):
            _add_obj_colours(temporary, vtk_to_numpy(colours))

    return _write(writer, triangles, path, points=triangles.GetNumberOfPoints(), cells=triangles.GetNumberOfCells(), finish=finish)


def _add_obj_colours(file: Path, rgb: np.ndarray) -> None:
    """Append each vertex's colour to the ``v`` lines of an OBJ file, in order: (c + 1/4) / 255 for c in 0-255
    (1 for 255) with 5 decimals, which readers that round (x 255) and readers that truncate (VTK) both read as c."""
    lines = Path(file).read_bytes().split(b"\n")
    vertex_lines = [i for i, line in enumerate(lines) if line.startswith(b"v ")]
    if len(vertex_lines) != len(rgb):
        raise WriteError(f"cannot write {file}: {len(vertex_lines)} vertices written, {len(rgb)} colours")
    text = np.char.mod("%.5f", np.minimum((np.asarray(rgb, dtype=np.float64) + 0.25) / 255.0, 1.0))
    suffixes = np.char.add(np.char.add(np.char.add(" ", text[:, 0]), np.char.add(" ", text[:, 1])), np.char.add(" ", text[:, 2]))
    for index, suffix in zip(vertex_lines, suffixes.tolist(), strict=True):
        lines[index] = lines[index].rstrip() + suffix.encode()
    Path(file).write_bytes(b"\n".join(lines))


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
    from vtkmodules.vtkIOGeometry import vtkOBJReader, vtkSTLReader
    from vtkmodules.vtkIOPLY import vtkPLYReader
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

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
    rgb = mesh.GetPointData().GetArray("RGB") if path.suffix.lower() in (".ply", ".obj") else None
    if rgb is not None and rgb.GetNumberOfComponents() == 3:  # PLY's red/green/blue, OBJ's v x y z r g b
        rgb.SetName(COLOUR_LAYER)
    return mesh


def _first_line(text: str) -> str:
    """VTK's first own message in ``text`` ("vtkX (0x...): message"), without the pipeline's dump."""
    import re

    text = re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", text)
    for match in re.finditer(r"(vtk\w+) \(0x[0-9a-fA-F]+\): ([^\n]+)", text):
        if "returned failure for request" not in match.group(2):
            return f"{match.group(1)}: {match.group(2).strip()}"
    return ""
