"""Which axes a recording's poses are written in, told by its frames: the sensor's own, or another convention's.

Poses are often written in other axes than the sensor's frames: KITTI's ground truth gives a camera's pose
(x right, y down, z forward) for a LiDAR's scans (x forward, y left, z up), and many capture apps and
graphics tools give a camera's pose in OpenGL's axes (x right, y up, z backward) where mabdi's camera is
OpenCV's (x right, y down, z forward). Read in the wrong axes, every frame is turned about two axes and
nothing registers; and poses are sometimes written the other way round, sensor from world (a view
matrix). The frames tell: two frames the poses place apart (at least :data:`MIN_MOTION_M` or
:data:`MIN_TURN_DEG`, per sensor) lie on each other only when the poses are read the right way.
:func:`pose_axes` measures each reading of :data:`READINGS` (the median distance from the later frame's
points to the earlier frame's, :data:`MATCH_CAP_M` at most each) and takes the best only where it fits at
least :data:`OTHER_FIT_RATIO` times better than the poses as written. The poses are then turned
(:func:`turned`):

* ``"camera"`` (a LiDAR's poses in a camera's axes): ``R^T P R``, R the camera-from-LiDAR rotation, as
  SemanticKITTI reads KITTI's (the world turned with them; the lever arm unknown and left out);
* ``"opengl"`` (a camera's poses in OpenGL's axes): ``P F``, F = diag(1, -1, -1) (the world kept);
* ``"inverted"``: ``P^-1``; ``"inverted camera"``, ``"inverted opengl"``: ``P^-1`` so turned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: Camera axes (x right, y down, z forward) from LiDAR axes (x forward, y left, z up): KITTI's Tr without its
#: lever arm.
CAMERA_FROM_LIDAR_AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
#: OpenGL's camera axes (x right, y up, z backward) from OpenCV's (x right, y down, z forward), and back.
OPENGL_FROM_OPENCV_AXES = np.diag([1.0, -1.0, -1.0])
#: The readings of each sensor's poses, the first as written (module docs).
READINGS = {
    "lidar": ("lidar", "camera", "inverted", "inverted camera"),
    "camera": ("opencv", "opengl", "inverted", "inverted opengl"),
}
#: What each reading is, for messages.
AXES_WORDS = {
    "lidar": "the LiDAR's axes (x forward, y left, z up)",
    "camera": "a camera's axes (x right, y down, z forward, as KITTI's ground truth)",
    "opencv": "the camera's axes (OpenCV's: x right, y down, z forward)",
    "opengl": "OpenGL's axes (x right, y up, z backward, as many capture apps write them)",
    "inverted": "sensor from world (inverted)",
    "inverted camera": "a camera's sensor from world (KITTI's axes, inverted)",
    "inverted opengl": "OpenGL's sensor from world (a view matrix)",
}
#: The least motion between the two frames compared, per sensor (m, degrees: less, and both readings place
#: them alike), and the frames looked at for it from the first (a LiDAR's scenes are metres to tens of metres
#: away, a hand-held camera's a metre or two, at 30 frames a second).
MIN_MOTION_M = {"lidar": 1.0, "camera": 0.2}
MIN_TURN_DEG = {"lidar": 5.0, "camera": 3.0}
LOOK_AHEAD = {"lidar": 30, "camera": 150}
#: A point's distance to the other frame counts at most this much (m): what the other frame does not see.
MATCH_CAP_M = 5.0
#: How many times better another reading must fit than the poses as written to be taken.
OTHER_FIT_RATIO = 3.0
#: Points nearer than this (m) are left out (a LiDAR's carrier; a camera's near speckle), and every n-th is used.
NEAR_M = {"lidar": 1.0, "camera": 0.1}
STRIDE = 5


@dataclass(frozen=True)
class PoseAxes:
    """What :func:`pose_axes` found: ``axes`` the reading taken (:data:`READINGS`; the first is the poses as
    written), or None (no two frames far enough apart to tell); the frames compared and each reading's median
    distance (m)."""

    axes: str | None
    written: str = ""
    frames: tuple[int, int] | None = None
    distances: dict | None = None

    @property
    def turned(self) -> bool:
        """Whether the poses are read another way than as written."""
        return self.axes is not None and self.axes != self.written

    def describe(self) -> str:
        i, j = self.frames
        return (
            f"frames {i} and {j} lie {self.distances[self.written] * 100:.1f} cm apart (median) with the poses read "
            f"as written (world from sensor, in {AXES_WORDS[self.written]}) and {self.distances[self.axes] * 100:.1f} "
            f"cm with them read as {AXES_WORDS[self.axes]}"
        )


def _homogeneous(rotation: np.ndarray) -> np.ndarray:
    turn = np.eye(4)
    turn[:3, :3] = rotation
    return turn


def turned(poses: np.ndarray, reading: str) -> np.ndarray:
    """(N, 4, 4) world-from-sensor poses in the sensor's axes of ``poses`` written as ``reading`` (module docs)."""
    poses = np.asarray(poses, dtype=np.float64)
    if reading.startswith("inverted"):
        poses = np.linalg.inv(poses)
        reading = reading[len("inverted"):].strip()
    if reading == "camera":
        turn = _homogeneous(CAMERA_FROM_LIDAR_AXES)
        return np.linalg.inv(turn) @ poses @ turn
    if reading == "opengl":
        return poses @ _homogeneous(OPENGL_FROM_OPENCV_AXES)
    if reading in ("", "lidar", "opencv"):
        return poses
    raise ValueError(f"unknown pose reading {reading!r}")


def _moved(poses: np.ndarray, sensor: str) -> int | None:
    """The first frame the poses place :data:`MIN_MOTION_M` or :data:`MIN_TURN_DEG` from the first, or None."""
    for j in range(1, min(len(poses), LOOK_AHEAD[sensor])):
        relative = np.linalg.inv(poses[0]) @ poses[j]
        turn = np.degrees(np.arccos(np.clip((np.trace(relative[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
        if np.linalg.norm(relative[:3, 3]) >= MIN_MOTION_M[sensor] or turn >= MIN_TURN_DEG[sensor]:
            return j
    return None


def _usable(points: np.ndarray, near: float) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    return points[np.linalg.norm(points, axis=1) > near][::STRIDE]


def _median_distance(tree: cKDTree, points: np.ndarray, relative: np.ndarray) -> float:
    moved = points @ relative[:3, :3].T + relative[:3, 3]
    distance, _ = tree.query(moved, distance_upper_bound=MATCH_CAP_M)
    return float(np.median(np.minimum(distance, MATCH_CAP_M)))


def pose_axes(poses: np.ndarray, read_points, sensor: str = "lidar") -> PoseAxes:
    """The reading of ``poses`` (world from sensor, as written) that two frames fit (``read_points(i)``: frame
    i's (N, 3) points in the sensor's axes, metres); ``sensor`` ``"lidar"`` or ``"camera"`` (module docs)."""
    readings = READINGS[sensor]
    poses = np.asarray(poses, dtype=np.float64)
    j = _moved(poses, sensor) if len(poses) > 1 else None
    if j is None:
        return PoseAxes(None, readings[0])
    first, later = _usable(read_points(0), NEAR_M[sensor]), _usable(read_points(j), NEAR_M[sensor])
    if len(first) < 100 or len(later) < 100:
        return PoseAxes(None, readings[0])
    tree = cKDTree(first)
    distances = {}
    for reading in readings:
        pair = turned(poses[[0, j]], reading)
        distances[reading] = _median_distance(tree, later, np.linalg.inv(pair[0]) @ pair[1])
    best = min(readings[1:], key=distances.get)
    taken = best if distances[best] * OTHER_FIT_RATIO <= distances[readings[0]] else readings[0]
    return PoseAxes(taken, readings[0], (0, j), distances)


__all__ = ["CAMERA_FROM_LIDAR_AXES", "OPENGL_FROM_OPENCV_AXES", "READINGS", "PoseAxes", "pose_axes", "turned"]
