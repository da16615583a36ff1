"""NoiseCalibration: the sensor's sigma(z) learnt online from D - E, for ``noise = "auto"``.

With ``[sensor] noise = "auto"`` the loop measures a camera's noise: where
the map already explains a pixel, D - E is the sensor's error there. Each
registered frame hands :meth:`NoiseCalibration.observe` the residuals of
D's returns on the map (every ``stride``-th pixel, away from E's
silhouettes, within ``gate_k`` sigma or ``min_gate``). Per depth bin
(``bin_width`` metres) it keeps the last ``samples_per_bin`` residuals and
reads sigma as 1.4826 times their median absolute value.

The curve is sigma(z) = sqrt(a^2 + (c z^2)^2) (metres): the z^2 law of
triangulating cameras plus a floor a, mostly the map's own error; the
sensor's own curve is c z^2 (:meth:`NoiseCalibration.sensor_sigma`). Before
the first fit it is the Kinect v1's c = 1.425e-3 / m, a = 0.

``correlation`` (pixels) is how far errors reach across pixels, fitted to
the residuals' correlation at ``CORRELATION_LAGS`` as a Gaussian-smoothed
field; 0 where neighbours are mostly independent
(``MIN_NEIGHBOUR_CORRELATION``), ``PRIOR_CORRELATION`` before enough pairs.

Everything that uses the sensor's noise reads this curve through
:meth:`mabdi.sensor_noise.SensorNoise.sigma`; each depth image carries the
curve as it stood when it was made (a :class:`NoiseCurve`). The result goes
into ``summary.json`` (:meth:`summary`). Why: docs/architecture.md
(``mabdi.noise_calibration``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from mabdi.noise_calibration_kernels import add_residuals_kernel

#: Median absolute deviation to standard deviation, for a normal distribution.
MAD_TO_SIGMA = 1.4826
#: The curve before the first fit: the Kinect v1's c (1/m), Khoshelham & Elberink 2012.
PRIOR_COEFFICIENT = 1.425e-3
#: The correlation length (pixels) before the first fit: the structured-light model's default, a Kinect v1's.
PRIOR_CORRELATION = 2.5
#: Pixel distances at which the residuals' correlation is measured.
CORRELATION_LAGS = (1, 2, 4, 8)
#: Pairs are taken along every this many rows and columns.
PAIR_LINE_STRIDE = 8
#: Below this correlation of neighbouring residuals the pixels' errors are taken as independent (length 0).
MIN_NEIGHBOUR_CORRELATION = 0.25


@dataclass(frozen=True)
class NoiseCurve:
    """sigma(z) = sqrt(floor^2 + (coefficient z^2)^2): the calibrated curve at one moment (``floor`` in m,
    ``coefficient`` in 1/m), as a depth image carries it, with the length (pixels) over which neighbouring
    pixels' errors are correlated (``correlation``, 0: independent; see the module docs)."""

    floor: float = 0.0
    coefficient: float = PRIOR_COEFFICIENT
    correlation: float = PRIOR_CORRELATION

    def sigma(self, depth) -> np.ndarray:
        """sigma (m) at metric depths ``depth``; float32 for float32 input."""
        z = np.asarray(depth)
        if z.dtype != np.float32:
            z = z.astype(np.float64)
        kind = z.dtype.type
        return np.sqrt(kind(self.floor**2) + (kind(self.coefficient) * z * z) ** 2)

    def sensor_sigma(self, depth) -> np.ndarray:
        """The sensor's part of the curve, c z^2 (m), without the floor (see the module docs)."""
        z = np.asarray(depth)
        if z.dtype != np.float32:
            z = z.astype(np.float64)
        return z.dtype.type(self.coefficient) * z * z


class NoiseCalibration:
    """sigma(z) of an unknown sensor from the residuals D - E of pixels the map explains (see the module docs).

    Lengths in metres. ``bin_width``: depth bins; ``max_depth``: the last
    bin's far edge; ``samples_per_bin``: residuals kept per bin (the most
    recent); ``min_samples``: a bin counts in the fit from this many;
    ``stride``: pixels sampled in u and v; ``gate_k`` and ``min_gate``:
    residuals within max(gate_k sigma(z), min_gate) are counted;
    ``min_correlation_pairs``: pairs of residuals each lag needs before the
    correlation length is fitted.
    """

    def __init__(
        self,
        bin_width: float = 0.25,
        max_depth: float = 10.0,
        samples_per_bin: int = 4096,
        min_samples: int = 200,
        stride: int = 2,
        gate_k: float = 5.0,
        min_gate: float = 0.02,
        min_correlation_pairs: int = 20000,
    ) -> None:
        self.bin_width = float(bin_width)
        self.edges = np.arange(0.0, max_depth + 0.5 * bin_width, bin_width)
        self.samples_per_bin = int(samples_per_bin)
        self.min_samples = int(min_samples)
        self.stride = int(stride)
        self.gate_k = float(gate_k)
        self.min_gate = float(min_gate)
        self.min_correlation_pairs = int(min_correlation_pairs)
        self.reset()

    def reset(self) -> None:
        bins = len(self.edges) - 1
        #: per bin: a ring of the most recent absolute residuals (m), how many were ever added
        self._residuals = np.full((bins, self.samples_per_bin), np.nan, dtype=np.float32)
        self._added = np.zeros(bins, dtype=np.int64)
        #: per lag (:data:`CORRELATION_LAGS`): sums over pairs of normalised residuals a, b of
        #: a b, a^2, b^2 and the number of pairs
        self._pair_sums = np.zeros((len(CORRELATION_LAGS), 4), dtype=np.float64)
        #: the current fit (the prior until the first)
        self.curve = NoiseCurve()
        self._fitted = False

    # -- the curve -------------------------------------------------------------
    def sigma(self, depth) -> np.ndarray:
        """sigma (m) at metric depths ``depth``: sqrt(a^2 + (c z^2)^2); float32 for float32 input."""
        return self.curve.sigma(depth)

    def sensor_sigma(self, depth) -> np.ndarray:
        """The sensor's part of the curve, c z^2 (m), without the floor (see the module docs)."""
        return self.curve.sensor_sigma(depth)

    @property
    def fitted(self) -> bool:
        """Whether the curve comes from measurements yet (else it is the prior)."""
        return self._fitted

    def bin_sigmas(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bin centres in m, sigma per bin in m (NaN with no residuals), residuals held per bin)."""
        held = np.minimum(self._added, self.samples_per_bin)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # bins with no residuals: NaN
            sigma = MAD_TO_SIGMA * np.nanmedian(self._residuals, axis=1)
        return 0.5 * (self.edges[:-1] + self.edges[1:]), sigma, held

    # -- learning ----------------------------------------------------------------
    def observe(self, measured: np.ndarray, expected: np.ndarray, silhouettes: np.ndarray | None = None) -> int:
        """Add one frame's residuals (D, E: (H, W) metres, NaN = none; ``silhouettes``: pixels to skip) and
        refit the curve and the correlation length. Returns the number of residuals added."""
        self._observe_pairs(measured, expected, silhouettes)
        skip = silhouettes if silhouettes is not None else np.zeros((1, 1), dtype=bool)
        counted = add_residuals_kernel(
            measured, expected, skip, silhouettes is not None, self.stride, self.curve.floor**2,
            self.curve.coefficient, self.gate_k, self.min_gate, self.edges, self._residuals, self._added,
        )  # fmt: skip
        self._fit()
        return int(counted)

    def _counted(self, residual: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """Which absolute residuals count: within max(gate_k sigma, min_gate) (new surfaces in front of the map
        and objects that left lie beyond it)."""
        return residual <= np.maximum(self.gate_k * sigma, self.min_gate)

    def _observe_pairs(self, measured: np.ndarray, expected: np.ndarray, silhouettes: np.ndarray | None) -> None:
        """Add the products of normalised residuals (D - E) / sigma(E) of pixels ``CORRELATION_LAGS`` apart,
        along every ``PAIR_LINE_STRIDE``-th row and column (the gate of :meth:`observe`)."""
        k = PAIR_LINE_STRIDE
        lines = []
        for take in (lambda a: a[::k], lambda a: a[:, ::k].T):  # rows, then columns
            d = take(np.asarray(measured, dtype=np.float32))
            e = take(np.asarray(expected, dtype=np.float32))
            with np.errstate(invalid="ignore"):
                residual = d - e
                sigma = np.maximum(self.sigma(e), np.float32(1e-6))
                usable = self._counted(np.abs(residual), sigma)
            if silhouettes is not None:
                usable &= ~take(silhouettes)
            lines.append(np.where(usable, residual / sigma, np.float32(np.nan)))
        for i, lag in enumerate(CORRELATION_LAGS):
            for normalised in lines:
                a, b = normalised[:, :-lag], normalised[:, lag:]
                both = np.isfinite(a) & np.isfinite(b)
                a, b = a[both].astype(np.float64), b[both].astype(np.float64)
                self._pair_sums[i] += (a @ b, a @ a, b @ b, len(a))

    def correlations(self) -> np.ndarray:
        """The residuals' correlation at each of :data:`CORRELATION_LAGS` (NaN where no pairs were seen)."""
        products, first, second, _ = self._pair_sums.T
        with np.errstate(invalid="ignore", divide="ignore"):
            return products / np.sqrt(first * second)

    def _fit_correlation(self) -> float | None:
        """The correlation length (pixels) of the residuals so far, or None before enough pairs (module docs)."""
        if not np.all(self._pair_sums[:, 3] >= self.min_correlation_pairs):
            return None
        rho = self.correlations()
        if not rho[0] >= MIN_NEIGHBOUR_CORRELATION:
            return 0.0
        lags = np.asarray(CORRELATION_LAGS, dtype=np.float64)
        use = rho > 0.02
        if use.sum() < 2:  # correlated at 1 pixel, nothing left at 2: a length well under a pixel
            return 0.5
        slope, _ = np.polyfit(lags[use] ** 2, np.log(rho[use]), 1)  # ln rho = ln f - k^2 / (4 L^2)
        if slope >= 0:  # no decay over 8 pixels: longer than the lags can tell
            return float(2 * CORRELATION_LAGS[-1])
        return float(min(np.sqrt(-1.0 / (4.0 * slope)), 2 * CORRELATION_LAGS[-1]))

    def _fit(self) -> None:
        correlation = self._fit_correlation()
        if correlation is not None:
            self.curve = NoiseCurve(self.curve.floor, self.curve.coefficient, correlation)
        centres, sigma, held = self.bin_sigmas()
        use = (held >= self.min_samples) & np.isfinite(sigma)
        if not use.any():
            return
        z = centres[use]
        weight = held[use].astype(np.float64)
        # sigma^2 = a^2 + c^2 z^4, linear in (a^2, c^2): least squares on the relative error of sigma^2
        # (each bin weighted by its residual count), both kept >= 0
        relative = np.sqrt(weight) / sigma[use] ** 2
        design = np.stack([np.ones_like(z), z**4], axis=1) * relative[:, None]
        target = sigma[use] ** 2 * relative
        if use.sum() >= 2:
            (a2, c2), *_ = np.linalg.lstsq(design, target, rcond=None)
            if a2 < 0 or c2 <= 0:
                a2 = max(a2, 0.0)
                w = weight / sigma[use] ** 4
                c2 = max(float(np.sum(w * (sigma[use] ** 2 - a2) * z**4) / np.sum(w * z**8)), 0.0)
        else:  # one bin: the z^2 law through it
            a2, c2 = 0.0, float(sigma[use][0] ** 2 / z[0] ** 4)
        self.curve = NoiseCurve(float(np.sqrt(max(a2, 0.0))), float(np.sqrt(max(c2, 0.0))), self.curve.correlation)
        self._fitted = True

    # -- checkpoints and reports ---------------------------------------------------
    def state(self) -> dict:
        """Plain arrays and numbers (for checkpoints)."""
        return {
            "residuals": self._residuals.copy(),
            "added": self._added.copy(),
            "pair_sums": self._pair_sums.copy(),
            "floor": self.curve.floor,
            "coefficient": self.curve.coefficient,
            "correlation": self.curve.correlation,
            "fitted": self._fitted,
        }

    def set_state(self, state: dict) -> None:
        self._residuals = np.array(state["residuals"], dtype=np.float32)
        self._added = np.array(state["added"], dtype=np.int64)
        self._pair_sums = np.array(state.get("pair_sums", np.zeros_like(self._pair_sums)), dtype=np.float64)
        self.curve = NoiseCurve(
            float(state["floor"]), float(state["coefficient"]), float(state.get("correlation", PRIOR_CORRELATION))
        )
        self._fitted = bool(state["fitted"])

    def summary(self) -> dict:
        """The calibrated curve for ``summary.json``: sigma(z) = sqrt(floor^2 + (coefficient z^2)^2), and its bins."""
        centres, sigma, held = self.bin_sigmas()
        used = held > 0
        return {
            "law": "sigma(z) = sqrt(floor_m^2 + (coefficient_per_m * z^2)^2); the sensor's part: coefficient_per_m * z^2",
            "fitted": self._fitted,
            "floor_m": self.curve.floor,
            "coefficient_per_m": self.curve.coefficient,
            "correlation_px": self.curve.correlation,
            "correlation_lags_px": list(CORRELATION_LAGS),
            "correlation_at_lags": [None if not np.isfinite(r) else round(float(r), 4) for r in self.correlations()],
            "bins_m": [round(float(c), 4) for c in centres[used]],
            "bin_sigma_m": [float(s) for s in sigma[used]],
            "bin_samples": [int(h) for h in held[used]],
        }
