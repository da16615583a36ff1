"""ScanRegistration: a LiDAR scan fitted to the map before it is classified (scan-to-map tracking).

The range-image sibling of :mod:`mabdi.stages.registration` (a camera's). MABDI compares a scan's range
image D with the map's, E, beam by beam, so a pose that is off turns the map's walls into "seen through"
and removal takes them. LiDAR poses in the wild come from odometry (LiDAR-inertial, wheel, GNSS) whose
heading lags or drifts by a degree or more when the sensor turns: at 10 m a degree is 17 cm, more than
a return's noise. This stage corrects such poses against the E the loop draws anyway:

1. E is drawn at the given pose with the last scan's correction carried over (odometry drifts slowly,
   so the correction of the last scan predicts the next one's); the map's points and normals come from
   E's ranges (:func:`map_points_and_normals`);
2. each pose is scored by how well it fits the returns to the map: the mean of
   min(r, :data:`JUDGE_GATE`)^2 over the returns whose pixel shows the map (:func:`truncated_cost`). The
   reference is the carried pose where it fits at least :data:`CARRY_FROM` times better than the given
   pose, else the given pose;
3. projective point-to-plane ICP from the reference over the scan's returns along their own rays
   (:func:`register_scan`): each return, moved by the estimate, falls in one pixel of E and is paired
   with the plane E holds there; gates of :data:`GATES` metres, coarse to fine, Huber weights beyond
   :data:`HUBER`;
4. checks: at least ``min_points`` pairs, ``min_inliers`` of the returns that see the map within the
   last gate, convergence, and the step from the reference within the coarsest gate (m; what the ICP
   can pair across) and ``max_rotation``; a scan that fails them is meshed at the reference and casts
   no removal votes;
5. the rule that keeps good poses: the ICP's pose replaces the reference only where it fits more than
   :data:`FOLLOW_FROM` times better (all of its step from :data:`FOLLOW_FULLY` times, linearly between).
   Good poses (a SLAM system's, a dataset's ground truth) fit the map about as well as the ICP's pose
   does: the map's own errors (its chords, the returns' noise, a sweep's motion) make up most of the
   cost, and the scan stays where it was given; a pose that is off by more than the map's errors costs
   several times more, and is corrected (docs/benchmarks.md has the ratios real recordings show).

A source that states its poses exact (the simulator without pose noise) keeps them and runs no fit. Where
the scan keeps the pose E was drawn at, the loop uses that drawing: a kept pose costs the fit alone.

Frames: the pose is ``world_from_sensor``; the map is in the world frame (the map's frame is the world's:
:meth:`~mabdi.loop.loop.MabdiLoop.world_from_map` is the identity). Units: metres and degrees in parameters and checks, radians inside.
Parameters: :class:`~mabdi.stages.registration.RegistrationParameters` (``[registration]``: ``enabled``,
``min_points``, ``min_inliers``, ``max_rotation``, ``device``; the rest are the camera's: a camera's frames come 30 a
second, a LiDAR's scans 2-20, metres apart, so a scan's step is bounded by the coarsest gate instead of
``max_translation``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mabdi.camera import pixel_rays
from mabdi.frame_values import Expected, Measured, Placement
from mabdi.pose_noise import PoseNoise
from mabdi.spherical import SphericalGeometry
from mabdi.stages.fit_check import JUDGED, fits_poorly
from mabdi.stages.registration_device import DeviceScan, warp_device
from mabdi.stages.registration import (
    RegistrationParameters,
    apply_correction,
    correction_between,
    correction_matrix,
    correction_vector,
    transform_size,
)
from mabdi.stages.registration_kernels import NO_DIRECTION_HELD, gauss_newton_update, rigid_size
from mabdi.stages.scan_registration_kernels import points_and_normals, scan_to_plane_system, truncated_cost

#: The ICP's gates (m), coarse to fine: a pair whose return lies farther than this from E's plane is left out.
GATES = (0.5, 0.25, 0.1)
#: Gauss-Newton steps at most per gate.
ITERATIONS = 10
#: Residuals beyond this (m) are weighted down (Huber): a few times a real LiDAR's range noise (1-3 cm).
HUBER = 0.05
#: A return pairs with E's pixel only where the map point lies within the gate plus this many pixel angles
#: (:meth:`~mabdi.spherical.SphericalGeometry.pixel_angle`) of its range: the pixel's footprint and the pose's
#: error, not another surface seen through the same pixel.
PAIR_PIXELS = 4.0
#: A gate's steps end once a step is below these (m, degrees); the last gate's last step must be below
#: :data:`CONVERGED_TRANSLATION` and :data:`CONVERGED_ROTATION` for the scan to count as registered.
STEP_TRANSLATION = 1e-4
STEP_ROTATION = 5e-3
CONVERGED_TRANSLATION = 5e-3
CONVERGED_ROTATION = 0.1
#: Poses are judged by the returns' fit to the map within this many metres (:func:`truncated_cost`).
JUDGE_GATE = 0.25
#: The carried correction is the reference (the ICP's start) where it fits this many times better than the given
#: pose.
CARRY_FROM = 1.2
#: The ICP's pose replaces the reference where it fits more than FOLLOW_FROM times better (part of the way,
#: linearly, up to FOLLOW_FULLY; all of it from there).
FOLLOW_FROM = 1.2
FOLLOW_FULLY = 1.5
#: E's normals: a neighbour further than this share of the pixel's range from it is another surface.
NORMAL_MAX_JUMP = 0.2
#: The ICP fits at most this many of a scan's returns (every k-th, in the image's order): a scan's 20-130
#: thousand returns hold six unknowns many times over, and each step costs what its returns do.
MAX_RETURNS = 25_000
#: Rotations count as lengths at this radius (m) where the ICP weighs them against translations.
LEVER_ARM = 10.0


def map_points_and_normals(expected_range: np.ndarray, geometry: SphericalGeometry) -> tuple[np.ndarray, np.ndarray]:
    """E's points and unit normals, (H, W, 3) float64 each in the sensor frame (NaN where E shows no map or the
    normal is not known). Each normal crosses the differences to the nearer-ranged of the two neighbours across
    and along the beams (columns wrap around), left out where that neighbour lies beyond
    :data:`NORMAL_MAX_JUMP` of the range; it faces the sensor (:func:`points_and_normals`)."""
    ranges = np.ascontiguousarray(expected_range, dtype=np.float64)
    return points_and_normals(ranges, pixel_rays(geometry), NORMAL_MAX_JUMP)


def scan_points(measured: Measured, most: int = MAX_RETURNS) -> np.ndarray:
    """(N, 3) float64 the scan's returns in the sensor frame, at most ``most`` of them (every k-th, in the
    image's order): each pixel's own return where D keeps them, else its range along the pixel's centre ray."""
    if measured.return_points is not None:
        points = np.asarray(measured.return_points, dtype=np.float64).reshape(-1, 3)
    else:
        points = (np.asarray(measured.depth, dtype=np.float64)[..., None] * pixel_rays(measured.geometry)).reshape(-1, 3)
    points = points[np.isfinite(points).all(axis=1)]
    step = -(-len(points) // most) if most > 0 else 1
    return np.ascontiguousarray(points[::step])


@dataclass(frozen=True)
class ScanFit:
    """What :func:`register_scan` found: ``transform`` (4x4, sensor-at-start from sensor-at-fit), ``status`` (an
    entry of :data:`~mabdi.stages.registration.STATUSES`), the pairs of the last step, their median |residual|
    (m), their share of the returns that see the map, and the Gauss-Newton steps taken."""

    transform: np.ndarray
    status: str
    pairs: int = 0
    residual: float = float("nan")
    inlier_share: float = 0.0
    iterations: int = 0
    #: The fitted pose's cost (m^2, :func:`truncated_cost`); NaN where the fit ended early.
    cost: float = float("nan")


class _Scene:
    """The returns and E's planes one scan is fitted with (sensor frame of the start pose)."""

    def __init__(self, points: np.ndarray, expected_range: np.ndarray, geometry: SphericalGeometry, device=None) -> None:
        """``device``: a Warp device (:func:`~mabdi.stages.registration_device.warp_device`) the sums run on; None:
        the numba kernels."""
        self.points = points
        self.e_points, self.e_normals = map_points_and_normals(expected_range, geometry)
        self.edges = geometry.row_edges()
        self.columns = geometry.columns
        self.angle_reach = PAIR_PIXELS * geometry.pixel_angle()
        self.on_device = None
        if device is not None:
            self.on_device = DeviceScan(
                points, self.e_points, self.e_normals, self.edges, self.columns, self.angle_reach, device
            )

    def system(self, transform: np.ndarray, gate: float):
        if self.on_device is not None:
            return self.on_device.system(transform, gate, HUBER)
        return scan_to_plane_system(
            self.points, np.ascontiguousarray(transform[:3, :3]), np.ascontiguousarray(transform[:3, 3]),
            self.e_points, self.e_normals, self.edges, self.columns, self.angle_reach, gate, HUBER,
        )  # fmt: skip

    def cost(self, transform: np.ndarray) -> tuple[float, int]:
        """(cost m^2, returns that see the map) of a pose (:func:`truncated_cost` at :data:`JUDGE_GATE`)."""
        if self.on_device is not None:
            return self.on_device.cost(transform, JUDGE_GATE)
        return truncated_cost(
            self.points, np.ascontiguousarray(transform[:3, :3]), np.ascontiguousarray(transform[:3, 3]),
            self.e_points, self.e_normals, self.edges, self.columns, self.angle_reach, JUDGE_GATE,
        )  # fmt: skip


def register_scan(scene: _Scene, p: RegistrationParameters, start: np.ndarray | None = None) -> ScanFit:
    """Fit the returns to E's planes from ``start`` (4x4 from the sensor where E was drawn; None: there), coarse to
    fine over :data:`GATES` (see the module docs for the checks; the bounds hold the fit's step from ``start``)."""
    start = np.eye(4) if start is None else np.asarray(start, dtype=np.float64)
    transform = start.copy()
    steps = 0
    translation = angle = np.inf
    pairs, residuals = 0, np.zeros(0)
    for gate in GATES:
        previous = np.zeros(6)
        for _ in range(ITERATIONS):
            a, b, residuals = scene.system(transform, gate)
            pairs = len(residuals)
            if pairs < p.min_points:
                return ScanFit(transform, "few_points", pairs)
            transform, translation, angle, previous = gauss_newton_update(a, b, transform, previous, LEVER_ARM, NO_DIRECTION_HELD)
            steps += 1
            if translation < STEP_TRANSLATION and angle < STEP_ROTATION:
                break
    cost, seen = scene.cost(transform)
    _, _, residuals = scene.system(transform, GATES[-1])
    pairs = len(residuals)
    share = pairs / seen if seen else 0.0
    residual = float(np.median(residuals)) if pairs else float("nan")
    moved, turned = rigid_size(np.linalg.inv(start) @ transform)
    if pairs < p.min_points:
        status = "few_points"
    elif share < p.min_inliers:
        status = "few_inliers"
    elif translation > CONVERGED_TRANSLATION or angle > CONVERGED_ROTATION:
        status = "not_converged"
    elif moved > GATES[0] or turned > p.max_rotation:
        status = "beyond_bound"
    else:
        status = "registered"
    return ScanFit(transform, status, pairs, residual, share, steps, cost)


def scan_follow_gain(improvement: float) -> float:
    """The share (0-1) of the ICP's step from the reference a scan takes, from how many times better the ICP's
    pose fits than the reference (:func:`truncated_cost`): none up to :data:`FOLLOW_FROM`, all from
    :data:`FOLLOW_FULLY`."""
    if not np.isfinite(improvement):
        return 0.0
    return float(np.clip((improvement - FOLLOW_FROM) / (FOLLOW_FULLY - FOLLOW_FROM), 0.0, 1.0))


class ScanRegistration:
    """Fit each scan to the map near its given pose (see the module docs). ``expected``: the loop's
    :class:`~mabdi.stages.expected_image.FilterExpectedImage`, which draws E at the carried pose (the loop reuses
    that drawing when the scan keeps that pose). Carries the last scan's correction to the next;
    :meth:`state` and :meth:`set_state` carry it over a checkpoint."""

    def __init__(self, parameters: RegistrationParameters, expected, pose_accuracy: PoseNoise | None = None) -> None:
        self.parameters = parameters
        #: the Warp device the fit's sums run on (``parameters.device``), None for the numba kernels
        self._device = None if parameters.device == "cpu" or not parameters.enabled else warp_device(parameters.device)
        self.expected = expected
        #: The source states its poses exact (``given_sigma``: :meth:`RegistrationParameters.given_variance`): each
        #: scan keeps its given pose and no fit is run (it could only confirm the pose).
        stated = parameters.given_variance(pose_accuracy)
        self.given_exact = stated is not None and not np.any(stated)
        self.reset()

    def reset(self) -> None:
        """Forget the carried correction."""
        self._correction: np.ndarray | None = None  # None: none (the given pose itself)
        self._last_frame = -1
        #: The last scan's scores (m^2): the given pose's, the carried correction's, the ICP's (NaN: not judged).
        self.last_costs = (float("nan"),) * 3

    def state(self) -> dict:
        """What is carried between scans (plain arrays and numbers, for checkpoints)."""
        correction = np.full((4, 4), np.nan) if self._correction is None else self._correction.copy()
        return {"correction": correction, "last_frame": self._last_frame}

    def set_state(self, state: dict) -> None:
        correction = np.asarray(state["correction"], dtype=np.float64).reshape(4, 4)
        self._correction = None if np.isnan(correction).any() else correction.copy()
        self._last_frame = int(state["last_frame"])

    def place(
        self, measured: Measured, world, earlier_residuals: np.ndarray | None = None
    ) -> tuple[Measured, Placement, Expected | None]:
        """The scan ``measured`` at the pose it is meshed with, its :class:`~mabdi.frame_values.Placement`, and E
        drawn at that pose when it is the one E was drawn at for the fit (else None: the loop draws E again).
        ``earlier_residuals``: the residuals (m) of the run's registered scans before this one, against which a
        scan that fits poorly is told (:mod:`mabdi.stages.fit_check`; None: not judged). Unlike a camera's frame
        (:meth:`mabdi.stages.registration.FilterRegistration.place`) such a scan still takes the fit's pose: the
        only real scans ever flagged (the first after a handheld sensor stood still, before still frames were left
        out of the run's level) were ones whose fit corrects a lagging pose (docs/benchmarks.md, "A frame no rigid
        pose fits keeps its start's pose")."""
        given = measured.pose
        new_frame = measured.index != self._last_frame or measured.index < 0
        carried = given if self._correction is None else apply_correction(self._correction, given)
        at_carried = measured.placed(carried)
        expected = self.expected.render(world, at_carried)
        if self.given_exact:
            return at_carried, self._placement("exact", given, carried, ScanFit(np.eye(4), "exact"), True), expected
        if not np.isfinite(expected.depth).any():
            return at_carried, self._placement("no_map", given, carried, ScanFit(np.eye(4), "no_map")), expected
        scene = _Scene(scan_points(measured), expected.depth, measured.geometry, self._device)
        # the start: the carried correction where it fits the map CARRY_FROM times better than the given pose
        # (transforms from the sensor at the carried pose, where E was drawn)
        given_transform = np.linalg.inv(carried) @ given
        carried_cost, _ = scene.cost(np.eye(4))
        given_cost = carried_cost if carried is given else scene.cost(given_transform)[0]
        reference, reference_cost, start = carried, carried_cost, np.eye(4)
        if not carried_cost * CARRY_FROM <= given_cost:
            reference, reference_cost, start = given, given_cost, given_transform
        fit = register_scan(scene, self.parameters, start)
        fit_cost = fit.cost if fit.status == "registered" else float("nan")
        self.last_costs = (given_cost, carried_cost, fit_cost)
        pose = reference
        poor_fit = fit.status in JUDGED and earlier_residuals is not None and fits_poorly(fit.residual, earlier_residuals)
        gain = scan_follow_gain(reference_cost / max(fit_cost, 1e-12)) if fit.status == "registered" else 0.0
        if gain > 0.0:
            fitted = carried @ fit.transform
            start_vector = correction_vector(correction_between(given, reference))
            end_vector = correction_vector(correction_between(given, fitted))
            pose = apply_correction(correction_matrix(start_vector + gain * (end_vector - start_vector)), given)
        if new_frame and fit.status == "registered":
            # none where the scan keeps its given pose: the next scan starts at its given pose, bit for bit
            self._correction = None if pose is given else correction_between(given, pose)
        if new_frame:
            self._last_frame = measured.index
        drawn = expected if pose is carried else None
        return measured.placed(pose), self._placement(fit.status, given, pose, fit, poor_fit=poor_fit), drawn

    @staticmethod
    def _placement(
        status: str, given: np.ndarray, pose: np.ndarray, fit: ScanFit, exact: bool = False, poor_fit: bool = False
    ) -> Placement:
        translation, angle = transform_size(np.linalg.inv(given) @ pose)
        return Placement(
            status, given.copy(), np.eye(4), translation, angle, fit.residual, fit.inlier_share, float("nan"), fit.iterations, exact,
            poor_fit=bool(poor_fit),
        )  # fmt: skip
