"""Cheap checks that a mesh file is whole, before VTK reads it and after a VTK writer wrote it.

VTK's readers trust a file: a binary PLY cut short makes ``vtkPLYReader``
read past the end (the process dies with a segmentation fault), and an
empty or damaged VTP, OBJ or STL gives an empty mesh or a raw error dump.
VTK's writers, the other way round, report success when the disk fills up
and leave a short file. :func:`check_mesh_file` reads a file's header (and
for PLY walks its binary layout, list properties included) and raises
:class:`~mabdi.errors.DamagedFileError` naming the file and what is wrong;
given the counts a writer was asked to write (``points``, ``cells``) it
also checks that they are all there.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mabdi.errors import DamagedFileError

#: PLY scalar types (both spellings) -> numpy type codes, without byte order.
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
HEADER_LIMIT = 1 << 16  # a PLY header longer than this is not one mabdi reads


def _damaged(path, what: str) -> DamagedFileError:
    return DamagedFileError(f"{path}: damaged {Path(path).suffix.lstrip('.').upper() or 'mesh'} file: {what}")


def check_mesh_file(path, points: int | None = None, cells: int | None = None) -> None:
    """Raise :class:`DamagedFileError` if the mesh file at ``path`` is empty, cut short or not its format.

    The format follows the suffix (.ply, .vtp, .vti, .obj, .stl; others pass).
    ``points``/``cells``: the counts the file must hold (a writer's check).
    """
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise _damaged(path, "the file is empty (0 bytes)")
    check = {".ply": check_ply, ".vtp": _check_xml, ".vti": _check_xml, ".obj": _check_obj, ".stl": _check_stl}
    checker = check.get(path.suffix.lower())
    if checker is not None:
        checker(path, size, points, cells)


# -- PLY ---------------------------------------------------------------------------------------


def ply_header(path) -> tuple[str, list[dict], int]:
    """(format, elements, data offset) of a PLY file; an element is ``{"name", "count", "properties"}``.

    A property is ``(name, type)`` or ``(name, (count type, item type))`` for a list.
    """
    with open(path, "rb") as stream:
        head = stream.read(HEADER_LIMIT)
    if not head.startswith(b"ply") or head[3:4] not in (b"\n", b"\r"):
        raise _damaged(path, "it does not start with the 'ply' line")
    end = head.find(b"end_header")
    if end < 0:
        raise _damaged(path, "the header has no 'end_header' line (cut short, or not a PLY file)")
    newline = head.find(b"\n", end)
    if newline < 0:
        raise _damaged(path, "the file ends right after 'end_header' (no data)")
    file_format, elements = None, []
    for number, raw in enumerate(head[:end].decode("ascii", errors="replace").splitlines()[1:], start=2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                file_format = words[1]
                if file_format not in PLY_FORMATS:
                    raise _damaged(path, f"unknown format {file_format!r} on header line {number}")
            elif words[0] == "element":
                count = int(words[2])
                if count < 0:
                    raise ValueError
                elements.append({"name": words[1], "count": count, "properties": []})
            elif words[0] == "property":
                if not elements:
                    raise _damaged(path, f"a property before any element on header line {number}")
                if words[1] == "list":
                    kinds = (PLY_TYPES[words[2]], PLY_TYPES[words[3]])
                    elements[-1]["properties"].append((words[4], kinds))
                else:
                    elements[-1]["properties"].append((words[2], PLY_TYPES[words[1]]))
            else:
                raise _damaged(path, f"unknown header line {number}: {raw.strip()!r}")
        except (IndexError, ValueError, KeyError):
            raise _damaged(path, f"header line {number} cannot be read: {raw.strip()!r}") from None
    if file_format is None:
        raise _damaged(path, "the header has no 'format' line")
    return file_format, elements, newline + 1


def check_ply(path, size: int | None = None, points: int | None = None, cells: int | None = None) -> None:
    """Check a PLY file's header and that its data is all there (binary: byte for byte)."""
    path = Path(path)
    size = path.stat().st_size if size is None else size
    file_format, elements, offset = ply_header(path)
    counts = {element["name"]: element["count"] for element in elements}
    for name, expected in (("vertex", points), ("face", cells)):
        if expected is not None and counts.get(name, 0) != expected:
            raise _damaged(path, f"the header has {counts.get(name, 0)} {name} elements, {expected} were written")
    order = PLY_FORMATS[file_format]
    if order is None:
        _check_ply_ascii(path, elements, offset)
        return
    with open(path, "rb") as stream:
        data = np.memmap(stream, dtype=np.uint8, mode="r") if size > offset else np.zeros(0, np.uint8)
        for element in elements:
            offset = _ply_element_end(path, data, offset, element, order, size)
    # Bytes after the last element are left alone: readers ignore them.


def _ply_element_end(path, data, offset: int, element: dict, order: str, size: int) -> int:
    """Where ``element``'s data ends; DamagedFileError if the file ends first."""
    name, count, properties = element["name"], element["count"], element["properties"]
    short = f"it ends inside the {count:,} '{name}' elements (the file is {size:,} bytes"
    lists = [i for i, (_, kind) in enumerate(properties) if isinstance(kind, tuple)]
    if not lists:
        end = offset + count * sum(np.dtype(kind).itemsize for _, kind in properties)
        if end > size:
            raise _damaged(path, f"{short}, the header needs {end:,})")
        return end
    if count == 0:
        return offset
    # One list property (a face's vertex indices), with fixed properties before and after it: rows
    # are read in runs of equal list length, each run checked at once with numpy.
    if len(lists) > 1:
        return _ply_rows_one_by_one(path, data, offset, element, order, size)
    index = lists[0]
    before = sum(np.dtype(kind).itemsize for _, kind in properties[:index])
    after = sum(np.dtype(kind).itemsize for _, kind in properties[index + 1 :])
    count_type, item_type = (np.dtype(order + kind) for kind in properties[index][1])
    item = item_type.itemsize
    row, runs = 0, 0
    while row < count:
        at = offset + before
        if at + count_type.itemsize > size:
            raise _damaged(path, f"{short}; row {row:,} is missing)")
        length = int(data[at : at + count_type.itemsize].view(count_type)[0])
        if length < 0:
            raise _damaged(path, f"'{name}' row {row:,} has a list of {length} items")
        stride = before + count_type.itemsize + length * item + after
        rows = min(count - row, max(0, (size - offset) // stride))
        if rows == 0:
            raise _damaged(path, f"{short}; row {row:,} is cut off)")
        starts = offset + before + stride * np.arange(rows, dtype=np.int64)
        lengths = data[starts[:, None] + np.arange(count_type.itemsize)].copy().view(count_type).ravel()
        different = np.flatnonzero(lengths != length)
        same = int(different[0]) if different.size else rows
        offset += same * stride
        row += same
        runs += 1
        if row < count and different.size == 0 and same == rows:
            raise _damaged(path, f"{short}; row {row:,} of {count:,} is missing)")
        if runs > 64 and row < count:  # many list lengths mixed: go row by row
            return _ply_rows_one_by_one(path, data, offset, dict(element, count=count - row), order, size)
    return offset


def _ply_rows_one_by_one(path, data, offset: int, element: dict, order: str, size: int) -> int:
    name, count = element["name"], element["count"]
    for row in range(count):
        for _, kind in element["properties"]:
            if isinstance(kind, tuple):
                count_type, item_type = (np.dtype(order + k) for k in kind)
                if offset + count_type.itemsize > size:
                    raise _damaged(path, f"it ends inside '{name}' row {row:,} of {count:,} (the file is {size:,} bytes)")
                length = int(data[offset : offset + count_type.itemsize].view(count_type)[0])
                offset += count_type.itemsize + length * item_type.itemsize
            else:
                offset += np.dtype(kind).itemsize
            if offset > size:
                raise _damaged(path, f"it ends inside '{name}' row {row:,} of {count:,} (the file is {size:,} bytes)")
    return offset


def _check_ply_ascii(path, elements: list[dict], offset: int) -> None:
    needed = sum(element["count"] for element in elements)
    with open(path, "rb") as stream:
        stream.seek(offset)
        rows = sum(1 for line in stream if line.strip())
    if rows < needed:
        raise _damaged(path, f"the header promises {needed:,} rows of data, the file has {rows:,}")


# -- VTK XML, OBJ, STL -------------------------------------------------------------------------


def _tail(path, size: int, length: int = 256) -> bytes:
    with open(path, "rb") as stream:
        stream.seek(max(0, size - length))
        return stream.read()


def _check_xml(path, size: int, points=None, cells=None) -> None:
    with open(path, "rb") as stream:
        head = stream.read(256).lstrip()
    if not (head.startswith(b"<?xml") or head.startswith(b"<VTKFile")):
        raise _damaged(path, "it is not a VTK XML file (no '<VTKFile' at the start)")
    if not _tail(path, size).rstrip().endswith(b"</VTKFile>"):
        raise _damaged(path, "it does not end with '</VTKFile>' (cut short?)")


def _check_obj(path, size: int, points=None, cells=None) -> None:
    with open(path, "rb") as stream:
        head = stream.read(4096)
    if b"\0" in head:
        raise _damaged(path, "it holds binary data, not OBJ text")
    if points is None and cells is None:
        return
    data = Path(path).read_bytes()
    found = {"v": data.count(b"\nv ") + data.startswith(b"v "), "f": data.count(b"\nf ") + data.startswith(b"f ")}
    for key, what, expected in (("v", "vertices", points), ("f", "faces", cells)):
        if expected is not None and found[key] != expected:
            raise _damaged(path, f"it has {found[key]:,} {what}, {expected:,} were written (cut short?)")
    if not data.endswith(b"\n"):
        raise _damaged(path, "its last line is cut off")


def _check_stl(path, size: int, points=None, cells=None) -> None:
    with open(path, "rb") as stream:
        head = stream.read(1024)
    if head.lstrip().startswith(b"solid") and b"facet" in head:  # ASCII STL
        if not _tail(path, size).rstrip().split(b"\n")[-1].strip().startswith(b"endsolid"):
            raise _damaged(path, "the ASCII STL does not end with 'endsolid' (cut short?)")
        return
    if size < 84:
        raise _damaged(path, f"a binary STL has an 84-byte header, the file is {size} bytes")
    triangles = int(np.frombuffer(head[80:84], dtype="<u4")[0])
    needed = 84 + 50 * triangles
    if size < needed:
        raise _damaged(path, f"its header promises {triangles:,} triangles ({needed:,} bytes), the file is {size:,} bytes")
    if cells is not None and triangles != cells:
        raise _damaged(path, f"it has {triangles:,} triangles, {cells:,} were written")
