"""Pose files as real tools write them, and numbers and times in file names: what every folder layout shares.

A pose file holds a pose a line (or a block of lines), world from sensor, in any of the forms SLAM tools and
datasets write (:func:`poses_of_lines`):

- 12 or 16 numbers (a 3x4 or 4x4 matrix, row-major), or 13 or 17: a time, then the matrix;
- 8: ``time tx ty tz qx qy qz qw`` (TUM's trajectory format), or 9: ``sec nsec tx ty tz qx qy qz qw``;
- 4-line (3-line) blocks of 4 numbers, a 4x4 (3x4) each.

Spaces or commas part the numbers; blank lines, ``#`` comments and a first line of column names are skipped.
A 4x4's last row is ``0 0 0 1``, or ``0 0 0 t`` with the frame's time t (BALM's ``alidarPose.csv``). Rotations
written to a few digits are made rigid (:class:`mabdi.camera.PoseRepairs`); a matrix that is no rigid motion,
or a line of another count, is a :class:`SequenceError` naming the file and line. Times in ns, us or ms since
the epoch are told by their size and read as seconds (:func:`in_seconds`).

A frame file's name orders it by the numbers it holds (:func:`file_numbers`: ``full9`` before ``full10``,
``cloud_1583836591_182590976`` by both) and may be its time (:func:`name_times`). Poses on their own clock
are interpolated at the frames' times (:func:`poses_at_times`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mabdi.camera import PoseRepairs
from mabdi.errors import PoseError
from mabdi.sources.sequence_files import SequenceError, bad_quaternions, interpolate_poses, poses_from_translations_quaternions

#: Words one of which a pose file's name holds (lower case), and the suffixes it may have.
POSE_FILE_WORDS = ("pose", "traj")
POSE_FILE_SUFFIXES = (".txt", ".csv")
#: Poses at their own clock are interpolated at a frame's time between samples at most this many times the
#: median spacing of the poses apart (a gap wider than that is no motion to interpolate across).
PAIRING_GAP = 1.5
_NUMBER = re.compile(r"\d+(?:\.\d+)?")
_SEPARATORS = re.compile(r"[,\s;]+")


def pose_file(path: Path) -> Path | None:
    """The one pose file of folder ``path`` (a name holding :data:`POSE_FILE_WORDS`, a suffix of
    :data:`POSE_FILE_SUFFIXES`), or None; two candidates are a SequenceError naming them."""
    found = sorted(
        p for p in path.iterdir()
        if p.is_file() and p.suffix.lower() in POSE_FILE_SUFFIXES and any(w in p.stem.lower() for w in POSE_FILE_WORDS)
    )
    if len(found) > 1:
        raise SequenceError(f"{path}: two pose files ({', '.join(p.name for p in found)}); keep one")
    return found[0] if found else None


def file_numbers(file: Path) -> tuple[float, ...]:
    """The numbers in a frame file's name, in order (``cloud_1583836591_182590976.pcd`` -> both; a decimal's
    value whole), or a SequenceError naming it."""
    stem = file.name[: -len(file.suffix)] if file.suffix else file.name
    numbers = tuple(float(n) for n in _NUMBER.findall(stem))
    if not numbers:
        raise SequenceError(f"{file}: a frame file's name must hold its number (as full12.pcd or 000012.png), to put the frames in order")
    return numbers


def in_seconds(times: np.ndarray) -> np.ndarray:
    """Times since the epoch in ns, us or ms told by their size (above 1e17, 1e14, 1e11) and made seconds."""
    times = np.asarray(times, dtype=np.float64)
    largest = np.nanmax(np.abs(times)) if np.isfinite(times).any() else 0.0
    for limit, unit in ((1e17, 1e-9), (1e14, 1e-6), (1e11, 1e-3)):
        if largest > limit:
            return times * unit
    return times


def name_times(files: list[Path]) -> np.ndarray:
    """Each frame file's time (s) from its name: its last number, or seconds and nanoseconds (two numbers, the
    first above 1e8 and the second below 1e9), the epoch's units made seconds (:func:`in_seconds`)."""
    times = []
    for file in files:
        numbers = file_numbers(file)
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
        matrix, kept = matrix_of(values, f"{path}:{number}")
        poses.append(rigid_pose(repairs, matrix, f"{path}:{number}"))
        times.append(time if np.isfinite(time) else kept)
    return np.array(poses), in_seconds(np.array(times))


def matrix_of(values: list[float], where: str) -> tuple[np.ndarray, float]:
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


def rigid_pose(repairs: PoseRepairs, matrix: np.ndarray, where: str) -> np.ndarray:
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


def poses_at_times(frame_times: np.ndarray, times: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the poses interpolated at ``frame_times``, which frames have one): linear in position and slerp in
    rotation between two samples at most :data:`PAIRING_GAP` median sample spacings apart, the nearest held
    within half of that past the ends; times in seconds."""
    spacing = float(np.median(np.diff(np.sort(times)))) if len(times) > 1 else 0.0
    paired = interpolate_poses(frame_times, times, poses, PAIRING_GAP * spacing / 2.0 + 1e-9)
    return paired, np.isfinite(paired).all(axis=(1, 2))


def paired_by_time(files: list[Path], frame_times, times: np.ndarray, poses: np.ndarray, where: str, what: str, unknown: str = ""):
    """(the files with a pose, their poses interpolated at ``frame_times`` (:func:`poses_at_times`), their times,
    how many were skipped outside the poses' times) where a pose file holds another count of poses than there
    are frame ``files`` (``what``: "scans", "depth images"); a SequenceError naming ``where`` when the poses or
    the frames (``frame_times`` None: ``unknown`` says where they would come from) have no times, or no frame
    falls within the poses'."""
    if not np.isfinite(times).all():
        raise SequenceError(f"{where}: {len(poses)} poses for {len(files)} {what}, and the poses hold no times to pair them by")
    if frame_times is None:
        raise SequenceError(f"{where}: {len(poses)} poses for {len(files)} {what}, and the {what}' times are unknown ({unknown}) to pair them by")
    paired, keep = poses_at_times(frame_times, times, poses)
    if not keep.any():
        raise SequenceError(
            f"{where}: no {what}' time ({frame_times.min():.3f}-{frame_times.max():.3f} s) falls within the poses' "
            f"({times.min():.3f}-{times.max():.3f} s)"
        )
    return [f for f, k in zip(files, keep, strict=True) if k], paired[keep], frame_times[keep], int((~keep).sum())


def ordered_by_numbers(files: list[Path], where: str) -> list[Path]:
    """``files`` in the order of the numbers in their names, or a SequenceError naming two of the same numbers."""
    keys = {file: file_numbers(file) for file in files}
    ordered = sorted(files, key=lambda p: (keys[p], p.name))
    for first, second in zip(ordered, ordered[1:], strict=False):
        if keys[first] == keys[second]:
            raise SequenceError(f"{where}: two files have the same number ({first.name}, {second.name})")
    return ordered


__all__ = [
    "PAIRING_GAP",
    "POSE_FILE_SUFFIXES",
    "POSE_FILE_WORDS",
    "file_numbers",
    "in_seconds",
    "matrix_of",
    "name_times",
    "ordered_by_numbers",
    "paired_by_time",
    "pose_file",
    "poses_at_times",
    "poses_of_lines",
    "read_pose_lines",
    "rigid_pose",
]
