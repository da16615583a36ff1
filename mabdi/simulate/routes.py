"""Waypoint and trajectory paths: the poses of a ``[path]`` of kind ``waypoints`` or ``trajectory``, and its checks.

:mod:`mabdi.simulate.path` has the rules (how waypoints are driven, headings,
full poses, trajectories, frames, the camera and LiDAR axes); this module is
their arithmetic on a ``[path]`` section (a :class:`mabdi.config.PathConfig`,
read by attribute), below the config, which checks a section and counts its
frames with it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mabdi.errors import ConfigError

if TYPE_CHECKING:
    from mabdi.config import PathConfig

#: The path kinds of ``[path] kind``.
PATH_KINDS = ("helix", "waypoints", "trajectory")
#: The sensor frames a path's poses can be given in (see :mod:`mabdi.simulate.path`).
AXES = ("camera", "lidar")
#: Keys of ``[path]`` that only the helix reads, and those of the other kinds.
HELIX_KEYS = ("center", "radius_x", "radius_y", "z0", "z1", "look_from", "look_to", "turns", "start_angle")
KIND_KEYS = {"helix": HELIX_KEYS, "waypoints": ("points", "speed", "rate"), "trajectory": ("file",)}

#: camera_from_lidar (4x4): LiDAR x = camera z (forward), y = camera -x (left), z = camera -y (up), so that
#: ``world_from_lidar = world_from_camera @ CAMERA_FROM_LIDAR`` looks where the camera looks.
CAMERA_FROM_LIDAR = np.array(
    [[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


def path_frame_count(config: PathConfig, base_dir=None) -> int | None:
    """The number of frames a waypoint or trajectory path gives (:mod:`mabdi.simulate.path`); None for the helix (``run.frames``)."""
    if config.kind == "helix":
        return None
    if config.kind == "waypoints":
        return len(waypoint_distances(config))
    return len(read_trajectory(trajectory_file(config, base_dir))[1])


def path_poses(config: PathConfig, base_dir=None, axes: str = "camera") -> np.ndarray:
    """(N, 4, 4) every ``world_from_sensor`` pose of a waypoint or trajectory path (:mod:`mabdi.simulate.path`)."""
    if config.kind == "trajectory":
        return read_trajectory(trajectory_file(config, base_dir))[1]
    if config.kind != "waypoints":
        raise ConfigError(f"key 'path.kind' = {config.kind!r} is not one of: {', '.join(PATH_KINDS)}")
    points = waypoint_array(config)
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points[:, :3], axis=0), axis=1))])
    distances = waypoint_distances(config)
    if points.shape[1] == 7:
        from mabdi.sources.sequence_files import interpolate_poses, poses_from_translations_quaternions

        poses = poses_from_translations_quaternions(points[:, :3], points[:, 3:])
        return interpolate_poses(distances, cumulative, poses, tolerance=math.inf)
    segment = np.clip(np.searchsorted(cumulative, distances, side="right") - 1, 0, len(points) - 2)
    alpha = (distances - cumulative[segment]) / (cumulative[segment + 1] - cumulative[segment])
    positions = points[segment, :3] + alpha[:, None] * (points[segment + 1, :3] - points[segment, :3])
    if points.shape[1] == 4:
        start = np.radians(points[:, 3])
        turn = math.pi - np.mod(math.pi - np.diff(start), 2.0 * math.pi)  # the shorter way, in (-pi, pi]
        headings = start[segment] + alpha * turn[segment]
    else:
        headings = travel_headings(points[:, :3])[segment]
    return heading_poses(positions, headings, axes)


def heading_poses(positions, headings, axes: str = "camera") -> np.ndarray:
    """(N, 4, 4) ``world_from_sensor`` poses at ``positions`` (N, 3) m looking horizontally along ``headings``
    (N,) radians counter-clockwise from +x: a camera (OpenCV: z along the heading, y = world -z) or a LiDAR
    (x along the heading, z = world +z)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    headings = np.asarray(headings, dtype=np.float64).reshape(-1)
    c, s, zero = np.cos(headings), np.sin(headings), np.zeros_like(headings)
    forward = np.stack([c, s, zero], axis=1)
    left = np.stack([-s, c, zero], axis=1)
    up = np.stack([zero, zero, np.ones_like(headings)], axis=1)
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    if axes == "lidar":
        poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2] = forward, left, up
    else:
        poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2] = -left, -up, forward
    poses[:, :3, 3] = positions
    return poses


def travel_headings(points) -> np.ndarray:
    """(K - 1,) the heading (radians, counter-clockwise from +x) of each segment of a polyline (K, 3); a vertical
    segment keeps the heading of the one before it (the first ones, that of the first horizontal one; 0 if none)."""
    steps = np.diff(np.asarray(points, dtype=np.float64)[:, :2], axis=0)
    horizontal = np.hypot(steps[:, 0], steps[:, 1]) > 1e-9
    headings = np.arctan2(steps[:, 1], steps[:, 0])
    if not horizontal.any():
        return np.zeros(len(steps))
    index = np.where(horizontal, np.arange(len(steps)), -1)
    index = np.maximum.accumulate(index)
    index[index < 0] = np.argmax(horizontal)
    return headings[index]


def waypoint_array(config: PathConfig) -> np.ndarray:
    """(K, 3 | 4 | 7) float64 the checked ``points`` of a waypoint path (ConfigError naming the key)."""
    rows = config.points
    if len(rows) < 2:
        raise ConfigError(f"key 'path.points' needs at least two waypoints for kind = \"waypoints\", got {len(rows)}")
    widths = {len(row) for row in rows}
    if len(widths) != 1 or next(iter(widths)) not in (3, 4, 7):
        bad = next(i for i, row in enumerate(rows) if len(row) not in (3, 4, 7) or len(row) != len(rows[0]))
        raise ConfigError(
            f"key 'path.points[{bad}]' has {len(rows[bad])} numbers: every waypoint is [x, y, z], [x, y, z, heading_deg] "
            "or [x, y, z, qx, qy, qz, qw], all of one form"
        )
    points = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(points).all():
        raise ConfigError(f"key 'path.points' must be finite numbers (row {int(np.argmax(~np.isfinite(points).all(axis=1)))})")
    if points.shape[1] == 7:
        from mabdi.sources.sequence_files import bad_quaternions

        bad = bad_quaternions(points[:, 3:])
        if bad.any():
            raise ConfigError(f"key 'path.points[{int(np.argmax(bad))}]' has a zero quaternion (qx, qy, qz, qw)")
    lengths = np.linalg.norm(np.diff(points[:, :3], axis=0), axis=1)
    if (lengths < 1e-9).any():
        k = int(np.argmax(lengths < 1e-9))
        raise ConfigError(
            f"keys 'path.points[{k}]' and 'path.points[{k + 1}]' are at the same position {points[k, :3].tolist()}: "
            "consecutive waypoints must differ (a heading change happens while driving to the next one)"
        )
    return points


def waypoint_distances(config: PathConfig) -> np.ndarray:
    """(N,) arc length (m) of each frame of a waypoint path: i * speed / rate for i = 0 .. floor(length * rate / speed)."""
    if not config.speed > 0:
        raise ConfigError(f"key 'path.speed' must be positive (m/s), got {config.speed}")
    if not config.rate > 0:
        raise ConfigError(f"key 'path.rate' must be positive (frames per second), got {config.rate}")
    points = waypoint_array(config)
    length = float(np.linalg.norm(np.diff(points[:, :3], axis=0), axis=1).sum())
    step = config.speed / config.rate
    count = int(math.floor(length / step + 1e-9)) + 1
    return np.minimum(np.arange(count) * step, length)


def trajectory_file(config: PathConfig, base_dir=None) -> Path:
    """The path of a trajectory's ``file`` (relative to ``base_dir``, the config's folder); ConfigError if missing."""
    if not config.file:
        raise ConfigError("key 'path.file' is required for kind = \"trajectory\" (a TUM trajectory file)")
    path = Path(config.file)
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    if not path.is_file():
        raise ConfigError(f"key 'path.file' = {config.file!r}: trajectory file {path} not found")
    return path


def read_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (s) and (N, 4, 4) poses of a TUM trajectory file (ConfigError naming the file and line)."""
    from mabdi.sources.tum import read_groundtruth

    try:
        times, poses = read_groundtruth(Path(path))
    except ConfigError as exc:  # a SequenceError naming the file and line
        raise ConfigError(f"key 'path.file': {exc}") from None
    if not len(poses):
        raise ConfigError(f"key 'path.file': trajectory {path} has no poses")
    return times, poses


def check_path_keys(config: PathConfig, given, where: str = "<config>") -> None:
    """Check a ``[path]`` section: its ``kind``, and that the keys ``given`` in the file belong to that kind."""
    if config.kind not in PATH_KINDS:
        raise ConfigError(f"{where}: key 'path.kind' = {config.kind!r} is not one of: {', '.join(PATH_KINDS)}")
    for key in given:
        owner = next((kind for kind, keys in KIND_KEYS.items() if key in keys), config.kind)
        if owner != config.kind:
            raise ConfigError(
                f"{where}: key 'path.{key}' belongs to kind = \"{owner}\", but this path is kind = \"{config.kind}\" "
                f"(its keys: {', '.join(KIND_KEYS[config.kind])})"
            )


def frame_reason(config: PathConfig) -> str:
    if config.kind != "waypoints":
        return f" (the poses of {config.file})"
    points = waypoint_array(config)
    length = float(np.linalg.norm(np.diff(points[:, :3], axis=0), axis=1).sum())
    return f" ({length:g} m at {config.speed:g} m/s and {config.rate:g} frames/s)"


__all__ = [
    "AXES",
    "CAMERA_FROM_LIDAR",
    "HELIX_KEYS",
    "KIND_KEYS",
    "PATH_KINDS",
    "check_path_keys",
    "frame_reason",
    "heading_poses",
    "path_frame_count",
    "path_poses",
    "read_trajectory",
    "travel_headings",
    "trajectory_file",
    "waypoint_array",
    "waypoint_distances",
]
