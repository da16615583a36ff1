"""A spinning LiDAR that moves during its sweep, deskewed as a driver deskews it, and its mount.

The ideal simulated LiDAR (``[sensor.lidar] sweep = "instant"``, the default)
renders each frame's range image from one pose. A real one fires one column
of beams after another while it turns and the vehicle moves, and its driver
*deskews* the sweep into the frame of one pose. ``sweep = "deskewed"``
(:class:`SweepSettings`) simulates that:

1. frame i's sweep takes ``duration`` seconds (``sweep_time``; 0: the time
   between frames) and ends at frame i's timestamp; columns fire in turn,
   clockwise seen from above, the seam behind the sensor;
2. each column is cast from the path's true pose at its time
   (:func:`poses_at`) times the mount, against the scene as it stands at
   frame i (:class:`SceneRayCaster`), with the ``noise`` model's range noise;
3. every return is moved with the true path into the sensor frame at the
   sweep's end, frame i's pose (:class:`Sweep`);
4. the range image is :func:`mabdi.sources.range_images.range_image` of those
   points with the sensor's own geometry.

The mount (``[sensor.lidar] mount_tilt``, ``mount_roll``, degrees; either sweep):
``base_from_sensor = R_y(mount_tilt) R_x(mount_roll)``; the sensor's pose
(``world_from_sensor``) is the path's pose times the mount.
More: docs/architecture.md (``mabdi.simulate.lidar_sweep``).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mabdi.errors import ConfigError
from mabdi.sensor_noise import SensorNoise, noise_rng
from mabdi.spherical import SphericalGeometry

#: ``[sensor.lidar] sweep``: the ideal range image from one pose, or a moving sweep deskewed as a driver does.
SWEEP_MODES = ("instant", "deskewed")
#: The ``[sensor.lidar]`` keys of the sweep and the mount (a camera with any of them set is an error).
SWEEP_KEYS = ("sweep", "sweep_time", "mount_tilt", "mount_roll")
#: The largest mount angle (degrees) either way.
MAX_MOUNT_ANGLE = 90.0


@dataclass(frozen=True)
class SweepSettings:
    """How the simulated LiDAR's sweep is made (module docs): ``mode`` (:data:`SWEEP_MODES`), ``duration``
    (seconds one sweep takes; 0: the time between frames), ``mount_tilt`` and ``mount_roll`` (degrees)."""

    mode: str = "instant"
    duration: float = 0.0
    mount_tilt: float = 0.0
    mount_roll: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in SWEEP_MODES:
            raise ConfigError(f"key 'sweep' = {self.mode!r} is not one of: {', '.join(SWEEP_MODES)}")
        if not (math.isfinite(self.duration) and self.duration >= 0):
            raise ConfigError(f"key 'sweep_time' must be >= 0 seconds (0: the time between frames), got {self.duration!r}")
        for key in ("mount_tilt", "mount_roll"):
            value = getattr(self, key)
            if not (math.isfinite(value) and abs(value) <= MAX_MOUNT_ANGLE):
                raise ConfigError(f"key '{key}' must be between -{MAX_MOUNT_ANGLE:g} and {MAX_MOUNT_ANGLE:g} degrees, got {value!r}")

    @property
    def deskewed(self) -> bool:
        return self.mode == "deskewed"

    @property
    def mounted(self) -> bool:
        """Whether the sensor is turned on its mount (a tilt or a roll)."""
        return self.mount_tilt != 0.0 or self.mount_roll != 0.0

    def base_from_sensor(self) -> np.ndarray:
        """(4, 4) the mount: ``R_y(mount_tilt) R_x(mount_roll)`` (module docs); the identity without one."""
        return mount_rotation(self.mount_tilt, self.mount_roll)


def mount_rotation(tilt: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """(4, 4) ``base_from_sensor`` of a sensor tilted ``tilt`` degrees about its y axis (positive: its x axis
    tips down) after a roll of ``roll`` degrees about its x axis (positive: its +y side up)."""
    t, r = math.radians(tilt), math.radians(roll)
    pitch = np.array([[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]])
    rolled = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(r), -math.sin(r)], [0.0, math.sin(r), math.cos(r)]])
    mount = np.eye(4)
    mount[:3, :3] = pitch @ rolled
    return mount


def poses_at(times, frame_times, frame_poses) -> np.ndarray:
    """(T, 4, 4) the poses at ``times`` (T,) s along a path of ``frame_poses`` (N, 4, 4) at ``frame_times`` (N,)
    s (increasing): between two frames the translation is linear and the rotation turns along the shortest arc at
    a constant rate; before the first frame or after the last, the first or last step's motion goes on. Two
    frames at one time, or a single frame: the pose of the first of them."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    frame_times = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    frame_poses = np.asarray(frame_poses, dtype=np.float64)
    if len(frame_poses) == 1:
        return np.repeat(frame_poses, len(times), axis=0)
    k = np.clip(np.searchsorted(frame_times, times, side="right") - 1, 0, len(frame_times) - 2)
    step = frame_times[k + 1] - frame_times[k]
    alpha = np.divide(times - frame_times[k], step, out=np.zeros_like(times), where=step > 0)
    start, end = frame_poses[k], frame_poses[k + 1]
    turn = Rotation.from_matrix(np.einsum("tji,tjk->tik", start[:, :3, :3], end[:, :3, :3])).as_rotvec()
    poses = np.tile(np.eye(4), (len(times), 1, 1))
    poses[:, :3, :3] = start[:, :3, :3] @ Rotation.from_rotvec(alpha[:, None] * turn).as_matrix()
    poses[:, :3, 3] = start[:, :3, 3] + alpha[:, None] * (end[:, :3, 3] - start[:, :3, 3])
    return poses


def column_times(geometry: SphericalGeometry, end: float, duration: float) -> np.ndarray:
    """(columns,) the time (s) each column of a sweep that ends at ``end`` and takes ``duration`` s is fired
    (module docs: column 0 first, the last half a column's time before ``end``)."""
    return end - duration + (np.arange(geometry.columns) + 0.5) * (duration / geometry.columns)


def open3d_or_error():
    """The ``open3d`` module, or a ConfigError saying how to install it (the moving sweep casts its rays with it)."""
    try:
        import open3d
    except (ImportError, OSError) as exc:
        raise ConfigError(
            f'[sensor.lidar] sweep = "deskewed" casts its rays with Open3D, which cannot be imported here ({exc}): '
            'pip install "mabdi[compare]" (on Debian, import open3d also needs libusb-1.0-0)'
        ) from None
    return open3d


class SceneRayCaster:
    """The nearest hit of rays with any origin against a triangle mesh: Open3D's ``RaycastingScene`` (a BVH, in
    float32) finds the triangle, and the range is recomputed in float64 on its plane."""

    def __init__(self, points, triangles) -> None:
        o3d = open3d_or_error()
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self._scene = o3d.t.geometry.RaycastingScene()
        #: Coordinates are cast about this point (float32 keeps micrometres within a street's extent of it).
        self.centre = 0.5 * (self.points.min(axis=0) + self.points.max(axis=0)) if len(self.points) else np.zeros(3)
        if len(self.triangles):
            self._scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(self.points - self.centre, dtype=np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(self.triangles, dtype=np.uint32)),
            )
        self._o3d = o3d
        corners = self.points[self.triangles]
        #: Each triangle's plane, n . p = offset (n not normalised), for the float64 range of a hit.
        self.normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]) if len(self.triangles) else np.zeros((0, 3))
        self.offsets = np.einsum("ij,ij->i", self.normals, corners[:, 0]) if len(self.triangles) else np.zeros(0)

    def cast(self, origins, directions) -> tuple[np.ndarray, np.ndarray]:
        """(N,) float64 distance along each unit ray (``origins``, ``directions``: (N, 3) world frame) to the
        first triangle it meets (inf: none), and (N,) int64 that triangle (-1: none)."""
        origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        count = len(directions)
        if not len(self.triangles) or not count:
            return np.full(count, np.inf), np.full(count, -1, dtype=np.int64)
        rays = np.empty((count, 6), dtype=np.float32)
        rays[:, :3] = origins - self.centre
        rays[:, 3:] = directions
        answer = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        distance = answer["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(distance)
        triangle = np.where(hit, answer["primitive_ids"].numpy().astype(np.int64), -1)
        # float64 on the hit triangle's plane: t = (offset - n . o) / n . d
        normal = self.normals[triangle[hit]]
        along = np.einsum("ij,ij->i", normal, directions[hit])
        exact = self.offsets[triangle[hit]] - np.einsum("ij,ij->i", normal, origins[hit])
        ok = np.abs(along) > 1e-9 * np.sqrt(np.einsum("ij,ij->i", normal, normal))
        refined = distance[hit]
        refined[ok] = exact[ok] / along[ok]
        distance[hit] = np.where(refined > 0, refined, distance[hit])
        return distance, triangle


@dataclass(frozen=True)
class Sweep:
    """One deskewed sweep (module docs): its returns as points in the sensor frame of the sweep's end pose."""

    #: (N, 3) float64 deskewed points (m), sensor frame at the sweep's end (x forward, y left, z up).
    points: np.ndarray
    #: (N,) int64 the beam (row of the sensor's beam layout, top first) and (N,) the column that fired each.
    beams: np.ndarray
    columns: np.ndarray
    #: (N,) float64 when each was measured (s).
    times: np.ndarray
    #: (4, 4) the true world_from_sensor at the sweep's end (the frame's true pose).
    world_from_sensor: np.ndarray

    def world_points(self) -> np.ndarray:
        """(N, 3) the points in the world (the end pose applied)."""
        return self.points @ self.world_from_sensor[:3, :3].T + self.world_from_sensor[:3, 3]


def simulate_sweep(
    caster: SceneRayCaster,
    geometry: SphericalGeometry,
    end_time: float,
    duration: float,
    frame_times,
    sensor_poses,
    end_pose=None,
    noise: SensorNoise | str = "none",
    rng: np.random.Generator | None = None,
) -> Sweep:
    """The sweep of a sensor with beams ``geometry`` (its own frame) that ends at ``end_time`` and takes
    ``duration`` s, moving along the path of true ``sensor_poses`` (N, 4, 4, world_from_sensor, the mount
    included) at ``frame_times``, against ``caster``'s scene, with ``noise`` drawn from ``rng``, deskewed into the
    sensor frame of ``end_pose`` (default: the path's pose at ``end_time``). Module docs, steps 1-3."""
    times = column_times(geometry, end_time, duration)
    poses = poses_at(times, frame_times, sensor_poses)  # (columns, 4, 4)
    end = poses_at([end_time], frame_times, sensor_poses)[0] if end_pose is None else np.asarray(end_pose, dtype=np.float64)
    rays = _sensor_rays(geometry)  # (columns, beams, 3) in the sensor frame, column by column
    directions = rays @ poses[:, :3, :3].transpose(0, 2, 1)  # (columns, beams, 3) in the world
    origins = np.broadcast_to(poses[:, None, :3, 3], directions.shape)
    distance = caster.cast(origins.reshape(-1, 3), directions.reshape(-1, 3))[0].reshape(geometry.columns, geometry.beams).T
    with np.errstate(invalid="ignore"):
        ranges = np.where((distance > geometry.range_min) & (distance < geometry.range_max), distance, np.nan)
    measured = SensorNoise.of(noise).ranges_with_noise(ranges.astype(np.float32), rng).astype(np.float64)
    beams, columns = np.nonzero(np.isfinite(measured))
    local = rays[columns, beams] * measured[beams, columns, None]  # in the sensor frame of the column's pose
    end_from_column = np.linalg.inv(end) @ poses  # (columns, 4, 4)
    moved = end_from_column[columns]
    points = (moved[:, :3, :3] @ local[:, :, None])[:, :, 0] + moved[:, :3, 3]
    return Sweep(points, beams.astype(np.int64), columns.astype(np.int64), times[columns], end)


@functools.lru_cache(maxsize=4)
def _sensor_rays(geometry: SphericalGeometry) -> np.ndarray:
    """(columns, beams, 3) the unit rays of ``geometry`` (:meth:`SphericalGeometry.rays`) column by column."""
    rays = np.ascontiguousarray(geometry.rays().transpose(1, 0, 2))
    rays.setflags(write=False)
    return rays


def sweep_noise_rng(noise: SensorNoise, seed: int, frame: int) -> np.random.Generator | None:
    """The random stream of frame ``frame``'s sweep (the ideal sensor's: (seed, frame)); None without noise."""
    return noise_rng(seed, frame) if noise.noisy else None


__all__ = [
    "MAX_MOUNT_ANGLE",
    "SWEEP_KEYS",
    "SWEEP_MODES",
    "SceneRayCaster",
    "Sweep",
    "SweepSettings",
    "column_times",
    "mount_rotation",
    "open3d_or_error",
    "poses_at",
    "simulate_sweep",
    "sweep_noise_rng",
]
