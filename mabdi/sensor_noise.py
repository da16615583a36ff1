"""SensorNoise: a depth sensor's noise model, how the simulator draws it and what sigma(z) it gives.

A depth image carries its sensor's noise model in its field data beside the
intrinsics (:func:`mabdi.depth.image_noise`), so every filter that needs
sigma(z) (metres, at depth z in metres) reads it from the image it is given.

Models:

* ``none``;
* ``zbuffer`` (seed 001): d + d N(0, sigma) on the normalised z-buffer value
  d (sigma = 0.001), then converted to metres; d >= 1 is NaN;
* ``kinect``: axial sigma(z) = 1.425e-3 z^2 m (Khoshelham & Elberink 2012);
* ``structured_light``: a structured-light / stereo camera modelled in
  disparity d = f b / z: ``disparity_sigma`` pixels of spatially correlated
  noise (``correlation_length``), rounded to ``disparity_step``, with returns
  lost beside depth edges (``edge_dropout``, ``edge_jump``) and at grazing
  incidence (``max_incidence``); sigma(z) = z^2 sigma_eff / (f b). The
  defaults are a Kinect v1;
* ``auto``: a camera of unknown noise, learnt by the loop
  (:mod:`mabdi.noise_calibration`); the simulator refuses it;
* ``range``: a LiDAR's Gaussian range noise of ``range_sigma`` metres (0.02,
  Velodyne HDL-64E S2's datasheet figure).

Noise is reproducible: frame i of a run with seed s draws from
``numpy.random.default_rng([s, i])``. Where each default comes from (the
Kinect v1 and RealSense figures): docs/architecture.md (``mabdi.sensor_noise``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

from mabdi.camera import Intrinsics, zbuffer_depth_derivative, zbuffer_to_depth
from mabdi.errors import ConfigError
from mabdi.noise_calibration import NoiseCalibration, NoiseCurve

#: Depth noise models (see the module docs).
NOISE_MODELS = ("none", "zbuffer", "kinect", "structured_light", "auto", "range")
#: The noise models a LiDAR's range images take (the others model a camera's depth).
RANGE_NOISE_MODELS = ("none", "range")


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
    #: ``auto``: the curve :meth:`sigma` reads: the loop's online calibration (made with the model; shared
    #: by copies), or the curve as it stood when a depth image was made (:meth:`from_array`).
    calibration: NoiseCalibration | NoiseCurve | None = field(default=None, compare=False, repr=False)

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
        """The noise of a ``[sensor]`` config section (:class:`mabdi.config.SensorConfig`): its ``noise`` model,
        the parameters of ``[sensor.noise_parameters]``; ``focal`` is the camera's ``fx``."""
        parameters = {f.name: getattr(sensor.noise_parameters, f.name) for f in fields(sensor.noise_parameters)}
        return cls(sensor.noise, focal=sensor.camera.fx, **parameters)

    @classmethod
    def parameter_names(cls) -> tuple[str, ...]:
        """The numeric parameters, in the order :meth:`to_array` writes them."""
        return tuple(f.name for f in fields(cls) if f.name not in ("model", "calibration"))

    def to_array(self) -> np.ndarray:
        """float64: the parameters in :meth:`parameter_names`' order, and for ``auto`` the curve's floor (m),
        coefficient (1/m) and correlation length (pixels) as they stand now (what a depth image carries,
        :func:`mabdi.depth.image_noise`)."""
        values = [float(getattr(self, name)) for name in self.parameter_names()]
        if self.model == "auto":
            curve = self._curve()
            values += [curve.floor, curve.coefficient, curve.correlation]
        return np.asarray(values, dtype=np.float64)

    def _curve(self) -> NoiseCurve:
        """``auto``: the curve as it stands now."""
        return self.calibration.curve if isinstance(self.calibration, NoiseCalibration) else self.calibration

    def snapshot(self) -> SensorNoise:
        """This model as it stands now (``auto``: its curve frozen), as a depth image carries it."""
        return SensorNoise.from_array(self.model, self.to_array())

    @classmethod
    def from_array(cls, model: str, values) -> SensorNoise:
        """The model :meth:`to_array` wrote (``auto`` with its curve frozen; images written before the curve
        had a correlation length carry two numbers, and get the prior's); ValueError on a wrong length."""
        names = cls.parameter_names()
        values = [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]
        expected = len(names) + (3 if model == "auto" else 0)
        if len(values) != expected and not (model == "auto" and len(values) == expected - 1):
            raise ValueError(f"noise model {model!r}: expected {expected} parameters ({', '.join(names)}), got {len(values)}")
        parameters = dict(zip(names, values[: len(names)], strict=True))
        parameters["edge_dropout"] = int(parameters["edge_dropout"])
        curve = NoiseCurve(*values[len(names) :]) if model == "auto" else None
        return cls(model, **parameters, calibration=curve)

    @property
    def learnt(self) -> bool:
        """Whether the model is learnt from a real camera's frames (``auto``), not one of the simulator's."""
        return self.model == "auto"

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
    def correlation_px(self) -> float:
        """How far (pixels) neighbouring pixels' errors reach together: ``structured_light``'s
        ``correlation_length`` (0 without the correlated field), ``auto``'s length learnt from the run
        (:mod:`mabdi.noise_calibration`), 0 for the models that draw each pixel on its own."""
        if self.model == "structured_light":
            return self.correlation_length if self.disparity_sigma > 0 else 0.0
        if self.model == "auto":
            return self._curve().correlation
        return 0.0

    @property
    def noisy(self) -> bool:
        """Whether the model adds noise at all (every model but ``none``)."""
        return self.model != "none"

    def mean_share(self, offsets) -> float:
        """The share of one pixel's noise (standard deviation) left in the mean of the pixels at ``offsets``
        ((N, 2) pixel offsets): sqrt(sum over pixel pairs of their correlation) / N, the correlation
        exp(-d^2 / (4 L^2)) at d pixels for :attr:`correlation_px` L (a Gaussian-smoothed field's), none between
        distinct pixels where L = 0 (so 1 / sqrt(N))."""
        offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
        length = self.correlation_px
        if length <= 0:
            return float(1.0 / np.sqrt(len(offsets)))
        squared = ((offsets[:, None, :] - offsets[None, :, :]) ** 2).sum(axis=-1)
        return float(np.sqrt(np.exp(-squared / (4.0 * length * length)).sum()) / len(offsets))

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
    rescaled to unit variance: a fraction of the full-resolution cost
    (docs/benchmarks.md, "Depth image"). Interpolation lengthens the
    correlation a little.
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
