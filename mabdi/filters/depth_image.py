"""FilterDepthImage: render a mesh from a sensor pose into a metric depth image.

vtkPolyData (or a composite dataset of polydata, drawn block by block) in,
depth image (see :mod:`mabdi.depth`) out. The filter renders off-screen in
one render window that it keeps across frames, multisampling off (with it,
the depth read back blends several samples instead of the pixel centre's), reads
the z-buffer, flips it to top-row-first and converts it to metres. Pixels
with no surface within [near, far] are NaN.

Noise models (:class:`SensorNoise`):

* ``none``
* ``zbuffer`` (seed 001): D_noisy = d + d N(0, sigma) on the normalised
  z-buffer value d (sigma = 0.001), then converted to metres; about 1, 6 and
  15 mm standard deviation at 1, 2 and 3 m for near = 0.5 m, far = 4 m. A
  value pushed to d >= 1 is beyond the far plane: NaN.
* ``kinect``: axial sigma(z) = 1.425e-3 z^2 m (Khoshelham & Elberink 2012),
  added in metres.
* ``structured_light``: a structured-light / stereo camera, modelled where
  its error arises, in disparity. The true depth z becomes the disparity
  d = f b / z (f = :attr:`SensorNoise.focal` in pixels, b = ``baseline`` in
  metres); d gets ``disparity_sigma`` pixels times a spatially correlated
  unit-variance Gaussian field (white noise smoothed by a Gaussian of
  ``correlation_length`` pixels, :func:`correlated_field`), is rounded to the
  disparity lattice (``disparity_step`` pixels) and turned back into
  z = f b / d. So the depth error grows with z^2, neighbouring pixels err
  together, and every depth lies on the lattice f b / (k step). Returns are
  lost (NaN) where a real camera loses them: within ``edge_dropout`` pixels
  of a depth discontinuity of the true image (neighbours whose depths differ
  by more than ``edge_jump`` times the nearer one, or a surface next to
  background), and at grazing incidence (the angle between the pixel's ray
  and the surface normal, estimated from the true depth image, beyond
  ``max_incidence`` degrees). Per-pixel standard deviation:
  sigma(z) = z^2 sigma_eff / (f b) with sigma_eff^2 = disparity_sigma^2 +
  disparity_step^2 / 12 (the quantisation as uniform error).

  The defaults are a Kinect v1 (PrimeSense). Khoshelham & Elberink,
  "Accuracy and resolution of Kinect depth data for indoor mapping
  applications", Sensors 12 (2012) 1437-1454: base length b = 7.5 cm, and
  the random error sigma_z = 1.425e-3 z^2 m, which they derive from a
  disparity error of half a disparity unit with m / (f b) = 2.85e-3 per unit
  and metre. Konolige & Mihelich, "Technical description of Kinect
  calibration" (ROS wiki, 2011): disparity in units of 1/8 pixel
  (``disparity_step`` = 0.125), IR focal length about 580 px at 640 x 480
  (``focal`` = 580; (1/8) / (580 x 0.075) = 2.87e-3 agrees with the m / (f b)
  above), block matching over a window of about 9 x 9 pixels. So
  sigma_eff = 1.425e-3 f b = 0.062 px, and ``disparity_sigma`` = 0.05 px once
  the quantisation's 0.125 / sqrt(12) = 0.036 px is counted (sigma(z) =
  1.42e-3 z^2 m). Our choices, with their reasons: ``correlation_length`` =
  2.5 px, because neighbouring pixels share most of their 9-pixel matching
  window, whose box profile has a standard deviation of 9 / sqrt(12) = 2.6 px;
  ``edge_dropout`` = 2 px, because a window that straddles an occluding edge
  fails to match (Kinect images show an invalid band of a few pixels around
  objects); ``max_incidence`` = 75 degrees, because the projected pattern
  seen more obliquely is too stretched to match (real images lose such
  surfaces); ``edge_jump`` = 0.05, a jump no plane makes between neighbours
  unless tilted past about 87 degrees. For an active stereo camera such as
  the RealSense D435, Intel's D400 datasheet gives a 50 mm baseline and a
  subpixel RMS error of about 0.08 px: ``baseline`` = 0.05,
  ``disparity_sigma`` = 0.08, a fine ``disparity_step`` (its disparity has
  sub-pixel resolution) and ``focal`` its fx.
* ``range`` (a spinning LiDAR's range images, :mod:`mabdi.filters.range_rendering`):
  Gaussian noise of ``range_sigma`` metres on the range along each beam,
  the same at every range. The default, 0.02 m, is the figure Velodyne's
  HDL-64E S2 datasheet gives for its 64 beams ("accuracy < 2 cm, one sigma
  at 25 m"); Ouster's OS1 datasheets give a precision of 1-3 cm over most of
  the range, the same order. Only ``none`` and ``range`` apply to a LiDAR.

Noise is reproducible: frame i of a run with seed s always draws from the
random stream ``numpy.random.default_rng([s, i])``, independent of every
other frame and of the order frames are rendered in.

Backends: ``egl`` (default; Mesa llvmpipe on a CPU machine, the GPU driver
where there is one; no X server) or ``osmesa`` (needs Debian's libosmesa6).
"""

from __future__ import annotations

import ctypes.util
import math
from dataclasses import dataclass, field

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkFloatArray, vtkUnsignedCharArray
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkDataObject, vtkImageData, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline
from vtkmodules.vtkRenderingCore import vtkActor, vtkMapper, vtkPolyDataMapper, vtkRenderer

import vtkmodules.vtkRenderingOpenGL2  # noqa: F401  (registers the OpenGL implementations)
from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import (
    Intrinsics,
    check_pose,
    configure_vtk_camera,
    frustum_planes,
    zbuffer_depth_derivative,
    zbuffer_to_depth,
)
from mabdi.depth import fill_depth_image
from mabdi.errors import ConfigError
from mabdi.face_identity import FaceCodes, FaceIdTable, block_address, face_rgb
from mabdi.filters.noise_calibration import NoiseCalibration
from mabdi.filters.range_rendering import TRIANGLE_RGB_ARRAY, RangeRenderer
from mabdi.polydata import FACE_RGB_ARRAY, named_leaves
from mabdi.spherical import SphericalGeometry

#: Depth noise models (see the module docs).
NOISE_MODELS = ("none", "zbuffer", "kinect", "structured_light", "auto", "range")
#: The noise models a LiDAR's range images take (the others model a camera's depth).
RANGE_NOISE_MODELS = ("none", "range")
#: Off-screen render backends; the first is the default.
BACKENDS = ("egl", "osmesa")


@dataclass(frozen=True)
class SensorNoise:
    """A depth noise model and its parameters (see the module docs).

    ``zbuffer_sigma``: the ``zbuffer`` model's relative sigma; ``kinect_coefficient``:
    the ``kinect`` model's c in c z^2 (1/m). The ``structured_light`` model's:
    ``baseline`` (m), ``focal`` (the disparity camera's focal length, pixels:
    :meth:`from_config` sets it to the sensor's ``fx``; a model built by
    name keeps the Kinect's 580), ``disparity_sigma``
    and ``disparity_step`` (pixels; step 0 = no quantisation),
    ``correlation_length`` (pixels, 0 = white noise), ``edge_dropout``
    (pixels), ``edge_jump`` (relative) and ``max_incidence`` (degrees, 90 =
    no loss at grazing incidence).
    """

    model: str = "none"
    zbuffer_sigma: float = 0.001
    kinect_coefficient: float = 1.425e-3
    baseline: float = 0.075
    focal: float = 580.0
    disparity_sigma: float = 0.05
    disparity_step: float = 0.125
    correlation_length: float = 2.5
    edge_dropout: int = 2
    edge_jump: float = 0.05
    max_incidence: float = 75.0
    #: ``range``: the LiDAR's range noise, one sigma in metres (see the module docs).
    range_sigma: float = 0.02
    #: ``auto``: the online calibration whose curve :meth:`sigma` reads (made with the model; shared by copies).
    calibration: NoiseCalibration | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.model not in NOISE_MODELS:
            raise ConfigError(f"unknown noise model {self.model!r} (known: {', '.join(NOISE_MODELS)})")
        if self.model == "auto" and self.calibration is None:
            object.__setattr__(self, "calibration", NoiseCalibration())
        checks = (
            ("zbuffer_sigma", self.zbuffer_sigma >= 0, ">= 0"),
            ("kinect_coefficient", self.kinect_coefficient >= 0, ">= 0"),
            ("baseline", self.baseline > 0, "> 0 (metres)"),
            ("focal", self.focal > 0, "> 0 (pixels)"),
            ("disparity_sigma", self.disparity_sigma >= 0, ">= 0 (pixels)"),
            ("disparity_step", self.disparity_step >= 0, ">= 0 (pixels; 0 = no quantisation)"),
            ("correlation_length", self.correlation_length >= 0, ">= 0 (pixels; 0 = white noise)"),
            ("edge_jump", self.edge_jump > 0, "> 0 (a relative depth jump)"),
            ("max_incidence", 0 < self.max_incidence <= 90, "in (0, 90] degrees"),
            ("range_sigma", self.range_sigma >= 0, ">= 0 (metres)"),
        )
        for name, ok, rule in checks:
            value = getattr(self, name)
            if not (ok and math.isfinite(value)):
                raise ConfigError(f"noise parameter {name} must be {rule}, got {value!r}")
        dropout = self.edge_dropout
        if isinstance(dropout, bool) or not isinstance(dropout, (int, np.integer)) or dropout < 0:
            raise ConfigError(f"noise parameter edge_dropout must be an integer >= 0 (pixels), got {dropout!r}")

    @classmethod
    def of(cls, value: SensorNoise | str) -> SensorNoise:
        """``value`` itself if it is a SensorNoise, else the model of that name with default parameters."""
        return value if isinstance(value, SensorNoise) else cls(value)

    @classmethod
    def from_config(cls, sensor) -> SensorNoise:
        """The noise of a ``[sensor]`` config section (:class:`mabdi.config.SensorConfig`); ``focal`` is its ``fx``."""
        return cls(
            sensor.noise,
            sensor.zbuffer_sigma,
            sensor.kinect_coefficient,
            baseline=sensor.baseline,
            focal=sensor.fx,
            disparity_sigma=sensor.disparity_sigma,
            disparity_step=sensor.disparity_step,
            correlation_length=sensor.correlation_length,
            edge_dropout=sensor.edge_dropout,
            edge_jump=sensor.edge_jump,
            max_incidence=sensor.max_incidence,
            range_sigma=sensor.range_sigma,
        )

    @property
    def correlated(self) -> bool:
        """Whether neighbouring pixels err together: ``structured_light`` with its correlated field or its
        disparity quantisation (a surface facing the camera comes as one terrace), and ``auto`` (a real
        camera: block matching and the device's own filtering correlate its errors). The simulator's
        ``zbuffer`` and ``kinect`` draw every pixel's error on its own."""
        if self.model == "structured_light":
            return (self.correlation_length > 0 and self.disparity_sigma > 0) or self.disparity_step > 0
        return self.model == "auto"

    @property
    def loses_returns(self) -> bool:
        """Whether the camera loses returns on surfaces within its range, so that a pixel without a return
        says nothing about free space: ``structured_light`` with its edge or grazing-incidence dropouts
        on, and ``auto`` (a real camera: they all lose returns at depth edges, at grazing incidence and
        on dark or shiny surfaces). The simulator's ``none``, ``zbuffer`` and ``kinect`` return every
        surface within the range."""
        if self.model == "structured_light":
            return self.edge_dropout > 0 or self.max_incidence < 90.0
        return self.model == "auto"

    @property
    def disparity_sigma_effective(self) -> float:
        """``structured_light``: the disparity error (pixels) with the quantisation, sqrt(sigma_d^2 + step^2 / 12)."""
        return math.sqrt(self.disparity_sigma**2 + self.disparity_step**2 / 12.0)

    def sigma(self, depth, near: float, far: float) -> np.ndarray:
        """Expected standard deviation (m) of a measurement at metric depth ``depth``.

        ``zbuffer``: sigma d |dz/dd| (first order); ``kinect``: c z^2;
        ``structured_light``: z^2 sigma_eff / (f b); ``range``: ``range_sigma`` (``depth`` is a range);
        ``none``: 0.
        Computed in float32 for float32 input, float64 otherwise.
        """
        z = np.asarray(depth)
        if z.dtype != np.float32:
            z = z.astype(np.float64)
        if self.model == "zbuffer":
            d = far * (z - near) / (z * (far - near))
            return self.zbuffer_sigma * d * zbuffer_depth_derivative(z, near, far)
        if self.model == "kinect":
            return self.kinect_coefficient * z * z
        if self.model == "structured_light":
            return z * z * z.dtype.type(self.disparity_sigma_effective / (self.focal * self.baseline))
        if self.model == "auto":
            return self.calibration.sigma(z)
        if self.model == "range":
            return np.full_like(z, self.range_sigma)
        return np.zeros_like(z)

    def ranges_with_noise(self, ranges: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """A LiDAR's ranges (float32 metres, NaN = no return) with this model's noise drawn from ``rng``
        (``range``: sigma = ``range_sigma``; ``none`` or no ``rng``: unchanged). Other models are a camera's."""
        if self.model not in RANGE_NOISE_MODELS:
            raise ConfigError(f"noise model {self.model!r} is a camera's; a LiDAR takes {' or '.join(RANGE_NOISE_MODELS)}")
        ranges = np.asarray(ranges, dtype=np.float32)
        if self.model == "range" and rng is not None and self.range_sigma > 0:
            valid = np.isfinite(ranges)
            ranges = ranges.copy()
            ranges[valid] += np.float32(self.range_sigma) * rng.standard_normal(int(valid.sum()), dtype=np.float32)
        return ranges

    def depth_from_zbuffer(
        self,
        zbuffer: np.ndarray,
        near: float,
        far: float,
        rng: np.random.Generator | None,
        intrinsics: Intrinsics | None = None,
    ) -> np.ndarray:
        """Metric depth (float32, NaN = no return) from a z-buffer, with this model's noise drawn from ``rng``.

        Works in float32: the z-buffer holds 24 bits, and float32 metres
        resolve 0.5 um at 4 m. ``structured_light`` needs ``intrinsics`` (its
        losses at grazing incidence look along each pixel's ray); its losses
        are applied with or without ``rng``, its disparity noise only with one.
        """
        if self.model == "auto" and rng is not None:
            raise ConfigError(
                "noise model 'auto' calibrates the thresholds to a recording's noise; a simulated sensor "
                "needs a model to draw noise from (none, zbuffer, kinect, structured_light)"
            )
        if self.model == "range" and rng is not None:
            raise ConfigError("noise model 'range' is a LiDAR's (noise in range along each beam); a camera takes none, zbuffer, kinect or structured_light")
        d = np.asarray(zbuffer, dtype=np.float32)
        if self.model == "zbuffer" and rng is not None:
            valid = d < 1.0
            dv = d[valid]
            d = d.copy()
            d[valid] = dv + dv * (np.float32(self.zbuffer_sigma) * rng.standard_normal(dv.size, dtype=np.float32))
        depth = zbuffer_to_depth(d, near, far)
        if self.model == "kinect" and rng is not None:
            valid = np.isfinite(depth)
            zv = depth[valid]
            depth[valid] = zv + np.float32(self.kinect_coefficient) * zv * zv * rng.standard_normal(zv.size, dtype=np.float32)
        if self.model == "structured_light":
            if intrinsics is None:
                raise ValueError("the structured_light noise model needs the intrinsics (depth_from_zbuffer(..., intrinsics=...))")
            depth = self._structured_light(depth, intrinsics, rng)
        return depth

    def _structured_light(self, depth: np.ndarray, intrinsics: Intrinsics, rng: np.random.Generator | None) -> np.ndarray:
        """The ``structured_light`` model on a true depth image (see the module docs)."""
        lost = edge_pixels(depth, self.edge_jump, self.edge_dropout)
        if self.max_incidence < 90.0:
            lost |= incidence_cosine(depth, intrinsics) < np.float32(math.cos(math.radians(self.max_incidence)))
        fb = np.float32(self.focal * self.baseline)
        with np.errstate(divide="ignore", invalid="ignore"):
            disparity = fb / depth
            if rng is not None and self.disparity_sigma > 0:
                field = correlated_field(depth.shape, self.correlation_length, rng)
                disparity += np.float32(self.disparity_sigma) * field
            if self.disparity_step > 0:
                step = np.float32(self.disparity_step)
                disparity = np.round(disparity / step) * step
            disparity[lost | ~(disparity > 0)] = np.nan
            return fb / disparity


def _gaussian_weights(sigma: float) -> np.ndarray:
    """The normalised 1-D kernel :func:`scipy.ndimage.gaussian_filter1d` uses for ``sigma`` (truncate 3)."""
    radius = int(_TRUNCATE * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


_TRUNCATE = 3.0


def correlated_field(shape: tuple[int, int], length: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 Gaussian field of unit variance, correlated over ``length`` pixels.

    White noise smoothed by a Gaussian of standard deviation ``length``
    pixels (0: the white noise itself), scaled back to unit variance by the
    kernel's own sum of squares (exact, not estimated). The white noise is
    drawn with a margin, so the field is stationary up to the image border.
    For ``length`` >= 2 it is made at half resolution (smoothed by
    ``length`` / 2) and interpolated bilinearly, each interpolated sample
    rescaled to unit variance: a 640 x 480 field then costs about 2 ms
    instead of 7 (one core of the 2-core test machine). Interpolation
    lengthens the correlation a little (neighbour correlation 0.963
    against 0.961 at 2.5 px).
    """
    from scipy.ndimage import gaussian_filter

    height, width = shape
    if length <= 0:
        return rng.standard_normal(shape, dtype=np.float32)
    factor = 2 if length >= 2.0 else 1
    sigma = length / factor
    weights = _gaussian_weights(sigma)
    margin = (len(weights) - 1) // 2
    rows, cols = -(-height // factor) + (factor - 1), -(-width // factor) + (factor - 1)
    white = rng.standard_normal((rows + 2 * margin, cols + 2 * margin), dtype=np.float32)
    field = gaussian_filter(white, sigma, mode="constant", truncate=_TRUNCATE)[margin : margin + rows, margin : margin + cols]
    field *= np.float32(1.0 / float(np.sum(weights**2)))  # 2-D variance = (sum w^2)^2; its square root
    if factor == 2:
        lag1 = float(np.sum(weights[:-1] * weights[1:]) / np.sum(weights**2))  # neighbour correlation per axis
        gain = np.float32(0.5 / math.sqrt(0.5 * (1.0 + lag1)))  # the mean of two neighbours, back to unit variance
        up = np.empty((2 * rows - 1, cols), dtype=np.float32)
        up[::2] = field
        np.add(field[:-1], field[1:], out=up[1::2])
        up[1::2] *= gain
        field = np.empty((2 * rows - 1, 2 * cols - 1), dtype=np.float32)
        field[:, ::2] = up
        np.add(up[:, :-1], up[:, 1:], out=field[:, 1::2])
        field[:, 1::2] *= gain
    return field[:height, :width]


def edge_pixels(depth: np.ndarray, jump: float, dropout: int) -> np.ndarray:
    """(H, W) bool: pixels within ``dropout`` pixels of a depth discontinuity (``dropout`` 0: none).

    A discontinuity lies between 4-neighbours whose depths differ by more
    than ``jump`` times the nearer one, or of which one has a return and the
    other none; the pixels on both sides of it are at distance 1.
    """
    edges = np.zeros(depth.shape, dtype=bool)
    if dropout <= 0:
        return edges
    valid = np.isfinite(depth)
    with np.errstate(invalid="ignore"):
        for axis in (0, 1):
            a = depth[:-1] if axis == 0 else depth[:, :-1]
            b = depth[1:] if axis == 0 else depth[:, 1:]
            va = valid[:-1] if axis == 0 else valid[:, :-1]
            vb = valid[1:] if axis == 0 else valid[:, 1:]
            step = (va != vb) | (np.abs(a - b) > np.float32(jump) * np.fmin(a, b))
            if axis == 0:
                edges[:-1] |= step
                edges[1:] |= step
            else:
                edges[:, :-1] |= step
                edges[:, 1:] |= step
    for _ in range(dropout - 1):  # grow by one pixel (a 3 x 3 square) per further pixel of dropout
        grown = edges.copy()
        grown[1:] |= edges[:-1]
        grown[:-1] |= edges[1:]
        edges = grown.copy()
        edges[:, 1:] |= grown[:, :-1]
        edges[:, :-1] |= grown[:, 1:]
    return edges


def incidence_cosine(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(H, W) float32 cosine of the angle between each pixel's ray and the surface normal (NaN: unknown).

    The normal comes from the gradient of inverse depth w = 1/z, which is
    linear in the ray coordinates (a, b) = ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy)
    on a plane n . p = c: w = (n_x a + n_y b + n_z) / c. So n / c =
    (dw/da, dw/db, w - a dw/da - b dw/db) and cos = |w| / (|n / c| |(a, b, 1)|),
    exact on planes. Central differences; one-sided at the image border.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.float32(1.0) / depth
        gu = np.empty_like(w)
        gv = np.empty_like(w)
        gu[:, 1:-1] = (w[:, 2:] - w[:, :-2]) * np.float32(0.5)
        gu[:, 0] = w[:, 1] - w[:, 0]
        gu[:, -1] = w[:, -1] - w[:, -2]
        gv[1:-1] = (w[2:] - w[:-2]) * np.float32(0.5)
        gv[0] = w[1] - w[0]
        gv[-1] = w[-1] - w[-2]
        a = ((np.arange(depth.shape[1], dtype=np.float32) + np.float32(0.5 - intrinsics.cx)) / np.float32(intrinsics.fx))[None, :]
        b = ((np.arange(depth.shape[0], dtype=np.float32) + np.float32(0.5 - intrinsics.cy)) / np.float32(intrinsics.fy))[:, None]
        ga = gu * np.float32(intrinsics.fx)
        gb = gv * np.float32(intrinsics.fy)
        nz = w - a * ga - b * gb
        norm = np.sqrt((ga * ga + gb * gb + nz * nz) * (a * a + b * b + np.float32(1.0)))
        return np.abs(w) / norm


def noise_rng(seed: int, frame: int) -> np.random.Generator:
    """The random stream of frame ``frame`` in a run with ``seed`` (independent per frame)."""
    return np.random.default_rng([int(seed), int(frame)])


def _check_backend_library(backend: str) -> None:
    from mabdi.errors import RenderBackendError  # a user's error: one line, no traceback
    library = {"egl": "EGL", "osmesa": "OSMesa"}[backend]
    if ctypes.util.find_library(library) is None:
        package = {"egl": "libegl1 libegl-mesa0 libgl1-mesa-dri", "osmesa": "libosmesa6"}[backend]
        raise RenderBackendError(
            f"render backend '{backend}' needs the system library lib{library}, which was not found; "
            f"on Debian/Ubuntu: apt-get install {package}"
        )


@dataclass
class _Drawn:
    """A leaf being drawn: the actor, and with face identity the copy that carries its codes."""

    leaf: vtkPolyData
    actor: vtkActor
    copy: vtkPolyData | None = None
    last_render: int = 0


#: Renders a block may go undrawn before its actor, upload and face codes are dropped.
KEEP_HIDDEN_RENDERS = 8


class DepthRenderer:
    """One reusable off-screen render window that renders z-buffers of a mesh.

    ``render_zbuffer(data, intrinsics, pose)`` returns the (H, W) float32
    z-buffer, top row first, values in [0, 1] (1 = background). ``data`` is a
    vtkPolyData or a composite dataset of them (the map's chunks of blocks).
    Only the blocks in view are drawn: a block whose metadata has a
    BOUNDING_BOX outside the frustum is skipped with its children. Each drawn
    polydata gets its own mapper and actor, kept while it stays in view: a
    mapper uploads its geometry when it first draws it or when it changes, so
    a map that grows by new blocks uploads only those; a block that leaves the
    view is hidden, and released after :data:`KEEP_HIDDEN_RENDERS` renders.

    Colour: ``identity_array`` names a uint8 RGB cell array each leaf draws in
    (flat, no lighting; the simulator's object colours), or ``face_identity``
    draws each face in the colour of a 24-bit code the renderer assigns
    (:mod:`mabdi.face_identity`): :meth:`render_identity` reads the codes back
    and :attr:`identities` says which block each range of codes belongs to.
    """

    def __init__(self, backend: str = "egl", identity_array: str | None = None, face_identity: bool = False) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"unknown render backend {backend!r} (known: {', '.join(BACKENDS)})")
        self.backend = backend
        self.identity_array = FACE_RGB_ARRAY if face_identity else identity_array
        self.face_identity = face_identity
        self._window = None
        self._size: tuple[int, int] | None = None
        self._renderer = vtkRenderer()
        self._renderer.SetBackground(0.0, 0.0, 0.0)  # identity 0: no face
        self._actors: dict[int, _Drawn] = {}
        self._codes = FaceCodes()
        self._names: dict[int, str] = {}
        self._addresses: dict[int, int] = {}  # block_address of each drawn polydata
        self._renders = 0
        self._drawn: set[int] = set()
        self._zbuffer = vtkFloatArray()
        self._rgb = vtkUnsignedCharArray()

    def _sync_actors(self, leaves: list[tuple[str, vtkPolyData]]) -> None:
        """One actor per polydata of ``leaves``, shown; actors of polydata not drawn are hidden, and dropped
        (with their codes and upload) after :data:`KEEP_HIDDEN_RENDERS` renders without them, so a block at
        the edge of the view (seen by one of two nearby poses) is not uploaded again and again."""
        self._renders += 1
        drawn: set[int] = set()
        for name, leaf in leaves:
            key = id(leaf)
            entry = self._actors.get(key)
            if entry is not None and entry.copy is not None and entry.copy.GetNumberOfCells() != leaf.GetNumberOfCells():
                self._drop(key)
                entry = None
            if entry is None:
                entry = self._actors[key] = self._new_actor(leaf)
            entry.actor.VisibilityOn()
            entry.last_render = self._renders
            self._names[key] = name
            self._addresses[key] = block_address(leaf)
            drawn.add(key)
        for key, entry in list(self._actors.items()):
            if key in drawn:
                continue
            if self._renders - entry.last_render > KEEP_HIDDEN_RENDERS:
                self._drop(key)
            else:
                entry.actor.VisibilityOff()
        self._drawn = drawn

    def _drop(self, key: int) -> None:
        entry = self._actors.pop(key)
        self._renderer.RemoveActor(entry.actor)
        self._codes.release(key)
        self._names.pop(key, None)
        self._addresses.pop(key, None)

    def _new_actor(self, leaf: vtkPolyData) -> _Drawn:
        drawn = leaf
        copy = None
        if self.face_identity:
            # the codes live on a shallow copy (points and cells shared, so moved points still show), never
            # on the map's own block
            count = leaf.GetNumberOfCells()
            base = self._codes.allocate(id(leaf), count)
            copy = vtkPolyData()
            copy.ShallowCopy(leaf)
            rgb = numpy_to_vtk(face_rgb(base, count), deep=True)
            rgb.SetName(FACE_RGB_ARRAY)
            copy.GetCellData().AddArray(rgb)
            drawn = copy
        mapper = vtkPolyDataMapper()
        mapper.SetInputData(drawn)
        if self.identity_array is not None and drawn.GetCellData().GetArray(self.identity_array) is not None:
            mapper.ScalarVisibilityOn()
            mapper.SetScalarModeToUseCellFieldData()
            mapper.SelectColorArray(self.identity_array)
            mapper.SetColorModeToDirectScalars()
        else:
            mapper.ScalarVisibilityOff()
        actor = vtkActor()
        actor.SetMapper(mapper)
        actor.GetProperty().LightingOff()
        if self.identity_array is not None:
            actor.GetProperty().SetColor(0.0, 0.0, 0.0)  # a block without identities reads as "no face"
        self._renderer.AddActor(actor)
        return _Drawn(leaf, actor, copy)

    @property
    def identities(self) -> FaceIdTable:
        """What the codes of the last :meth:`render_identity` mean (``face_identity`` renderers): block names,
        first codes and face counts of the blocks drawn."""
        names, bases, counts, addresses = [], [], [], []
        for key, (base, count) in self._codes.ranges.items():
            if key not in self._drawn:
                continue
            names.append(self._names[key])
            bases.append(base)
            counts.append(count)
            addresses.append(self._addresses[key])
        return FaceIdTable(names, np.array(bases, dtype=np.int64), np.array(counts, dtype=np.int64), np.array(addresses, dtype=np.int64))

    def _make_window(self, width: int, height: int):
        _check_backend_library(self.backend)
        if self.backend == "egl":
            from vtkmodules.vtkRenderingOpenGL2 import vtkEGLRenderWindow as window_class
        else:
            from vtkmodules.vtkRenderingOpenGL2 import vtkOSOpenGLRenderWindow as window_class
        window = window_class()
        window.SetOffScreenRendering(1)
        window.SetShowWindow(False)
        window.SetMultiSamples(0)
        window.SetSize(width, height)
        window.AddRenderer(self._renderer)
        return window

    @property
    def window(self):
        """The render window (None before the first render)."""
        return self._window

    def render_zbuffer(self, data, intrinsics: Intrinsics, world_from_camera) -> np.ndarray:
        size = (intrinsics.width, intrinsics.height)
        if self._window is None or self._size != size:
            if self._window is not None:
                self._window.RemoveRenderer(self._renderer)
                self._window.Finalize()
            self._window = self._make_window(*size)
            self._size = size
        self._sync_actors(named_leaves(data, frustum_planes(intrinsics, world_from_camera)))
        configure_vtk_camera(self._renderer.GetActiveCamera(), intrinsics, world_from_camera)
        # Polygon offsets would bias depth; the setting is global in VTK, so restore it after.
        coincident = vtkMapper.GetResolveCoincidentTopology()
        vtkMapper.SetResolveCoincidentTopologyToOff()
        try:
            self._window.Render()
        finally:
            vtkMapper.SetResolveCoincidentTopology(coincident)
        width, height = size
        self._window.GetZbufferData(0, 0, width - 1, height - 1, self._zbuffer)
        return vtk_to_numpy(self._zbuffer).reshape(height, width)[::-1]

    def render_identity(self) -> np.ndarray:
        """(H, W) int64 identity of the last render (top row first): the 24-bit RGB of the face seen, 0 = none.

        Call right after :meth:`render_zbuffer` (same frame); needs ``identity_array``.
        """
        width, height = self._size
        self._window.GetPixelData(0, 0, width - 1, height - 1, 0, self._rgb, 0)
        rgb = vtk_to_numpy(self._rgb).reshape(height, width, 3)[::-1].astype(np.int64)
        return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)

    def describe(self) -> dict:
        """The backend that drew the frames: name, window class and OpenGL renderer string."""
        if self._window is None:
            return {"backend": self.backend}
        renderer = "?"
        for line in self._window.ReportCapabilities().splitlines():
            if "renderer string" in line:
                renderer = line.split(":", 1)[1].strip()
                break
        return {"backend": self.backend, "window": self._window.GetClassName(), "gl_renderer": renderer}

    def close(self) -> None:
        """Release the render window (a later render makes a new one)."""
        if self._window is not None:
            self._window.RemoveRenderer(self._renderer)
            self._window.Finalize()
            self._window = None
            self._size = None


class FilterDepthImage(MabdiAlgorithm):
    """Render the input mesh from ``pose`` into a metric depth image (see the module docs).

    Properties: ``pose`` (4x4 world_from_camera, required), ``intrinsics``,
    ``noise`` (:class:`SensorNoise` or a model name), ``seed`` and ``frame``
    (select the noise stream; ``frame`` is also stored in the output).
    """

    def __init__(
        self,
        intrinsics: Intrinsics | SphericalGeometry | None = None,
        noise: SensorNoise | str = "none",
        seed: int = 0,
        backend: str = "egl",
    ) -> None:
        super().__init__(nInputPorts=1, inputType="vtkDataObject", nOutputPorts=1, outputType="vtkImageData")
        self._intrinsics = intrinsics if intrinsics is not None else Intrinsics()
        self._noise = SensorNoise.of(noise)
        self._seed = int(seed)
        self._frame = 0
        self._pose: np.ndarray | None = None
        self.renderer = DepthRenderer(backend)
        #: A LiDAR's range images (:mod:`mabdi.filters.range_rendering`), made at the first one.
        self.range_renderer: RangeRenderer | None = None

    # -- properties --------------------------------------------------------
    @property
    def pose(self) -> np.ndarray | None:
        return None if self._pose is None else self._pose.copy()

    @pose.setter
    def pose(self, value) -> None:
        self._set("_pose", check_pose(value, "FilterDepthImage.pose"))

    @property
    def intrinsics(self) -> Intrinsics | SphericalGeometry:
        """The sensor's geometry: a camera's intrinsics, or a LiDAR's :class:`~mabdi.spherical.SphericalGeometry`."""
        return self._intrinsics

    @intrinsics.setter
    def intrinsics(self, value: Intrinsics | SphericalGeometry) -> None:
        if not isinstance(value, (Intrinsics, SphericalGeometry)):
            raise TypeError(f"intrinsics must be mabdi.camera.Intrinsics or mabdi.spherical.SphericalGeometry, got {type(value).__name__}")
        self._set("_intrinsics", value)

    @property
    def noise(self) -> SensorNoise:
        return self._noise

    @noise.setter
    def noise(self, value: SensorNoise | str) -> None:
        self._set("_noise", SensorNoise.of(value))

    @property
    def seed(self) -> int:
        return self._seed

    @seed.setter
    def seed(self, value: int) -> None:
        self._set("_seed", int(value))

    @property
    def frame(self) -> int:
        return self._frame

    @frame.setter
    def frame(self, value: int) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"FilterDepthImage.frame must be an integer >= 0, got {value!r}")
        self._set("_frame", int(value))

    # -- pipeline ----------------------------------------------------------
    def RequestInformation(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        info = outInfo.GetInformationObject(0)
        width, height = self._intrinsics.width, self._intrinsics.height
        info.Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), (0, width - 1, 0, height - 1, 0, 0), 6)
        info.Set(vtkImageData.SPACING(), (1.0, 1.0, 1.0), 3)
        info.Set(vtkImageData.ORIGIN(), (0.0, 0.0, 0.0), 3)
        return 1

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        data = vtkDataObject.GetData(inInfo[0], 0)
        if not isinstance(data, (vtkPolyData, vtkCompositeDataSet)):
            raise TypeError(
                "FilterDepthImage: input must be a vtkPolyData or a composite dataset of polydata, "
                f"got {data.GetClassName() if data is not None else None}"
            )
        if self._pose is None:
            raise ValueError("FilterDepthImage: pose is not set (assign a 4x4 world_from_camera to .pose)")
        intr = self._intrinsics
        rng = None if self._noise.model == "none" else noise_rng(self._seed, self._frame)
        if isinstance(intr, SphericalGeometry):
            if self.range_renderer is None:
                self.range_renderer = RangeRenderer(DepthRenderer(self.renderer.backend, identity_array=TRIANGLE_RGB_ARRAY))
            depth = self._noise.ranges_with_noise(self.range_renderer.render(data, intr, self._pose), rng)
        else:
            zbuffer = self.renderer.render_zbuffer(data, intr, self._pose)
            depth = self._noise.depth_from_zbuffer(zbuffer, intr.near, intr.far, rng, intrinsics=intr)
        fill_depth_image(vtkImageData.GetData(outInfo), depth, intr, self._pose, self._frame)
        return 1


class SensorRenderer:
    """Noise-free images of a mesh for either sensor geometry, one window reused across frames:
    ``render(data, geometry, world_from_sensor)`` gives a camera's metric depth (:class:`DepthRenderer`)
    or a LiDAR's range image (:class:`~mabdi.filters.range_rendering.RangeRenderer`), (H, W) float32, NaN
    where no surface lies within the range."""

    def __init__(self, backend: str = "egl") -> None:
        self.backend = backend
        self.camera = DepthRenderer(backend)
        self.lidar: RangeRenderer | None = None

    def render(self, data, geometry: Intrinsics | SphericalGeometry, world_from_sensor) -> np.ndarray:
        if isinstance(geometry, SphericalGeometry):
            if self.lidar is None:
                self.lidar = RangeRenderer(DepthRenderer(self.backend, identity_array=TRIANGLE_RGB_ARRAY))
            return self.lidar.render(data, geometry, world_from_sensor)
        zbuffer = self.camera.render_zbuffer(data, geometry, world_from_sensor)
        return zbuffer_to_depth(zbuffer, geometry.near, geometry.far)

    def close(self) -> None:
        self.camera.close()
        if self.lidar is not None:
            self.lidar.close()
