"""Which axes a LiDAR recording's poses are written in: the LiDAR's own, or a camera's, told by the scans.

A LiDAR's points are in its own axes (x forward, y left, z up). Its poses are often not: KITTI's ground
truth, and the many recordings derived from it, gives the pose of a camera (x right, y down, z forward),
and a folder without the calibration that relates the two reads those as the LiDAR's poses. Then every
scan is placed turned by 90 degrees about two axes, the car's forward motion reads as motion downwards,
and nothing registers. The scans themselves tell: two scans the poses place apart (at least
:data:`MIN_MOTION_M` or :data:`MIN_TURN_DEG`) lie on each other only when the poses are read in the right
axes. :func:`pose_axes` measures both readings (the median distance from the later scan's returns to the
earlier scan's, :data:`MATCH_CAP_M` at most each) and takes the camera's only where it fits at least
:data:`CAMERA_FIT_RATIO` times better than the poses as written; the poses are then turned into the LiDAR's
axes as SemanticKITTI reads KITTI's (``R^T P R``, R the camera-from-LiDAR rotation, the lever arm unknown
and left out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: Camera axes (x right, y down, z forward) from LiDAR axes (x forward, y left, z up): KITTI's Tr without its
#: lever arm.
CAMERA_FROM_LIDAR_AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: The least motion between the two scans compared (m, degrees): less, and both readings place them alike.
MIN_MOTION_M = 1.0
MIN_TURN_DEG = 5.0
#: The scans looked at for that motion (from the first).
LOOK_AHEAD = 30
#: A return's distance to the other scan counts at most this much (m): what the other scan does not see.
MATCH_CAP_M = 5.0
#: How many times better the camera's axes must fit than the poses as written to be taken.
CAMERA_FIT_RATIO = 3.0
#: Returns nearer than this (m) are left out (the carrier), and every n-th return is used.
NEAR_M = 1.0
STRIDE = 5


@dataclass(frozen=True)
class PoseAxes:
    """What :func:`pose_axes` found: ``"lidar"`` (as written), ``"camera"`` (turned into the LiDAR's axes), or
    ``None`` (no two scans far enough apart to tell); the scans compared and each reading's median distance (m)."""

    axes: str | None
    scans: tuple[int, int] | None = None
    as_written_m: float = float("nan")
    camera_m: float = float("nan")

    def describe(self) -> str:
        i, j = self.scans
        return (
            f"scans {i} and {j} lie {self.as_written_m * 100:.0f} cm apart (median) with the poses read in the LiDAR's "
            f"axes (x forward, y left, z up) and {self.camera_m * 100:.1f} cm with them read as a camera's (x right, "
            "y down, z forward, as KITTI's ground truth)"
        )


def in_lidar_axes(poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) poses of a camera's axes turned into the LiDAR's: ``R^T P R`` (module docs)."""
    turn = np.eye(4)
    turn[:3, :3] = CAMERA_FROM_LIDAR_AXES
    return np.linalg.inv(turn) @ np.asarray(poses, dtype=np.float64) @ turn


def _moved(poses: np.ndarray) -> int | None:
    """The first scan the poses place :data:`MIN_MOTION_M` or :data:`MIN_TURN_DEG` from the first, or None."""
    for j in range(1, min(len(poses), LOOK_AHEAD)):
        relative = np.linalg.inv(poses[0]) @ poses[j]
        turn = np.degrees(np.arccos(np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        if np.linalg.norm(relative[:3, 3]) >= MIN_MOTION_M or turn >= MIN_TURN_DEG:
            return j
    return None


def _returns(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    points = points[np.isfinite(points).all(axis=1)]
    return points[np.linalg.norm(points, axis=1) > NEAR_M][::STRIDE]


def _median_distance(tree: cKDTree, points: np.ndarray, relative: np.ndarray) -> float:
    moved = points @ relative[:3, :3].T + relative[:3, 3]
    distance, _ = tree.query(moved, distance_upper_bound=MATCH_CAP_M)
    return float(np.median(np.minimum(distance, MATCH_CAP_M)))


def pose_axes(poses: np.ndarray, read_points) -> PoseAxes:
    """The axes ``poses`` (world from sensor, as written) are in, told by two of the scans
    (``read_points(i)``: scan i's (N, 3) points in the LiDAR's axes); module docs."""
    poses = np.asarray(poses, dtype=np.float64)
    j = _moved(poses) if len(poses) > 1 else None
    if j is None:
        return PoseAxes(None)
    first, later = _returns(read_points(0)), _returns(read_points(j))
    if len(first) < 100 or len(later) < 100:
        return PoseAxes(None)
    tree = cKDTree(first)
    as_written = _median_distance(tree, later, np.linalg.inv(poses[0]) @ poses[j])
    turned = in_lidar_axes(poses[[0, j]])
    camera = _median_distance(tree, later, np.linalg.inv(turned[0]) @ turned[1])
    axes = "camera" if camera * CAMERA_FIT_RATIO <= as_written else "lidar"
    return PoseAxes(axes, (0, j), as_written, camera)


__all__ = ["CAMERA_FROM_LIDAR_AXES", "PoseAxes", "in_lidar_axes", "pose_axes"]
