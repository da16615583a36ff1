"""FilterClassifier: which pixels of the measured image D are novel, given the expected image E.

Port 0 is D (what the sensor measured), port 1 is E (the map rendered from the same pose); both are depth
images (:mod:`mabdi.depth`, metres) of the same size, intrinsics and pose. Per pixel, with
tau = max(tau_min, k_sigma * sqrt(sigma(z)^2 + sigma_pose^2)) at z = D
(sigma from D's noise model, sigma_pose from D's ``pose_covariance`` when
registration put one there):

====  ============  ====================================================
label  name          rule
====  ============  ====================================================
0     no return     D is NaN
1     known         -tau_front <= D - E <= tau
2     novel         E is NaN (the map has no surface there), or D < E - tau_front
3     contradicted  D > E + tau: the sensor sees through a surface of the map
====  ============  ====================================================

tau_front is tau with ``front_k`` for k_sigma (refinement's gate where the loop refines a real camera's
map: such a look refines the face, not a second surface in front of it). Known besides: a novel pixel in
front of the map or a contradicted one that agrees with E once D is placed at the pose registration fitted it at
(:func:`explained_by_fit`), and a region of either whose D - E steps by more
than tau across fewer than :data:`GRADUAL_STEP_SHARE` of its border with
known pixels (``gradual``, :func:`gradual_regions`; contradicted regions
where the pose is trusted, :func:`pose_trusted`): the map seen with a real
camera's bias, where a new or departed object's border is a step.
Specks: the novel mask is opened with a ``min_width`` square and regions of
fewer than ``min_region`` pixels go (label 1); a speck that fills a hole of
the map stays novel (``fill_holes``, :func:`hole_fills`). A real camera's
new surface (novel where E has none) beyond ``outer_radius`` waits, unmeshed
but novel, while its motion brings it nearer the centre (:func:`waiting_for_centre`), and one in front of
the map until ``front_frames`` frames have seen it there (:mod:`mabdi.stages.front_confirmation`).

Output: ``depth`` is D on the novel pixels and a ``rim`` of pixels around them (NaN elsewhere; ``rim_on_map``
puts the rim's known pixels on E), point arrays ``measured_depth``, ``label``, ``pose_sigma`` and, where faces
wholly on the rim are trimmed (:mod:`mabdi.surfaces.seam_trim`), ``novel_pixels``; field data D's and
``pixel_counts`` (:func:`pixel_counts`).
Defaults: tau_min = 0.01 m, k_sigma = 3, front_k, rim, rim_on_map and outer_radius "auto", min_width = 3 px,
min_region = 32 px, fill_holes = true, gradual = true; front_frames "auto".

Why the rules are what they are: docs/architecture.md (``mabdi.stages.classifier``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import Intrinsics
from mabdi.depth import MEASURED_ARRAY, image_intrinsics
from mabdi.errors import ConfigError, check_switch
from mabdi.sensor_noise import SensorNoise, incidence_cosine
from mabdi.stages.expected_image import expected_of_image
from mabdi.frame_values import Classified, Expected, Measured
from mabdi.stages.front_confirmation import FrontConfirmation
from mabdi.stages.image_kernels import border_steps_kernel, dilate_kernel, explained_by_fit_kernel
from mabdi.stages.registration import image_fitted_pose, image_pose_covariance, pose_depth_sigma
from mabdi.surfaces.seam_trim import NOVEL_PIXELS_ARRAY, trims

NO_RETURN, KNOWN, NOVEL, CONTRADICTED = 0, 1, 2, 3
LABEL_ARRAY = "label"
#: Point data of the output when D carries a pose covariance: E's depth uncertainty from the pose (m).
POSE_SIGMA_ARRAY = "pose_sigma"
#: Field data of the output: int64 pixel counts (valid, novel, specks, contradicted) of this frame.
PIXEL_COUNTS_ARRAY = "pixel_counts"
PIXEL_COUNT_NAMES = ("valid", "novel", "specks", "contradicted")

_EIGHT_NEIGHBOURS = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class ClassifierParameters:
    """Thresholds of :class:`FilterClassifier` (metres and pixels; see the module docs).

    The ``[classifier]`` section of a run config. ``enabled = false`` is the
    loop's "black box": the surface filter meshes every valid pixel of D,
    every frame, and neither object removal nor refinement runs (their own
    switches: ``[removal] enabled``, ``[refinement] enabled``).
    """

    enabled: bool = True
    tau_min: float = 0.01
    k_sigma: float = 3.0
    #: k_sigma for a pixel in front of the map (see the module docs); "auto": k_sigma, or where the loop refines
    #: the map, the refinement's gate if that is wider (:func:`mabdi.loop.loop.resolve_settings`).
    front_k: float | str = "auto"
    min_width: int = 3
    min_region: int = 32
    #: Pixels around the novel ones passed on with them (see the module docs); "auto": what the surface needs.
    rim: int | str = "auto"
    #: The rim's known pixels carry E's depth (see the module docs); "auto": where the loop refines the map.
    rim_on_map: bool | str = "auto"
    #: Keep the specks that fill a hole of the map (see the module docs).
    fill_holes: bool = True
    #: Regions that depart from the map gradually are the map seen with a bias: known (see the module docs).
    gradual: bool = True
    #: A camera's new surface beyond this normalised radius (0 at the principal point, 1 at the image's corners)
    #: waits while the camera's motion brings it inside (see the module docs); 1: nothing waits; "auto":
    #: :data:`REAL_CAMERA_OUTER_RADIUS` with a noise model learnt from a real camera's frames, else 1.
    outer_radius: float | str = "auto"
    #: Frames a surface in front of the map must be seen there before it is meshed (see the module docs); 1: at
    #: once; "auto": :data:`REAL_CAMERA_FRONT_FRAMES` with a noise model learnt from a real camera's frames, else 1.
    front_frames: int | str = "auto"

    def __post_init__(self) -> None:
        check_switch("rim_on_map", self.rim_on_map)
        if not self.tau_min > 0:
            raise ConfigError(f"tau_min must be > 0 metres, got {self.tau_min}")
        if self.k_sigma < 0:
            raise ConfigError(f"k_sigma must be >= 0, got {self.k_sigma}")
        if self.front_k != "auto" and (
            isinstance(self.front_k, (bool, str)) or not isinstance(self.front_k, (int, float)) or self.front_k < 0
        ):
            raise ConfigError(f'front_k must be >= 0 (sigmas) or "auto", got {self.front_k!r}')
        if self.min_width < 1:
            raise ConfigError(f"min_width must be >= 1 pixel, got {self.min_width}")
        if self.min_region < 0:
            raise ConfigError(f"min_region must be >= 0 pixels, got {self.min_region}")
        if self.outer_radius != "auto" and (
            isinstance(self.outer_radius, (bool, str)) or not 0 < self.outer_radius <= 1
        ):
            raise ConfigError(f'outer_radius must be in (0, 1] (1: nothing waits) or "auto", got {self.outer_radius!r}')
        if self.front_frames != "auto" and (
            isinstance(self.front_frames, bool) or not isinstance(self.front_frames, int) or self.front_frames < 1
        ):
            raise ConfigError(f'front_frames must be an integer >= 1 (frames) or "auto", got {self.front_frames!r}')
        if self.rim != "auto" and (isinstance(self.rim, bool) or not isinstance(self.rim, int) or self.rim < 0):
            raise ConfigError(f'rim must be an integer >= 0 (pixels) or "auto", got {self.rim!r}')

    def outer_radius_for(self, noise: SensorNoise) -> float:
        """``outer_radius``, or for "auto" :data:`REAL_CAMERA_OUTER_RADIUS` where ``noise`` is learnt from a real
        camera's frames (model ``auto``) and 1 (nothing waits) for a model of the simulator's."""
        if self.outer_radius != "auto":
            return float(self.outer_radius)
        return REAL_CAMERA_OUTER_RADIUS if noise.learnt else 1.0

    def front_frames_for(self, noise: SensorNoise) -> int:
        """``front_frames``, or for "auto" :data:`REAL_CAMERA_FRONT_FRAMES` where ``noise`` is learnt from a real
        camera's frames and 1 (meshed at once) for a model of the simulator's."""
        if self.front_frames != "auto":
            return int(self.front_frames)
        return REAL_CAMERA_FRONT_FRAMES if noise.learnt else 1

    @property
    def front_sigmas(self) -> float:
        """``front_k``, or ``k_sigma`` where it is "auto" and no loop has set it."""
        return self.k_sigma if self.front_k == "auto" else float(self.front_k)

    @property
    def rim_pixels(self) -> int:
        """The rim in pixels: ``rim``, or 1 where it is "auto" and no surface has set it (the loop does)."""
        return 1 if self.rim == "auto" else self.rim


def classify(
    measured: np.ndarray, expected: np.ndarray, tau: np.ndarray, tau_front: np.ndarray | None = None
) -> np.ndarray:
    """uint8 labels (0-3, see the module docs) from D, E and the per-pixel thresholds tau and, in front of the map,
    ``tau_front`` (None: tau) (all (H, W), metres)."""
    labels = np.full(measured.shape, KNOWN, dtype=np.uint8)
    d_valid = np.isfinite(measured)
    e_valid = np.isfinite(expected)
    with np.errstate(invalid="ignore"):
        difference = measured - expected
        labels[difference < -(tau if tau_front is None else tau_front)] = NOVEL
        labels[difference > tau] = CONTRADICTED
    labels[d_valid & ~e_valid] = NOVEL
    labels[~d_valid] = NO_RETURN
    return labels


def _depth_sigma(
    depth: np.ndarray, noise: SensorNoise, near: float, far: float, pose_sigma: np.ndarray | None
) -> np.ndarray:
    """sqrt(sigma(z)^2 + pose_sigma^2) per pixel (metres): ``noise``'s sigma at D's depth, widened by E's depth
    uncertainty from the pose (``pose_sigma``, None or NaN: 0)."""
    sigma = noise.sigma(depth, near, far)
    if pose_sigma is not None:
        sigma = np.sqrt(sigma * sigma + np.nan_to_num(pose_sigma, nan=0.0).astype(sigma.dtype) ** 2)
    return sigma


def neighbourhood_3x3(values: np.ndarray, combine, outside=None) -> np.ndarray:
    """``combine`` (np.logical_and / np.logical_or / np.minimum / np.maximum) over each pixel's 3x3
    neighbourhood, as array slices; outside the image counts as ``outside`` (None: the border's own values)."""
    padded = np.pad(values, 1, mode="edge") if outside is None else np.pad(values, 1, constant_values=outside)
    rows = combine(combine(padded[:, :-2], padded[:, 1:-1]), padded[:, 2:])
    return combine(combine(rows[:-2], rows[1:-1]), rows[2:])


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary erosion by a (2 radius + 1) square, as ``radius`` 3x3 steps of array slices."""
    for _ in range(radius):
        mask = neighbourhood_3x3(mask, np.logical_and, outside=False)
    return mask


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation by a (2 radius + 1) square, outside the image False (``radius`` 3x3 steps of
    :func:`neighbourhood_3x3` with ``np.logical_or``, in one compiled row and column pass)."""
    if radius <= 0:
        return np.asarray(mask, dtype=bool)
    return dilate_kernel(np.ascontiguousarray(mask, dtype=bool), int(radius))


def remove_specks(novel: np.ndarray, min_width: int, min_region: int, covered: np.ndarray | None = None) -> np.ndarray:
    """The novel mask without regions thinner than ``min_width`` or smaller than ``min_region`` pixels.

    Thin parts go by a binary opening with a ``min_width`` square (odd widths
    by array slices; even widths through scipy.ndimage), small regions by
    counting the pixels of each 8-connected region. With ``covered`` (True where
    the map reaches into the pixel's footprint), thin pixels go only where it is True.
    """
    mask = novel
    if min_width > 1 and mask.any():
        if min_width % 2:
            radius = min_width // 2
            mask = dilate(erode(mask, radius), radius)
        else:
            mask = ndimage.binary_opening(mask, structure=np.ones((min_width, min_width), dtype=bool))
        if covered is not None:
            mask = mask | (novel & ~covered)
    if min_region > 0 and mask.any():
        regions, count = ndimage.label(mask, structure=_EIGHT_NEIGHBOURS)
        sizes = np.bincount(regions.ravel(), minlength=count + 1)
        keep = sizes >= min_region
        keep[0] = False
        mask = keep[regions]
    return mask


#: A speck that fills a hole sees through the map by more than this share of D's depth (or 2 tau where that
#: is more), and its ring lies within the same jump of its depth (see the module docs).
HOLE_JUMP = 0.05
#: The share of a speck's ring that must be the map at its depth for it to fill a hole (see the module docs).
HOLE_RING_SHARE = 0.8
#: The fewest ring pixels of the map at its depth.
HOLE_RING_MIN = 6
#: Pixels without a return in a run of D (along a row or a column) narrower than this many pixels leave a
#: speck's ring as if not there, where E has no surface either.
HOLE_BAND_PX = 9


def _lost_run_narrow(valid: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """For pixels (``rows``, ``cols``) without a return: whether the run of pixels without one through each,
    along its row or along its column, is narrower than :data:`HOLE_BAND_PX` (the image's border ends a run)."""
    height, width = valid.shape
    steps = np.arange(1, HOLE_BAND_PX)
    narrow = np.zeros(len(rows), dtype=bool)
    for along_rows in (True, False):
        size = width if along_rows else height
        start = cols if along_rows else rows
        run = np.ones(len(rows), dtype=np.int64)  # the pixel itself
        for sign in (-1, 1):
            at = start[:, None] + sign * steps[None, :]
            inside = (at >= 0) & (at < size)
            clipped = np.clip(at, 0, size - 1)
            hit = ~inside | (valid[rows[:, None], clipped] if along_rows else valid[clipped, cols[:, None]])
            first = np.where(hit.any(axis=1), hit.argmax(axis=1), HOLE_BAND_PX - 1)  # lost pixels before a return
            run += first
        narrow |= run < HOLE_BAND_PX
    return narrow


def hole_fills(
    specks: np.ndarray,
    measured: np.ndarray,
    expected: np.ndarray,
    labels: np.ndarray,
    tau: np.ndarray,
    covered: np.ndarray | None = None,
) -> np.ndarray:
    """The specks (bool (H, W)) that fill a hole of the map: 8-connected regions most of whose pixels see
    through the map (E empty, or beyond D by more than the jump), ringed by the map at their depth
    (see the module docs). ``labels``: :func:`classify`'s; ``tau``: the threshold per pixel (m).
    Works on the speck pixels and the rings of the candidate regions alone, not on whole images."""
    fills = np.zeros_like(specks)
    if not specks.any():
        return fills
    height, width = specks.shape
    regions, count = ndimage.label(specks, structure=_EIGHT_NEIGHBOURS)
    pixels = np.flatnonzero(specks)
    region = regions.ravel()[pixels]
    d = measured.ravel()[pixels].astype(np.float64)
    e = expected.ravel()[pixels].astype(np.float64)
    sizes = np.bincount(region, minlength=count + 1)
    # each region's median depth (every label 1..count has pixels)
    ordered = d[np.lexsort((d, region))]
    first = np.concatenate([[0], np.cumsum(sizes[1:-1])])
    depth = np.zeros(count + 1)
    depth[1:] = 0.5 * (ordered[first + (sizes[1:] - 1) // 2] + ordered[first + sizes[1:] // 2])
    with np.errstate(invalid="ignore"):
        through = ~np.isfinite(e) | (e - d > np.maximum(HOLE_JUMP * d, 2.0 * tau.ravel()[pixels]))
    if covered is not None:
        through &= ~covered.ravel()[pixels]  # the map reaches into the beam's footprint: the beam missed it, no hole
    through_share = np.bincount(region[through], minlength=count + 1) / np.maximum(sizes, 1)
    # a hole at least 2 x 2 pixels wide: not a one-pixel crack of E between the map's triangles
    seeing = np.zeros(specks.size, dtype=bool)
    seeing[pixels[through]] = True
    row, col = np.divmod(pixels, width)
    corner = through & (row < height - 1) & (col < width - 1)
    top_left = pixels[corner]
    block = seeing[top_left + 1] & seeing[top_left + width] & seeing[top_left + width + 1]
    wide_count = np.bincount(region[corner][block], minlength=count + 1)
    candidate = (through_share >= 0.5) & (wide_count > 0)
    candidate[0] = False
    if not candidate.any():
        return fills
    # the ring of each candidate: pixels beside it that are not specks, once per region they touch
    chosen = candidate[region]
    row, col, chosen_region = row[chosen], col[chosen], region[chosen]
    ring_pixels, ring_regions = [], []
    flat_specks = specks.ravel()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = row + dr, col + dc
            inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
            q = r[inside] * width + c[inside]
            beside = ~flat_specks[q]
            ring_pixels.append(q[beside])
            ring_regions.append(chosen_region[inside][beside])
    key = np.sort(np.concatenate(ring_pixels) * (count + 1) + np.concatenate(ring_regions))
    key = key[np.concatenate([[True], key[1:] != key[:-1]])]  # each (pixel, region) once
    q, owner = np.divmod(key, count + 1)
    d_ring = measured.ravel()[q].astype(np.float64)
    e_ring = expected.ravel()[q].astype(np.float64)
    has_d, has_e = np.isfinite(d_ring), np.isfinite(e_ring)
    # the ring leaves out pixels lost in a narrow band between D's returns where the map has no surface
    # either: such a band (a structured-light camera's beside a depth edge) says nothing of the map beyond
    counted = np.ones(len(q), dtype=bool)
    unknown = np.flatnonzero(~has_d & ~has_e)
    if len(unknown):
        r, c = np.divmod(q[unknown], width)
        counted[unknown] = ~_lost_run_narrow(np.isfinite(measured), r, c)
    # the map around it: known pixels, and pixels without a return where E has a surface (the map goes on
    # where D lost a pixel), at its depth; a pixel where neither has one is the map's edge against nothing
    surface = np.where(has_d, d_ring, e_ring)
    mapped = (labels.ravel()[q] == KNOWN) | (~has_d & has_e)
    with np.errstate(invalid="ignore"):
        level = mapped & (np.abs(surface - depth[owner]) <= np.fmax(HOLE_JUMP * depth[owner], 2.0 * tau.ravel()[q]))
    ring_count = np.bincount(owner[counted], minlength=count + 1)
    ring_level = np.bincount(owner[counted & level], minlength=count + 1)
    keep = candidate & (ring_level >= HOLE_RING_MIN) & (ring_level >= HOLE_RING_SHARE * ring_count)
    fills.ravel()[pixels[keep[region]]] = True
    return fills


def image_at(image: np.ndarray, uv: np.ndarray, wraps_around: bool = False) -> np.ndarray:
    """(N,) ``image`` (H, W) read at continuous pixel coordinates ``uv`` (N, 2: u column, v row; pixel centres at
    + 0.5): bilinear between the four pixel centres around each where all four hold a value, else the pixel the
    point falls in; NaN outside the image (columns wrap around with ``wraps_around``: a LiDAR's 360 degrees)."""
    height, width = image.shape
    out = np.full(len(uv), np.nan)
    with np.errstate(invalid="ignore"):
        u, v = uv[:, 0], uv[:, 1]
        if wraps_around:
            u = np.mod(u, width)
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v = u[inside], v[inside]
    nearest = image[v.astype(np.int64), u.astype(np.int64)].astype(np.float64)
    x, y = u - 0.5, v - 0.5
    c0, r0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    tx, ty = x - c0, y - r0
    if wraps_around:
        c0, c1 = np.mod(c0, width), np.mod(c0 + 1, width)
    else:
        c0, c1 = np.clip(c0, 0, width - 1), np.clip(c0 + 1, 0, width - 1)
    r0, r1 = np.clip(r0, 0, height - 1), np.clip(r0 + 1, 0, height - 1)
    corners = [image[r, c].astype(np.float64) for r, c in ((r0, c0), (r0, c1), (r1, c0), (r1, c1))]
    blended = (1 - ty) * ((1 - tx) * corners[0] + tx * corners[1]) + ty * ((1 - tx) * corners[2] + tx * corners[3])
    out[inside] = np.where(np.isfinite(blended), blended, nearest)
    return out


def explained_by_fit(
    labels: np.ndarray, measured: np.ndarray, expected: np.ndarray, tau: np.ndarray, geometry, meshed_from_fitted: np.ndarray
) -> np.ndarray:
    """Bool (H, W): the novel pixels in front of the map and the contradicted pixels whose return, placed at the
    pose registration fitted D to the map at, lies within tau of E (see the module docs). ``meshed_from_fitted``:
    4x4, the fitted sensor frame in the frame of the pose D is meshed at; ``geometry``: D's (a camera's or a
    LiDAR's); E is read where the moved return falls (:func:`image_at`, in inverse depth)."""
    suspect = ((labels == NOVEL) & np.isfinite(expected)) | (labels == CONTRADICTED)
    if isinstance(geometry, Intrinsics):  # a camera: one compiled pass
        k, fitted = geometry, np.ascontiguousarray(meshed_from_fitted, dtype=np.float64)
        return explained_by_fit_kernel(suspect, measured, expected, tau, k.fx, k.fy, k.cx, k.cy, fitted)
    return explained_at(suspect, measured, expected, tau, geometry, meshed_from_fitted)


def explained_at(
    suspect: np.ndarray, measured: np.ndarray, expected: np.ndarray, tau: np.ndarray, geometry, meshed_from_fitted: np.ndarray
) -> np.ndarray:
    """:func:`explained_by_fit` of the ``suspect`` pixels (bool (H, W)) in array passes, for any sensor geometry
    (a LiDAR's; a camera's takes the compiled :func:`~mabdi.stages.image_kernels.explained_by_fit_kernel`)."""
    explained = np.zeros(suspect.shape, dtype=bool)
    rows, cols = np.nonzero(suspect)
    if not len(rows):
        return explained
    points = geometry.rays_at(cols + 0.5, rows + 0.5) * measured[rows, cols].astype(np.float64)[:, None]
    uv, value = geometry.project_points(points @ meshed_from_fitted[:3, :3].T + meshed_from_fitted[:3, 3], np.eye(4))
    # inverse depth: across a plane it is linear in a camera's pixel coordinates (near enough in a LiDAR's angles),
    # so reading it between pixel centres follows a slanted surface where depth itself would not
    with np.errstate(divide="ignore"):
        there = 1.0 / image_at(1.0 / expected.astype(np.float64), uv, getattr(geometry, "wraps_around", False))
    with np.errstate(invalid="ignore"):
        agree = (value > 0) & (np.abs(value - there) <= tau[rows, cols])
    explained[rows[agree], cols[agree]] = True
    return explained


#: A region departs from the map gradually when fewer than this share of the pixel pairs across its border with
#: known pixels step by more than tau in D - E (see the module docs).
GRADUAL_STEP_SHARE = 0.25
#: The fewest such border pairs a region is judged by (fewer: it stays as it is).
GRADUAL_MIN_PAIRS = 8
#: The least share of a region's border (its pixels' 4-neighbours in the image outside it) that must be known
#: pixels for the region to be judged by them (less: it stays as it is).
GRADUAL_KNOWN_SHARE = 0.5


#: A region at least half of whose pixels lie further than this many tau from E's surface along its normal is an
#: object's size, not a bias (a door turned about its hinge departs gradually there and by a metre at its edge).
GRADUAL_MAX_TAU = 6.0
#: Contradicted regions are judged gradual only in frames whose pose uncertainty moves E by at most this share of
#: the sensor's sigma (the median over E's pixels): where the poses are poorer, the map's patches may lie where
#: poor poses put them, and a gradual contradiction is as likely such a patch, which removal mends.
TRUSTED_POSE_SHARE = 0.5


#: ``outer_radius = "auto"`` for a real camera (a noise model learnt from its frames): its depth errs most at the
#: image's corners. The simulator's models err alike across the image: nothing waits there (docs/benchmarks.md,
#: "New surface meshed nearer the centre of the image").
REAL_CAMERA_OUTER_RADIUS = 0.7
#: ``front_frames = "auto"`` for a real camera: a surface in front of its map is meshed in the third frame that
#: sees it there (docs/benchmarks.md, "Surface in front of the map waits for a second and third look"). The
#: simulator's poses and depth agree with its map: what lies in front of it is new, and is meshed at once.
REAL_CAMERA_FRONT_FRAMES = 3
#: A pixel of new surface nears the image centre when the camera's motion, carried on one more frame, moves it at
#: least this many pixels towards the principal point (less: the camera is still and no better look is coming).
INWARD_STEP_PX = 0.5


@functools.lru_cache(maxsize=4)
def normalised_radius(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W) float32, read-only: each pixel centre's distance from the principal point, x over the image's
    half-width and y over its half-height, divided by sqrt(2): 0 at the principal point, about 1 at the corners."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width]
    x = (u + 0.5 - intrinsics.cx) / (intrinsics.width / 2)
    y = (v + 0.5 - intrinsics.cy) / (intrinsics.height / 2)
    radius = (np.hypot(x, y) / np.sqrt(2)).astype(np.float32)
    radius.flags.writeable = False
    return radius


def waiting_for_centre(
    new_surface: np.ndarray, measured: np.ndarray, intrinsics: Intrinsics, camera_motion: np.ndarray, outer_radius: float
) -> np.ndarray:
    """Bool (H, W): the pixels of ``new_surface`` (bool (H, W), D where the map has none) beyond ``outer_radius``
    (:func:`normalised_radius`) that the next frame should see nearer the image centre: D's point at the pixel,
    moved by ``camera_motion`` once more (4x4, the last frame's camera from this one's: constant velocity), lands
    at least :data:`INWARD_STEP_PX` pixels nearer the principal point, in front of the camera (see the module
    docs). ``measured``: D (metres, z-depth)."""
    radius = normalised_radius(intrinsics)
    rows, cols = np.nonzero(new_surface & (radius > outer_radius))
    waiting = np.zeros(new_surface.shape, dtype=bool)
    if not len(rows):
        return waiting
    points = intrinsics.rays_at(cols + 0.5, rows + 0.5) * measured[rows, cols].astype(np.float64)[:, None]
    # at constant velocity the next camera stands to this one as this one to the last: camera_motion is its pose here
    uv, z_next = intrinsics.project_points(points, np.asarray(camera_motion, dtype=np.float64))
    off_axis = np.hypot(cols + 0.5 - intrinsics.cx, rows + 0.5 - intrinsics.cy)  # pixels from the principal point
    with np.errstate(invalid="ignore"):
        nearer = (z_next > 0) & (off_axis - np.hypot(uv[:, 0] - intrinsics.cx, uv[:, 1] - intrinsics.cy) >= INWARD_STEP_PX)
    waiting[rows[nearer], cols[nearer]] = True
    return waiting


def pose_trusted(pose_sigma: np.ndarray | None, sensor_sigma: np.ndarray) -> bool:
    """Whether a frame's pose is good enough for a contradicted region to be read as the camera's bias: no pose
    uncertainty, or E's depth uncertainty from it (``pose_sigma``, (H, W) m, NaN where E has no surface) at most
    :data:`TRUSTED_POSE_SHARE` of the sensor's ``sensor_sigma`` (H, W) (the median over every 4th pixel)."""
    if pose_sigma is None:
        return True
    with np.errstate(invalid="ignore", divide="ignore"):
        share = (pose_sigma[::4, ::4] / sensor_sigma[::4, ::4]).ravel()
    share = share[np.isfinite(share)]
    return not len(share) or float(np.median(share)) <= TRUSTED_POSE_SHARE


def gradual_regions(
    mask: np.ndarray,
    labels: np.ndarray,
    measured: np.ndarray,
    expected: np.ndarray,
    tau: np.ndarray,
    cosine: np.ndarray | None = None,
) -> np.ndarray:
    """Bool (H, W): the 8-connected regions of ``mask`` (pixels where D departs from E by more than tau) whose
    border with known pixels is gradual (see the module docs): D - E changes by more than tau across fewer than
    :data:`GRADUAL_STEP_SHARE` of the 4-neighbour pairs of a region pixel and a known pixel, there are at
    least :data:`GRADUAL_MIN_PAIRS` of them, they are at least :data:`GRADUAL_KNOWN_SHARE` of the region's
    border, and at most half of its pixels lie more than :data:`GRADUAL_MAX_TAU` tau from E's surface along its
    normal (|D - E| times ``cosine``, the incidence on E, (H, W); None: along the ray)
    (:func:`~mabdi.stages.image_kernels.border_steps_kernel`)."""
    if not mask.any():
        return np.zeros(mask.shape, dtype=bool)
    regions, count = ndimage.label(mask, structure=_EIGHT_NEIGHBOURS)
    if cosine is None:
        cosine = np.ones(mask.shape, dtype=np.float32)
    pairs, steps, outline, size, far = border_steps_kernel(
        regions.astype(np.int32, copy=False), int(count), labels == KNOWN, measured, expected, tau, cosine, GRADUAL_MAX_TAU
    )  # fmt: skip
    keep = (pairs >= GRADUAL_MIN_PAIRS) & (steps < GRADUAL_STEP_SHARE * pairs) & (pairs >= GRADUAL_KNOWN_SHARE * outline)
    keep &= 2 * far <= size
    keep[0] = False
    return keep[regions]


class FilterClassifier(MabdiAlgorithm):
    """Label D's pixels against E and pass on the novel ones (2 depth images -> depth image)."""

    def __init__(self, parameters: ClassifierParameters | None = None) -> None:
        super().__init__(nInputPorts=2, inputType="vtkImageData", nOutputPorts=1, outputType="vtkImageData")
        self._parameters = parameters if parameters is not None else ClassifierParameters()

    @property
    def parameters(self) -> ClassifierParameters:
        return self._parameters

    @parameters.setter
    def parameters(self, value: ClassifierParameters) -> None:
        self._set("_parameters", value)

    def threshold(
        self, depth: np.ndarray, noise: SensorNoise, near: float, far: float, pose_sigma: np.ndarray | None = None
    ) -> np.ndarray:
        """tau = max(tau_min, k_sigma sqrt(sigma(z)^2 + pose_sigma^2)) in metres, sigma(z) of the sensor's
        ``noise`` model (the one D carries) (``pose_sigma`` NaN counts as 0)."""
        return self._tau(_depth_sigma(depth, noise, near, far, pose_sigma), self._parameters.k_sigma)

    def _tau(self, sigma: np.ndarray, k: float) -> np.ndarray:
        """max(tau_min, k sigma) (metres) for the per-pixel ``sigma`` of :func:`_depth_sigma`."""
        return np.maximum(sigma.dtype.type(self._parameters.tau_min), sigma.dtype.type(k) * sigma)

    def RequestInformation(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        source = inInfo[0].GetInformationObject(0)
        extent = source.Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
        if extent is not None:
            outInfo.GetInformationObject(0).Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), extent, 6)
        return 1

    def RequestUpdateExtent(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        # Always ask both inputs for their whole image, whatever sizes they claim:
        # a size mismatch is reported in RequestData, not by VTK's extent checks.
        for port in (0, 1):
            info = inInfo[port].GetInformationObject(0)
            whole = info.Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
            if whole is not None:
                info.Set(vtkStreamingDemandDrivenPipeline.UPDATE_EXTENT(), whole, 6)
        return 1

    def classify(
        self,
        measured: Measured,
        expected: Expected,
        pose_covariance: np.ndarray | None = None,
        fitted_pose: np.ndarray | None = None,
        camera_motion: np.ndarray | None = None,
        front_memory: FrontConfirmation | None = None,
    ) -> Classified:
        """Label D (``measured``) against E (``expected``, drawn from the same pose with the same geometry) and
        choose the pixels the surface meshes (see the module docs). ``pose_covariance``: 6x6 of D's pose
        (registration's), which widens tau by E's depth uncertainty; None: the pose is taken as exact.
        ``fitted_pose``: 4x4 camera-to-map where registration fitted D to the map (None: not registered).
        ``camera_motion``: 4x4, the last frame's camera from this frame's (None: no last frame; no new surface
        waits for a look nearer the image centre). ``front_memory``: the frames each part of the map was seen
        covered by something in front of it, which this frame counts on (the loop's; None: what lies in front of
        the map is meshed at once)."""
        intrinsics = measured.geometry
        if intrinsics != expected.geometry:
            raise ValueError(
                "FilterClassifier: D (port 0) and E (port 1) must share size and intrinsics; "
                f"D has {intrinsics}, E has {expected.geometry}"
            )
        difference = np.abs(measured.pose - expected.pose).max()
        if difference > 1e-9:
            raise ValueError(
                f"FilterClassifier: D (port 0) and E (port 1) must be taken from the same pose (largest difference {difference:.3g})"
            )
        depth, expected_depth, noise = measured.depth, expected.depth, measured.noise
        pose_sigma = None if pose_covariance is None else pose_depth_sigma(expected_depth, intrinsics, pose_covariance)
        p = self._parameters
        sigma = _depth_sigma(depth, noise, intrinsics.near, intrinsics.far, pose_sigma)
        tau = self._tau(sigma, p.k_sigma)
        tau_front = self._tau(sigma, p.front_sigmas) if p.front_sigmas != p.k_sigma else None
        labels = classify(depth, expected_depth, tau, tau_front)
        if fitted_pose is not None:
            meshed_from_fitted = np.linalg.inv(measured.pose) @ fitted_pose
            if np.abs(meshed_from_fitted - np.eye(4)).max() > 1e-12:
                labels[explained_by_fit(labels, depth, expected_depth, tau, intrinsics, meshed_from_fitted)] = KNOWN
        raw_novel = labels == NOVEL
        covered = expected.covered
        novel = remove_specks(raw_novel, p.min_width, p.min_region, covered)
        if p.fill_holes and noise.noisy:
            novel |= hole_fills(raw_novel & ~novel, depth, expected_depth, labels, tau, covered)
        specks = raw_novel & ~novel
        in_front, contradicted = novel & np.isfinite(expected_depth), labels == CONTRADICTED
        if p.gradual and (in_front.any() or contradicted.any()):  # a frame that departs nowhere costs nothing here
            # E's incidence, so that a departure is measured along E's normal (a camera's; a LiDAR's along the ray)
            cosine = incidence_cosine(expected_depth, intrinsics) if isinstance(intrinsics, Intrinsics) else None
            bulges = gradual_regions(in_front, labels, depth, expected_depth, tau, cosine)
            novel &= ~bulges
            labels[bulges] = KNOWN
            if contradicted.any() and pose_trusted(pose_sigma, noise.sigma(depth, intrinsics.near, intrinsics.far)):
                labels[gradual_regions(contradicted, labels, depth, expected_depth, tau, cosine)] = KNOWN
        if front_memory is not None and isinstance(intrinsics, Intrinsics):
            # a surface in front of the map waits until it has been seen there in a few frames: a real camera's
            # look at a known surface falls in front of it now and then, a new object stays there
            finite = np.isfinite(expected_depth)
            known = (labels == KNOWN) & finite
            novel &= ~front_memory.waiting(novel & finite, known, expected_depth, intrinsics, measured.pose)
        outer_radius = p.outer_radius_for(noise)
        if camera_motion is not None and outer_radius < 1 and isinstance(intrinsics, Intrinsics):
            # new surface at the image's rim that the camera is bringing towards the centre: meshed from a later,
            # more central look (a camera's depth errs most at its corners); it stays labelled novel
            novel &= ~waiting_for_centre(novel & ~np.isfinite(expected_depth), depth, intrinsics, camera_motion, outer_radius)
        on_map = labels == KNOWN  # D is the map's surface (a speck is not: it lies in front of the map)
        labels[specks] = KNOWN
        meshed = novel
        if p.rim_pixels > 0 and novel.any():
            meshed = dilate(novel, p.rim_pixels) & np.isfinite(depth)
        meshed_depth = np.where(meshed, depth, np.float32(np.nan)).astype(np.float32)
        if p.rim_on_map is True:
            rim_on_map = meshed & ~novel & on_map
            meshed_depth[rim_on_map] = expected_depth[rim_on_map]
        counts = (
            np.count_nonzero(labels != NO_RETURN), np.count_nonzero(novel), np.count_nonzero(specks),
            np.count_nonzero(labels == CONTRADICTED),
        )  # fmt: skip
        novel_pixels = novel if trims(intrinsics, p.rim_pixels) else None  # the rim's own faces are trimmed
        counted = dict(zip(PIXEL_COUNT_NAMES, (int(c) for c in counts), strict=True))
        return Classified(labels, meshed_depth, counted, pose_sigma, novel_pixels)

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        measured_image = vtkImageData.GetData(inInfo[0])
        measured = Measured.from_image(measured_image)
        classified = self.classify(
            measured, expected_of_image(vtkImageData.GetData(inInfo[1])), image_pose_covariance(measured_image),
            image_fitted_pose(measured_image),
        )
        write_classified(vtkImageData.GetData(outInfo), measured, classified)
        return 1


def write_classified(image, measured: Measured, classified: Classified) -> None:
    """The classifier's output image (the filter's edge): the depth the surface meshes with D's geometry,
    pose, frame, noise and colour; point data ``measured_depth`` (all of D), ``label``, with a pose
    covariance ``pose_sigma``, and where the patch is trimmed ``novel_pixels``; field data ``pixel_counts``."""
    measured.showing(classified.depth).fill(image)
    whole = numpy_to_vtk(measured.depth.ravel(), deep=True)  # D's values as they are now
    whole.SetName(MEASURED_ARRAY)
    image.GetPointData().AddArray(whole)
    labels = numpy_to_vtk(classified.labels.ravel(), deep=True)
    labels.SetName(LABEL_ARRAY)
    image.GetPointData().AddArray(labels)
    if classified.novel_pixels is not None:
        own = numpy_to_vtk(classified.novel_pixels.ravel().astype(np.uint8), deep=True)
        own.SetName(NOVEL_PIXELS_ARRAY)
        image.GetPointData().AddArray(own)
    if classified.pose_sigma is not None:
        sigma = numpy_to_vtk(classified.pose_sigma.ravel(), deep=True)
        sigma.SetName(POSE_SIGMA_ARRAY)
        image.GetPointData().AddArray(sigma)
    counts = numpy_to_vtk(np.array([classified.counts[name] for name in PIXEL_COUNT_NAMES], dtype=np.int64), deep=True)
    counts.SetName(PIXEL_COUNTS_ARRAY)
    image.GetFieldData().AddArray(counts)


def pixel_counts(image) -> dict[str, int]:
    """The classifier output's pixel counts: ``valid``, ``novel``, ``specks``, ``contradicted``."""
    array = image.GetFieldData().GetArray(PIXEL_COUNTS_ARRAY)
    if array is None:
        raise ValueError(f"image has no field-data array '{PIXEL_COUNTS_ARRAY}' (is it a FilterClassifier output?)")
    return dict(zip(PIXEL_COUNT_NAMES, (int(v) for v in vtk_to_numpy(array)), strict=True))


def label_array(image) -> np.ndarray:
    """(H, W) uint8 labels of a classifier output (0 no return, 1 known, 2 novel, 3 contradicted)."""
    labels = image.GetPointData().GetArray(LABEL_ARRAY)
    if labels is None:
        raise ValueError(f"image has no point array '{LABEL_ARRAY}' (is it a FilterClassifier output?)")
    return vtk_to_numpy(labels).reshape(image_intrinsics(image).shape)


def pose_sigma_array(image) -> np.ndarray | None:
    """(H, W) float32 ``pose_sigma`` of a classifier output (m, NaN where E has no surface), or None when D had no pose covariance."""
    array = image.GetPointData().GetArray(POSE_SIGMA_ARRAY)
    return None if array is None else vtk_to_numpy(array).reshape(image_intrinsics(image).shape)
