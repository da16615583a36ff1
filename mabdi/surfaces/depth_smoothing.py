"""Noise-aware smoothing of a depth image before it is meshed (``smooth_depth`` of the pixel grid and quad-tree).

A map is first made of a single noisy look, and the first look stays; the
sensor's noise is largely independent from pixel to pixel, so averaging
each pixel with its neighbours on the same surface removes most of it.

The rule, per pixel with depth z (metres) and sigma = sigma(z) from the
image's noise model (:meth:`mabdi.sensor_noise.SensorNoise.sigma`):

* the 8 neighbours form 4 opposite pairs; a pair is used when both its
  pixels lie within ``gate_k sqrt(2) sigma`` of the centre's depth, so
  steps, silhouettes and holes (NaN) keep their edges;
* the result is the mean of the inverse depth 1/z over the centre and the
  used pairs: a plane at any orientation comes out unbiased;
* pixels with no usable pair keep their depth, NaN stays NaN, and sigma = 0
  leaves the image as it is.

Where the noise model says pixels err together
(:attr:`~mabdi.sensor_noise.SensorNoise.correlated`), the window grows to
``SMOOTHING_RADIUS_PER_CORRELATION`` correlation lengths each way, at most
``MAX_SMOOTHING_RADIUS`` pixels. ``smooth_depth = false`` meshes the raw image.

Why: docs/architecture.md (``mabdi.surfaces.depth_smoothing``); what it
gains: docs/benchmarks.md ("Depth smoothing before meshing").
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mabdi.surfaces.depth_smoothing_kernels import pair_directions, smooth_depth_kernel
from mabdi.sensor_noise import SensorNoise

if TYPE_CHECKING:
    from mabdi.camera import Intrinsics

#: Gate of a neighbour pair, in standard deviations of one pixel's noise (times sqrt 2 for a difference).
SMOOTHING_GATE_K = 3.0
#: Where the noise is correlated, the window reaches this many correlation lengths from the pixel ...
SMOOTHING_RADIUS_PER_CORRELATION = 1.5
#: ... and at most this many pixels (84 pairs).
MAX_SMOOTHING_RADIUS = 6


def smoothing_radius(noise: SensorNoise) -> int:
    """The half-width (pixels) of the smoothing window for ``noise``: 1 (3 x 3) where pixels err on their own,
    ``SMOOTHING_RADIUS_PER_CORRELATION`` correlation lengths (1 to ``MAX_SMOOTHING_RADIUS``) where they err
    together."""
    if not noise.correlated:
        return 1
    return int(min(MAX_SMOOTHING_RADIUS, max(1, round(SMOOTHING_RADIUS_PER_CORRELATION * noise.correlation_px))))


def smoothed_noise_share(noise: SensorNoise) -> float:
    """The share of a pixel's noise (standard deviation) left after smoothing over the window for ``noise``
    (:func:`smoothing_radius`), every pair of the window taken with its correlation
    (:meth:`~mabdi.sensor_noise.SensorNoise.mean_share`; a 3 x 3 window of independent noise: 1 / 3)."""
    radius = smoothing_radius(noise)
    return noise.mean_share([(du, dv) for du in range(-radius, radius + 1) for dv in range(-radius, radius + 1)])


def smooth_depth(depth: np.ndarray, sigma: np.ndarray, gate_k: float = SMOOTHING_GATE_K, radius: int = 1) -> np.ndarray:
    """(H, W) float32 depth (metres, NaN = no return) smoothed as the module docs say.

    ``sigma``: (H, W) or scalar standard deviation of each pixel's noise (metres), from the sensor's
    noise model at that pixel's depth; ``radius``: the window's half-width in pixels (1: 3 x 3).
    """
    z = np.asarray(depth)
    if z.ndim != 2:
        raise ValueError(f"smooth_depth: need an (H, W) depth image, got shape {z.shape}")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 1:
        raise ValueError(f"smooth_depth: radius must be an integer >= 1 (pixels), got {radius!r}")
    sigma = np.broadcast_to(np.asarray(sigma), z.shape)
    if gate_k <= 0 or not np.any(sigma > 0):
        return np.asarray(depth, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        return smooth_depth_kernel(z, sigma, gate_k * np.sqrt(2.0), pair_directions(radius))


def smooth_depth_by_noise(depth: np.ndarray, noise: SensorNoise, intrinsics: Intrinsics) -> np.ndarray:
    """``depth`` smoothed with each pixel's sigma from the sensor's ``noise`` model at its own depth (the
    intrinsics' near and far planes) over the window the noise calls for (:func:`smoothing_radius`); a
    noise-free model returns ``depth`` itself, with no pass over it."""
    if not noise.noisy:
        return depth
    sigma = noise.sigma(np.asarray(depth, dtype=np.float32), intrinsics.near, intrinsics.far)
    return smooth_depth(depth, sigma, radius=smoothing_radius(noise))


def measured_around(depth: np.ndarray, measured: np.ndarray, noise: SensorNoise, intrinsics: Intrinsics, smooth: bool) -> np.ndarray:
    """The whole measured image behind ``depth`` (which may hold only the pixels being meshed) as the surfaces'
    flat-ground test reads it: smoothed like ``depth`` when ``smooth``, with ``depth``'s own values where it has them."""
    if smooth:
        measured = smooth_depth_by_noise(measured, noise, intrinsics)
    return np.where(np.isfinite(depth), depth, measured)
