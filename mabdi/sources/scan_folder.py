"""Folders of LiDAR scans beside their poses, as SLAM tools and datasets ship them: read as range-image frames.

Many LiDAR recordings are a folder of scan files in the LiDAR's frame (PCL's ``.pcd``, :mod:`mabdi.sources.pcd`,
or KITTI's float32 ``x y z intensity`` ``.bin``) beside the scans' poses (world from LiDAR), in no one layout:

* **Scans**: the ``.pcd`` (or ``.bin``, not both) files of the folder, else of its ``clouds/``, ``pcd/``,
  ``pcds/``, ``scans/`` or ``points/``, else of the one folder below it (two levels at most) that holds
  two or more, each named with a number; ordered by the numbers in their names (``full9`` before
  ``full10``, ``cloud_1583836591_182590976`` by both). A name without a number, or two scans of the same
  numbers, is an error naming them.
* **Poses**: a ``poses/`` folder of a file a scan (``poses/<scan name>.txt``, a 4x4 or 3x4 matrix), or one
  file of the folder whose name holds ``pose`` or ``traj`` (``.txt``, ``.csv``; ``poses.txt``,
  ``alidarPose.csv``, ``trajectory.txt``) in any of the forms :mod:`mabdi.sources.pose_files` reads
  (3x4 / 4x4 lines with or without a time, TUM lines, 4-line blocks; a repair of rotations written to a
  few digits said once).
* **Pairing**: as many poses as scans pair in order. Otherwise poses with times are interpolated at the
  scans' times (``times.txt``, one a line, else the scans' names: a number, or seconds and nanoseconds;
  :func:`~mabdi.sources.pose_files.poses_at_times`); a scan outside the poses' span is skipped, and the
  source's description counts those.
* ``calib.txt`` (optional): KITTI's ``Tr:`` line; the poses are then camera 0's and read as a KITTI
  folder reads them (``Tr^-1 P Tr``); without it, poses in a camera's axes are told by the scans
  (:mod:`mabdi.sources.pose_axes`).
* ``mabdi.toml`` (optional): a ``[lidar]`` table as for a KITTI folder; without it the geometry is learnt
  from the first scans (:class:`~mabdi.sources.kitti.KittiSequence`, whose reading this shares).

A folder with ``velodyne/`` and ``poses.txt`` is a KITTI folder (:mod:`mabdi.sources.kitti`) and read so.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from mabdi.camera import PoseRepairs
from mabdi.errors import PoseFileWarning
from mabdi.sources.kitti import CALIB_FILE, KittiSequence, is_kitti, read_calibration, read_times
from mabdi.sources.pose_files import (
    POSE_FILE_SUFFIXES,
    POSE_FILE_WORDS,
    in_seconds,
    matrix_of,
    name_times,
    ordered_by_numbers,
    paired_by_time,
    pose_file,
    poses_of_lines,
    read_pose_lines,
    rigid_pose,
)
from mabdi.sources.sequence_files import SequenceError

#: A scan file's suffixes (one kind a folder).
SCAN_SUFFIXES = (".pcd", ".bin")
#: The folders, after the folder itself, whose scan files are the scans.
SCAN_FOLDERS = ("clouds", "pcd", "pcds", "scans", "points")
#: The folder of one pose file a scan.
POSE_FOLDER = "poses"
TIMES_FILE = "times.txt"


def _scan_files(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in SCAN_SUFFIXES]


def _numbered_scans(folder: Path) -> bool:
    """Whether ``folder`` holds two scans or more, each named with a number (not another tool's ``.bin`` files)."""
    scans = _scan_files(folder)
    return len(scans) >= 2 and all(any(c.isdigit() for c in p.stem) for p in scans)


def scan_folder(path: Path) -> Path | None:
    """The folder holding ``path``'s scans (module docs), or None; scans in two folders below it and none in
    the named ones are a SequenceError naming them."""
    for folder in (path, *(path / name for name in SCAN_FOLDERS)):
        if folder.is_dir() and _scan_files(folder):
            return folder
    below = [f for f in sorted(path.glob("*/")) + sorted(path.glob("*/*/")) if f.is_dir() and _numbered_scans(f)]
    if len(below) > 1:
        raise SequenceError(
            f"LiDAR scan folder {path}: scans in {len(below)} folders ({', '.join(str(f.relative_to(path)) for f in below[:4])}); "
            "open the folder of one sensor's scans, with its poses beside them"
        )
    return below[0] if below else None


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


def ordered_scans(folder: Path) -> list[Path]:
    """The scan files of ``folder`` in the order of the numbers in their names (module docs)."""
    scans = _scan_files(folder)
    kinds = sorted({p.suffix.lower() for p in scans})
    if len(kinds) > 1:
        raise SequenceError(f"LiDAR scan folder {folder}: holds both {' and '.join(kinds)} scans; keep one kind")
    return ordered_by_numbers(scans, f"LiDAR scan folder {folder}")


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
        matrix, time = matrix_of(flat, str(file))
        poses.append(rigid_pose(repairs, matrix, str(file)))
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
        if (path / CALIB_FILE).is_file():  # KITTI's Tr: the poses are camera 0's, as in a KITTI folder
            self._axes_stated = True
            tr = read_calibration(path / CALIB_FILE)
            poses = np.linalg.inv(tr) @ poses @ tr
        if len(poses) == len(scans):
            return scans, poses, times if scan_times is None or np.isfinite(times).all() else scan_times
        scan_times = scan_times if scan_times is not None else self._name_times(scans)
        scans, poses, scan_times, skipped = paired_by_time(
            scans, scan_times, times, poses, where, "scans", f"a {TIMES_FILE}, or names that are their times"
        )
        self.description += " (poses interpolated at the scans' times" + (f"; {skipped} scans without a pose skipped)" if skipped else ")")
        return scans, poses, scan_times

    @staticmethod
    def _name_times(scans: list[Path]) -> np.ndarray | None:
        try:
            return name_times(scans)
        except SequenceError:
            return None


__all__ = ["ScanFolderSequence", "is_scan_folder", "ordered_scans", "scan_folder"]
