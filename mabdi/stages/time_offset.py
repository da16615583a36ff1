"""The offset between a recording's pose clock and its depth clock, learnt from the depth.

A depth image stamped t was taken when the recording's pose stream (motion
capture, an odometry topic) said t + offset. While the camera turns, frames
are placed where it was a few milliseconds away, frames turning one way
disagree with frames turning the other, and removal takes what the later ones
see through. :func:`learn_time_offset` finds the offset before a run: pairs of
frames where the camera's motion changes (:func:`choose_pairs`), each pair's
relative pose from its depth by the loop's projective ICP, and the offset whose
interpolated poses agree best with those, applied where it stands out of its
own uncertainty (:class:`TimeOffset`). The rule and its numbers:
docs/architecture.md (``mabdi.sources.tum``, "The pose clock").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mabdi.camera import Intrinsics
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.sequence_files import interpolate_poses
from mabdi.stages.registration import IcpWorkspace, RegistrationParameters, register_depth

#: The option's word for "learn it" (``--time-offset auto``, the default).
AUTO = "auto"
#: Seconds between the two frames of a pair (the nearest whole number of frames, at least one).
PAIR_SECONDS = 0.1
#: The pose stream's relative motion of a pair at most (degrees, metres): the two depth images overlap.
MAX_PAIR_DEGREES = 15.0
MAX_PAIR_METRES = 0.3
#: Pairs registered, at most; and the least sensitivity a pair must have (degrees of relative pose per second of
#: offset; a translation counted as the angle it subtends at a metre).
MAX_PAIRS = 40
MIN_PAIRS = 8
MIN_SENSITIVITY = 2.0
#: The offsets tried: +-MAX_OFFSET seconds in steps of GRID_STEP.
MAX_OFFSET = 0.1
GRID_STEP = 0.001
#: An offset is learnt only from a pose stream sampled at least this often (its median gap, s): sparser samples (a
#: pose per key frame, taken at the frame's own time) put no pose between the frames to move the pairing to.
MAX_POSE_GAP = MAX_OFFSET / 2
#: Pairs whose error at the best offset exceeds TRIM times the median are dropped (a registration that failed).
TRIM = 3.0
#: Applied only where the offset is at least SIGNIFICANT standard errors and MIN_OFFSET seconds, and the summed
#: squared error falls by at least MIN_GAIN (a share) from the recording's own pairing.
SIGNIFICANT = 3.0
MIN_OFFSET = 0.002
MIN_GAIN = 0.1


@dataclass(frozen=True)
class TimeOffset:
    """What :func:`learn_time_offset` found: ``seconds`` (added to a depth timestamp to find its pose; the best
    on the grid), ``standard_error`` (s), ``pairs`` (pairs used), ``error_before`` and ``error_after`` (the pairs'
    median error in degrees, rotation and translation over depth together, at offset 0 and at ``seconds``),
    ``applied`` (the rule: docs/architecture.md, "The pose clock") and ``reason`` (why not, when not)."""

    seconds: float
    standard_error: float
    pairs: int
    error_before: float
    error_after: float
    applied: bool
    reason: str = ""

    def note(self) -> str:
        """One line for the run's messages."""
        if not self.pairs:
            return f"poses taken at the depth timestamps ({self.reason})"
        found = (
            f"{1000 * self.seconds:+.1f} ms (+-{1000 * self.standard_error:.1f}) from {self.pairs} pairs of frames, "
            f"their median disagreement {self.error_before:.2f} -> {self.error_after:.2f} deg"
        )
        if self.applied:
            return (
                f"poses taken {1000 * self.seconds:+.1f} ms from the depth timestamps: the pose clock's offset learnt "
                f"from the depth, {found}"
            )
        return f"poses taken at the depth timestamps ({self.reason}; the best offset {found})"

    def as_dict(self) -> dict:
        return {
            "seconds": self.seconds, "standard_error": self.standard_error, "pairs": self.pairs,
            "error_before_deg": self.error_before, "error_after_deg": self.error_after, "applied": self.applied,
            "reason": self.reason,
        }  # fmt: skip


def _relative(times_a: np.ndarray, times_b: np.ndarray, pose_times: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N, 4, 4) a_from_b of the pose stream interpolated at each pair of times (NaN where it has no pose)."""
    a = interpolate_poses(times_a, pose_times, poses, np.inf, bridge_gaps=True)
    b = interpolate_poses(times_b, pose_times, poses, np.inf, bridge_gaps=True)
    return np.linalg.inv(a) @ b


def _errors(found: np.ndarray, stream: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(N, 6) found^-1 stream per pair: its rotation vector (rad) and translation over the pair's ``depth`` (m)."""
    difference = np.linalg.inv(found) @ stream
    rotation = Rotation.from_matrix(difference[:, :3, :3]).as_rotvec()
    return np.concatenate([rotation, difference[:, :3, 3] / depth[:, None]], axis=1)


def _angle_degrees(relative: np.ndarray) -> np.ndarray:
    cosine = np.clip((np.trace(relative[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cosine))


def choose_pairs(timestamps: np.ndarray, pose_times: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, second) frame indices of the pairs to register (docs/architecture.md, "The pose clock", step 1), the
    most sensitive first."""
    timestamps = np.asarray(timestamps, dtype=np.float64)
    if len(timestamps) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    step = float(np.median(np.diff(timestamps)))
    lag = max(1, int(round(PAIR_SECONDS / step))) if step > 0 else 1
    first = np.arange(len(timestamps) - lag)
    second = first + lag
    if not len(first):
        return first, second
    now = _relative(timestamps[first], timestamps[second], pose_times, poses)
    ok = np.isfinite(now).all(axis=(1, 2))
    ok[ok] &= (_angle_degrees(now[ok]) <= MAX_PAIR_DEGREES) & (np.linalg.norm(now[ok, :3, 3], axis=1) <= MAX_PAIR_METRES)
    h = 0.005
    later = _relative(timestamps[first] + h, timestamps[second] + h, pose_times, poses)
    earlier = _relative(timestamps[first] - h, timestamps[second] - h, pose_times, poses)
    with np.errstate(invalid="ignore"):
        change = np.linalg.inv(earlier) @ later  # a translation counted as the angle it subtends at a metre
        sensitivity = (_angle_degrees(change) + np.degrees(np.linalg.norm(change[:, :3, 3], axis=1))) / (2 * h)
    ok &= np.isfinite(sensitivity) & (sensitivity >= MIN_SENSITIVITY)
    candidates = np.flatnonzero(ok)
    order = candidates[np.argsort(-sensitivity[candidates], kind="stable")]
    chosen: list[int] = []
    used: set[int] = set()
    for index in order:  # pairs that share no frame, so one bad image spoils one pair
        if first[index] in used or second[index] in used:
            continue
        chosen.append(int(index))
        used.update((int(first[index]), int(second[index])))
        if len(chosen) == MAX_PAIRS:
            break
    chosen_array = np.asarray(chosen, dtype=np.int64)
    return first[chosen_array], second[chosen_array]


def learn_time_offset(
    read_depth, timestamps: np.ndarray, pose_times: np.ndarray, poses: np.ndarray, intrinsics: Intrinsics,
    noise: SensorNoise | None = None,
) -> TimeOffset | None:
    """The pose clock's offset from the depth clock (docs/architecture.md, "The pose clock"), or None where no pair
    of frames can tell it (the camera's motion never changes enough, or too few pairs registered). ``read_depth(i)`` -> frame i's (H, W)
    depth (m, NaN = none); ``timestamps`` (N,) s of the frames; ``pose_times`` (M,) s and ``poses`` (M, 4, 4) the
    pose stream (world_from_camera); ``noise``: the depth's noise model for the ICP's gates (a Kinect's when None)."""
    noise = noise if noise is not None else SensorNoise("kinect")
    timestamps = np.asarray(timestamps, dtype=np.float64)
    pose_times = np.asarray(pose_times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    gap = float(np.median(np.diff(pose_times))) if len(pose_times) > 1 else np.inf
    if gap > MAX_POSE_GAP:
        reason = (
            f"a pose every {1000 * gap:.0f} ms (median): too sparse to tell an offset of up to "
            f"+-{1000 * MAX_OFFSET:g} ms from"
        )
        return TimeOffset(0.0, float("nan"), 0, float("nan"), float("nan"), False, reason)
    first, second = choose_pairs(timestamps, pose_times, poses)
    if len(first) < MIN_PAIRS:
        return None
    parameters = RegistrationParameters()
    workspace = IcpWorkspace()
    found, depth, kept = [], [], []
    start = _relative(timestamps[first], timestamps[second], pose_times, poses)
    for k, (a, b) in enumerate(zip(first, second, strict=True)):
        reference, moving = read_depth(int(a)), read_depth(int(b))
        result = register_depth(
            moving, reference, intrinsics, noise, parameters, starts=(start[k],), workspace=workspace, from_identity=False
        )
        if not result.registered:
            continue
        found.append(result.transform)
        values = reference[np.isfinite(reference)]
        depth.append(float(np.median(values)) if values.size else 1.0)
        kept.append(k)
    if len(found) < MIN_PAIRS:
        return None
    found_array, depth_array = np.asarray(found), np.asarray(depth)
    first_times, second_times = timestamps[first[kept]], timestamps[second[kept]]
    grid = np.arange(-MAX_OFFSET, MAX_OFFSET + GRID_STEP / 2, GRID_STEP)

    def errors_at(offset: float) -> np.ndarray:
        return _errors(found_array, _relative(first_times + offset, second_times + offset, pose_times, poses), depth_array)

    squared = np.array([np.sum(errors_at(offset) ** 2, axis=1) for offset in grid])  # (grid, pairs)
    best = int(np.argmin(squared.sum(axis=1)))
    use = squared[best] <= TRIM**2 * np.median(squared[best])  # failed registrations out
    cost = squared[:, use].sum(axis=1)
    best = int(np.argmin(cost))
    seconds = float(grid[best])
    at, zero = errors_at(seconds)[use], errors_at(0.0)[use]
    h = GRID_STEP
    slope = (errors_at(seconds + h)[use] - errors_at(seconds - h)[use]) / (2 * h)
    dof = max(at.size - 1, 1)
    variance = float(np.sum(at**2)) / dof
    standard_error = float(np.sqrt(variance / max(float(np.sum(slope**2)), 1e-300)))
    before = float(np.degrees(np.median(np.linalg.norm(zero, axis=1))))
    after = float(np.degrees(np.median(np.linalg.norm(at, axis=1))))
    gain = 1.0 - cost[best] / cost[int(np.argmin(np.abs(grid)))] if cost[int(np.argmin(np.abs(grid)))] > 0 else 0.0
    pairs = int(np.count_nonzero(use))
    reason = ""
    if best in (0, len(grid) - 1):
        reason = f"the best offset lies at the edge of the +-{1000 * MAX_OFFSET:g} ms searched: check the recording's timestamps"
    elif abs(seconds) < MIN_OFFSET:
        reason = f"under {1000 * MIN_OFFSET:g} ms"
    elif abs(seconds) < SIGNIFICANT * standard_error:
        reason = f"within {SIGNIFICANT:g} standard errors of none"
    elif gain < MIN_GAIN:
        reason = f"the pairs agree only {100 * gain:.0f}% better with it"
    return TimeOffset(seconds, standard_error, pairs, before, after, not reason, reason)


def learn_recording_time_offset(recording, frames: int | None = None, noise: SensorNoise | None = None) -> TimeOffset | None:
    """:func:`learn_time_offset` on a recording with a pose stream of its own (``pose_samples``, ``timestamps``,
    ``read``, ``intrinsics``), over its first ``frames`` frames (None: all); None for any other source."""
    samples = getattr(recording, "pose_samples", None)
    if samples is None or not isinstance(recording.intrinsics, Intrinsics):
        return None
    count = len(recording) if frames is None else min(int(frames), len(recording))
    timestamps = np.asarray(recording.timestamps, dtype=np.float64)[:count]

    def read_depth(index: int) -> np.ndarray:
        return recording.read(index).depth

    return learn_time_offset(read_depth, timestamps, samples[0], samples[1], recording.intrinsics, noise)
