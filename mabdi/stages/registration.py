"""FilterRegistration: align the measured image D to the map before it is classified (frame-to-map tracking).

MABDI compares D and E pixel by pixel, so it is only as right as the pose it is given. This filter
corrects the given pose G as KinectFusion's frame-to-model tracking does (Newcombe et al. 2011),
against the E the loop renders anyway:

1. G is moved into the map's own frame (:mod:`mabdi.stages.map_anchor`); E is rendered
   at G, its points and normals taken from its depth;
2. two starts (G, and G with the last frame's correction carried over);
   the one that puts more of D's coarse samples on E is taken;
3. projective point-to-plane ICP, coarse to fine, over samples of D
   (:func:`sample_points`), with a gate of ``gate_k`` noise units or the
   residuals' robust spread, Huber weights, and no step along directions the scene does not
   constrain or only the tilts of the map's faces hold (:func:`noise_held_directions`); every
   ``sparse_stride``-th pixel first, every ``stride``-th where that leaves a direction loosely held or
   the frame unregistered (:func:`register_depth`);
4. checks (``min_points``, ``min_inliers``, ``min_support``, the last step, ``max_translation``,
   ``max_rotation``): a frame that fails them, or fits the map several times worse than the run's
   frames (:mod:`mabdi.stages.fit_check`), is meshed at its start and casts no removal votes;
5. where the source states its poses' accuracy, the ICP's pose is weighed
   against the given one by their covariances (:func:`fuse_with_given`);
   where not (a recording), a frame keeps the given pose or the last
   frame's slow correction unless the ICP's pose fits D to the map several
   times better than the given pose with its jitter taken off
   (:func:`follow_gain`, :meth:`FilterRegistration._jitter_free`), and its
   jitter about that is learnt from the run (:class:`PoseJitter`).

Units: metres and degrees in parameters; poses are 4x4 ``world_from_camera``
in the map's frame. Output: D with the registered pose, and in field data
``given_world_from_camera``, ``world_from_map``, ``registration``
(:data:`REGISTRATION_FIELDS`) and, when registered, ``pose_covariance``
(6x6, rotation vector in radians then translation in metres, camera frame),
which the classifier turns into each pixel's depth uncertainty
(:func:`pose_depth_sigma`), and ``fitted_world_from_camera``, the ICP's pose
(map frame), where the classifier explains D's departures from E that the
difference between the two poses makes.

Parameters: :class:`RegistrationParameters` (``[registration]``; ``enabled = false`` or ``--no-registration``
passes D on with the given pose; ``device``: the steps' sums as GPU kernels, :mod:`mabdi.stages.registration_device`).
The reasoning behind each step: docs/architecture.md (``mabdi.stages.registration``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData

from mabdi.camera import Intrinsics
from mabdi.depth import image_pose
from mabdi.errors import ConfigError
from mabdi.render.depth_image import BACKENDS, DepthRenderer
from mabdi.sensor_noise import SensorNoise
from mabdi.stages.expected_image import MEASURED_PORT, MapAndImageAlgorithm, map_input, render_expected
from mabdi.stages.fit_check import JUDGED, fits_poorly
from mabdi.stages.registration_device import DeviceImage, check_device, warp_device
from mabdi.stages.map_anchor import MapAnchor
from mabdi.frame_values import Measured, Placement
from mabdi.noise_calibration import MAD_TO_SIGMA
from mabdi.stages.registration_kernels import (
    NO_DIRECTION_HELD,
    NORMAL_UNKNOWN,
    UNCONSTRAINED,
    gauss_newton_update,
    median_every,
    point_to_plane_residuals,
    point_to_plane_system,
    pose_sigma_image,
    rigid_from_vector,
    rigid_size,
    sample_depth_points,
    solve_normal_equations,
    structure_information,
)
from mabdi.pose_noise import PoseNoise


GIVEN_POSE_ARRAY = "given_world_from_camera"
WORLD_FROM_MAP_ARRAY = "world_from_map"
REGISTRATION_ARRAY = "registration"
POSE_COVARIANCE_ARRAY = "pose_covariance"
FITTED_POSE_ARRAY = "fitted_world_from_camera"
#: The values of the ``registration`` field-data array, in order.
REGISTRATION_FIELDS = ("status", "correction_m", "correction_deg", "residual_m", "inlier_share", "support", "iterations", "given_exact")
#: The words ``given_sigma`` takes besides [m, deg]: the source's statement (learnt without one), or always learnt.
GIVEN_SIGMA_WORDS = ("source", "learnt")
#: Status codes: 0 registered; the rest leave the frame unregistered (see the module docs).
#: ``exact``: the source states the frame's pose exact; it is meshed as given and the ICP is not run (it could only
#: confirm the pose).
STATUSES = ("registered", "off", "no_map", "few_points", "few_inliers", "not_converged", "beyond_bound", "exact")
REGISTERED = 0

#: A frame of a recording takes none of the ICP's step where the ICP's pose fits D to the map up to this many times
#: better than the given pose (median |residual|; :func:`follow_gain`), all of it from this many times better.
FOLLOW_FROM = 3.0
FOLLOW_FULLY = 4.0
#: A recording's frame keeps the last frame's slow correction only where it fits D to the map this many times
#: better than the given pose (median |residual|): a real camera's map disagrees with good poses by up to about
#: twice the ICP's residual (its own depth distortion), so less is no evidence against the given pose.
CARRY_FROM = 2.0
#: :class:`PoseJitter`'s trend is a mean over about this many frames; its jitter is learnt from this many pairs of
#: frames two apart on.
JITTER_TREND_FRAMES = 20
MIN_JITTER_PAIRS = 5
#: A frame's deviation from the slow pose is taken as jitter up to this many of the jitter's standard deviations
#: (the Mahalanobis norm over the six components; 4.7: chi-square with 6 degrees of freedom at 0.999).
JITTER_BOUND = 4.7
#: A floor on a variance (rad^2 or m^2) divided by.
VARIANCE_FLOOR = 1e-14

#: The support check (:func:`constraint_support`) asks the pairs to hold the directions with at least this share
#: of the strongest direction's information.
SUPPORTED = 1e-3
#: A direction of the pose is held by the scene's structure only where normals lie more than this (degrees) out of
#: the plane it moves points in; what normals within it hold, a map's faces tilted by their own error make
#: (:func:`noise_held_directions`).
STRUCTURE_MIN_ANGLE = 15.0
#: Normals of E: central differences over this many pixels; none across a relative depth jump above this.
NORMAL_STEP = 2
NORMAL_MAX_JUMP = 0.05
#: Tiles (pixels a side) whose residuals the pose covariance takes as one unit (:func:`pose_covariance`):
#: wider than the correlations of a camera's matching window (about 9 pixels for a Kinect v1).
COVARIANCE_TILE = 32
#: D's samples average the 2 x 2 pixels that end at each cell's centre pixel (these offsets from the centre: the
#: kernel's block; a sample of n pixels has its noise reckoned as the first n's) whose depths lie within this share
#: of the centre pixel's.
SAMPLE_BLOCK = ((0, 0), (0, -1), (-1, 0), (-1, -1))
SAMPLE_MAX_JUMP = NORMAL_MAX_JUMP
#: The last step of a registered frame is below these (m, degrees).
CONVERGED_TRANSLATION = 1e-3
CONVERGED_ROTATION = 0.05
#: The ICP stops at a level once a step is below these (m, degrees).
STEP_TRANSLATION = 5e-5
STEP_ROTATION = 5e-4
#: ... and at each level coarser than the finest, this many times more (they only bring the pose near).
COARSE_TOLERANCE = 10.0
#: The residuals' median is taken over every MEDIAN_STRIDE-th residual (or, judging poses, sample) where there
#: are more than MEDIAN_MANY.
MEDIAN_STRIDE = 4
MEDIAN_MANY = 20_000
#: The gate's reach shrinks with the residuals only while the pairs hold every direction the map constrains at
#: least this share of what all candidates hold (:func:`constraint_support`).
SHRINK_SUPPORT = 0.5
#: A sparse pass (``sparse_stride``) whose pairs hold some direction the map constrains by less than this share
#: of what all its candidates hold is done again with every ``stride``-th pixel: where few pixels hold a direction
#: (a recess's edges, a table's legs), fewer samples leave it loosely held.
DENSE_BELOW_SUPPORT = 0.8
#: One ICP step's samples are summed in two halves from this many on (the finest levels; the sparse pass's on a
#: VGA frame with returns on half its pixels: about 17,000).
SPLIT_MIN_POINTS = 9_000
SPLIT_PARTS = 2


@dataclass(frozen=True)
class RegistrationParameters:
    """Frame-to-map registration (see the module docs): the ``[registration]`` section of a run config.

    Lengths in metres, angles in degrees, ``stride`` in pixels; ``huber`` and
    ``gate_k`` in units of a point's noise (``huber = 0``: Tukey's biweight
    over the gate instead); ``min_inliers`` and ``min_support`` shares (0-1).
    """

    enabled: bool = True
    levels: int = 3
    stride: int = 2
    #: The ICP first samples D every ``sparse_stride`` pixels at its finest level, and every ``stride`` only where
    #: that pass does not register the frame or leaves a direction the map constrains held by under
    #: :data:`DENSE_BELOW_SUPPORT` of its information (:func:`register_depth`); ``stride`` or less: one pass.
    sparse_stride: int = 3
    iterations: int = 10
    max_distance: float = 0.1
    gate_k: float = 4.0
    huber: float = 2.0
    model_sigma: float = 0.002
    min_points: int = 300
    min_inliers: float = 0.3
    min_support: float = 0.3
    max_translation: float = 0.1
    max_rotation: float = 5.0
    #: How far the given poses are off: ``[translation m, rotation degrees]``, the standard deviation per
    #: axis of white jitter (a motion-capture system's stated accuracy; ``[0, 0]`` for exact poses);
    #: ``"source"``: what the frame source states (:attr:`mabdi.sources.frames.FrameSource.pose_accuracy`:
    #: the simulator its ``[sensor.pose_noise]``), learnt where it states nothing (recordings);
    #: ``"learnt"``: learnt from the run whatever the source states
    #: (:meth:`~mabdi.stages.map_anchor.MapAnchor.given_variance`).
    given_sigma: list[float] | str = "source"
    #: Where the ICP's steps sum their normal equations: ``"cpu"`` (the numba kernels), ``"cuda"`` or
    #: ``"cuda:N"`` (Warp kernels on a GPU), ``"warp-cpu"`` (the same Warp kernels on the CPU):
    #: :mod:`mabdi.stages.registration_device`.
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_device(self.device)
        for name in ("levels", "stride", "sparse_stride", "iterations", "min_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"registration: {name} must be an integer >= 1, got {value!r}")
        for name in ("max_distance", "gate_k", "max_translation", "max_rotation"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"registration: {name} must be > 0, got {getattr(self, name)!r}")
        if not self.huber >= 0:
            raise ConfigError(f"registration: huber must be >= 0 noise units (0: Tukey's biweight), got {self.huber!r}")
        if not self.model_sigma >= 0:
            raise ConfigError(f"registration: model_sigma must be >= 0 metres, got {self.model_sigma!r}")
        for name in ("min_inliers", "min_support"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"registration: {name} must be a share in [0, 1], got {getattr(self, name)!r}")
        if isinstance(self.given_sigma, str):
            if self.given_sigma not in GIVEN_SIGMA_WORDS:
                raise ConfigError(
                    f"registration: given_sigma must be [translation m, rotation degrees] or one of {', '.join(map(repr, GIVEN_SIGMA_WORDS))}, got {self.given_sigma!r}"
                )
        else:
            sigma = self.given_sigma
            if len(sigma) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < np.inf for v in sigma):
                raise ConfigError(f"registration: given_sigma must be [translation m, rotation degrees], both >= 0, got {sigma!r}")

    def given_variance(self, source: PoseNoise | None = None) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """What is stated of the given poses' error: ((sigma^2, q) of the rotation in rad^2 and rad^2 per metre,
        the same of the translation in m^2), from ``given_sigma`` (white: q = 0) or from ``source``, the
        frame source's :attr:`~mabdi.sources.frames.FrameSource.pose_accuracy`, where ``given_sigma`` is
        ``"source"``; None when it is to be learnt."""
        if isinstance(self.given_sigma, str):
            return source.variances() if self.given_sigma == "source" and source is not None else None
        translation, rotation = self.given_sigma
        return PoseNoise(jitter_translation=translation, jitter_rotation=rotation).variances()


@dataclass
class RegistrationResult:
    """What :func:`register_depth` found: ``transform`` (4x4, E-camera from D-camera; when not registered,
    the start the search began from), the status
    (an entry of :data:`STATUSES`), the RMS residual of the pairs (m), the inlier share, the
    Gauss-Newton iterations, and the 6x6 pose covariance (rotation vector in rad, translation in m)."""

    transform: np.ndarray
    status: str
    residual: float = float("nan")
    inlier_share: float = 0.0
    support: float = 0.0
    iterations: int = 0
    covariance: np.ndarray | None = None
    #: How much better the result fits D to E than the pose it is judged against (the first of the reference poses,
    #: or :func:`register_depth`'s ``judged_against``) does: the median |residual| of D's finest samples there over
    #: that at the result (1: no better; NaN when not registered), and which reference fits D best (an index into
    #: ``references``).
    improvement: float = float("nan")
    reference: int = 0

    @property
    def registered(self) -> bool:
        return self.status == STATUSES[REGISTERED]


def sample_points(
    measured: np.ndarray, intrinsics: Intrinsics, stride: int, average: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray]:
    """D's samples, one per ``stride`` x ``stride`` cell whose centre pixel has a return. With ``average``
    (where D is noisy), the mean point of the 2 x 2 pixels ending at that pixel that lie on its surface
    (within :data:`SAMPLE_MAX_JUMP` of its depth): a sample then carries the information of the pixels the
    stride passes over, and its noise is half a pixel's where pixels err apart. Without, the centre pixel's
    point (noise-free depth: averaging would only blur it). Returns the points (N, 3, camera frame, m), their
    depths (N,), the :data:`COVARIANCE_TILE` tile of the image each lies in (N,), the number of tiles, and
    the pixels each sample averages (N,)."""
    tiles_across = -(-measured.shape[1] // COVARIANCE_TILE)
    n_tiles = tiles_across * -(-measured.shape[0] // COVARIANCE_TILE)
    k = intrinsics
    tolerance = SAMPLE_MAX_JUMP if average else 0.0
    points, z, tiles, counts = sample_depth_points(measured, stride, k.fx, k.fy, k.cx, k.cy, COVARIANCE_TILE, tiles_across, tolerance)
    return points, z, tiles, n_tiles, counts


def sample_scale(z: np.ndarray, counts: np.ndarray, intrinsics: Intrinsics, noise: SensorNoise, model_sigma: float) -> np.ndarray:
    """(N,) each sample's noise (m): the sensor's sigma(z) left in the mean of its ``counts`` pixels
    (:meth:`~mabdi.sensor_noise.SensorNoise.mean_share`: a half for four pixels that err apart, less gained
    where neighbours err together), with ``model_sigma`` (the map's own error) added in quadrature; at
    least 0.1 mm."""
    shares = np.array([1.0, *(noise.mean_share(SAMPLE_BLOCK[:n]) for n in range(1, len(SAMPLE_BLOCK) + 1))])
    sigma = noise.sigma(z, intrinsics.near, intrinsics.far) * shares[counts]
    return np.maximum(np.sqrt(sigma**2 + model_sigma**2), 1e-4)


def _rigid(rotation_vector: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a rotation vector (radians; Rodrigues' formula) and a translation."""
    return rigid_from_vector(np.asarray(rotation_vector, dtype=np.float64), np.asarray(translation, dtype=np.float64))


def transform_size(transform: np.ndarray) -> tuple[float, float]:
    """(translation in m, rotation angle in degrees) of a 4x4 rigid transform (the angle from both its sine and
    its cosine, exact for small angles too)."""
    translation, angle = rigid_size(np.ascontiguousarray(transform, dtype=np.float64))
    return float(translation), float(angle)


class IcpWorkspace:
    """Memory the ICP reuses from frame to frame: a cache of E's normals (H x W x 3, float64) per half of
    D's samples (:data:`SPLIT_MIN_POINTS`) that the steps fill
    (:func:`~mabdi.stages.registration_kernels.cached_point_and_normal`) and which pixels each holds.
    Each half has its own cache, so the two halves summed at once never write the same memory.
    Touching 7 MB of fresh pages for every frame costs more than the normals themselves, so a caller that
    registers many frames (:class:`FilterRegistration`) keeps one; one workspace serves one registration
    at a time."""

    def __init__(self) -> None:
        self._caches: list[tuple[np.ndarray, np.ndarray]] = []
        self._devices: dict[str, object] = {}  # the Warp device of each ``device`` setting used

    def map_image(self, expected: np.ndarray, intrinsics: Intrinsics, device: str = "cpu") -> _MapImage:
        """E as one registration's ICP reads it, its steps summed on ``device``
        (:attr:`RegistrationParameters.device`)."""
        if device == "cpu":
            return _MapImage(expected, intrinsics, self)
        return _DeviceMapImage(expected, intrinsics, self, self.warp_device(device))

    def warp_device(self, device: str):
        """The Warp device of a ``device`` setting other than "cpu", found once (a ConfigError where it cannot run:
        :func:`~mabdi.stages.registration_device.warp_device`)."""
        if device not in self._devices:
            self._devices[device] = warp_device(device)
        return self._devices[device]

    def normal_caches(self, shape: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(normals (H, W, 3), known (H, W) int8 all unknown)] for each half of the samples, for an E of ``shape``."""
        if not self._caches or self._caches[0][1].shape != tuple(shape):
            self._caches = [(np.empty((*shape, 3)), np.zeros(shape, dtype=np.int8)) for _ in range(SPLIT_PARTS)]
        else:
            for _, known in self._caches:
                known.fill(NORMAL_UNKNOWN)
        return self._caches


def _split_bounds(count: int) -> list[tuple[int, int]]:
    """The [start, stop) ranges of the samples that are summed apart: halves from :data:`SPLIT_MIN_POINTS` on."""
    if count < SPLIT_MIN_POINTS:
        return [(0, count)]
    middle = count // 2
    return [(0, middle), (middle, count)]


def _in_halves(count: int, part: Callable) -> list:
    """``part(index, start, stop)`` over the [start, stop) ranges of :func:`_split_bounds` of ``count`` samples,
    the second on the helper thread where there is a second core (the kernels release the GIL); the results in
    the ranges' order, so what is made of them does not depend on the cores."""
    bounds = _split_bounds(count)
    helper = _helper_thread() if len(bounds) > 1 else None
    if helper is None:
        return [part(index, *bound) for index, bound in enumerate(bounds)]
    pending = helper.submit(part, 1, *bounds[1])
    first = part(0, *bounds[0])
    return [first, pending.result()]


_helper: ThreadPoolExecutor | None = None


def _helper_thread() -> ThreadPoolExecutor | None:
    """The thread that sums the second half of a step's samples, or None on a single core (both halves then
    run one after the other, with the same sums). Started on first use; a forked child starts its own."""
    global _helper
    if _helper is None and _cores() > 1:
        _helper = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mabdi-icp")
    return _helper


def _cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _forget_helper() -> None:
    global _helper
    _helper = None  # the parent's thread does not exist in a forked child


os.register_at_fork(after_in_child=_forget_helper)


class _MapImage:
    """E as the ICP reads it: its depth (float32) and the caches of the normals its steps computed, kept while
    one frame is registered."""

    def __init__(self, expected: np.ndarray, intrinsics: Intrinsics, workspace: IcpWorkspace) -> None:
        self.depth = np.ascontiguousarray(expected, dtype=np.float32)
        self.caches = workspace.normal_caches(self.depth.shape)
        self.intrinsics = intrinsics

    def system(self, points, tiles, n_tiles, scale, gate, transform, huber, summaries):
        """One ICP step's normal equations at ``transform`` (E-camera from D-camera, 4x4):
        :func:`~mabdi.stages.registration_kernels.point_to_plane_system`. From
        :data:`SPLIT_MIN_POINTS` samples on, the two halves are summed apart (the second on a helper thread
        where there is a second core: the kernel releases the GIL) and added in a fixed order, so the
        result does not depend on the cores."""
        k = self.intrinsics
        rotation, translation = transform[:3, :3], np.ascontiguousarray(transform[:3, 3])

        def part(index: int, start: int, stop: int):
            normals, known = self.caches[index]
            return point_to_plane_system(
                points[start:stop], tiles[start:stop], n_tiles, scale[start:stop], gate[start:stop], rotation, translation,
                self.depth, normals, known, k.fx, k.fy, k.cx, k.cy, NORMAL_STEP, NORMAL_MAX_JUMP, huber, summaries,
            )  # fmt: skip

        halves = _in_halves(len(points), part)
        if len(halves) == 1:
            return halves[0]
        first, second = halves
        a, b, chi2, pairs, candidates, residuals, support, tile_gradients = first
        a2, b2, chi22, pairs2, candidates2, residuals2, support2, tile_gradients2 = second
        return (
            a + a2, b + b2, chi2 + chi22, pairs + pairs2, candidates + candidates2,
            np.concatenate((residuals, residuals2)), support + support2, tile_gradients + tile_gradients2,
        )  # fmt: skip

    def structure(self, points, scale, gate, transform, directions) -> np.ndarray:
        """The information the pairs at ``transform`` give along each column of ``directions`` from normals
        across the motion only: :func:`~mabdi.stages.registration_kernels.structure_information`."""
        k = self.intrinsics
        normals, known = self.caches[0]
        return structure_information(
            points, scale, gate, transform[:3, :3], np.ascontiguousarray(transform[:3, 3]), self.depth, normals, known,
            k.fx, k.fy, k.cx, k.cy, NORMAL_STEP, NORMAL_MAX_JUMP, np.ascontiguousarray(directions),
            float(np.sin(np.radians(STRUCTURE_MIN_ANGLE))),
        )  # fmt: skip

    def residuals(self, points, transform) -> np.ndarray:
        """The absolute point-to-plane residuals (m) of every candidate at ``transform``, in the order of
        :meth:`system`'s (:func:`~mabdi.stages.registration_kernels.point_to_plane_residuals`): how well a
        pose fits D to the map, without the normal equations."""
        k = self.intrinsics
        rotation, translation = transform[:3, :3], np.ascontiguousarray(transform[:3, 3])

        def part(index: int, start: int, stop: int):
            normals, known = self.caches[index]
            return point_to_plane_residuals(
                points[start:stop], rotation, translation, self.depth, normals, known, k.fx, k.fy, k.cx, k.cy, NORMAL_STEP,
                NORMAL_MAX_JUMP,
            )  # fmt: skip

        halves = _in_halves(len(points), part)
        return halves[0] if len(halves) == 1 else np.concatenate(halves)


class _DeviceMapImage(_MapImage):
    """:class:`_MapImage` with the steps' sums and residuals on a Warp device
    (:class:`~mabdi.stages.registration_device.DeviceImage`); :meth:`structure`, once a frame, stays on the CPU."""

    def __init__(self, expected: np.ndarray, intrinsics: Intrinsics, workspace: IcpWorkspace, device) -> None:
        super().__init__(expected, intrinsics, workspace)
        k = intrinsics
        self.on_device = DeviceImage(self.depth, k.fx, k.fy, k.cx, k.cy, NORMAL_STEP, NORMAL_MAX_JUMP, device)

    def system(self, points, tiles, n_tiles, scale, gate, transform, huber, summaries):
        return self.on_device.system(points, tiles, n_tiles, scale, gate, transform, huber, summaries)

    def residuals(self, points, transform) -> np.ndarray:
        return self.on_device.residuals(points, transform)


def register_depth(
    measured: np.ndarray,
    expected: np.ndarray,
    intrinsics: Intrinsics,
    noise: SensorNoise,
    parameters: RegistrationParameters,
    starts: tuple[np.ndarray, ...] = (),
    workspace: IcpWorkspace | None = None,
    references: tuple[np.ndarray, ...] = (),
    judged_against: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    from_identity: bool = True,
) -> RegistrationResult:
    """Align D (``measured``) to E (``expected``, the map rendered at D's pose) by projective point-to-plane ICP,
    D sampled every ``parameters.stride`` pixels at the finest level, or first every ``sparse_stride`` pixels
    where that is more: that pass's result stands unless it does not register the frame or its pairs hold some
    direction the map constrains by less than :data:`DENSE_BELOW_SUPPORT` (then the dense pass decides).

    Both are (H, W) metric depth images (NaN = none) with ``intrinsics``.
    Returns the transform E-camera from D-camera: the registered pose is the
    rendering pose times it. The search starts from the identity or from the
    transform in ``starts`` under which more of D's samples lie on E within
    their noise (``from_identity`` False: from ``starts`` alone). ``workspace``: memory kept from one call to the next (:class:`IcpWorkspace`; a
    fresh one when None). ``references``: the transforms the result is judged against (the first; none: the
    identity) and which fits best (another than the first only where it fits :data:`CARRY_FROM` times better;
    :attr:`RegistrationResult.improvement`); ``judged_against``: where given, the
    transform the result is judged against instead, made from the result's transform and covariance (a recording's
    given pose with the jitter the result shows taken off, :meth:`FilterRegistration._jitter_free`). See the module
    docs for the steps and checks.
    """
    p = parameters
    if p.sparse_stride > p.stride:  # the sparse pass: one pass at sparse_stride
        sparse = register_depth(
            measured, expected, intrinsics, noise, replace(p, stride=p.sparse_stride), starts, workspace, references,
            judged_against, from_identity,
        )  # fmt: skip
        if sparse.status == "no_map" or (sparse.registered and sparse.support >= DENSE_BELOW_SUPPORT):
            return sparse
    references = references or (np.eye(4),)
    if np.count_nonzero(np.isfinite(expected[::4, ::4])) * 16 < p.min_points:
        # nothing to fit: the last correction carried on is the best guess (drift grows; jitter stays small)
        return RegistrationResult(starts[-1].copy() if starts else np.eye(4), "no_map")
    map_image = (workspace if workspace is not None else IcpWorkspace()).map_image(expected, intrinsics, p.device)
    transform = _best_start(measured, map_image, intrinsics, (np.eye(4), *starts) if from_identity or not starts else starts, noise, p)
    a = b = None
    chi2 = 0.0
    pairs = candidates = 0
    iterations = 0
    step_size = (np.inf, np.inf)
    reach = p.max_distance  # the gate beyond the noise: shrinks with the residuals as the pose converges
    start = transform.copy()
    wide = reach  # the reach before it last shrank
    last_step = np.zeros(6)
    summaries = None  # the last step's (support, tile_gradients), where it took them
    contraction = None  # how much a step shrank the one before, at the last coarser level that took two
    remaining = (np.inf, np.inf)  # the step that would follow the last one (its size, or a prediction of it)
    average = noise.noisy  # D's samples average their neighbours where D is noisy
    held_by_noise = NO_DIRECTION_HELD
    for level in range(p.levels):
        points, z, tiles, n_tiles, counts = sample_points(measured, intrinsics, p.stride * 2 ** (p.levels - 1 - level), average)
        # rotations taken as lengths at the samples' median depth: once per level (the two-cycle test keeps the coarsest's)
        level_length = _median(z) if len(z) else 1.0
        if level == 0:
            length = level_length
        scale = sample_scale(z, counts, intrinsics, noise, p.model_sigma)
        # a coarser level only brings the pose near: the finer ones end it (steps below these end the level)
        loose = COARSE_TOLERANCE ** (p.levels - 1 - level)
        step_translation, step_rotation = STEP_TRANSLATION * loose, STEP_ROTATION * loose
        step_size = previous = (np.inf, np.inf)
        finest = level == p.levels - 1
        for iteration in range(p.iterations):
            gate = np.maximum(reach, p.gate_k * scale)
            if iterations == 0:
                # how far off the prediction is, before the first step: pairs beyond that are other surfaces
                *_, candidates, residuals, _, _ = map_image.system(points, tiles, n_tiles, scale, gate, transform, p.huber, False)
                if candidates:
                    reach = min(reach, p.gate_k * MAD_TO_SIGMA * _median(residuals))
                gate = np.maximum(reach, p.gate_k * scale)
            # a finest step after a small one is likely the last: it takes what the checks need as it goes
            likely_last = finest and (
                (step_size[0] < 10 * step_translation and step_size[1] < 10 * step_rotation)
                or (contraction is not None and not np.isfinite(step_size[0]))
            )
            held = likely_last or not finest  # which directions the pairs hold: cheap at the coarser levels
            a, b, chi2, pairs, candidates, residuals, support, tile_gradients = map_image.system(
                points, tiles, n_tiles, scale, gate, transform, p.huber, held
            )
            summaries = (support, tile_gradients) if likely_last else None
            iterations += 1
            if pairs < max(6, p.min_points // 4 ** (p.levels - 1 - level)):
                return RegistrationResult(start, "few_points", iterations=iterations)
            if iteration == 0 and noise.noisy:  # which directions only the tilts a noisy map's faces carry hold: once a level
                held_by_noise = noise_held_directions(map_image, points, scale, gate, transform, a, length)
            previous = step_size
            transform, *step_size, last_step = gauss_newton_update(a, b, transform, last_step, length, held_by_noise)
            remaining = step_size
            done = step_size[0] < step_translation and step_size[1] < step_rotation
            if done and not finest and np.isfinite(previous[0]):
                contraction = max(step_size[0] / max(previous[0], 1e-12), step_size[1] / max(previous[1], 1e-12))
            elif not done and (likely_last or not finest) and contraction is not None and contraction < 1.0:
                # Gauss-Newton near the optimum shrinks each step by about what it did at a coarser level:
                # where the step that would follow is predicted below the tolerance, it is not taken
                predicted = (step_size[0] * contraction, step_size[1] * contraction)
                done = predicted[0] < step_translation and predicted[1] < step_rotation
                if done:
                    remaining = predicted
            if not (done and summaries is not None):
                # the spread of the residuals says how far off the pose still is (robust: a median, of every
                # MEDIAN_STRIDE-th of many); the last step that took the summaries needs it no more
                if held and constraint_support(support, level_length) < SHRINK_SUPPORT:
                    # the reach cut loose a direction the map constrains (the few pixels that hold it, a table's
                    # edges and legs, were still off when the floor's residuals said the pose was near): back
                    reach = max(reach, wide)
                else:
                    wide, reach = reach, min(reach, p.gate_k * MAD_TO_SIGMA * _median(residuals))
            if done:
                break
    if summaries is None:  # the last step did not take them: the pose found, judged at its own pairs
        gate = np.maximum(reach, p.gate_k * scale)
        a, b, chi2, pairs, candidates, residuals, *summaries = map_image.system(
            points, tiles, n_tiles, scale, gate, transform, p.huber, True
        )
    support, tile_gradients = summaries
    _, inverse = solve_normal_equations(a, b, length, held_by_noise)
    covariance = pose_covariance(inverse, chi2, pairs, tile_gradients)
    residual = float(np.sqrt(chi2 / max(pairs, 1)))  # in units of the noise; metres below
    share = pairs / max(candidates, 1)
    translation, angle = transform_size(np.linalg.inv(start) @ transform)
    status = "registered"
    held = constraint_support(support, level_length)
    if share < p.min_inliers or pairs < p.min_points or held < p.min_support:
        status = "few_inliers"
    elif remaining[0] > CONVERGED_TRANSLATION or remaining[1] > CONVERGED_ROTATION:
        status = "not_converged"
    elif translation > p.max_translation or angle > p.max_rotation:
        status = "beyond_bound"
    median_scale = _median(scale) if len(scale) else 0.0
    improvement, reference_index = float("nan"), 0
    if status == "registered":
        # D's finest samples against E at each reference and at the result, every candidate (the gate is moot);
        # a median of many needs every MEDIAN_STRIDE-th sample only, so only those are paired (up to four passes)
        judged = () if judged_against is None else (judged_against(transform, covariance),)
        fit_points = points[::MEDIAN_STRIDE] if len(points) > MEDIAN_MANY else points
        medians = [
            float(median_every(r, 1)) if len(r) else np.inf
            for r in (map_image.residuals(fit_points, pose) for pose in (*references, *judged, transform))
        ]
        reference_index = int(np.argmin(medians[: len(references)]))
        if reference_index > 0 and medians[0] < CARRY_FROM * medians[reference_index]:
            reference_index = 0  # the first (the given pose) unless another fits clearly better
        improvement = medians[len(references) if judged else 0] / max(medians[-1], 1e-9)
    return RegistrationResult(
        transform if status == "registered" else start,
        status,
        residual=residual * median_scale,
        inlier_share=float(share),
        support=held,
        iterations=iterations,
        covariance=covariance if status == "registered" else None,
        improvement=improvement,
        reference=reference_index,
    )


def noise_held_directions(map_image: _MapImage, points, scale, gate, transform: np.ndarray, a: np.ndarray, length: float) -> np.ndarray:
    """The directions of the pose that only the noise of E's normals holds: (6, m) unit columns, rotations taken
    as lengths at ``length`` metres, as :func:`~mabdi.stages.registration_kernels.solve_normal_equations` takes
    them (m = 0: none). Each eigenvector of the step's normal equations ``a`` is a candidate; it is held by noise
    where the information that normals more than :data:`STRUCTURE_MIN_ANGLE` out of its motion give along it is
    under :data:`~mabdi.stages.registration_kernels.UNCONSTRAINED` of the best direction's. A camera facing a wall
    whose map is several faces a degree or two apart: the slide along the wall and the turn about its normal."""
    scaling = np.array([1.0 / length] * 3 + [1.0] * 3)
    _, vectors = np.linalg.eigh(a * np.outer(scaling, scaling))
    structure = map_image.structure(points, scale, gate, transform, vectors * scaling[:, None])
    held = structure < UNCONSTRAINED * max(float(structure.max()), 0.0)
    return np.ascontiguousarray(vectors[:, held]) if held.any() else NO_DIRECTION_HELD


def _median(values: np.ndarray) -> float:
    """The median of ``values``, over every :data:`MEDIAN_STRIDE`-th where there are more than :data:`MEDIAN_MANY`
    (a robust figure of many samples needs no more; the full median of 40,000 costs half a millisecond)."""
    return float(median_every(values, MEDIAN_STRIDE if len(values) > MEDIAN_MANY else 1))


def pose_covariance(inverse: np.ndarray, chi2: float, pairs: int, tile_gradients: np.ndarray) -> np.ndarray:
    """The 6x6 pose covariance of a converged ICP: the larger, direction by direction, of two estimates.

    * **Independent residuals**: A^-1 scaled by the residuals' chi-square per degree of freedom (at
      least 1), what the normal equations say when every pixel's error is its own.
    * **Correlated residuals** (a tile-robust "sandwich"): A^-1 M A^-1 with M = sum over image tiles of
      g_t g_t^T, g_t the gradient b summed over the tile's pairs. Neighbouring pixels of a
      structured-light or stereo camera err together (they share a matching window) and a map's
      faces are chords of curved surfaces; the normal equations count such pixels as independent and
      the covariance comes out several times too small. Summing within tiles of
      :data:`COVARIANCE_TILE` pixels, wider than such correlations, and taking the spread of the tile
      sums counts each tile once, whatever the correlation inside it (the cluster-robust covariance of
      regression, clusters = tiles); for independent errors it agrees with the first estimate.

    The result is the first estimate plus the positive part of their difference (so it is never below
    either in any direction).
    """
    independent = inverse * max(1.0, chi2 / max(pairs - 6, 1))
    sandwich = inverse @ (tile_gradients.T @ tile_gradients) @ inverse
    values, vectors = np.linalg.eigh(sandwich - independent)
    return independent + (vectors * np.maximum(values, 0.0)) @ vectors.T


def constraint_support(support: np.ndarray, length: float) -> float:
    """The least share, over the directions the map constrains, of the constraint that the pairs within the
    gate carry (1: every direction as well held as by all candidates; near 0: some direction is held only by
    points the registration left out, as when a wall is 30 cm from where the map has it).

    ``support``: the pairs' and the candidates' information (2, 6, 6) from the last ICP step; ``length``:
    the median depth of D's samples (m), which turns rotations into lengths. Directions with under
    :data:`SUPPORTED` of the strongest one's information are not counted (the scene does not constrain them,
    or too weakly to ask it of the pairs; under
    :data:`~mabdi.stages.registration_kernels.UNCONSTRAINED` the ICP takes no step along them).
    """
    scaling = np.diag([1.0 / length] * 3 + [1.0] * 3)
    pairs = scaling @ support[0] @ scaling
    candidates = scaling @ support[1] @ scaling
    values, vectors = np.linalg.eigh(candidates)
    if values[-1] <= 0:
        return 0.0
    constrained = values > SUPPORTED * values[-1]
    shares = np.einsum("ij,jk,ki->i", vectors.T, pairs, vectors)[constrained] / values[constrained]
    return float(shares.min())


def _best_start(measured, map_image: _MapImage, intrinsics: Intrinsics, starts, noise: SensorNoise, p: RegistrationParameters) -> np.ndarray:
    """The transform of ``starts`` under which most of D's coarsest samples lie on E within their noise gate
    (a count, not a median: a heading error leaves the floor where it was and moves only the objects)."""
    if len(starts) == 1:
        return starts[0].copy()
    points, z, tiles, n_tiles, counts = sample_points(measured, intrinsics, p.stride * 2 ** (p.levels - 1), noise.noisy)
    scale = sample_scale(z, counts, intrinsics, noise, p.model_sigma)
    gate = p.gate_k * scale
    best, best_pairs = starts[0], -1
    for transform in starts:
        _, _, _, pairs, *_ = map_image.system(points, tiles, n_tiles, scale, gate, transform, p.huber, False)
        if pairs > best_pairs:
            best, best_pairs = transform, pairs
    return best.copy()


def pose_depth_sigma(expected: np.ndarray, intrinsics: Intrinsics, covariance: np.ndarray, max_incidence: float = 80.0) -> np.ndarray:
    """(H, W) float32 standard deviation (m) of E's depth that the pose uncertainty ``covariance`` causes.

    A pose error xi = (rotation vector, translation) moves the map's surface
    at a pixel by J xi along its normal, J = (p x n, n) for the point p and
    normal n E shows there; along the pixel's ray that is J xi / cos(theta)
    (theta the angle of incidence, capped at ``max_incidence`` degrees): a
    lateral error d becomes d tan(theta) in depth. Pixels of E without a
    normal (silhouettes) take the head-on value. NaN where E has no surface. A zero covariance (a pose stated
    exact) moves nothing: 0 wherever E has a surface, without the per-pixel work.
    """
    if not np.any(covariance):
        return np.where(np.isfinite(expected), np.float32(0.0), np.float32(np.nan)).astype(np.float32)
    return pose_sigma_image(
        np.ascontiguousarray(expected, dtype=np.float32), intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy,
        NORMAL_STEP, NORMAL_MAX_JUMP, np.ascontiguousarray(covariance, dtype=np.float64), float(np.cos(np.radians(max_incidence))),
    )  # fmt: skip


def registration_values(image) -> dict | None:
    """The ``registration`` field data of a registered D as a dict (status as its name), or None if absent."""
    array = image.GetFieldData().GetArray(REGISTRATION_ARRAY)
    if array is None:
        return None
    values = vtk_to_numpy(array)
    result = dict(zip(REGISTRATION_FIELDS, (float(v) for v in values), strict=True))
    result["status"] = STATUSES[int(result["status"])]
    result["iterations"] = int(result["iterations"])
    result["given_exact"] = bool(result["given_exact"])
    return result


def write_placement(image, placement: Placement) -> None:
    """Put a frame's :class:`~mabdi.frame_values.Placement` into a registered D's field data (the filter's edge)."""
    _add_field(image, GIVEN_POSE_ARRAY, placement.given_pose)
    _add_field(image, WORLD_FROM_MAP_ARRAY, placement.world_from_map)
    values = (
        STATUSES.index(placement.status), placement.correction_m, placement.correction_deg, placement.residual_m,
        placement.inlier_share, placement.support, placement.iterations, float(placement.given_exact),
    )  # fmt: skip
    _add_field(image, REGISTRATION_ARRAY, values)
    if placement.covariance is not None:
        _add_field(image, POSE_COVARIANCE_ARRAY, placement.covariance)
    if placement.fitted_pose is not None:
        _add_field(image, FITTED_POSE_ARRAY, placement.fitted_pose)


def image_pose_covariance(image) -> np.ndarray | None:
    """The 6x6 ``pose_covariance`` of a registered D, or None when the frame was not registered."""
    array = image.GetFieldData().GetArray(POSE_COVARIANCE_ARRAY)
    return None if array is None else vtk_to_numpy(array).reshape(6, 6).copy()


def image_fitted_pose(image) -> np.ndarray | None:
    """The 4x4 ``fitted_world_from_camera`` of a registered D (the ICP's pose, map frame), or None when not registered."""
    array = image.GetFieldData().GetArray(FITTED_POSE_ARRAY)
    return None if array is None else vtk_to_numpy(array).reshape(4, 4).copy()


def image_world_from_map(image) -> np.ndarray:
    """The ``world_from_map`` of a registered D (where the map's frame lies in the world), identity if absent."""
    array = image.GetFieldData().GetArray(WORLD_FROM_MAP_ARRAY)
    return np.eye(4) if array is None else vtk_to_numpy(array).reshape(4, 4).copy()


def given_pose(image) -> np.ndarray:
    """The pose the source gave for D (its ``world_from_camera`` when it was not registered)."""
    array = image.GetFieldData().GetArray(GIVEN_POSE_ARRAY)
    return image_pose(image) if array is None else vtk_to_numpy(array).reshape(4, 4).copy()


def correction_between(given: np.ndarray, registered: np.ndarray) -> np.ndarray:
    """The correction that takes pose ``given`` to ``registered``, as (rotation about the camera centre,
    translation in the world): a 4x4 [dR, dt] with R_registered = dR R_given and t_registered = t_given + dt.
    Odometry drifts that way (a heading error turns the camera where it stands), so it carries to the next frame."""
    correction = np.eye(4)
    correction[:3, :3] = registered[:3, :3] @ given[:3, :3].T
    correction[:3, 3] = registered[:3, 3] - given[:3, 3]
    return correction


def apply_correction(correction: np.ndarray, given: np.ndarray) -> np.ndarray:
    """Pose ``given`` with a :func:`correction_between` applied."""
    pose = np.eye(4)
    pose[:3, :3] = correction[:3, :3] @ given[:3, :3]
    pose[:3, 3] = given[:3, 3] + correction[:3, 3]
    return pose


def fuse_with_given(
    given: np.ndarray, registered: np.ndarray, covariance: np.ndarray, given_variance: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """The registered pose weighed against the given one: (pose, its 6x6 covariance in the camera frame).

    ``given``: the given pose in the map frame; ``registered``: the ICP's pose, with ``covariance`` (rotation
    vector in rad, then translation in m, camera frame); ``given_variance``: the variance (rad^2, m^2 per
    component) of the given pose's error (:meth:`MapAnchor.given_variance`). Both are estimates of the
    same pose: the correction c from the given pose (a rotation about the camera centre and a world
    translation, :func:`correction_between`) is shrunk to K c with K = V (V + S)^-1, V the given pose's
    covariance and S the registration's in the same terms, and the result's covariance is V - K V. An
    exact given pose (V = 0) is kept as it is however the registration wanders; a jittery one
    (V >> S) gives way to the registration.
    """
    frame = np.zeros((6, 6))
    frame[:3, :3] = frame[3:, 3:] = given[:3, :3]  # camera-frame perturbations to world-frame ones
    observed = frame @ covariance @ frame.T
    correction = correction_between(given, registered)
    values = np.concatenate([Rotation.from_matrix(correction[:3, :3]).as_rotvec(), correction[:3, 3]])
    prior = np.diag([given_variance[0]] * 3 + [given_variance[1]] * 3)
    gain = prior @ np.linalg.pinv(prior + observed)
    fused = gain @ values
    posterior = prior - gain @ prior
    pose = apply_correction(_rigid(fused[:3], fused[3:]), given)
    return pose, frame.T @ (0.5 * (posterior + posterior.T)) @ frame


def correction_vector(correction: np.ndarray) -> np.ndarray:
    """(6,) a :func:`correction_between` as its rotation vector (rad) and its translation (m)."""
    return np.concatenate([Rotation.from_matrix(correction[:3, :3]).as_rotvec(), correction[:3, 3]])


def correction_matrix(vector: np.ndarray) -> np.ndarray:
    """The 4x4 correction of a :func:`correction_vector`."""
    return _rigid(vector[:3], vector[3:])


class PoseJitter:
    """What a recording's given poses scatter about their own course, learnt from the ICP's corrections.

    Each registered frame adds the ICP's correction from its given pose (:func:`correction_vector`), ``r``, that
    correction less what the slow rule (:func:`follow_evidence`) took of it, and the ICP's covariance. Corrections
    one frame apart differ in mean square by D1 = 2 (J + S) + q, two frames apart by D2 = 2 (J + S) + 2 q, for white
    jitter J, the ICP's own variance S and a walk of q a frame (drift, or a map that moves with the poses that
    follow it), so J = D1 - D2 / 2 - S: a walk is not read as jitter. :meth:`variance` is J (rad^2, m^2 per
    component), and :attr:`trend` the mean of ``r`` (over the first :data:`JITTER_TREND_FRAMES` frames, then
    exponential over about as many): the part of a frame's ``r`` that is jitter is ``r`` less the trend, where the
    trend stands out of the jitter's noise (:meth:`slow_part`)."""

    def __init__(self) -> None:
        self.trend = np.zeros(6)
        self._count = 0
        self._last = np.full((2, 6), np.nan)  # the corrections of the last two frames, the latest first
        self._sums = np.zeros((2, 3))  # per lag (1, 2): summed mean squares of the rotation's and translation's differences, less the ICP's, and the count
        self._course = np.zeros(6)  # the corrections' own mean, as the trend (what the slow rule took or not)
        self._about_course = np.zeros(3)  # summed mean squares of the corrections about that mean before them (rotation, translation), less the ICP's, and the count

    def add(self, correction: np.ndarray, r: np.ndarray, covariance: np.ndarray) -> None:
        """One registered frame: the ICP's ``correction`` from the given pose (6,), ``r`` (6,), the ICP's 6x6
        ``covariance``."""
        own = np.array([np.trace(covariance[:3, :3]), np.trace(covariance[3:, 3:])]) / 3.0
        for lag in range(2):
            if not np.isnan(self._last[lag]).any():
                step = (correction - self._last[lag]) ** 2
                self._sums[lag] += [step[:3].mean() - 2 * own[0], step[3:].mean() - 2 * own[1], 1.0]
        self._last = np.stack([correction, self._last[0]])
        if self._count >= MIN_JITTER_PAIRS:  # a trend of a few frames predicts nothing yet
            miss = (correction - self._course) ** 2
            self._about_course += [miss[:3].mean() - own[0], miss[3:].mean() - own[1], 1.0]
        self._count += 1
        self.trend += (r - self.trend) / min(self._count, JITTER_TREND_FRAMES)  # the mean of the first frames, then exponential
        self._course += (correction - self._course) / min(self._count, JITTER_TREND_FRAMES)

    def variance(self) -> tuple[float, float] | None:
        """(rad^2, m^2) per component, None before :data:`MIN_JITTER_PAIRS` pairs of frames two apart were
        registered (a few frames' scatter is no evidence of jitter: they keep to the slow rule)."""
        if self._sums[1, 2] < MIN_JITTER_PAIRS:
            return None
        one, two = self._sums[0, :2] / self._sums[0, 2], self._sums[1, :2] / self._sums[1, 2]
        return tuple(max(float(d1 - d2 / 2), 0.0) for d1, d2 in zip(one, two, strict=True))

    def bias_variance(self, jitter: tuple[float, float]) -> np.ndarray:
        """(6,) the variance (rad^2, m^2 per component) of what a mean over frames leaves of the map's bias in a frame's
        correction: the corrections' mean square about their mean over the frames before, less the ICP's own variance
        and the ``jitter`` (:meth:`variance`). The map's error varies with what a frame sees, faster than a mean over frames follows;
        it weighs the ICP's correction down as its covariance does (:meth:`FilterRegistration._about_slow`)."""
        if self._about_course[2] < 1:
            return np.zeros(6)
        spread = self._about_course[:2] / self._about_course[2]
        return np.repeat(np.maximum(spread - np.asarray(jitter, dtype=np.float64), 0.0), 3)

    def slow_part(self, jitter: tuple[float, float]) -> np.ndarray:
        """(6,) the trend, each component shrunk by how much of it the jitter's own scatter in the mean
        explains (``jitter``: :meth:`variance`): a trend no larger than the noise of a mean of the frames is
        taken as none."""
        noise = np.repeat(np.asarray(jitter, dtype=np.float64), 3) / min(self._count, 2 * JITTER_TREND_FRAMES - 1)
        square = np.maximum(self.trend**2, 1e-300)
        return self.trend * np.maximum(1.0 - noise / square, 0.0)

    def state(self) -> dict:
        return {
            "trend": self.trend.copy(), "count": self._count, "last": self._last.copy(), "sums": self._sums.copy(),
            "course": self._course.copy(), "about_course": self._about_course.copy(),
        }  # fmt: skip

    def set_state(self, state: dict) -> None:
        self.trend = np.asarray(state["trend"], dtype=np.float64).copy()
        self._count = int(state["count"])
        self._last = np.asarray(state["last"], dtype=np.float64).reshape(2, 6).copy()
        self._sums = np.asarray(state["sums"], dtype=np.float64).reshape(2, 3).copy()
        self._course = np.asarray(state.get("course", self.trend), dtype=np.float64).reshape(6).copy()
        self._about_course = np.asarray(state.get("about_course", np.zeros(3)), dtype=np.float64).reshape(3).copy()


def follow_gain(improvement: float) -> float:
    """The share (0-1) of the ICP's step from the default pose that a frame of a recording takes, from how much
    better the ICP's pose fits D to the map than the given pose does (:attr:`RegistrationResult.improvement`):
    none up to :data:`FOLLOW_FROM`, all from :data:`FOLLOW_FULLY`, linear between."""
    if not np.isfinite(improvement):
        return 1.0 if improvement > 0 else 0.0
    return float(np.clip((improvement - FOLLOW_FROM) / (FOLLOW_FULLY - FOLLOW_FROM), 0.0, 1.0))


def follow_evidence(given: np.ndarray, registered: np.ndarray, carried: np.ndarray, gain: float) -> np.ndarray:
    """The pose a frame whose given pose's accuracy is not stated is meshed at: the correction ``carried``
    (:func:`correction_between`: none, or the last frame's, whichever fits D to the map better) moved by
    ``gain`` (:func:`follow_gain`) of the way to the ICP's (``registered``), rotation and translation together.
    ``given``: the given pose in the map frame. See the module docs for the rule and its reasons."""
    start, end = correction_vector(carried), correction_vector(correction_between(given, registered))
    return apply_correction(correction_matrix(start + gain * (end - start)), given)


def map_placement_variance(depth: float, noise: SensorNoise, intrinsics: Intrinsics) -> tuple[float, float]:
    """How far a frame registered to the map can be off the world for the map's own error, whatever its pose
    covariance says (rad^2, m^2 per component). The map was meshed from earlier frames of the same sensor,
    and the part of their error that is correlated across the image (depth calibration, distortion,
    correlated noise, a surface's chords) moves or tilts the map as a whole; no number of pixels averages
    it away. Its size: the sensor's depth noise sigma(z) at the median ``depth`` (m) the frame sees, in
    translation, and that over the half-width of the view at that depth (the lever a depth error tilts a
    fit by; at most the depth itself) in rotation. (0, 0) without a depth."""
    if not depth > 0:
        return 0.0, 0.0
    sigma = float(noise.sigma(np.array([depth], dtype=np.float64), intrinsics.near, intrinsics.far)[0])
    lever = depth * min(1.0, 0.5 * intrinsics.width / intrinsics.fx)
    return (sigma / lever) ** 2, sigma**2


def _median_depth(depth: np.ndarray) -> float:
    """The median of a depth image's returns (m; every 4th pixel each way), 0 without any: where the
    frame looks (:meth:`MapAnchor.add`)."""
    sample = depth[::4, ::4]
    sample = sample[np.isfinite(sample)]
    return float(np.median(sample)) if sample.size else 0.0


def _add_field(image, name: str, values) -> None:
    array = numpy_to_vtk(np.asarray(values, dtype=np.float64).ravel(), deep=True)
    array.SetName(name)
    image.GetFieldData().AddArray(array)


class FilterRegistration(MapAndImageAlgorithm):
    """Register D (port 1) to the map (port 0): D out with the registered pose (see the module docs).

    ``renderer``: the :class:`DepthRenderer` that draws the map (share the
    expected image's so the map is uploaded once). ``pose_accuracy``: what the frame source states of its
    poses' error (``given_sigma = "source"``), None when it states nothing. The filter keeps the
    world-frame correction of the last registered frame, which predicts the
    next frame's pose; :meth:`state` and :meth:`set_state` carry it over a checkpoint.
    """

    def __init__(
        self,
        parameters: RegistrationParameters | None = None,
        renderer: DepthRenderer | None = None,
        backend: str = BACKENDS[0],
        pose_accuracy: PoseNoise | None = None,
    ) -> None:
        super().__init__(nInputPorts=2, nOutputPorts=1, outputType="vtkImageData")
        self._parameters = parameters if parameters is not None else RegistrationParameters()
        self._pose_accuracy = pose_accuracy
        self.renderer = renderer if renderer is not None else DepthRenderer(backend)
        self._workspace = IcpWorkspace()
        self._check_device(self._parameters)
        self.reset()

    def _check_device(self, parameters: RegistrationParameters) -> None:
        """Stop at once where the ICP's device cannot run here, not at the first frame that needs it."""
        if parameters.enabled and parameters.device != "cpu":
            self._workspace.warp_device(parameters.device)

    @property
    def parameters(self) -> RegistrationParameters:
        return self._parameters

    @parameters.setter
    def parameters(self, value: RegistrationParameters) -> None:
        self._check_device(value)
        self._set("_parameters", value)
        self.anchor.stated = value.given_variance(self._pose_accuracy)

    def reset(self) -> None:
        """Forget the correction and the anchor (the next frame starts a new map at its given pose)."""
        #: the last registered frame's correction (map frame), carried to the next frame as one start
        self._correction = np.eye(4)
        #: the distance the given poses travelled (m) and the last given position, for the anchor
        self._travelled = 0.0
        self._last_position: np.ndarray | None = None
        self._last_frame = -1
        self.anchor = MapAnchor(stated=self._parameters.given_variance(self._pose_accuracy))
        self._jitter = PoseJitter()
        self._slow = np.eye(4)  # the slow part of the last learnt correction (see _learnt_pose)
        self.Modified()

    def state(self) -> dict:
        """What is carried between frames (plain arrays and numbers, for checkpoints)."""
        return {
            "correction": self._correction.copy(),
            "travelled": self._travelled,
            "last_position": np.full(3, np.nan) if self._last_position is None else self._last_position.copy(),
            "last_frame": self._last_frame,
            "anchor": self.anchor.state(),
            "jitter": self._jitter.state(),
        }

    def set_state(self, state: dict) -> None:
        self._correction = np.asarray(state["correction"], dtype=np.float64).reshape(4, 4).copy()
        self._travelled = float(state["travelled"])
        position = np.asarray(state["last_position"], dtype=np.float64)
        self._last_position = None if np.isnan(position).any() else position.copy()
        self._last_frame = int(state["last_frame"])
        self.anchor.set_state(state["anchor"])
        self._jitter = PoseJitter()
        if "jitter" in state:  # older checkpoints have none: learnt again from the next frames
            self._jitter.set_state(state["jitter"])
        self.Modified()

    def _learnt_pose(
        self, given: np.ndarray, registered: np.ndarray, result: RegistrationResult, new_frame: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pose (map frame) and its covariance of a registered frame whose given pose's accuracy is learnt:
        the slow part by the evidence rule (:func:`follow_evidence`), then the ICP's correction less its trend
        weighed as jitter about it (:class:`PoseJitter`, :meth:`_about_slow`)."""
        default = (np.eye(4), self._correction)[result.reference]  # the given pose or the carried correction
        jitter = self._jitter.variance()
        gain = follow_gain(result.improvement)
        slow = follow_evidence(given, registered, default, gain)
        pose, covariance = slow, gain * result.covariance
        slow_vector = correction_vector(correction_between(given, slow))
        found = correction_vector(correction_between(given, registered))
        if jitter is not None:
            pose, fused = self._about_slow(given, slow_vector, found, result.covariance, jitter)
            covariance = covariance + fused
        if new_frame:
            self._jitter.add(found, found - slow_vector, result.covariance)
            self._slow = correction_matrix(slow_vector)  # jitter is a frame's own: only the slow part carries on
        return pose, covariance

    def _about_slow(
        self, given: np.ndarray, slow_vector: np.ndarray, found: np.ndarray, covariance: np.ndarray, jitter: tuple[float, float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(pose, its covariance): the ICP's correction ``found`` (:func:`correction_vector`) less its trend,
        weighed as ``jitter`` (:meth:`PoseJitter.variance`) about the slow correction ``slow_vector`` of the
        ``given`` pose (map frame), and bounded at :data:`JITTER_BOUND` standard deviations of the jitter (beyond:
        a change of the map's bias, not jitter). ``covariance``: the ICP's; the map's bias that the trend leaves
        (:meth:`PoseJitter.bias_variance`) is added to it."""
        deviation = found - self._jitter.slow_part(jitter) - slow_vector
        spread = np.sqrt(np.maximum(np.repeat(np.asarray(jitter, dtype=np.float64), 3), VARIANCE_FLOOR))
        size = float(np.linalg.norm(deviation / spread))
        if size > JITTER_BOUND:
            deviation *= JITTER_BOUND / size
        slow = apply_correction(correction_matrix(slow_vector), given)
        target = apply_correction(correction_matrix(slow_vector + deviation), given)
        return fuse_with_given(slow, target, covariance + np.diag(self._jitter.bias_variance(jitter)), jitter)

    def _jitter_free(self, given: np.ndarray, transform: np.ndarray, covariance: np.ndarray) -> np.ndarray:
        """The pose a frame is judged against before it follows any of the ICP's slow correction (as a transform
        from the ``given`` pose, map frame): the given pose with the jitter the ICP's ``transform`` (with its
        ``covariance``) shows taken off (:meth:`_about_slow`). A jittered given pose fits the map worse than the
        ICP's by its jitter alone; this one only by the slow part."""
        found = correction_vector(correction_between(given, given @ transform))
        pose, _ = self._about_slow(given, np.zeros(6), found, covariance, self._jitter.variance())
        return np.linalg.inv(given) @ pose

    def place(self, measured: Measured, world, earlier_residuals: np.ndarray | None = None) -> tuple[Measured, Placement]:
        """Register D (``measured``, at its given world_from_camera) to the map ``world`` (a vtkPolyData or the
        world mesh's blocks, in the map's frame): D at the pose it is meshed with (map frame), and the
        :class:`~mabdi.frame_values.Placement` that says how it was found. A frame placed again (the same
        index) does not count twice in what the filter carries between frames. ``earlier_residuals``: the
        residuals (m) of the run's registered frames before this one, oldest first, against which a frame that
        fits poorly is told (:mod:`mabdi.stages.fit_check`; None: not judged)."""
        intrinsics, given, frame, noise, depth = measured.geometry, measured.pose, measured.index, measured.noise, measured.depth
        new_frame = frame != self._last_frame or frame < 0  # a re-executed frame is not counted twice
        if new_frame and self._last_position is not None:
            self._travelled += float(np.linalg.norm(given[:3, 3] - self._last_position))
        p = self._parameters
        # stated exact (no white part, no drift; not learnt so): the frame is meshed at its given pose, and an ICP
        # could only confirm it
        given_exact = p.enabled and self.anchor.stated is not None and not np.any(self.anchor.stated)
        given_in_map = self.anchor.map_from_world @ given if p.enabled else given
        if not p.enabled:
            result = RegistrationResult(np.eye(4), "off")
        elif given_exact:
            result = RegistrationResult(np.eye(4), "exact", covariance=np.zeros((6, 6)))
        else:
            expected = render_expected(self.renderer, world, intrinsics, given_in_map)
            carried = np.linalg.inv(given_in_map) @ apply_correction(self._correction, given_in_map)
            judged_against = None
            if self.anchor.stated is None and self._jitter.variance() is not None:  # learnt: see _learnt_pose
                def judged_against(transform, covariance):
                    return self._jitter_free(given_in_map, transform, covariance)
            result = register_depth(
                depth, expected, intrinsics, noise, p, starts=(carried,), workspace=self._workspace,
                references=(np.eye(4), carried), judged_against=judged_against,
            )  # fmt: skip
        pose = given_in_map @ result.transform
        fitted = pose.copy() if result.registered else None  # where D fits the map, whatever pose it is meshed at
        covariance = result.covariance
        learnt = self.anchor.stated is None
        poor_fit = result.status in JUDGED and earlier_residuals is not None and fits_poorly(result.residual, earlier_residuals)
        if poor_fit and result.registered:
            # no rigid pose fits D as the run's frames fit (a smeared or bent image): the ICP's pose is no evidence
            # against the pose the fit started from, which the frame keeps (the given pose, or the carried
            # correction where that fitted better); it teaches nothing and carries nothing on
            pose = apply_correction((np.eye(4), self._correction)[result.reference], given_in_map)
        elif result.registered or result.status == "exact":
            if learnt:  # how good the given poses are is not stated: learnt from the run (see the module docs)
                pose, covariance = self._learnt_pose(given_in_map, pose, result, new_frame)
            else:
                variance = self.anchor.given_variance(self._travelled)
                pose, covariance = fuse_with_given(given_in_map, pose, result.covariance, variance)
        if p.enabled and new_frame and not poor_fit:
            if result.registered:
                self._correction = self._slow if learnt else correction_between(given_in_map, pose)
                median_depth = _median_depth(depth)
                map_error = map_placement_variance(median_depth, noise, intrinsics)
                if learnt:
                    # the map lies where the frames were meshed: where the rule kept the given poses, so does it
                    self.anchor.add(given, pose, self._travelled, covariance, median_depth, map_error)
                else:
                    self.anchor.add(given, given_in_map @ result.transform, self._travelled, result.covariance, median_depth, map_error)
            elif result.status == "no_map" and len(self.anchor) == 0:
                self.anchor.add(given, pose, self._travelled)  # the first frame starts the map where it is given
        if new_frame:
            self._last_position = given[:3, 3].copy()
            self._last_frame = frame
        world_from_map = self.anchor.world_from_map
        # the correction in the world: the camera centre moved, and turned
        translation, angle = transform_size(np.linalg.inv(given) @ world_from_map @ pose)
        placement = Placement(
            result.status, given.copy(), world_from_map.copy(), translation, angle, result.residual, result.inlier_share,
            result.support, result.iterations, bool(given_exact), None if covariance is None else np.asarray(covariance, dtype=np.float64),
            fitted, bool(poor_fit),
        )  # fmt: skip
        return measured.placed(pose), placement

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        world = map_input(inInfo, "FilterRegistration")
        measured, placement = self.place(Measured.from_image(vtkImageData.GetData(inInfo[MEASURED_PORT], 0)), world)
        output = vtkImageData.GetData(outInfo)
        measured.fill(output)
        write_placement(output, placement)
        return 1
