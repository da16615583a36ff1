"""Noise-aware smoothing of a depth image before it is meshed (``smooth_depth`` of the pixel grid and quad-tree).

A single noisy look is what a map is first made of, and the first look
stays: the classifier calls later looks of the same surface "known". With
the ``kinect`` model a surface seen from 3.5 m has sigma = 17 mm, so a
pixel-grid vertex made from it is more than 1 cm off the surface about
half the time. The sensor's noise is independent from pixel to pixel, so
averaging each pixel with its neighbours on the same surface removes most
of it before the surface filter meshes the image.

The rule, per pixel with depth z (metres) and sigma = sigma(z) from the
sensor's noise model (:meth:`mabdi.sensor_noise.SensorNoise.sigma`):

* The 8 neighbours form 4 opposite pairs (left/right, up/down and the two
  diagonals). A pair is used when *both* its pixels lie within
  ``gate_k sqrt(2) sigma`` of the centre's depth (3 by default: two
  noisy samples of the same surface differ by sigma sqrt(2)), so a depth
  step, a silhouette or a hole (NaN) removes the pairs that cross it and
  edges stay sharp.
* The result is the mean of the *inverse* depth 1/z over the centre and the
  used pairs (1, 3, 5, 7 or 9 pixels). A plane's inverse depth is an
  affine function of the pixel coordinates, and a symmetric pair's mean of
  an affine function is its value at the centre, so planes at any
  orientation come out unbiased; a curved surface is bent by its curvature
  over one pixel (under 0.3 mm for a 10 cm radius seen from 3.5 m).
* With all 4 pairs the noise falls to sigma/3. Pixels with no usable pair
  keep their depth, NaN stays NaN, and a noise-free sensor (sigma = 0)
  leaves the image as it is.

What it gains (F@1cm and P@1cm of both surfaces on the noisy runs, raw against
smoothed): docs/benchmarks.md, section "Depth smoothing before meshing".

**Noise correlated across pixels** (a structured-light or stereo camera
matches its disparity over a window, so neighbouring pixels err together,
and a surface comes as terraces): the 3 x 3 window then averages pixels
that share one error and takes out little of it. Where the noise model says
so (:attr:`~mabdi.sensor_noise.SensorNoise.correlated`), the window grows to
``SMOOTHING_RADIUS_PER_CORRELATION`` (1.5) correlation lengths each way
(:attr:`~mabdi.sensor_noise.SensorNoise.correlation_px`: the model's, or
the one ``noise = "auto"`` learns; 2.5 px gives a 9 x 9 window, 40 pairs),
at most ``MAX_SMOOTHING_RADIUS`` pixels: every opposite pair in it is used
under the same gate, so planes stay unbiased and steps sharp, and a
terrace a few pixels wide is averaged with its neighbours. The price is
the curvature term, which grows with the window's second moment (about
2-3 mm on a 10 cm radius seen from 3 m for the 9 x 9 window, ten times the
3 x 3 window's, against centimetres of correlated error). Independent noise
keeps the 3 x 3 window.

``smooth_depth = false`` in the surface's config section meshes the raw
image.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mabdi.filters.depth_smoothing_kernels import pair_directions, smooth_depth_kernel
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
