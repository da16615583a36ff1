"""Colours for mesh maps: by normal (seed 000, eqs. 5-7) and by the frame that created a face.

**By normal.** Voxel planes and most depth-derived surfaces have unoriented
normals, so the colour must be the same for n and -n, and continuous. Seed
000 §IV-D: flip normals into the upper hemisphere (eq. 5: n' = -n where
n_z < 0), stretch that hemisphere over the whole sphere by doubling the
polar angle, and map the stretched unit vector to RGB (eqs. 6-7):

    theta = arccos(n'_z),  phi = atan2(n'_y, n'_x)
    [R, G, B] = 1/2 [sin 2theta cos phi + 1, sin 2theta sin phi + 1, cos 2theta + 1]

phi uses atan2 (the seed writes arctan(n'_y / n'_x), which loses the
quadrant and jumps where n_x changes sign). Every horizontal normal
(theta = 90 deg) maps to the same colour (1/2, 1/2, 0), which is what makes
the flip at n_z = 0 seamless. Vertical normals are blue (0.5, 0.5, 1).

**By frame.** A perceptually uniform ramp (viridis) from the first frame to
the last, so the passage of time reads as dark to bright.
"""

from __future__ import annotations

import numpy as np


def normal_colours_float(normals: np.ndarray) -> np.ndarray:
    """(M, 3) RGB in [0, 1] of (M, 3) normals by seed 000 eqs. 5-7 (normals need not be unit length)."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(length > 0, n / length, np.array([0.0, 0.0, 1.0]))
    n = np.where(n[:, 2:3] < 0, -n, n)  # eq. 5
    theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))  # eq. 6
    phi = np.arctan2(n[:, 1], n[:, 0])
    return 0.5 * np.stack(  # eq. 7
        [np.sin(2 * theta) * np.cos(phi) + 1, np.sin(2 * theta) * np.sin(phi) + 1, np.cos(2 * theta) + 1], axis=1
    )


def colours_by_normal(normals: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 RGB of (M, 3) normals by seed 000 eqs. 5-7 (see the module docs)."""
    return np.round(255.0 * normal_colours_float(normals)).astype(np.uint8)


def colours_by_frame(frames: np.ndarray, first: int | None = None, last: int | None = None) -> np.ndarray:
    """(M, 3) uint8 RGB of creation frames on the viridis ramp, ``first`` dark to ``last`` bright."""
    from matplotlib import colormaps

    frames = np.asarray(frames, dtype=np.float64).ravel()
    if len(frames) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    lo = float(frames.min()) if first is None else float(first)
    hi = float(frames.max()) if last is None else float(last)
    t = np.zeros_like(frames) if hi <= lo else np.clip((frames - lo) / (hi - lo), 0.0, 1.0)
    return np.round(255.0 * colormaps["viridis"](t)[:, :3]).astype(np.uint8)
