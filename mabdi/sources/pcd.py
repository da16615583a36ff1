"""PCD files (the Point Cloud Library's format) as a LiDAR scan's points.

A scan saved by PCL's tools (``pcl_ros``' ``bag_to_pcd``, most LiDAR
datasets' ``*.pcd``) is a text header and the points:

* the header's ``FIELDS``, ``SIZE``, ``TYPE`` (F float, I signed, U unsigned)
  and ``COUNT`` give each point's fields; ``x``, ``y`` and ``z`` (metres,
  the sensor frame) are read, the others (``intensity``, ``ring``, ``t``,
  padding ``_``) are skipped; ``POINTS`` (or ``WIDTH`` x ``HEIGHT``) counts
  them;
* ``DATA ascii`` (one point a line), ``binary`` (the points packed, little
  endian) or ``binary_compressed`` (each field's values one after the other,
  LZF-compressed, as PCL writes them);
* ``VIEWPOINT`` (tx ty tz qw qx qy qz) is where the sensor stood in the
  points' frame: points are returned in the sensor's frame (the identity,
  PCL's default, leaves them as they are).

A file that is not so is a :class:`~mabdi.sources.sequence_files.SequenceError`
naming it and what is wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from mabdi.sources.sequence_files import SequenceError, bad_quaternions, poses_from_translations_quaternions

#: The header's keys, in the order PCL writes them; DATA ends the header.
HEADER_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_KINDS = {"F": "f", "I": "i", "U": "u"}


def read_pcd(path) -> np.ndarray:
    """(N, 3) float32 x, y, z (metres, the sensor's frame: module docs) of the PCD file at ``path``."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SequenceError(f"{path}: cannot read the scan: {exc}") from None
    header, body = _header(raw, path)
    names, dtype = _point_type(header, path)
    count = _point_count(header, path)
    data = header["DATA"][0].lower()
    if data == "ascii":
        values = _ascii_points(body, dtype, count, path)
    elif data == "binary":
        if len(body) < count * dtype.itemsize:
            raise SequenceError(f"{path}: {count} points of {dtype.itemsize} bytes need {count * dtype.itemsize} bytes, the file holds {len(body)}")
        values = np.frombuffer(body, dtype=dtype, count=count)
    elif data == "binary_compressed":
        values = _compressed_points(body, dtype, count, path)
    else:
        raise SequenceError(f"{path}: DATA {header['DATA'][0]!r}: a PCD file's data is ascii, binary or binary_compressed")
    points = np.stack([np.asarray(values[name], dtype=np.float64).reshape(count) for name in ("x", "y", "z")], axis=1)
    return _in_sensor_frame(points, header, path).astype(np.float32)


def _header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], bytes]:
    """The header's fields (key: its words) and the bytes after the DATA line."""
    header: dict[str, list[str]] = {}
    position = 0
    while position < len(raw):
        end = raw.find(b"\n", position)
        end = len(raw) if end < 0 else end
        line = raw[position:end].decode("ascii", errors="replace").strip()
        position = end + 1
        if not line or line.startswith("#"):
            continue
        key, *words = line.split()
        if key.upper() not in HEADER_KEYS:
            raise SequenceError(f"{path}: not a PCD file: the header line {line[:60]!r} is none of {', '.join(HEADER_KEYS)}")
        header[key.upper()] = words
        if key.upper() == "DATA":
            return header, raw[position:]
    raise SequenceError(f"{path}: not a PCD file: no DATA line ends its header")


def _point_type(header: dict, path: Path) -> tuple[list[str], np.dtype]:
    """The fields' names and the numpy type of one packed point."""
    names = header.get("FIELDS")
    if not names:
        raise SequenceError(f"{path}: the PCD header has no FIELDS")
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise SequenceError(f"{path}: the PCD file's fields ({' '.join(names)}) lack {', '.join(missing)}")
    sizes = header.get("SIZE", [])
    types = header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(names))
    if not (len(sizes) == len(types) == len(counts) == len(names)):
        raise SequenceError(f"{path}: the PCD header's FIELDS, SIZE, TYPE and COUNT differ in length")
    fields = []
    for index, (name, size, kind, count) in enumerate(zip(names, sizes, types, counts)):
        if kind.upper() not in _KINDS or size not in ("1", "2", "4", "8") or not count.isdigit() or int(count) < 1:
            raise SequenceError(f"{path}: PCD field {name!r}: SIZE {size} TYPE {kind} COUNT {count} is not a number type PCL writes")
        base = np.dtype(f"<{_KINDS[kind.upper()]}{size}")
        fields.append((name if name != "_" else f"_pad{index}", base if int(count) == 1 else (base, (int(count),))))
    return names, np.dtype(fields)


def _point_count(header: dict, path: Path) -> int:
    try:
        if "POINTS" in header:
            return int(header["POINTS"][0])
        return int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    except (KeyError, IndexError, ValueError):
        raise SequenceError(f"{path}: the PCD header gives no number of POINTS (nor WIDTH and HEIGHT)") from None


def _ascii_points(body: bytes, dtype: np.dtype, count: int, path: Path) -> np.ndarray:
    columns = sum(int(np.prod(dtype[name].shape)) if dtype[name].shape else 1 for name in dtype.names)
    words = body.split()
    if len(words) < count * columns:
        raise SequenceError(f"{path}: {count} points of {columns} values need {count * columns} values, the file holds {len(words)}")
    try:
        table = np.array(words[: count * columns], dtype=np.float64).reshape(count, columns)
    except ValueError:
        raise SequenceError(f"{path}: a value of the PCD file's ascii data is not a number") from None
    values = np.zeros(count, dtype=[(name, np.float64) for name in ("x", "y", "z")])
    column = 0
    for name in dtype.names:
        width = int(np.prod(dtype[name].shape)) if dtype[name].shape else 1
        if name in ("x", "y", "z"):
            values[name] = table[:, column]
        column += width
    return values


def _compressed_points(body: bytes, dtype: np.dtype, count: int, path: Path) -> np.ndarray:
    """PCL's binary_compressed data: uint32 compressed and uncompressed sizes, then LZF of each field's values
    one field after another."""
    if len(body) < 8:
        raise SequenceError(f"{path}: binary_compressed data shorter than its two sizes")
    compressed, size = (int(v) for v in np.frombuffer(body[:8], dtype="<u4"))
    if len(body) < 8 + compressed or size != count * dtype.itemsize:
        raise SequenceError(
            f"{path}: binary_compressed data of {compressed} bytes ({len(body) - 8} in the file) unpacking to {size} "
            f"bytes; {count} points need {count * dtype.itemsize}"
        )
    out = np.empty(size, dtype=np.uint8)
    written = lzf_decompress(np.frombuffer(body, dtype=np.uint8, count=compressed, offset=8), out)
    if written != size:
        raise SequenceError(f"{path}: binary_compressed data unpacks to {written} bytes, not the {size} its header says")
    values = np.empty(count, dtype=dtype)
    offset = 0
    for name in dtype.names:
        field = dtype[name]
        width = count * field.itemsize
        values[name] = np.frombuffer(out[offset : offset + width].tobytes(), dtype=field.base).reshape((count, *field.shape))
        offset += width
    return values


@njit(cache=True)
def lzf_decompress(data, out):
    """Decompress LZF ``data`` (uint8) into ``out`` (uint8, its uncompressed size); the bytes written, or -1 where
    the data is damaged (a reference before the start, a run past either end)."""
    ip, op = 0, 0
    n, m = data.shape[0], out.shape[0]
    while ip < n:
        ctrl = int(data[ip])
        ip += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n or op + length > m:
                return -1
            for k in range(length):
                out[op + k] = data[ip + k]
            ip += length
            op += length
        else:  # a back reference: length (3 bits, 7 = more in the next byte) and offset (13 bits)
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    return -1
                length += int(data[ip])
                ip += 1
            if ip >= n:
                return -1
            ref = op - ((ctrl & 0x1F) << 8) - 1 - int(data[ip])
            ip += 1
            length += 2
            if ref < 0 or op + length > m:
                return -1
            for k in range(length):  # byte by byte: a reference may overlap what it writes
                out[op + k] = out[ref + k]
            op += length
    return op


def _in_sensor_frame(points: np.ndarray, header: dict, path: Path) -> np.ndarray:
    """``points`` moved from the PCD's frame into the VIEWPOINT's (module docs)."""
    viewpoint = header.get("VIEWPOINT")
    if viewpoint is None:
        return points
    try:
        tx, ty, tz, qw, qx, qy, qz = (float(v) for v in viewpoint)
    except ValueError:
        raise SequenceError(f"{path}: VIEWPOINT must be 7 numbers (tx ty tz qw qx qy qz), got {' '.join(viewpoint)}") from None
    if bad_quaternions([qx, qy, qz, qw])[0]:
        raise SequenceError(f"{path}: VIEWPOINT's quaternion is not a rotation: {' '.join(viewpoint[3:])}")
    if (tx, ty, tz, qx, qy, qz) == (0.0,) * 6:
        return points
    pose = poses_from_translations_quaternions([tx, ty, tz], [qx, qy, qz, qw])[0]
    return (points - pose[:3, 3]) @ pose[:3, :3]


__all__ = ["HEADER_KEYS", "lzf_decompress", "read_pcd"]
