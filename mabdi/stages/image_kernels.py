"""Compiled (numba) neighbourhood operations on images, one pass each with no image-sized temporaries.

* :func:`depth_edges_kernel`: the silhouettes of a depth image (a relative
  jump within a pixel's 3x3 neighbourhood, or a pixel without a return in
  it), what :func:`mabdi.stages.removal.depth_edges` documents;
* :func:`dilate_kernel`: binary dilation by a (2 radius + 1) square, outside
  the image False (:func:`mabdi.stages.classifier.dilate`);
* :func:`border_steps_kernel`: each region's pixel pairs with known pixels
  across its border, and how many of them step
  (:func:`mabdi.stages.classifier.gradual_regions`);
* :func:`explained_by_fit_kernel`: a camera's suspect pixels whose return,
  moved to the pose registration fitted, lands on E within tau
  (:func:`mabdi.stages.classifier.explained_by_fit`).

The tests compare each with its array-slice formulation.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def depth_edges_kernel(depth, factor):
    """(H, W) bool: a NaN in the pixel's 3x3 neighbourhood, or its largest depth over ``factor`` (float32,
    1 + jump) times its smallest; the image's border counts as its own nearest pixels. A row pass (min, max,
    any NaN of three), then a column pass; where a NaN is near, the min and max are not looked at."""
    height, width = depth.shape
    low = np.empty((height, width), dtype=np.float32)
    high = np.empty((height, width), dtype=np.float32)
    missing = np.empty((height, width), dtype=np.bool_)
    for row in range(height):
        for col in range(width):
            a = depth[row, max(col - 1, 0)]
            b = depth[row, col]
            c = depth[row, min(col + 1, width - 1)]
            missing[row, col] = (a != a) | (b != b) | (c != c)
            low[row, col] = min(a, min(b, c))
            high[row, col] = max(a, max(b, c))
    out = np.empty((height, width), dtype=np.bool_)
    for row in range(height):
        up, down = max(row - 1, 0), min(row + 1, height - 1)
        for col in range(width):
            near_missing = missing[up, col] | missing[row, col] | missing[down, col]
            smallest = min(low[up, col], min(low[row, col], low[down, col]))
            largest = max(high[up, col], max(high[row, col], high[down, col]))
            out[row, col] = near_missing | (largest > factor * smallest)
    return out


@njit(cache=True)
def _dilate_rows(mask, radius):
    """(H, W) bool: ``mask`` dilated along its rows by 2 radius + 1 pixels, outside False."""
    height, width = mask.shape
    out = np.zeros((height, width), dtype=np.bool_)
    for row in range(height):
        last = -(radius + 1)  # the column of the last True seen
        for col in range(width + radius):
            if col < width and mask[row, col]:
                last = col
            target = col - radius
            if target >= 0:
                # a True within 2 radius to the left of col (col included) covers target
                out[row, target] = col - last <= 2 * radius
    return out


@njit(cache=True)
def _dilate_columns(mask, radius):
    """(H, W) bool: ``mask`` dilated along its columns by 2 radius + 1 pixels, outside False; row by row, each
    column's last True row carried along (the memory read in order, not down the columns)."""
    height, width = mask.shape
    out = np.zeros((height, width), dtype=np.bool_)
    last = np.full(width, -(radius + 1), dtype=np.int64)  # per column, the row of the last True seen
    for row in range(height + radius):
        if row < height:
            for col in range(width):
                if mask[row, col]:
                    last[col] = row
        target = row - radius
        if target >= 0:
            for col in range(width):
                out[target, col] = row - last[col] <= 2 * radius
    return out


@njit(cache=True)
def dilate_kernel(mask, radius):
    """(H, W) bool: ``mask`` dilated by a (2 radius + 1) square: along the rows, then along the columns."""
    return _dilate_columns(_dilate_rows(mask, radius), radius)


@njit(cache=True)
def border_steps_kernel(regions, count, known, measured, expected, tau, cosine, far_k):
    """(pairs, steps, outline, size, far), int64 (count + 1,) each: for every region of ``regions`` (int32 (H, W),
    0 none, 1..count), the 4-neighbour pairs of one of its pixels and a ``known`` pixel (bool (H, W)), how many of
    them have D - E (``measured`` - ``expected``, (H, W), in float64) differing by more than ``tau`` (the region
    pixel's, (H, W)), the pairs of one of its pixels and any pixel of the image outside it, its pixels, and those
    of them where |D - E| exceeds ``far_k`` tau. One pass."""
    height, width = regions.shape
    pairs = np.zeros(count + 1, dtype=np.int64)
    steps = np.zeros(count + 1, dtype=np.int64)
    outline = np.zeros(count + 1, dtype=np.int64)
    size = np.zeros(count + 1, dtype=np.int64)
    far = np.zeros(count + 1, dtype=np.int64)
    for row in range(height):
        for col in range(width):
            region = regions[row, col]
            if region == 0:
                continue
            here = np.float64(measured[row, col]) - np.float64(expected[row, col])
            limit = tau[row, col]
            size[region] += 1
            slant = cosine[row, col]
            if abs(here) * (slant if slant == slant else 1.0) > far_k * limit:
                far[region] += 1
            for k in range(4):
                r = row + (1 if k == 0 else (-1 if k == 1 else 0))
                c = col + (1 if k == 2 else (-1 if k == 3 else 0))
                if r < 0 or r >= height or c < 0 or c >= width or regions[r, c] == region:
                    continue
                outline[region] += 1
                if not known[r, c]:
                    continue
                pairs[region] += 1
                if abs(here - (np.float64(measured[r, c]) - np.float64(expected[r, c]))) > limit:
                    steps[region] += 1
    return pairs, steps, outline, size, far


@njit(cache=True)
def _inverse_depth_at(expected, u, v):
    """1 / E read at the continuous pixel coordinates (u column, v row; centres at + 0.5): bilinear in inverse
    depth between the four pixel centres around the point where all four hold a value, else the pixel's own; NaN
    outside the image (:func:`mabdi.stages.classifier.image_at` of 1 / E)."""
    height, width = expected.shape
    if not (u >= 0.0 and u < width and v >= 0.0 and v < height):
        return np.nan
    nearest = 1.0 / np.float64(expected[int(v), int(u)])
    x, y = u - 0.5, v - 0.5
    c0, r0 = int(np.floor(x)), int(np.floor(y))
    tx, ty = x - c0, y - r0
    c1, r1 = min(max(c0 + 1, 0), width - 1), min(max(r0 + 1, 0), height - 1)
    c0, r0 = min(max(c0, 0), width - 1), min(max(r0, 0), height - 1)
    e00 = 1.0 / np.float64(expected[r0, c0])
    e01 = 1.0 / np.float64(expected[r0, c1])
    e10 = 1.0 / np.float64(expected[r1, c0])
    e11 = 1.0 / np.float64(expected[r1, c1])
    blended = (1 - ty) * ((1 - tx) * e00 + tx * e01) + ty * ((1 - tx) * e10 + tx * e11)
    return blended if np.isfinite(blended) else nearest


@njit(cache=True)
def explained_by_fit_kernel(suspect, measured, expected, tau, fx, fy, cx, cy, meshed_from_fitted):
    """(H, W) bool: the ``suspect`` pixels of a camera's D (metres, z-depth) whose point, carried by
    ``meshed_from_fitted`` (4x4) and projected with the intrinsics (fx, fy, cx, cy), lies in front of the camera
    within ``tau`` (H, W, metres) of E read there (:func:`_inverse_depth_at`, then inverted)."""
    height, width = suspect.shape
    explained = np.zeros((height, width), dtype=np.bool_)
    m = meshed_from_fitted
    for row in range(height):
        for col in range(width):
            if not suspect[row, col]:
                continue
            depth = np.float64(measured[row, col])
            x = (col + 0.5 - cx) / fx * depth
            y = (row + 0.5 - cy) / fy * depth
            z = depth
            px = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]
            py = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]
            pz = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
            if not pz > 0.0:
                continue
            there = 1.0 / _inverse_depth_at(expected, fx * px / pz + cx, fy * py / pz + cy)
            explained[row, col] = abs(pz - there) <= tau[row, col]
    return explained
