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

Real sensors' noise is partly correlated between neighbouring pixels (a
Kinect's disparity is matched over a window), so the gain on recorded data
is smaller than on the simulated sensor; ``smooth_depth = false`` in the
surface's config section meshes the raw image.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mabdi.filters.depth_smoothing_kernels import PAIR_DIRECTIONS, smooth_depth_kernel
from mabdi.sensor_noise import SensorNoise

if TYPE_CHECKING:
    from mabdi.camera import Intrinsics

#: Gate of a neighbour pair, in standard deviations of one pixel's noise (times sqrt 2 for a difference).
SMOOTHING_GATE_K = 3.0


def smooth_depth(depth: np.ndarray, sigma: np.ndarray, gate_k: float = SMOOTHING_GATE_K) -> np.ndarray:
    """(H, W) float32 depth (metres, NaN = no return) smoothed as the module docs say.

    ``sigma``: (H, W) or scalar standard deviation of each pixel's noise (metres), from the sensor's
    noise model at that pixel's depth.
    """
    z = np.asarray(depth)
    if z.ndim != 2:
        raise ValueError(f"smooth_depth: need an (H, W) depth image, got shape {z.shape}")
    sigma = np.broadcast_to(np.asarray(sigma), z.shape)
    if gate_k <= 0 or not np.any(sigma > 0):
        return np.asarray(depth, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        return smooth_depth_kernel(z, sigma, gate_k * np.sqrt(2.0), PAIR_DIRECTIONS)


def smooth_depth_by_noise(depth: np.ndarray, noise: SensorNoise, intrinsics: Intrinsics) -> np.ndarray:
    """``depth`` smoothed with each pixel's sigma from the sensor's ``noise`` model at its own depth (the
    intrinsics' near and far planes); a noise-free model returns ``depth`` itself, with no pass over it."""
    if noise.model == "none":
        return depth
    return smooth_depth(depth, noise.sigma(np.asarray(depth, dtype=np.float32), intrinsics.near, intrinsics.far))


def measured_around(depth: np.ndarray, measured: np.ndarray, noise: SensorNoise, intrinsics: Intrinsics, smooth: bool) -> np.ndarray:
    """The whole measured image behind ``depth`` (which may hold only the pixels being meshed) as the surfaces'
    flat-ground test reads it: smoothed like ``depth`` when ``smooth``, with ``depth``'s own values where it has them."""
    if smooth:
        measured = smooth_depth_by_noise(measured, noise, intrinsics)
    return np.where(np.isfinite(depth), depth, measured)
