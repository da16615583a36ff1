"""Folders of PCD scans with their poses, as LiDAR SLAM tools and datasets ship them: read as range-image frames.

Many LiDAR recordings are a folder of PCL's ``.pcd`` files (:mod:`mabdi.sources.pcd`), one a scan in the
LiDAR's frame, beside the scans' poses (world from LiDAR), in no one layout. This reader takes them as
they come:

* **Scans**: the ``.pcd`` files of the folder itself, or of its ``clouds/``, ``pcd/``, ``pcds/``, ``scans/``
  or ``points/`` folder, in the order of the number in their names (``full9`` before ``full10``; a name
  that is a timestamp, ``1630577758.569490.pcd``, by its value). A name without a number, or two scans of
  one number, is an error naming them.
* **Poses**, either a ``poses/`` folder of one file a scan (``poses/<scan name>.txt``: a 4x4 or 3x4 matrix,
  one row a line, or all of it on one line), or one file of the folder whose name holds ``pose`` or
  ``traj`` (``.txt`` or ``.csv``; ``poses.txt``, ``alidarPose.csv``, ``trajectory.txt``) with a pose a
  scan, in scan order, as one of:

  - a line of 12 numbers (a 3x4 row-major matrix, KITTI's) or 16 (a 4x4);
  - a line of 8: ``time tx ty tz qx qy qz qw`` (the TUM trajectory format, as ``evo`` reads it);
  - blocks of 4 lines of 4 numbers (a 4x4 matrix each) or of 3 lines (a 3x4).

  Numbers are parted by spaces or commas (a trailing comma is no number); blank lines, ``#`` comments and
  a first line of column names are skipped. A 4x4's last row is ``0 0 0 1``, or ``0 0 0 t`` where a tool
  keeps the scan's time t (s) there, as BALM's ``alidarPose.csv`` does. Rotations written to a few digits
  are made rigid (:class:`mabdi.camera.PoseRepairs`, said once); a matrix that is no rigid motion, or a
  line of another count, is an error naming the file and line.
* **Timestamps**: the poses' times where they hold them, else a ``times.txt`` of one a line, else unknown.
* ``mabdi.toml`` (optional): a ``[lidar]`` table as for a KITTI folder; without it the geometry is learnt
  from the first scans (:class:`~mabdi.sources.kitti.KittiSequence`, whose reading this shares).

A folder with ``velodyne/`` and ``poses.txt`` is a KITTI folder (:mod:`mabdi.sources.kitti`) and read so.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from mabdi.camera import PoseRepairs
from mabdi.errors import PoseError, PoseFileWarning
from mabdi.sources.kitti import KittiSequence, read_times
from mabdi.sources.sequence_files import SequenceError, bad_quaternions, poses_from_translations_quaternions

#: The folders, after the folder itself, whose ``.pcd`` files are the scans.
SCAN_FOLDERS = ("clouds", "pcd", "pcds", "scans", "points")
#: The folder of one pose file a scan.
POSE_FOLDER = "poses"
#: Words one of which a pose file's name holds (lower case), and the suffixes it may have.
POSE_FILE_WORDS = ("pose", "traj")
POSE_FILE_SUFFIXES = (".txt", ".csv")
TIMES_FILE = "times.txt"
#: The number in a scan's name that orders it: the last run of digits, with its decimals if it has any.
_NUMBER = re.compile(r"\d+(?:\.\d+)?")
_SEPARATORS = re.compile(r"[,\s;]+")


def scan_folder(path: Path) -> Path | None:
    """The folder holding ``path``'s PCD scans (module docs), or None."""
    for folder in (path, *(path / name for name in SCAN_FOLDERS)):
        if folder.is_dir() and any(folder.glob("*.pcd")):
            return folder
    return None


def pose_file(path: Path) -> Path | None:
    """The one pose file of ``path`` (module docs), or None; two candidates are a SequenceError naming them."""
    found = sorted(
        p for p in path.iterdir()
        if p.is_file() and p.suffix.lower() in POSE_FILE_SUFFIXES and any(w in p.stem.lower() for w in POSE_FILE_WORDS)
    )
    if len(found) > 1:
        raise SequenceError(f"PCD scan folder {path}: two pose files ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def is_pcd_folder(path) -> bool:
    """Whether ``path`` is a folder of PCD scans with poses (module docs)."""
    path = Path(path)
    if not path.is_dir() or scan_folder(path) is None:
        return False
    if (path / POSE_FOLDER).is_dir():
        return True
    try:
        return pose_file(path) is not None
    except SequenceError:
        return True  # ours to read, and to say what is wrong with


def pcd_scans(folder: Path) -> list[Path]:
    """The ``.pcd`` files of ``folder`` in the order of the numbers in their names (module docs)."""
    scans = list(folder.glob("*.pcd"))
    keys = {}
    for scan in scans:
        numbers = _NUMBER.findall(scan.stem)
        if not numbers:
            raise SequenceError(f"{scan}: a scan's name must hold its number (as full12.pcd or 000012.pcd), to put the scans in order")
        keys[scan] = float(numbers[-1])
    ordered = sorted(scans, key=lambda p: (keys[p], p.name))
    for first, second in zip(ordered, ordered[1:]):
        if keys[first] == keys[second]:
            raise SequenceError(f"PCD scan folder {folder}: two scans are number {numbers_text(keys[first])} ({first.name}, {second.name})")
    return ordered


def numbers_text(value: float) -> str:
    return f"{value:.0f}" if value == int(value) else f"{value:g}"


def read_pose_lines(path: Path) -> list[tuple[int, list[float]]]:
    """The lines of numbers of a pose file as (line number, numbers), skipping blank lines, ``#`` comments and a
    first line of column names; a later line that is not all numbers is a SequenceError naming it."""
    rows = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = [f for f in _SEPARATORS.split(text) if f]
            try:
                values = [float(f) for f in fields]
            except ValueError:
                if not rows and not any(_is_number(f) for f in fields):
                    continue  # the column names
                raise SequenceError(f"{path}:{number}: pose: a field is not a number: {text!r}") from None
            if not np.isfinite(values).all():
                raise SequenceError(f"{path}:{number}: pose: a number is not finite: {text!r}")
            rows.append((number, values))
    return rows


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def poses_of_lines(rows: list[tuple[int, list[float]]], path: Path, repairs: PoseRepairs) -> tuple[np.ndarray, np.ndarray]:
    """(N, 4, 4) rigid poses and (N,) times (s, NaN where the file holds none) of a pose file's numbered lines in
    any of the module docs' forms, or a SequenceError naming the file and line."""
    if not rows:
        raise SequenceError(f"{path}: no poses")
    counts = {len(values) for _, values in rows}
    if counts <= {12, 16}:
        blocks = rows
    elif counts == {8}:
        return _tum_poses(rows, path)
    elif counts == {4}:
        height = 4 if len(rows) % 4 == 0 and all(rows[i][1][:3] == [0.0, 0.0, 0.0] for i in range(3, len(rows), 4)) else 3
        if len(rows) % height:
            raise SequenceError(f"{path}: {len(rows)} lines of 4 numbers is not a whole number of {height}-line matrices")
        blocks = [(rows[i][0], [v for _, values in rows[i : i + height] for v in values]) for i in range(0, len(rows), height)]
    else:
        lengths = [len(v) for _, v in rows]
        usual = max(counts, key=lengths.count)  # the odd line is one of another count than most
        number, values = next((n, v) for n, v in rows if len(v) != usual) if len(counts) > 1 else rows[0]
        raise SequenceError(
            f"{path}:{number}: pose: {len(values)} numbers; a pose file holds lines of 12 (a 3x4 matrix) or 16 (a 4x4), "
            "of 8 (time tx ty tz qx qy qz qw), or 4-line blocks of 4 numbers, the same form on every line"
        )
    poses, times = [], []
    for number, values in blocks:
        matrix, time = _matrix(values, f"{path}:{number}")
        poses.append(repairs_read(repairs, matrix, f"{path}:{number}"))
        times.append(time)
    return np.array(poses), np.array(times, dtype=np.float64)


def _matrix(values: list[float], where: str) -> tuple[np.ndarray, float]:
    """The 4x4 of 12 or 16 row-major numbers and the time a 4x4's last element holds where it is not 1."""
    matrix = np.eye(4)
    if len(values) == 12:
        matrix[:3] = np.reshape(values, (3, 4))
        return matrix, np.nan
    if len(values) != 16:
        raise SequenceError(f"{where}: pose: {len(values)} numbers, expected a 3x4 (12) or 4x4 (16) matrix")
    matrix[:] = np.reshape(values, (4, 4))
    if not np.allclose(matrix[3, :3], 0.0, atol=1e-6):
        raise SequenceError(f"{where}: pose: a 4x4 matrix's last row must be 0 0 0 1 (or 0 0 0 and the time), got {matrix[3].tolist()}")
    time = np.nan if abs(matrix[3, 3] - 1.0) <= 1e-6 else float(matrix[3, 3])
    matrix[3] = (0.0, 0.0, 0.0, 1.0)
    return matrix, time


def repairs_read(repairs: PoseRepairs, matrix: np.ndarray, where: str) -> np.ndarray:
    try:
        return repairs.read(matrix, where)
    except PoseError as exc:
        raise SequenceError(f"{where}: not a rigid transform: {exc}") from None


def _tum_poses(rows: list[tuple[int, list[float]]], path: Path) -> tuple[np.ndarray, np.ndarray]:
    values = np.array([v for _, v in rows], dtype=np.float64)
    bad = bad_quaternions(values[:, 4:8])
    if bad.any():
        number = rows[int(np.flatnonzero(bad)[0])][0]
        raise SequenceError(f"{path}:{number}: pose: the quaternion (qx qy qz qw) is not a rotation")
    return poses_from_translations_quaternions(values[:, 1:4], values[:, 4:8]), values[:, 0]


class PcdFolderSequence(KittiSequence):
    """A folder of PCD scans and their poses (module docs) as range-image frames; ``geometry`` replaces the
    ``[lidar]`` table's."""

    label = "PCD scan folder"

    def _read_layout(self, path: Path) -> tuple[list[Path], np.ndarray, np.ndarray]:
        if not path.is_dir() or (folder := scan_folder(path)) is None:
            raise SequenceError(f"PCD scan folder {path}: no .pcd scans in it or in {', '.join(f'{n}/' for n in SCAN_FOLDERS)}")
        scans = pcd_scans(folder)
        repairs = PoseRepairs()
        if (path / POSE_FOLDER).is_dir():
            poses, times = self._pose_per_scan(path / POSE_FOLDER, scans, repairs)
            where = f"{path / POSE_FOLDER}/"
        elif (file := pose_file(path)) is not None:
            poses, times = poses_of_lines(read_pose_lines(file), file, repairs)
            where = str(file)
            if len(poses) != len(scans):
                raise SequenceError(f"{file}: {len(poses)} poses, but {folder} holds {len(scans)} .pcd scans")
        else:
            raise SequenceError(
                f"PCD scan folder {path}: no poses: expected a {POSE_FOLDER}/ folder of one file a scan, or a file "
                f"whose name holds {' or '.join(repr(w) for w in POSE_FILE_WORDS)} ({', '.join(POSE_FILE_SUFFIXES)})"
            )
        if (note := repairs.note(where)) is not None:
            warnings.warn(note, PoseFileWarning, stacklevel=4)
        if np.isnan(times).all() and (path / TIMES_FILE).is_file():
            times = read_times(path / TIMES_FILE)
            if len(times) != len(scans):
                raise SequenceError(f"{path / TIMES_FILE}: {len(times)} timestamps, but {folder} holds {len(scans)} .pcd scans")
        return scans, poses, times

    @staticmethod
    def _pose_per_scan(folder: Path, scans: list[Path], repairs: PoseRepairs) -> tuple[np.ndarray, np.ndarray]:
        poses, times = [], []
        for scan in scans:
            file = next((folder / (scan.stem + s) for s in POSE_FILE_SUFFIXES if (folder / (scan.stem + s)).is_file()), None)
            if file is None:
                raise SequenceError(f"{folder}: no pose for scan {scan.name} (expected {folder / (scan.stem + '.txt')})")
            rows = read_pose_lines(file)
            flat = [v for _, values in rows for v in values]
            if not rows or len(flat) not in (12, 16):
                raise SequenceError(f"{file}: a scan's pose file holds one 4x4 or 3x4 matrix, got {len(flat)} numbers")
            matrix, time = _matrix(flat, str(file))
            poses.append(repairs_read(repairs, matrix, str(file)))
            times.append(time)
        return np.array(poses), np.array(times, dtype=np.float64)


__all__ = ["PcdFolderSequence", "is_pcd_folder", "pcd_scans", "poses_of_lines", "read_pose_lines"]
