"""Pose noise: the poses a robot gives are not the poses it had.

A real robot's depth frames come with poses from odometry, SLAM or a motion
capture system, each a little off. :class:`PoseNoise` turns the true poses of
a simulated path into such *given* poses: the simulated sensor still renders
from the true pose (the world is where it is), while the frame carries the
given one (what the map is built with). A ``[sensor.pose_noise]`` table of a
run config sets it (:class:`mabdi.config.SensorConfig`); all zero (the
default) gives the true poses exactly.

Two parts, both in the world frame for translations and about the camera's
own centre for rotations (given pose = true rotation R times Exp(omega),
true position plus tau; omega a rotation vector in the camera frame):

* **jitter**, independent per frame: each component of tau is
  N(0, ``jitter_translation``^2) (metres) and each component of omega
  N(0, ``jitter_rotation``^2) (degrees);
* **drift**, a random walk along the distance travelled: with s_i the length
  of the true path up to frame i (metres), each component of the drift's
  tau and omega is a Brownian motion in s, so after travelling L metres its
  standard deviation is ``drift_translation`` * sqrt(L) metres and
  ``drift_rotation`` * sqrt(L) degrees (the rates are the spread after one
  metre: units m / sqrt(m) and degrees / sqrt(m)). Frame 0 has no drift.

Jitter and drift add up: omega = omega_jitter + omega_drift, tau likewise.

Reproducible: the whole trajectory's noise comes from one random stream,
``numpy.random.default_rng([seed, POSE_STREAM])``, drawn frame by frame
(frame i's draws are the same whatever the number of frames after it), and
independent of the depth noise's streams (:func:`mabdi.sensor_noise.noise_rng`,
``[seed, frame]``: :data:`POSE_STREAM` is larger than any frame index).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mabdi.camera import check_pose
from mabdi.errors import ConfigError

#: The second word of the pose noise's random stream (above 2^32: never a frame index of the depth noise).
POSE_STREAM = 0x504F53455F4E4F49  # "POSE_NOI"


@dataclass(frozen=True)
class PoseNoise:
    """Jitter and drift of the given poses (see the module docs): metres, degrees, per sqrt(metre travelled)."""

    jitter_translation: float = 0.0
    jitter_rotation: float = 0.0
    drift_translation: float = 0.0
    drift_rotation: float = 0.0

    def __post_init__(self) -> None:
        for name in ("jitter_translation", "jitter_rotation", "drift_translation", "drift_rotation"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"pose noise parameter {name} must be a finite number >= 0, got {value!r}")

    @property
    def enabled(self) -> bool:
        """Whether any part is non-zero (else the given poses are the true ones)."""
        return any((self.jitter_translation, self.jitter_rotation, self.drift_translation, self.drift_rotation))

    def variances(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """What this noise says of a given pose's error, per component: ((sigma^2, q) of the rotation in rad^2
        and rad^2 per metre travelled, (sigma^2, q) of the translation in m^2 and m^2 per metre): the white
        jitter's variance and the drift's growth (the form :class:`mabdi.stages.map_anchor.MapAnchor` takes)."""
        rotation = (math.radians(self.jitter_rotation) ** 2, math.radians(self.drift_rotation) ** 2)
        return rotation, (self.jitter_translation**2, self.drift_translation**2)

    def given_poses(self, true_poses, seed: int) -> np.ndarray:
        """(N, 4, 4) given poses for the (N, 4, 4) ``true_poses``, with the noise of run ``seed``.

        Every result is a rigid ``world_from_camera`` (checked with
        :func:`mabdi.camera.check_pose`); with no noise, a copy of ``true_poses``.
        """
        poses = np.array(true_poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"PoseNoise.given_poses: poses must be (N, 4, 4), got shape {poses.shape}")
        if not self.enabled or len(poses) == 0:
            return poses
        from scipy.spatial.transform import Rotation

        count = len(poses)
        rng = np.random.default_rng([int(seed), POSE_STREAM])
        # frame by frame: jitter tau, jitter omega, drift step of tau, drift step of omega
        draws = rng.standard_normal((count, 4, 3))
        travelled = np.zeros(count)
        travelled[1:] = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        scale = np.sqrt(travelled)[:, None]  # a step of s metres adds variance rate^2 s
        tau = self.jitter_translation * draws[:, 0] + self.drift_translation * np.cumsum(scale * draws[:, 2], axis=0)
        omega = self.jitter_rotation * draws[:, 1] + self.drift_rotation * np.cumsum(scale * draws[:, 3], axis=0)
        turn = Rotation.from_rotvec(np.radians(omega)).as_matrix()
        given = poses.copy()
        given[:, :3, :3] = poses[:, :3, :3] @ turn
        given[:, :3, 3] += tau
        for i, pose in enumerate(given):
            check_pose(pose, f"given pose {i}")
        return given
