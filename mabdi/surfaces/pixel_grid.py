"""FilterPixelGrid: the seed's pixel-grid surface (``pixel_grid`` in configs).

Depth image in (metres), triangle mesh in the world frame out (the image's
pose). Every 2x2 square of pixels gives two triangles, (a, c, b) and
(b, c, d) with a the top-left and d the bottom-right corner, each kept when
its three corners are valid and do not straddle a depth discontinuity:

    max(z) - min(z) <= max_jump * min(z)        (max_jump = 0.01: 1% of the depth)

which is what a surface seen at about 79 degrees from its normal makes
between neighbouring pixels at a 525 px focal length. A LiDAR's range image
(:mod:`mabdi.spherical`) is meshed the same way along its rays, with
``max_jump`` scaled to its pixel angle (the geometry's ``jump_scale()``; with a
beam table, each pair of rows by its own spacing) and the azimuth seam joined.
``grazing`` (on for range images) also keeps an edge whose two samples
continue one straight line with the samples beyond
(:func:`mabdi.depth.straight_continuations`): flat ground at grazing incidence.

Triangles face the sensor; vertices are the pixel-centre rays scaled by the
depth (:func:`mabdi.camera.pixel_rays`), or a LiDAR pixel's own return where the
frame carries it (:func:`mabdi.camera.at_returns`). The output keeps the input's field
data, and point data ``colour`` when the image carries colour. The image is
first smoothed by the sensor's noise model (``smooth_depth``,
:mod:`mabdi.surfaces.depth_smoothing`).

Why these rules: docs/architecture.md (``mabdi.surfaces.pixel_grid``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics, at_returns, pixel_rays
from mabdi.depth import (
    straight_continuations,
)
from mabdi.errors import ConfigError, check_switch
from mabdi.frame_values import Measured
from mabdi.surfaces.frame_surface import FrameSurface
from mabdi.surfaces.depth_smoothing import measured_around, smooth_depth_by_noise
from mabdi.mesh_maps.mesh_map import colour_point_array
from mabdi.polydata import triangles_polydata
from mabdi.spherical import SphericalGeometry, on_for_range_images


@dataclass(frozen=True)
class PixelGridParameters:
    """Parameters of :class:`FilterPixelGrid`: ``max_jump``, the largest depth spread within a
    triangle as a fraction of its nearest corner's depth (0.01 = 1%; see the module docs);
    ``smooth_depth``, smooth the image by the sensor's noise model before meshing it."""

    max_jump: float = 0.01
    smooth_depth: bool = True
    #: Keep edges that continue a straight line though they fail the jump rule (see the module docs): true,
    #: false, or "auto" (range images only).
    grazing: bool | str = "auto"

    def __post_init__(self) -> None:
        check_switch("grazing", self.grazing)
        if not (isinstance(self.max_jump, (int, float)) and self.max_jump > 0):
            raise ConfigError(f"max_jump must be > 0 (a fraction of the depth), got {self.max_jump!r}")
        if not isinstance(self.smooth_depth, bool):
            raise ConfigError(f"smooth_depth must be true or false, got {self.smooth_depth!r}")


def pixel_grid_triangles(depth: np.ndarray, max_jump, straight: tuple[np.ndarray, ...] | None = None) -> np.ndarray:
    """(M, 3) int64 pixel ids (v * W + u) of the kept triangles of a (H, W) depth image: each of a triangle's
    three edges within ``max_jump`` (a number, or (H - 1,) one for the squares between each row and the next:
    a beam table's rows lie at their own spacings), or (``straight``: the edge masks of
    :func:`mabdi.depth.straight_continuations`, which may come from a wider image than ``depth``: an edge
    counts only between two valid corners of ``depth``) on one straight line with the samples beyond it."""
    height, width = depth.shape
    z = np.asarray(depth, dtype=np.float32)
    jump = np.asarray(max_jump, dtype=np.float64)
    ratio = (1.0 + jump).astype(np.float32)[:, None] if jump.ndim else np.float32(1.0 + jump)

    def within(p, q):
        # NaN compares false, so invalid corners drop out; max <= (1 + jump) * min.
        with np.errstate(invalid="ignore"):
            return np.maximum(p, q) <= ratio * np.minimum(p, q)

    vertical = within(z[:-1, :], z[1:, :])  # (v, u) - (v + 1, u)
    diagonal = within(z[:-1, 1:], z[1:, :-1])  # (v, u + 1) - (v + 1, u)
    # each square's top and bottom edges, judged by the square's own rows' jump (one jump: each edge once)
    if jump.ndim:
        top, bottom = within(z[:-1, :-1], z[:-1, 1:]), within(z[1:, :-1], z[1:, 1:])
    else:
        horizontal = within(z[:, :-1], z[:, 1:])  # (v, u) - (v, u + 1)
        top, bottom = horizontal[:-1], horizontal[1:]
    if straight is not None:
        ok = np.isfinite(z)
        vertical = vertical | (straight[0] & ok[:-1, :] & ok[1:, :])
        across = straight[1] & ok[:, :-1] & ok[:, 1:]
        top, bottom = top | across[:-1], bottom | across[1:]
        diagonal = diagonal | (straight[2] & ok[:-1, 1:] & ok[1:, :-1])
    # square (v, u): a, b, c, d = (v, u), (v, u + 1), (v + 1, u), (v + 1, u + 1)
    keep_first = vertical[:, :-1] & top & diagonal  # (a, c, b)
    keep_second = vertical[:, 1:] & bottom & diagonal  # (b, c, d)
    first = np.flatnonzero(keep_first)
    second = np.flatnonzero(keep_second)
    # square index s = v * (W - 1) + u  ->  top-left pixel id p = v * W + u
    p1 = first + first // (width - 1)
    p2 = second + second // (width - 1)
    triangles = np.empty((len(p1) + len(p2), 3), dtype=np.int64)
    triangles[: len(p1), 0] = p1
    triangles[: len(p1), 1] = p1 + width
    triangles[: len(p1), 2] = p1 + 1
    triangles[len(p1) :, 0] = p2 + 1
    triangles[len(p1) :, 1] = p2 + width
    triangles[len(p1) :, 2] = p2 + width + 1
    return triangles


def _jump_scales(intrinsics):
    """What ``max_jump`` scales by: 1 for a camera; a range image's (:meth:`SphericalGeometry.jump_scale`), or with a
    beam table, each pair of rows' own (their spacing, :meth:`SphericalGeometry.pair_angles`, over a camera's
    pixel angle): (beams - 1,)."""
    if isinstance(intrinsics, SphericalGeometry) and intrinsics.beam_elevations:
        return intrinsics.pair_angles() * Intrinsics.fx
    return intrinsics.jump_scale()


class FilterPixelGrid(FrameSurface):
    """Mesh a depth image's valid pixels as a pixel grid in world coordinates (depth image -> vtkPolyData).

    ``FilterPixelGrid(PixelGridParameters(max_jump=0.01))``; a bare number is taken as ``max_jump``.
    ``smooth_depth`` and ``grazing`` follow the sensor's noise model that the image carries
    (:func:`mabdi.depth.image_noise`).
    """

    def __init__(self, parameters: PixelGridParameters | float | None = None) -> None:
        super().__init__()
        if parameters is None:
            parameters = PixelGridParameters()
        elif not isinstance(parameters, PixelGridParameters):
            parameters = PixelGridParameters(max_jump=float(parameters))
        self._parameters = parameters

    @property
    def parameters(self) -> PixelGridParameters:
        return self._parameters

    @parameters.setter
    def parameters(self, value: PixelGridParameters) -> None:
        if not isinstance(value, PixelGridParameters):
            raise TypeError(f"FilterPixelGrid.parameters must be PixelGridParameters, got {type(value).__name__}")
        self._set("_parameters", value)

    @property
    def max_jump(self) -> float:
        """Largest depth spread within a triangle, as a fraction of its nearest corner's depth."""
        return self._parameters.max_jump

    @max_jump.setter
    def max_jump(self, value: float) -> None:
        self.parameters = replace(self._parameters, max_jump=value)

    def mesh_frame(self, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
        """The pixel grid of ``frame``'s depth (the pixels to mesh; NaN elsewhere), in the world of its pose;
        ``whole``: (H, W) all of D where ``frame`` holds only some of it (the samples beyond an edge), None: the
        frame is all of D."""
        world_points, triangles, pixel_ids = pixel_grid_surface(frame, whole, self._parameters)
        mesh = triangles_polydata(world_points, triangles, dtype=np.float32)
        if frame.colour is not None:  # each vertex is a pixel: its colour
            mesh.GetPointData().AddArray(colour_point_array(frame.colour.reshape(-1, 3)[pixel_ids]))
        return mesh


def pixel_grid_surface(
    frame: Measured, whole: np.ndarray | None, parameters: PixelGridParameters, straight_only: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel grid of a frame's depth (the module docs; ``whole``: all of D behind it, or None): its vertices in the world (N, 3, metres), its
    triangles (M, 3, indices into them) and each vertex's pixel id (N,: v * W + u). ``straight_only``: only
    triangles whose three edges lie on straight lines with the samples beyond them (the straight-line rule,
    whatever ``grazing`` says, without the jump rule, which also admits the chord across a crease)."""
    intrinsics, pose, depth, noise = frame.geometry, frame.pose, frame.depth, frame.noise
    raw = depth
    if parameters.smooth_depth:
        depth = smooth_depth_by_noise(depth, noise, intrinsics)
    rays = pixel_rays(intrinsics)
    wrap = intrinsics.wraps_around  # 360 degrees of azimuth: the last column meets the first
    straight = None
    if straight_only or on_for_range_images(parameters.grazing, intrinsics):
        # the samples beyond an edge come from the whole measured image (the novel pixels' neighbours too)
        context = depth if whole is None else measured_around(depth, whole, noise, intrinsics, parameters.smooth_depth)
        # two columns beyond each side of the seam, so that edges across it have samples beyond them too
        wide = (lambda a: np.concatenate([a[:, -2:], a, a[:, :3]], axis=1)) if wrap else (lambda a: a)
        sigma = noise.sigma(context, intrinsics.near, intrinsics.far)
        straight = straight_continuations(wide(rays) * wide(context)[..., None], wide(sigma))
        if wrap:
            width = depth.shape[1]
            straight = (straight[0][:, 2 : width + 3], straight[1][:, 2 : width + 2], straight[2][:, 2 : width + 2])
    jump = -1.0 if straight_only else parameters.max_jump * _jump_scales(intrinsics)  # -1: no edge within the jump
    if wrap:
        height, width = depth.shape
        triangles = pixel_grid_triangles(np.concatenate([depth, depth[:, :1]], axis=1), jump, straight)
        row, col = np.divmod(triangles, width + 1)
        triangles = row * width + col % width  # column W is column 0 again
    else:
        triangles = pixel_grid_triangles(depth, jump, straight)
    # Keep only the pixels the triangles use, renumbered in order.
    used = np.zeros(depth.size, dtype=bool)
    used[triangles.ravel()] = True
    pixel_ids = np.flatnonzero(used)
    renumber = np.cumsum(used) - 1
    camera_points = rays.reshape(-1, 3)[pixel_ids] * depth.ravel()[pixel_ids, None]
    if frame.return_points is not None:  # a LiDAR's vertex at its pixel's own return
        shift = depth.ravel()[pixel_ids] - raw.ravel()[pixel_ids]
        camera_points = at_returns(camera_points, frame.return_points.reshape(-1, 3)[pixel_ids], shift)
    return camera_points @ pose[:3, :3].T + pose[:3, 3], renumber[triangles], pixel_ids
