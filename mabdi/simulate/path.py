"""The sensor's path: the helix of seed 001 §4.1, waypoints a robot drives, or a recorded trajectory.

``[path] kind`` (:class:`mabdi.config.PathConfig`) picks one:

``helix`` (the default)
    ``turns`` circles on an ellipse (``radius_x``, ``radius_y``, metres)
    about ``center``, rising from ``z0`` to ``z1``, looking at a point that
    moves from ``look_from`` to ``look_to``; ``run.frames`` frames span it.

``waypoints``
    A polyline ``points`` driven at ``speed`` (m/s), one frame every
    1 / ``rate`` seconds. Rows are ``[x, y, z]`` (heading along travel),
    ``[x, y, z, heading]`` (degrees, counter-clockwise from +x) or
    ``[x, y, z, qx, qy, qz, qw]`` (full poses, slerped).

``trajectory``
    ``file`` is a TUM trajectory (``timestamp tx ty tz qx qy qz qw``), one
    frame per pose, taken as it is.

A waypoint or trajectory path has its own number of frames
(:func:`path_frame_count`); ``run.frames`` may run the first of them.

Frames of a pose: every pose is ``world_from_sensor``. A camera
(``axes="camera"``: OpenCV optical frame, z forward, y down) looks along a
heading with image-up = world +z; a LiDAR (``axes="lidar"``: x forward,
y left, z up) has x along the heading and z up (the helix's look-at poses
are turned by :data:`CAMERA_FROM_LIDAR`). Full poses are not turned.
Details: docs/architecture.md (``mabdi.simulate.path``).
"""

from __future__ import annotations

import math

import numpy as np

from mabdi.camera import look_at
from mabdi.config import PathConfig
from mabdi.errors import ConfigError
from mabdi.simulate.routes import (
    AXES,
    CAMERA_FROM_LIDAR,
    HELIX_KEYS,
    PATH_KINDS,
    frame_reason,
    heading_poses,
    path_frame_count,
    path_poses,
    read_trajectory,
    trajectory_file,
)


def helical_path(frames: int, **parameters) -> np.ndarray:
    """(frames, 4, 4) ``world_from_camera`` poses along the helix (metres; ``start_angle`` in degrees).

    ``parameters`` are the helix keys of :class:`mabdi.config.PathConfig` (``center``,
    ``radius_x``, ``radius_y``, ``z0``, ``z1``, ``look_from``, ``look_to``,
    ``turns``, ``start_angle``), which also holds their defaults. The angle
    runs counter-clockwise seen from above, starting at ``start_angle``
    (-90 degrees = on the -y side of the centre).
    """
    unknown = sorted(set(parameters) - set(HELIX_KEYS))
    if unknown:
        raise TypeError(f"helical_path: unknown parameter {unknown[0]!r}")
    return _helix(_check_frames(frames), PathConfig(**parameters))


def circle_index(frames: int, turns: float) -> np.ndarray:
    """(frames,) which circle of the helix each frame is in (frame i at t = i / (N - 1); the last
    frame counts to the last circle)."""
    circles = max(1, int(round(turns)))
    t = np.arange(frames) / max(frames - 1, 1)
    return np.minimum((t * turns).astype(int), circles - 1)


def path_targets(frames: int, config: PathConfig) -> np.ndarray:
    """(frames, 3) look-at points of the helix (where each pose looks)."""
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    a, b = np.asarray(config.look_from), np.asarray(config.look_to)
    return a + t[:, None] * (b - a)


def path_from_config(frames: int, config: PathConfig, base_dir=None, axes: str = "camera") -> np.ndarray:
    """(frames, 4, 4) ``world_from_sensor`` poses of a ``[path]`` section (module docs: kinds, frames, axes).

    ``base_dir`` is the folder a trajectory ``file`` is relative to (the config file's); ``axes`` is
    ``"camera"`` or ``"lidar"``, the frame of the sensor the poses carry.
    """
    frames = _check_frames(frames)
    if axes not in AXES:
        raise ValueError(f"path_from_config: axes must be one of {', '.join(AXES)}, got {axes!r}")
    if config.kind == "helix":
        poses = _helix(frames, config)
        return poses @ CAMERA_FROM_LIDAR if axes == "lidar" else poses
    poses = path_poses(config, base_dir, axes)
    if frames > len(poses):
        raise ConfigError(
            f"run.frames = {frames} but the [path] ({config.kind}) gives {len(poses)} frames{frame_reason(config)}; "
            "leave run.frames out to run them all"
        )
    return poses[:frames]


def path_timestamps(frames: int, config: PathConfig, base_dir=None) -> np.ndarray | None:
    """(frames,) seconds of each frame of a waypoint path (i / rate) or a trajectory (its file's timestamps);
    None for the helix (the simulated sensor's own frame rate)."""
    frames = _check_frames(frames)
    if config.kind == "helix":
        return None
    if config.kind == "waypoints":
        return np.arange(frames) / config.rate
    times = read_trajectory(trajectory_file(config, base_dir))[0]
    if frames > len(times):
        raise ConfigError(f"run.frames = {frames} but the [path] (trajectory) gives {len(times)} frames (the poses of {config.file})")
    return times[:frames]


def _check_frames(frames) -> int:
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ConfigError(f"helical_path: frames must be a positive integer, got {frames!r}")
    return int(frames)


def _helix(frames: int, config: PathConfig) -> np.ndarray:
    """(frames, 4, 4) world_from_camera poses along the helix of ``config`` (module docs)."""
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    angle = math.radians(config.start_angle) + 2.0 * math.pi * config.turns * t
    eye = np.stack(
        [
            config.center[0] + config.radius_x * np.cos(angle),
            config.center[1] + config.radius_y * np.sin(angle),
            config.z0 + (config.z1 - config.z0) * t,
        ],
        axis=1,
    )
    return np.stack([look_at(e, g) for e, g in zip(eye, path_targets(frames, config), strict=True)])


__all__ = [
    "AXES",
    "CAMERA_FROM_LIDAR",
    "PATH_KINDS",
    "circle_index",
    "heading_poses",
    "helical_path",
    "path_frame_count",
    "path_from_config",
    "path_poses",
    "path_targets",
    "path_timestamps",
    "read_trajectory",
]
