"""Folders of LiDAR scans beside their poses, as SLAM tools and datasets ship them: read as range-image frames.

Many LiDAR recordings are a folder of scan files in the LiDAR's frame (PCL's ``.pcd``, :mod:`mabdi.sources.pcd`,
or KITTI's float32 ``x y z intensity`` ``.bin``) beside the scans' poses (world from LiDAR), in no one layout:

* **Scans**: the ``.pcd`` (or ``.bin``, not both) files of the folder, else of its ``clouds/``, ``pcd/``,
  ``pcds/``, ``scans/`` or ``points/``, else of the one folder below it (two levels at most) that holds
  any; ordered by the numbers in their names (``full9`` before ``full10``, ``cloud_1583836591_182590976``
  by both). A name without a number, or two scans of the same numbers, is an error naming them.
* **Poses**: a ``poses/`` folder of a file a scan (``poses/<scan name>.txt``, a 4x4 or 3x4 matrix), or one
  file of the folder whose name holds ``pose`` or ``traj`` (``.txt``, ``.csv``), a pose a line as

  - 12 or 16 numbers (a 3x4 or 4x4 matrix, row-major), or 13 or 17: a time, then the matrix;
  - 8: ``time tx ty tz qx qy qz qw`` (TUM's trajectory format), or 9: ``sec nsec tx ty tz qx qy qz qw``;

  or as 4-line (3-line) blocks of 4 numbers, a 4x4 (3x4) each. Spaces or commas part the numbers; blank
  lines, ``#`` comments and a first line of column names are skipped. A 4x4's last row is ``0 0 0 1``, or
  ``0 0 0 t`` with the scan's time t (BALM's ``alidarPose.csv``). Rotations written to a few digits are
  made rigid (:class:`mabdi.camera.PoseRepairs`, said once); anything else is an error naming file and line.
* **Pairing**: as many poses as scans pair in order. Otherwise poses with times are interpolated at the
  scans' times (``times.txt``, one a line, else the scans' names: a number, or seconds and nanoseconds),
  between samples at most :data:`PAIRING_GAP` sample spacings apart; a scan outside the poses' span is
  skipped, and the source's description counts those. Times in ns, us or ms since the epoch are told by
  their size and read as seconds.
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
from mabdi.sources.kitti import KittiSequence, is_kitti, read_times
from mabdi.sources.sequence_files import SequenceError, bad_quaternions, interpolate_poses, poses_from_translations_quaternions

#: A scan file's suffixes (one kind a folder).
SCAN_SUFFIXES = (".pcd", ".bin")
#: The folders, after the folder itself, whose scan files are the scans.
SCAN_FOLDERS = ("clouds", "pcd", "pcds", "scans", "points")
#: The folder of one pose file a scan.
POSE_FOLDER = "poses"
#: Words one of which a pose file's name holds (lower case), and the suffixes it may have.
POSE_FILE_WORDS = ("pose", "traj")
POSE_FILE_SUFFIXES = (".txt", ".csv")
TIMES_FILE = "times.txt"
#: Poses at their own clock are interpolated at a scan's time between samples at most this many times the
#: median spacing of the poses apart (a gap wider than that is no motion to interpolate across).
PAIRING_GAP = 1.5
_NUMBER = re.compile(r"\d+(?:\.\d+)?")
_SEPARATORS = re.compile(r"[,\s;]+")


def _scan_files(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]


def scan_folder(path: Path) -> Path | None:
    """The folder holding ``path``'s scans (module docs), or None; scans in two folders below it and none in
    the named ones are a SequenceError naming them."""
    for folder in (path, *(path / name for name in SCAN_FOLDERS)):
        if folder.is_dir() and _scan_files(folder):
            return folder
    below = [f for f in sorted(path.glob("*/")) + sorted(path.glob("*/*/")) if f.is_dir() and _scan_files(f)]
    if len(below) > 1:
        raise SequenceError(
            f"LiDAR scan folder {path}: scans in {len(below)} folders ({', '.join(str(f.relative_to(path)) for f in below[:4])}); "
            "open the folder of one sensor's scans, with its poses beside them"
        )
    return below[0] if below else None


def pose_file(path: Path) -> Path | None:
    """The one pose file of ``path`` (module docs), or None; two candidates are a SequenceError naming them."""
    found = sorted(
        p for p in path.iterdir()
        if p.is_file() and p.suffix.lower() in POSE_FILE_SUFFIXES and any(w in p.stem.lower() for w in POSE_FILE_WORDS)
    )
    if len(found) > 1:
        raise SequenceError(f"LiDAR scan folder {path}: two pose files ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def is_scan_folder(path) -> bool:
    """Whether ``path`` is a folder of LiDAR scans with poses (module docs) and not a KITTI folder."""
    path = Path(path)
    if not path.is_dir() or is_kitti(path):
        return False
    try:
        if scan_folder(path) is None:
            return False
        return (path / POSE_FOLDER).is_dir() or pose_file(path) is not None
    except SequenceError:
        return True  # ours to read, and to say what is wrong with


def scan_numbers(scan: Path) -> tuple[float, ...]:
    """The numbers in a scan file's name, in order (``cloud_1583836591_182590976.pcd`` -> both; a decimal's
    value whole), or a SequenceError naming it."""
    stem = scan.name[: -len(scan.suffix)] if scan.suffix else scan.name
    numbers = tuple(float(n) for n in _NUMBER.findall(stem))
    if not numbers:
        raise SequenceError(f"{scan}: a scan's name must hold its number (as full12.pcd or 000012.bin), to put the scans in order")
    return numbers


def ordered_scans(folder: Path) -> list[Path]:
    """The scan files of ``folder`` in the order of the numbers in their names (module docs)."""
    scans = _scan_files(folder)
    kinds = sorted({p.suffix.lower() for p in scans})
    if len(kinds) > 1:
        raise SequenceError(f"LiDAR scan folder {folder}: holds both {' and '.join(kinds)} scans; keep one kind")
    keys = {scan: scan_numbers(scan) for scan in scans}
    ordered = sorted(scans, key=lambda p: (keys[p], p.name))
    for first, second in zip(ordered, ordered[1:]):
        if keys[first] == keys[second]:
            raise SequenceError(f"LiDAR scan folder {folder}: two scans have the same number ({first.name}, {second.name})")
    return ordered


def in_seconds(times: np.ndarray) -> np.ndarray:
    """Times since the epoch in ns, us or ms told by their size (above 1e17, 1e14, 1e11) and made seconds."""
    times = np.asarray(times, dtype=np.float64)
    largest = np.nanmax(np.abs(times)) if np.isfinite(times).any() else 0.0
    for limit, unit in ((1e17, 1e-9), (1e14, 1e-6), (1e11, 1e-3)):
        if largest > limit:
            return times * unit
    return times


def scan_name_times(scans: list[Path]) -> np.ndarray:
    """Each scan's time (s) from its name: its one number, or seconds and nanoseconds (module docs)."""
    times = []
    for scan in scans:
        numbers = scan_numbers(scan)
        if len(numbers) == 2 and numbers[1] < 1e9 and numbers[0] > 1e8:
            times.append(numbers[0] + numbers[1] * 1e-9)
        else:
            times.append(numbers[-1])
    return in_seconds(np.array(times))


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
    lengths = [len(values) for _, values in rows]
    counts = set(lengths)
    if counts == {8} or counts == {9}:
        return _quaternion_poses(rows, path)
    if counts <= {12, 16} or counts <= {13, 17}:
        timed = counts <= {13, 17}
        blocks = [(n, v[1:] if timed else v, v[0] if timed else np.nan) for n, v in rows]
    elif counts == {4}:
        height = 4 if len(rows) % 4 == 0 and all(rows[i][1][:3] == [0.0, 0.0, 0.0] for i in range(3, len(rows), 4)) else 3
        if len(rows) % height:
            raise SequenceError(f"{path}: {len(rows)} lines of 4 numbers is not a whole number of {height}-line matrices")
        blocks = [(rows[i][0], [v for _, values in rows[i : i + height] for v in values], np.nan) for i in range(0, len(rows), height)]
    else:
        usual = max(counts, key=lengths.count)  # the odd line is one of another count than most
        number, values = next((n, v) for n, v in rows if len(v) != usual) if len(counts) > 1 else rows[0]
        raise SequenceError(
            f"{path}:{number}: pose: {len(values)} numbers; a pose file holds lines of 12 (a 3x4 matrix) or 16 (a 4x4), "
            "each after a time or not (13, 17), of 8 (time tx ty tz qx qy qz qw) or 9 (sec nsec tx ...), "
            "or 4-line blocks of 4 numbers, the same form on every line"
        )
    poses, times = [], []
    for number, values, time in blocks:
        matrix, kept = _matrix(values, f"{path}:{number}")
        poses.append(_rigid(repairs, matrix, f"{path}:{number}"))
        times.append(time if np.isfinite(time) else kept)
    return np.array(poses), in_seconds(np.array(times))


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


def _rigid(repairs: PoseRepairs, matrix: np.ndarray, where: str) -> np.ndarray:
    try:
        return repairs.read(matrix, where)
    except PoseError as exc:
        raise SequenceError(f"{where}: not a rigid transform: {exc}") from None


def _quaternion_poses(rows: list[tuple[int, list[float]]], path: Path) -> tuple[np.ndarray, np.ndarray]:
    values = np.array([v for _, v in rows], dtype=np.float64)
    if values.shape[1] == 9:  # sec nsec: one time
        values = np.column_stack([values[:, 0] + values[:, 1] * 1e-9, values[:, 2:]])
    bad = bad_quaternions(values[:, 4:8])
    if bad.any():
        number = rows[int(np.flatnonzero(bad)[0])][0]
        raise SequenceError(f"{path}:{number}: pose: the quaternion (qx qy qz qw) is not a rotation")
    return poses_from_translations_quaternions(values[:, 1:4], values[:, 4:8]), in_seconds(values[:, 0])


def _pose_per_scan(folder: Path, scans: list[Path], repairs: PoseRepairs) -> tuple[np.ndarray, np.ndarray]:
    """The poses and times of a ``poses/`` folder of one file a scan, or a SequenceError naming a scan without one."""
    poses, times = [], []
    for scan in scans:
        stem = scan.name[: -len(scan.suffix)]
        file = next((folder / (stem + s) for s in POSE_FILE_SUFFIXES if (folder / (stem + s)).is_file()), None)
        if file is None:
            raise SequenceError(f"{folder}: no pose for scan {scan.name} (expected {folder / (stem + '.txt')})")
        flat = [v for _, values in read_pose_lines(file) for v in values]
        if len(flat) not in (12, 16):
            raise SequenceError(f"{file}: a scan's pose file holds one 4x4 or 3x4 matrix, got {len(flat)} numbers")
        matrix, time = _matrix(flat, str(file))
        poses.append(_rigid(repairs, matrix, str(file)))
        times.append(time)
    return np.array(poses), in_seconds(np.array(times))


class ScanFolderSequence(KittiSequence):
    """A folder of LiDAR scans and their poses (module docs) as range-image frames; ``geometry`` replaces the
    ``[lidar]`` table's."""

    label = "LiDAR scan folder"

    def _read_layout(self, path: Path) -> tuple[list[Path], np.ndarray, np.ndarray]:
        if not path.is_dir() or (folder := scan_folder(path)) is None:
            raise SequenceError(
                f"LiDAR scan folder {path}: no .pcd or .bin scans in it, in {', '.join(f'{n}/' for n in SCAN_FOLDERS)} or in a folder below it"
            )
        scans = ordered_scans(folder)
        repairs = PoseRepairs()
        if (path / POSE_FOLDER).is_dir():
            poses, times = _pose_per_scan(path / POSE_FOLDER, scans, repairs)
            where = f"{path / POSE_FOLDER}/"
        elif (file := pose_file(path)) is not None:
            poses, times = poses_of_lines(read_pose_lines(file), file, repairs)
            where = str(file)
        else:
            raise SequenceError(
                f"LiDAR scan folder {path}: no poses: expected a {POSE_FOLDER}/ folder of one file a scan, or a file "
                f"whose name holds {' or '.join(repr(w) for w in POSE_FILE_WORDS)} ({', '.join(POSE_FILE_SUFFIXES)})"
            )
        if (note := repairs.note(where)) is not None:
            warnings.warn(note, PoseFileWarning, stacklevel=4)
        scan_times = None
        if (path / TIMES_FILE).is_file():
            scan_times = in_seconds(read_times(path / TIMES_FILE))
            if len(scan_times) != len(scans):
                raise SequenceError(f"{path / TIMES_FILE}: {len(scan_times)} timestamps, but {folder} holds {len(scans)} scans")
        if len(poses) == len(scans):
            return scans, poses, times if scan_times is None or np.isfinite(times).all() else scan_times
        return self._paired_by_time(scans, poses, times, scan_times, where)

    def _paired_by_time(self, scans, poses, times, scan_times, where: str) -> tuple[list[Path], np.ndarray, np.ndarray]:
        """The scans with a pose interpolated at their times (module docs); the skipped ones counted in the
        description."""
        if not np.isfinite(times).all():
            raise SequenceError(f"{where}: {len(poses)} poses for {len(scans)} scans, and the poses hold no times to pair them by")
        if scan_times is None:
            try:
                scan_times = scan_name_times(scans)
            except SequenceError:
                scan_times = None
        if scan_times is None or not np.isfinite(scan_times).all():
            raise SequenceError(
                f"{where}: {len(poses)} poses for {len(scans)} scans, and the scans' times are unknown "
                f"(a {TIMES_FILE}, or names that are their times) to pair them by"
            )
        spacing = float(np.median(np.diff(np.sort(times)))) if len(times) > 1 else 0.0
        paired = interpolate_poses(scan_times, times, poses, PAIRING_GAP * spacing / 2.0 + 1e-9)
        keep = np.isfinite(paired).all(axis=(1, 2))
        if not keep.any():
            raise SequenceError(
                f"{where}: no scan's time ({scan_times.min():.3f}-{scan_times.max():.3f} s) falls within the poses' "
                f"({times.min():.3f}-{times.max():.3f} s)"
            )
        skipped = int((~keep).sum())
        self.description += f" (poses interpolated at the scans' times; {skipped} scans without a pose skipped)" if skipped else (
            " (poses interpolated at the scans' times)"
        )
        return [s for s, k in zip(scans, keep) if k], paired[keep], scan_times[keep]


__all__ = ["ScanFolderSequence", "in_seconds", "is_scan_folder", "ordered_scans", "poses_of_lines", "read_pose_lines", "scan_name_times"]
