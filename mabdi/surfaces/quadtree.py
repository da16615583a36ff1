"""FilterQuadTree: quad-tree meshing of a depth image (seed 002), closed and without bridges.

Depth image in (D, or the classifier's output: only its valid pixels are
meshed; a camera's depth in metres along z, or a LiDAR's range image of
:mod:`mabdi.spherical`), mesh in the world frame out (the image's pose).
The image is first smoothed by the sensor's noise model (``smooth_depth``,
:mod:`mabdi.surfaces.depth_smoothing`), then seed 002's stages:

1. reduce: the NaN-aware median of ``reduction`` x ``reduction`` blocks
   ("auto": 3 for a camera, 1 for a range image);
2. back-project each block to a camera-frame point, and take per-pixel
   normals from the point map (seed eqs. 4-6), facing the sensor;
3. build a mip-map pyramid: four children merge when each is one region,
   their normals agree within ``n_t`` per component (eq. 14) and their
   centroids lie within ``d_t`` of the averaged plane (defaults 0.1 and
   0.02 m; ``noise_merge`` sizes both by the sensor's noise instead);
4. every leaf becomes a face over its pixel block, its corners the rays
   through the block's corners cut with the leaf's plane.

Beyond the seed: no face spans invalid pixels or a depth jump; corners of
neighbouring leaves merge only when their depths (``max_jump``) and normals
(45 degrees) agree; T-vertices close the cracks between leaf sizes;
silhouette corners move in onto the surface; non-planar faces are split.
``grazing`` meshes flat ground a LiDAR sees at grazing incidence.

Output: vtkPolyData of polygons or triangles (``triangles=True``), cell
data ``level`` and ``Normals`` (world frame), the input's field data, and
point data ``colour`` when the image carries colour. Stages 1-3 and finding
the leaves run as numba kernels (:mod:`mabdi.surfaces.quadtree_kernels`).

The reasoning behind each rule: docs/architecture.md (``mabdi.surfaces.quadtree``);
measured figures: docs/benchmarks.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

from mabdi.camera import Intrinsics, at_returns, unit_rays
from mabdi.depth import (
    colours_at,
    straight_continuations,
)
from mabdi.errors import ConfigError, check_switch
from mabdi.frame_values import Measured
from mabdi.surfaces.frame_surface import FrameSurface
from mabdi.sensor_noise import SensorNoise
from mabdi.surfaces.depth_smoothing import measured_around, smooth_depth_by_noise, smoothed_noise_share
from mabdi.mesh_maps.mesh_map import colour_point_array
from mabdi.spherical import SphericalGeometry, on_for_range_images

from mabdi.surfaces import quadtree_kernels as kernels


#: A leaf of one or two pixels a side whose plane misses one of its own or its neighbouring
#: same-surface pixels by more than this many pixel footprints gets no face (it sits on a crease
#: or a corner, where no plane fits).
RESIDUAL_FOOTPRINTS = 0.4
#: A LiDAR's neighbouring beams are on one surface when their ranges differ by no more than a surface
#: seen this far from its normal (degrees) makes: the pixel grid's rule (its 1% at 525 px).
LIDAR_INCIDENCE = 79.0
#: With the grazing rule, a leaf's silhouette and wild-corner tests allow this many times the depth change
#: its own plane makes per pixel, up to this incidence (degrees).
GRAZING_MARGIN = 2.0
MAX_GRAZING_INCIDENCE = 88.0
#: The noise-aware merge test allows this many standard deviations of what the noise makes a pixel's
#: normal and point stray (:func:`merge_allowances`) ...
MERGE_NOISE_K = 1.5
#: ... and children's centroids at least this far (m) from their plane.
MERGE_MIN_DISTANCE = 0.002
#: Corners of leaves whose normals differ by more than 45 degrees are not merged (a crease).
CREASE_COSINE = float(np.cos(np.radians(45.0)))


@dataclass(frozen=True)
class QuadTreeParameters:
    """Parameters of :class:`FilterQuadTree` (see the module docs); lengths in metres."""

    n_t: float = 0.1
    d_t: float = 0.02
    #: Block size of the first stage: an integer, or "auto" (3 for a camera, 1 for a range image: :func:`resolved`).
    reduction: int | str = "auto"
    max_jump: float = 0.05
    planarity: float = 0.002
    #: Smooth the depth image by the sensor's noise model first (:mod:`mabdi.surfaces.depth_smoothing`).
    smooth_depth: bool = True
    #: Flat ground at grazing incidence on a range image (see the module docs): true, false, or "auto"
    #: (range images only; a camera's images keep the jump rule alone).
    grazing: bool | str = "auto"
    #: Merge by what the noise allows (see the module docs): true, false, or "auto" (where the sensor's noise
    #: is correlated across pixels, which smoothing cannot take out: a structured-light or stereo camera).
    noise_merge: bool | str = "auto"
    #: Triangulate every face. Not a config key: in the MABDI loop faces are always triangulated.
    triangles: bool = field(default=False, metadata={"toml": False})

    def __post_init__(self) -> None:
        if self.n_t < 0 or self.d_t <= 0:
            raise ConfigError(f"need n_t >= 0 and d_t > 0 (metres), got n_t={self.n_t}, d_t={self.d_t}")
        if self.reduction != "auto" and (isinstance(self.reduction, bool) or not isinstance(self.reduction, (int, np.integer)) or self.reduction < 1):
            raise ConfigError(f"reduction must be \"auto\" or an integer >= 1, got {self.reduction!r}")
        if self.max_jump <= 0 or self.planarity <= 0:
            raise ConfigError(f"max_jump and planarity must be > 0, got max_jump={self.max_jump}, planarity={self.planarity}")
        if not isinstance(self.smooth_depth, bool):
            raise ConfigError(f"smooth_depth must be true or false, got {self.smooth_depth!r}")
        check_switch("grazing", self.grazing)
        check_switch("noise_merge", self.noise_merge)

    def seam_pixels(self, noisy: bool) -> int:
        """The classifier's rim (pixels) this surface needs to close the seam between a new patch and the map:
        ``reduction`` where the depth is ``noisy``, 1 where it is not. A block needs a valid majority and a
        patch's edge corners move up to half a block in (the silhouette rule), so a new patch can start up to a block
        inside the novel region; with noise the map's edge and the novel region's are ragged too, and only a rim
        of a whole block closes the crack between them (tests/test_classifier.py). Noise-free edges are clean:
        one pixel does. ("auto" unresolved: a camera's 3.)"""
        reduction = CAMERA_REDUCTION if self.reduction == "auto" else self.reduction
        return reduction if noisy else 1


#: The reduction "auto" gives a camera's images (the seed's 3 x 3); a range image's is 1.
CAMERA_REDUCTION = 3


def resolved(p: QuadTreeParameters, geometry) -> QuadTreeParameters:
    """``p`` with ``reduction = "auto"`` made a number for images of ``geometry``: 3 for a camera (the seed's), 1
    for a LiDAR's range image (on a real 64-beam sweep a 3 x 3 block spans 4 degrees of elevation: its faces
    stood in front of the walls, and removal took a fifth of the map)."""
    if p.reduction != "auto":
        return p
    return replace(p, reduction=1 if geometry.range_image else CAMERA_REDUCTION)


# ---------------------------------------------------------------------------
# 1-5: filter and reduce, transform, convert, build and locate (numba kernels: mabdi.surfaces.quadtree_kernels)


@dataclass
class Leaves:
    """The leaf regions: pyramid level, row and column of the block (in blocks of 2**level), plane."""

    level: np.ndarray
    row: np.ndarray
    col: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    regions: int = 0

    @property
    def size(self) -> np.ndarray:
        return 1 << self.level


# ---------------------------------------------------------------------------
# 6: project, with shared vertices, T-vertices and planarity


@dataclass(frozen=True)
class ReducedSpherical:
    """A LiDAR range image's grid after the r x r reduction: block (row, col) covers beams [r row, r row + r)
    and columns [r col, r col + r) of ``geometry`` (what the reduced intrinsics are for a camera)."""

    geometry: SphericalGeometry
    reduction: int
    width: int
    height: int

    @property
    def near(self) -> float:
        return self.geometry.near

    @property
    def far(self) -> float:
        return self.geometry.far

    @property
    def footprint(self) -> float:
        """Radians per reduced pixel (the larger of the azimuth step and the beam spacing, times r)."""
        return self.geometry.pixel_angle() * self.reduction

    def row_footprints(self) -> np.ndarray:
        """(height,) radians per reduced pixel of each reduced row: :attr:`footprint` for every row of a uniform
        image; with a beam table, the widest spacing of the beams its block holds and meets, times r (an uneven
        sensor's dense beams are not judged by its widest gap, :meth:`SphericalGeometry.pair_angles`)."""
        if not self.geometry.beam_elevations or self.geometry.beams < 2:
            return np.full(self.height, self.footprint)
        pairs, r = self.geometry.pair_angles(), self.reduction
        # the pairs that touch rows r row .. r row + r - 1: from the one above the block to the one below it
        spans = [(max(row * r - 1, 0), min(row * r + r, len(pairs))) for row in range(self.height)]
        return np.array([pairs[start:stop].max() * r for start, stop in spans])

    def rays_at(self, u, v) -> np.ndarray:
        """Unit rays at continuous reduced-grid coordinates (block corners at integers)."""
        return self.geometry.rays_at(np.asarray(u, dtype=np.float64) * self.reduction, np.asarray(v, dtype=np.float64) * self.reduction)


#: The grid the quad-tree meshes: a camera's (reduced) intrinsics or a LiDAR's reduced range-image grid.
Grid = Intrinsics | ReducedSpherical


@dataclass(frozen=True)
class SilhouetteEvidence:
    """The image a reduced point map was made from (``depth``: a camera's z or a LiDAR's range per input pixel,
    NaN where invalid, after smoothing) and its noise: where inside a border block a silhouette lies."""

    depth: np.ndarray
    noise: SensorNoise


def _ray(u: np.ndarray, v: np.ndarray, k: Grid) -> np.ndarray:
    """Rays through continuous pixel coordinates (pixel corners at integers): a camera's with z = 1, a LiDAR's
    unit rays (seed 002 §3.2's transform: either way, the depth image's value times the ray is the point)."""
    return k.rays_at(u, v)


def _row_jumps(p: QuadTreeParameters, k: Grid, height: int) -> np.ndarray:
    """(height,) the largest relative depth change between neighbouring pixels of one surface, row by row:
    ``max_jump`` for a camera; for a LiDAR, whose beams lie much further apart, what a surface seen at
    :data:`LIDAR_INCIDENCE` degrees makes between neighbouring (reduced) beams, tan(incidence) times their angle
    (:meth:`ReducedSpherical.row_footprints`). The rules that compare two estimates of one point (corners shared
    by leaves) keep ``max_jump`` as given."""
    if isinstance(k, ReducedSpherical):
        return math.tan(math.radians(LIDAR_INCIDENCE)) * k.row_footprints()
    return np.full(height, p.max_jump)


def _row_angles(k: Grid, height: int) -> np.ndarray:
    """(height,) radians per (reduced) pixel, row by row: a camera's 1 / focal length, a range image's footprints."""
    return k.row_footprints() if isinstance(k, ReducedSpherical) else np.full(height, 1.0 / min(k.fx, k.fy))


def _over_leaf_rows(values: np.ndarray, leaves: Leaves) -> np.ndarray:
    """(L,) the largest of per-row ``values`` (H,) over the rows each leaf covers."""
    if not len(leaves.level):
        return np.zeros(0)
    top = leaves.row * leaves.size
    bottom = np.minimum(top + leaves.size, len(values))
    if np.all(values == values[0]):
        return np.full(len(top), values[0])
    return np.array([values[a:b].max() for a, b in zip(top, bottom)])


def grazing_on(p: QuadTreeParameters, k: Grid | SphericalGeometry) -> bool:
    """Whether the grazing rule applies to an image of ``k``: ``grazing`` true, or "auto" on a range image."""
    return on_for_range_images(p.grazing, k.geometry if isinstance(k, ReducedSpherical) else k)


def _grid_height(k: Grid) -> int:
    return k.height


def _leaf_jump(leaves: Leaves, p: QuadTreeParameters, k: Grid) -> np.ndarray:
    """(L, 1) the relative depth change per pixel each leaf's surface may make (the silhouette and wild-corner
    tests): :func:`_row_jumps` over its rows, and with the grazing rule at least what the leaf's own plane makes at its
    incidence, :data:`GRAZING_MARGIN` tan(incidence) times the pixel's angle (incidence capped at
    :data:`MAX_GRAZING_INCIDENCE` degrees): a plane seen steeply is still one surface."""
    height = _grid_height(k)
    jump = _over_leaf_rows(_row_jumps(p, k, height), leaves)[:, None]
    if not grazing_on(p, k) or not len(leaves.level):
        return jump
    angle = _over_leaf_rows(_row_angles(k, height), leaves)
    distance = np.linalg.norm(leaves.point, axis=1)
    cosine = np.abs(np.einsum("ij,ij->i", leaves.normal, leaves.point)) / np.where(distance > 0, distance, 1.0)
    cosine = np.maximum(cosine, math.cos(math.radians(MAX_GRAZING_INCIDENCE)))
    tangent = np.sqrt(1.0 - cosine**2) / cosine
    widened = np.maximum(jump, (GRAZING_MARGIN * tangent * angle)[:, None])
    return np.where((leaves.level > 0)[:, None], widened, jump)  # a single pixel's normal is no fitted plane


def pyramid(points: np.ndarray, normals: np.ndarray, k: Grid, p: QuadTreeParameters, noise: SensorNoise):
    """Stages 4-5, the merge pyramid and its leaves (:func:`~mabdi.surfaces.quadtree_kernels.pyramid_kernel`),
    with the noise-aware test where :func:`noise_merge_on`."""
    aware = noise_merge_on(p, noise)
    if aware:
        normal_noise, distance_noise = merge_allowances(points, k, noise, p.smooth_depth)
    else:
        normal_noise = distance_noise = np.zeros(points.shape[:2], dtype=np.float32)
    return kernels.pyramid_kernel(points, normals, p.n_t, p.d_t, normal_noise, distance_noise, aware, MERGE_MIN_DISTANCE)


def noise_merge_on(p: QuadTreeParameters, noise: SensorNoise) -> bool:
    """Whether the merge test allows for the noise: ``noise_merge`` true, or "auto" where the noise is correlated."""
    return noise.correlated if p.noise_merge == "auto" else bool(p.noise_merge)


def merge_allowances(points: np.ndarray, k: Grid, noise: SensorNoise, smoothed: bool) -> tuple[np.ndarray, np.ndarray]:
    """(normal, distance) float32 (H, W): how far the noise lets one reduced pixel's normal (per component)
    and point (m, along the normal) stray from a plane through its neighbours, :data:`MERGE_NOISE_K` times
    their standard deviations. A pixel's depth errs by s = sigma(z) (the sensor's model; times
    :func:`~mabdi.surfaces.depth_smoothing.smoothed_noise_share` where the image was smoothed first), its
    normal rests on differences over two pixels either side, s sqrt(2) over a baseline of twice the pixel
    spacing u (z times a reduced pixel's angle): s / (sqrt(2) u) per component. Zero where the model has
    no noise."""
    depth = _depth(points, k)
    depth = np.where(np.isfinite(depth), depth, k.near)  # no pixel there: its allowance is never read
    sigma = np.nan_to_num(noise.sigma(depth, k.near, k.far), nan=0.0)
    if smoothed:
        sigma = sigma * smoothed_noise_share(noise)
    angle = _row_angles(k, depth.shape[0])[:, None]
    spacing = np.maximum(depth * angle, 1e-9)
    normal = MERGE_NOISE_K * sigma / (math.sqrt(2.0) * spacing)
    distance = MERGE_NOISE_K * sigma
    return np.ascontiguousarray(normal, dtype=np.float32), np.ascontiguousarray(distance, dtype=np.float32)


def _depth(points: np.ndarray, k: Grid) -> np.ndarray:
    """What the image holds for sensor-frame points (..., 3): a camera's z, a LiDAR's range."""
    return (k.geometry if isinstance(k, ReducedSpherical) else k).sensor_values(points)


def _on_plane(rays: np.ndarray, normal: np.ndarray, point: np.ndarray, k: Grid) -> np.ndarray:
    """Where the rays meet the planes (normal, point), row by row; the point's depth where the ray grazes."""
    denominator = np.einsum("...i,...i->...", normal, rays)
    numerator = np.einsum("...i,...i->...", normal, point)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = numerator / denominator
    fallback = np.broadcast_to(_depth(point, k), t.shape)
    t = np.where(np.isfinite(t) & (t > 0), t, fallback)
    return rays * t[..., None]


def select(leaves: Leaves, keep: np.ndarray) -> Leaves:
    """The leaves where ``keep`` is true."""
    return Leaves(*(getattr(leaves, name)[keep] for name in ("level", "row", "col", "normal", "point")))


def _on_silhouette(pixel_depth: np.ndarray, corner_u: np.ndarray, corner_v: np.ndarray, depth: np.ndarray, max_jump) -> np.ndarray:
    """Whether a corner's four surrounding pixels (``pixel_depth``, (H, W)) are not all on the leaf's surface
    (valid, within max_jump)."""
    h, w = pixel_depth.shape[:2]
    outside = np.zeros(corner_u.shape, dtype=bool)
    for dv in (-1, 0):
        for du in (-1, 0):
            row, col = corner_v + dv, corner_u + du
            inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
            z = pixel_depth[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
            with np.errstate(invalid="ignore"):
                same = ~inside | (np.abs(z - depth) <= max_jump * depth)
            outside |= ~same
    return outside


def _silhouette_inset(
    leaves: Leaves, k: Grid, p: QuadTreeParameters, fine: SilhouetteEvidence,
    corner_u: np.ndarray, corner_v: np.ndarray, step_u: np.ndarray, step_v: np.ndarray, leaf_depth: np.ndarray,
    reach: np.ndarray,
) -> np.ndarray:
    """How far (reduced pixels) each silhouette corner moves in: to the centre of the first input pixel on the
    leaf's plane (its depth within :func:`plane_allowance` of the plane's along its ray), walking diagonally
    in from the corner's own input pixel (``step_u``/``step_v``: +1 or -1 towards the leaf's centre), at most
    to the block's middle pixel; half a reduced pixel (the middle) where none of those lies on the plane, or
    r is 1. A pixel where the plane's depth is further than ``reach``
    (metres, (L, 1)) from the leaf's own (``leaf_depth``, (L, 1)) does not count: a corner there would fall back to the leaf's depth
    (a plane seen at a grazing angle, steeper than a surface turns within the leaf)."""
    r = p.reduction
    inset = np.full(corner_u.shape, 0.5)
    h, w = fine.depth.shape[:2]
    angle = _over_leaf_rows(_row_angles(k, _grid_height(k)), leaves)[:, None]
    normal, point = leaves.normal[:, None, :], leaves.point[:, None, :]
    for step in reversed(range((r - 1) // 2)):  # the outermost pixel on the plane wins
        col = r * corner_u + np.where(step_u > 0, step, -1 - step)
        row = r * corner_v + np.where(step_v > 0, step, -1 - step)
        inside = (row >= 0) & (row < h) & (col >= 0) & (col < w)
        value = fine.depth[np.clip(row, 0, h - 1), np.clip(col, 0, w - 1)]
        ray = _ray((col + 0.5) / r, (row + 0.5) / r, k)
        with np.errstate(invalid="ignore", divide="ignore"):
            # along the pixel's ray, where the corner would go: a plane seen at a grazing angle passes
            # close (perpendicular) to the surface behind a silhouette while its depth there is far off
            plane_depth = np.einsum("...i,...i->...", normal, point) / np.einsum("...i,...i->...", normal, ray)
            on_plane = inside & (np.abs(value - plane_depth) <= plane_allowance(value, k, fine.noise, angle))
            on_plane &= np.abs(plane_depth - leaf_depth) <= reach
        inset = np.where(on_plane, (step + 0.5) / r, inset)
    return inset


def leaf_corners(
    leaves: Leaves, k: Grid, p: QuadTreeParameters, points: np.ndarray | None = None, fine: SilhouetteEvidence | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The leaves' quad corners: (corner_u, corner_v (L, 4) lattice points, corners (L, 4, 3) sensor frame,
    wild (L, 4): corners the leaf's plane put too far from its depth, put at its depth instead).

    ``points``: the reduced point map (None: no silhouette rule); ``fine``: the image it was reduced from, which
    tells how far into its border block a silhouette lies (None: half a block in)."""
    size = leaves.size
    u0, v0 = leaves.col * size, leaves.row * size
    corner_u = np.stack([u0, u0, u0 + size, u0 + size], axis=1)  # TL, BL, BR, TR (faces the sensor)
    corner_v = np.stack([v0, v0 + size, v0 + size, v0], axis=1)
    ray_u, ray_v = corner_u.astype(float), corner_v.astype(float)
    centre_depth = _depth(leaves.point, k)[:, None]
    jump = _leaf_jump(leaves, p, k)
    # a surface changes depth by at most max_jump per pixel: how far a corner may lie from the leaf's depth
    allowed = jump * centre_depth * (0.71 * size)[:, None]
    if points is not None:
        # On a silhouette the surface ends inside the border pixel: the corner moves in, to the centre of
        # the outermost input pixel on the surface (where the samples are), instead of hanging past it.
        rim = _on_silhouette(_depth(points, k), corner_u, corner_v, centre_depth, jump)
        step_u = np.sign(((leaves.col + 0.5) * size)[:, None] - ray_u)
        step_v = np.sign(((leaves.row + 0.5) * size)[:, None] - ray_v)
        if fine is None:
            inset = 0.5
        else:
            inset = _silhouette_inset(leaves, k, p, fine, corner_u, corner_v, step_u, step_v, centre_depth, allowed)
            sliver = (size == 1) & rim.all(axis=1)
            inset = np.where(sliver[:, None], 0.5, inset)
        ray_u = np.where(rim, ray_u + inset * step_u, ray_u)
        ray_v = np.where(rim, ray_v + inset * step_v, ray_v)
    corner_rays = _ray(ray_u, ray_v, k)
    corners = _on_plane(corner_rays, leaves.normal[:, None, :], leaves.point[:, None, :], k)
    # A single pixel's one-sided normal (beside an edge or a hole) is no plane to extrapolate: its
    # corners sit at its own depth, and shared corners average the pixels around them. Any
    # plane seen at a grazing angle can still put a corner far away; a surface changes depth by
    # at most max_jump per pixel, so a corner further than max_jump * z * 0.71 * size (its
    # distance from the centre in pixels) from the leaf's depth falls back the same way.
    with np.errstate(invalid="ignore"):
        misses = np.einsum("...i,...i->...", leaves.normal[:, None, :], corner_rays) * np.einsum("...i,...i->...", leaves.normal, leaves.point)[:, None] <= 0
    wild = (np.abs(_depth(corners, k) - centre_depth) > allowed) | misses  # (a ray that misses the plane: at its depth too)
    corners[wild] = corner_rays[wild] * np.broadcast_to(centre_depth, wild.shape)[wild][:, None]
    return corner_u, corner_v, corners, wild


def quad_mesh(
    leaves: Leaves, k: Grid, p: QuadTreeParameters, points: np.ndarray | None = None, fine: SilhouetteEvidence | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Faces of the leaves: (vertices (V, 3) camera frame, offsets, connectivity, face leaf index, face normals).
    ``points`` and ``fine``: as :func:`leaf_corners` takes them."""
    count = len(leaves.level)
    corner_u, corner_v, corners, _ = leaf_corners(leaves, k, p, points, fine)
    # one vertex per lattice point and depth cluster
    stride = int(max(k.width, k.height)) * 2 + 4
    keys = (corner_v * stride + corner_u).ravel()
    depth = _depth(corners, k).ravel()
    corner_normal = np.repeat(leaves.normal, 4, axis=0)
    order = np.lexsort((depth, keys))
    sorted_keys, sorted_depth, sorted_normal = keys[order], depth[order], corner_normal[order]
    new = np.ones(len(order), dtype=bool)
    # a new vertex where the lattice point changes, the depth jumps, or the surface folds (a crease)
    new[1:] = (
        (sorted_keys[1:] != sorted_keys[:-1])
        | (sorted_depth[1:] > sorted_depth[:-1] * (1.0 + p.max_jump))
        | (np.einsum("ij,ij->i", sorted_normal[1:], sorted_normal[:-1]) < CREASE_COSINE)
    )
    vertex_of_sorted = np.cumsum(new) - 1
    corner_vertex = np.empty(len(order), dtype=np.int64)
    corner_vertex[order] = vertex_of_sorted
    corner_vertex = corner_vertex.reshape(count, 4)
    n_vertices = int(vertex_of_sorted[-1]) + 1 if len(order) else 0
    flat_vertex = corner_vertex.ravel()
    flat_corners = corners.reshape(-1, 3)
    uses = np.bincount(flat_vertex, minlength=n_vertices)
    vertices = np.stack([np.bincount(flat_vertex, flat_corners[:, a], minlength=n_vertices) for a in range(3)], axis=1)
    vertices /= uses[:, None]
    vertex_key = sorted_keys[new]
    # entries are sorted by vertex, depth ascending: a vertex's deepest entry is its last
    vertex_depth = sorted_depth[np.flatnonzero(np.append(new[1:], True))]
    vertex_normal = sorted_normal[new]

    # T-vertices: lattice points inside the edges of bigger leaves, snapped onto them (big leaves first)
    extra_leaf, extra_param, extra_vertex = [], [], []
    for level in sorted(set(leaves.level.tolist()), reverse=True):
        if level == 0:
            continue
        hosts = np.flatnonzero(leaves.level == level)
        s = 1 << level
        steps = np.arange(1, s)
        # edges in perimeter order: left (TL->BL), bottom (BL->BR), right (BR->TR), top (TR->TL)
        for edge, (start, end) in enumerate(((0, 1), (1, 2), (2, 3), (3, 0))):
            su, sv = corner_u[hosts, start][:, None], corner_v[hosts, start][:, None]
            eu, ev = corner_u[hosts, end][:, None], corner_v[hosts, end][:, None]
            pu = su + (eu - su) // s * steps
            pv = sv + (ev - sv) // s * steps
            key = (pv * stride + pu).ravel()
            lo = np.searchsorted(vertex_key, key, side="left")
            hi = np.searchsorted(vertex_key, key, side="right")
            host = np.repeat(hosts, s - 1)
            fraction = np.tile(steps / s, len(hosts))
            expected = _depth(_on_plane(_ray(pu.ravel().astype(float), pv.ravel().astype(float), k), leaves.normal[host], leaves.point[host], k), k)
            chosen = np.full(len(key), -1)
            for m in range(int((hi - lo).max()) if len(key) else 0):
                candidate = lo + m
                ok = (candidate < hi) & (chosen < 0)
                candidate = np.where(ok, candidate, 0)
                close = (np.abs(vertex_depth[candidate] - expected) <= p.max_jump * expected) & (
                    np.einsum("ij,ij->i", vertex_normal[candidate], leaves.normal[host]) >= CREASE_COSINE
                )
                chosen = np.where(ok & close, candidate, chosen)
            found = chosen >= 0
            if not found.any():
                continue
            a = vertices[corner_vertex[host[found], start]]
            b = vertices[corner_vertex[host[found], end]]
            f = fraction[found][:, None]
            vertices[chosen[found]] = a + (b - a) * f
            extra_leaf.append(host[found])
            extra_param.append(edge * 4096.0 + fraction[found])
            extra_vertex.append(chosen[found])

    # polygons: corners at perimeter positions 0, 1, 2, 3 (x 4096) plus the T-vertices between them
    leaf_ids = np.concatenate([np.repeat(np.arange(count), 4), *extra_leaf])
    params = np.concatenate([np.tile(np.arange(4) * 4096.0, count), *extra_param])
    members = np.concatenate([corner_vertex.ravel(), *extra_vertex])
    order = np.lexsort((params, leaf_ids))
    leaf_ids, members = leaf_ids[order], members[order]
    sizes = np.bincount(leaf_ids, minlength=count)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    return vertices, starts, members, np.arange(count), sizes


def _faces(vertices, starts, members, sizes, leaves: Leaves, k: Grid, p: QuadTreeParameters):
    """Polygons, split where not planar (or always with ``triangles``): (offsets, connectivity, leaf per face, vertices)."""
    count = len(sizes)
    # planarity: largest distance of a face's vertices from its leaf's plane
    owner = np.repeat(np.arange(count), sizes)
    offset_from_plane = np.abs(np.einsum("ij,ij->i", vertices[members] - leaves.point[owner], leaves.normal[owner]))
    worst = np.zeros(count)
    np.maximum.at(worst, owner, offset_from_plane)
    tolerance = np.maximum(0.001, p.planarity * _depth(leaves.point, k))
    planar = worst <= tolerance
    keep = planar & ~p.triangles
    quad = (sizes == 4) & ~keep
    fan = (sizes > 4) & ~keep
    out_offsets, out_members, out_leaf = [], [], []
    kept = np.flatnonzero(keep)
    if len(kept):
        out_members.append(_gather(members, starts, kept))
        out_offsets.append(sizes[kept])
        out_leaf.append(kept)
    quads = np.flatnonzero(quad)
    if len(quads):
        q = members[starts[quads][:, None] + np.arange(4)]
        d02 = np.linalg.norm(vertices[q[:, 0]] - vertices[q[:, 2]], axis=1)
        d13 = np.linalg.norm(vertices[q[:, 1]] - vertices[q[:, 3]], axis=1)
        short02 = d02 <= d13
        first = np.where(short02[:, None], q[:, [0, 1, 2]], q[:, [0, 1, 3]])
        second = np.where(short02[:, None], q[:, [0, 2, 3]], q[:, [1, 2, 3]])
        out_members.append(np.stack([first, second], axis=1).ravel())
        out_offsets.append(np.full(2 * len(quads), 3))
        out_leaf.append(np.repeat(quads, 2))
    fans = np.flatnonzero(fan)
    if len(fans):
        centre_u = (leaves.col[fans] + 0.5) * leaves.size[fans]
        centre_v = (leaves.row[fans] + 0.5) * leaves.size[fans]
        centres = _on_plane(_ray(centre_u, centre_v, k), leaves.normal[fans], leaves.point[fans], k)
        centre_ids = len(vertices) + np.arange(len(fans))
        vertices = np.concatenate([vertices, centres])
        ring_sizes = sizes[fans]
        ring = _gather(members, starts, fans)
        ring_owner = np.repeat(np.arange(len(fans)), ring_sizes)
        ring_start = np.concatenate([[0], np.cumsum(ring_sizes)])[:-1]
        position = np.arange(len(ring)) - ring_start[ring_owner]
        following = ring[ring_start[ring_owner] + (position + 1) % ring_sizes[ring_owner]]
        out_members.append(np.stack([centre_ids[ring_owner], ring, following], axis=1).ravel())
        out_offsets.append(np.full(len(ring), 3))
        out_leaf.append(fans[ring_owner])
    if not out_members:
        return np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), vertices
    sizes_out, members_out, leaf_out = np.concatenate(out_offsets), np.concatenate(out_members), np.concatenate(out_leaf)
    # A single pixel on a silhouette on two sides has corners moved to its middle, onto the same line: its
    # triangles have no area. Nothing shows them or can see through them; they go.
    starts_out = np.concatenate([[0], np.cumsum(sizes_out)])[:-1]
    triangle = np.flatnonzero(sizes_out == 3)
    corners = vertices[members_out[starts_out[triangle][:, None] + np.arange(3)]]
    doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
    flat = triangle[doubled <= 1e-9 * longest**2]
    if len(flat):
        keep = np.ones(len(sizes_out), dtype=bool)
        keep[flat] = False
        members_out = members_out[np.repeat(keep, sizes_out)]
        sizes_out, leaf_out = sizes_out[keep], leaf_out[keep]
    return np.concatenate([[0], np.cumsum(sizes_out)]), members_out, leaf_out, vertices


def _gather(members: np.ndarray, starts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The members of ``faces`` (ranges of ``members``), concatenated in order."""
    sizes = starts[faces + 1] - starts[faces]
    first = np.concatenate([[0], np.cumsum(sizes)])[:-1]
    index = np.repeat(starts[faces] - first, sizes) + np.arange(sizes.sum())
    return members[index]


def leaves_of_image(
    depth: np.ndarray,
    intrinsics: Intrinsics | SphericalGeometry,
    p: QuadTreeParameters,
    noise: SensorNoise,
    measured: np.ndarray | None = None,
    return_points: np.ndarray | None = None,
) -> tuple[np.ndarray, Grid, Leaves, np.ndarray]:
    """Smoothing, stages 1-5 and the small-leaf plane test: (reduced points, reduced grid, kept leaves, the
    smoothed image they were reduced from).

    ``measured``: the whole measured image behind ``depth`` (which may hold only the novel pixels), where the
    grazing rule finds the pixels beyond an edge; None: ``depth`` itself. ``return_points``: a LiDAR's own
    returns (:func:`mabdi.camera.at_returns`), its pixels' points where the image is not reduced.

    Stages 1-5 and the plane test are the numba kernels of :mod:`mabdi.surfaces.quadtree_kernels`.
    The leaves carry ``regions``, the pyramid root's region count. A LiDAR's range image
    (``intrinsics`` a :class:`~mabdi.spherical.SphericalGeometry`) goes through :func:`_range_leaves`.
    """
    p = resolved(p, intrinsics)
    if not grazing_on(p, intrinsics):
        measured = None  # only the grazing rule looks beyond the pixels it meshes
    raw = depth
    if p.smooth_depth:
        depth = smooth_depth_by_noise(depth, noise, intrinsics)
    if measured is not None:
        measured = measured_around(depth, measured, noise, intrinsics, p.smooth_depth)
    if intrinsics.range_image:
        returns = None
        if return_points is not None and p.reduction == 1:  # each pixel's point and its shift by smoothing
            returns = (return_points, depth - raw)
        return (*_range_leaves(depth, intrinsics, p, noise, measured, returns), depth)
    k = intrinsics
    r = p.reduction

    def back_projected(image):
        if r > 1:
            return kernels.reduce_points_kernel(np.ascontiguousarray(image, dtype=np.float64), r, k.fx, k.fy, k.cx, k.cy)
        return k.rays() * np.asarray(image, dtype=np.float64)[..., None]  # every pixel through its centre

    points = np.ascontiguousarray(back_projected(depth))
    h, w = points.shape[:2]
    reduced = Intrinsics(k.fx / r, k.fy / r, k.cx / r, k.cy / r, w, h, k.near, k.far) if r > 1 else k
    grazing = grazing_on(p, reduced)
    if grazing:
        z = np.ascontiguousarray(points[:, :, 2])
        around = points if measured is None else np.ascontiguousarray(back_projected(measured))
        right, down = straight_neighbours(around, around[:, :, 2], noise, reduced, z)
        normals = kernels.point_normals_depth_kernel(points, z, np.full(h, p.max_jump), right, down)
    else:
        normals = kernels.point_normals_kernel(points, p.max_jump)
    level, row, col, normal, point, regions = pyramid(points, normals, reduced, p, noise)
    leaves = Leaves(level, row, col, normal, point)
    residual = kernels.plane_residual_kernel(points, level, row, col, normal, point, p.max_jump, 2)
    leaves = fitting_leaves(leaves, residual, reduced, noise)
    if grazing:
        leaves = fitted_planes(leaves, points)
    leaves.regions = regions
    return points, reduced, leaves, depth


#: A LiDAR pixel's normal reaches along its row for at most this many columns (:func:`normal_column_step`).
MAX_NORMAL_COLUMN_STEP = 8


def normal_column_step(geometry: SphericalGeometry) -> int:
    """How many columns along a row a LiDAR pixel's normal reaches each way: its beams' median spacing over
    the azimuth step (at most :data:`MAX_NORMAL_COLUMN_STEP`), so that the row's points span about the angle
    that the rows above and below do (docs/architecture.md, "Meshed at the returns themselves")."""
    azimuth = 2.0 * math.pi / geometry.columns
    pairs = geometry.pair_angles() if geometry.beams > 1 else np.array([azimuth])
    return int(np.clip(round(float(np.median(pairs)) / azimuth), 1, MAX_NORMAL_COLUMN_STEP))


def _range_leaves(
    ranges: np.ndarray,
    geometry: SphericalGeometry,
    p: QuadTreeParameters,
    noise: SensorNoise,
    measured: np.ndarray | None = None,
    returns: tuple | None = None,
) -> tuple[np.ndarray, Grid, Leaves]:
    """Stages 1-5 and the plane test on a LiDAR's range image: seed 002 §3.2's transform (every beam block to a
    sensor-frame point: its median range times its unit ray, so a straight wall is flat again), §3.3's normals
    from the point map's differences, with the depth tests on range instead of z. ``returns``: (the pixels'
    own returns, the shift of ``ranges`` by smoothing), unreduced images only: the tests read the range image
    (its ranges along the pixel centres' rays), and every leaf's plane is then fitted to its own returns."""
    r = p.reduction
    rays = unit_rays(geometry)[0]

    def back_projected(image):
        if r > 1:
            return kernels.reduce_ranges_kernel(np.ascontiguousarray(image, dtype=np.float64), r, rays)
        return rays * np.asarray(image, dtype=np.float64)[..., None]

    points = back_projected(ranges)
    reduced = ReducedSpherical(geometry, r, points.shape[1], points.shape[0])
    depth = np.ascontiguousarray(_depth(points, reduced))
    jump = _row_jumps(p, reduced, points.shape[0])
    points = np.ascontiguousarray(points)
    grazing = grazing_on(p, reduced)
    if grazing:
        around = points if measured is None else np.ascontiguousarray(back_projected(measured))
        right, down = straight_neighbours(around, _depth(around, reduced), noise, reduced, depth)
    else:
        right = down = np.zeros(depth.shape, dtype=bool)
    # each pixel's normal from where its neighbours' returns were measured, not their centres' rays
    measured_points = points if returns is None else np.ascontiguousarray(at_returns(points, *returns))
    normals = kernels.point_normals_depth_kernel(measured_points, depth, jump, right, down, normal_column_step(geometry))
    level, row, col, normal, point, regions = pyramid(points, normals, reduced, p, noise)
    leaves = Leaves(level, row, col, normal, point)
    residual = kernels.plane_residual_depth_kernel(points, depth, level, row, col, normal, point, _depth(point, reduced), jump, 2)
    leaves = fitting_leaves(leaves, residual, reduced, noise)
    if returns is not None:
        leaves = on_returns(leaves, measured_points)
    elif grazing:
        leaves = fitted_planes(leaves, points)
    leaves.regions = regions
    return points, reduced, leaves


def on_returns(leaves: Leaves, returns: np.ndarray) -> Leaves:
    """The leaves placed on a LiDAR's own returns (H, W, 3, sensor frame, m; :func:`mabdi.camera.at_returns`):
    a one-pixel leaf's point is its pixel's return, a larger leaf takes the plane fitted to its returns
    (:func:`fitted_planes`); normals of one-pixel leaves are kept."""
    leaves = fitted_planes(leaves, returns)
    single = np.flatnonzero(leaves.level == 0)
    point = leaves.point.copy()
    own = returns[leaves.row[single], leaves.col[single]]
    point[single] = np.where(np.isfinite(own).all(axis=1)[:, None], own, point[single])
    return Leaves(leaves.level, leaves.row, leaves.col, leaves.normal, point, leaves.regions)


def fitted_planes(leaves: Leaves, points: np.ndarray) -> Leaves:
    """The leaves of two or more pixels a side with the least-squares plane of their own points (centroid and
    the covariance's smallest eigenvector, facing the sensor) instead of the pyramid's averaged normal. With
    the grazing rule a leaf may stretch metres along a surface seen nearly edge-on, where each pixel's normal
    comes from neighbours a beam apart; the fitted plane is what keeps its far corners on the surface."""
    height, width = points.shape[:2]
    normal, point = leaves.normal.copy(), leaves.point.copy()
    for level in np.unique(leaves.level):
        if level == 0:
            continue
        which = np.flatnonzero(leaves.level == level)
        side = 1 << int(level)
        rows = leaves.row[which, None] * side + np.arange(side)
        cols = leaves.col[which, None] * side + np.arange(side)
        inside = (rows[:, :, None] < height) & (cols[:, None, :] < width)
        block = points[np.minimum(rows, height - 1)[:, :, None], np.minimum(cols, width - 1)[:, None, :]].reshape(len(which), -1, 3)
        valid = (inside.reshape(len(which), -1) & np.isfinite(block).all(axis=2))[:, :, None]
        count = valid.sum(axis=1)
        fit = count[:, 0] >= 3
        centroid = np.where(valid, block, 0.0).sum(axis=1) / np.maximum(count, 1)
        offset = np.where(valid, block - centroid[:, None, :], 0.0)
        covariance = np.einsum("lpi,lpj->lij", offset, offset)
        _, vectors = np.linalg.eigh(covariance[fit])
        fitted = vectors[:, :, 0]
        fitted *= np.where(np.einsum("li,li->l", fitted, centroid[fit]) > 0, -1.0, 1.0)[:, None]  # facing the sensor
        normal[which[fit]] = fitted
        point[which[fit]] = centroid[fit]
    return Leaves(leaves.level, leaves.row, leaves.col, normal, point, leaves.regions)


def straight_neighbours(
    points: np.ndarray, depth: np.ndarray, noise: SensorNoise, k: Grid, meshed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(right, down) (H, W) bool: whether pixels (i, j) and (i, j + 1), and (i, j) and (i + 1, j), lie on one straight
    line with the pixels beyond them (:func:`mabdi.depth.straight_continuations`, within the noise of
    ``depth``: the image's z or range): one flat surface however steeply it is seen. ``meshed`` (H, W): the depth
    of the pixels being meshed when ``points`` is the whole measured image; a pair counts only where both hold one."""
    sigma = noise.sigma(depth, k.near, k.far)
    vertical, horizontal, _ = straight_continuations(points, np.nan_to_num(sigma, nan=0.0))
    right = np.zeros(depth.shape, dtype=bool)
    down = np.zeros(depth.shape, dtype=bool)
    right[:, :-1] = horizontal
    down[:-1, :] = vertical
    if meshed is not None:
        ok = np.isfinite(meshed)
        right[:, :-1] &= ok[:, :-1] & ok[:, 1:]
        down[:-1, :] &= ok[:-1, :] & ok[1:, :]
    return right, down


def fitting_leaves(leaves: Leaves, residual: np.ndarray, reduced: Grid, noise: SensorNoise) -> Leaves:
    """The leaves whose plane fits their own and their neighbouring same-surface pixels: a small leaf whose
    plane misses one by more than :data:`RESIDUAL_FOOTPRINTS` pixel footprints and 3 sigma of the noise
    (``residual``, metres) sits on a crease or a corner and gets no face."""
    angle = _over_leaf_rows(_row_angles(reduced, _grid_height(reduced)), leaves)
    return select(leaves, residual <= plane_allowance(_depth(leaves.point, reduced), reduced, noise, angle))


def plane_allowance(depth: np.ndarray, reduced: Grid, noise: SensorNoise, angle=None) -> np.ndarray:
    """How far (metres) a pixel at ``depth`` may lie from a leaf's plane and still be on it: the larger of
    :data:`RESIDUAL_FOOTPRINTS` reduced pixel footprints and 3 sigma(z) of the noise. ``angle``: a range image's
    radians per reduced pixel where it differs by row (broadcast with ``depth``); None: its :attr:`footprint`."""
    if isinstance(reduced, ReducedSpherical):
        footprint = depth * (reduced.footprint if angle is None else angle)
    else:
        footprint = depth / reduced.fx
    return np.maximum(RESIDUAL_FOOTPRINTS * footprint, 3.0 * noise.sigma(depth, reduced.near, reduced.far))


class FilterQuadTree(FrameSurface):
    """Quad-tree mesh of a depth image's valid pixels (depth image -> vtkPolyData), see the module docs.

    The small-leaf plane test allows 3 sigma(z) of the sensor's noise model, the one the image carries
    (:func:`mabdi.depth.image_noise`).
    """

    def __init__(self, parameters: QuadTreeParameters | None = None) -> None:
        super().__init__()
        self._parameters = parameters if parameters is not None else QuadTreeParameters()
        #: Region count of the last image (the pyramid root's, seed invariant 1).
        self.regions = 0

    @property
    def parameters(self) -> QuadTreeParameters:
        return self._parameters

    @parameters.setter
    def parameters(self, value: QuadTreeParameters) -> None:
        self._set("_parameters", value)

    def mesh_frame(self, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
        """The quad-tree faces of ``frame``'s depth (the pixels to mesh; NaN elsewhere), in the world of its pose
        (cell data ``level``, ``Normals``); ``whole``: (H, W) all of D where ``frame`` holds only some of it,
        None: the frame is all of D. Sets :attr:`regions`."""
        intrinsics, pose, noise = frame.geometry, frame.pose, frame.noise
        p = resolved(self._parameters, intrinsics)
        points, reduced, leaves, smoothed = leaves_of_image(frame.depth, intrinsics, p, noise, whole, frame.return_points)
        fine = SilhouetteEvidence(smoothed, noise)
        self.regions = leaves.regions
        if isinstance(reduced, ReducedSpherical) and len(leaves.level):
            # a LiDAR's beams lie far apart: a leaf whose plane puts a corner far from its range is a surface
            # seen edge-on between two beams, and its corners at its own range would float off it: no face
            leaves = select(leaves, ~leaf_corners(leaves, reduced, p, points, fine)[3].any(axis=1))
        mesh = vtkPolyData()
        if len(leaves.level):
            vertices, starts, members, _, sizes = quad_mesh(leaves, reduced, p, points, fine)
            offsets, connectivity, face_leaf, vertices = _faces(vertices, starts, members, sizes, leaves, reduced, p)
            world = vertices @ pose[:3, :3].T + pose[:3, 3]
            vtk_points = vtkPoints()
            vtk_points.SetData(numpy_to_vtk(np.ascontiguousarray(world, dtype=np.float32), deep=True))
            mesh.SetPoints(vtk_points)
            cells = vtkCellArray()
            cells.SetData(numpy_to_vtkIdTypeArray(offsets.astype(np.int64), deep=True), numpy_to_vtkIdTypeArray(connectivity.astype(np.int64), deep=True))
            mesh.SetPolys(cells)
            level = numpy_to_vtk((leaves.size[face_leaf] * p.reduction).astype(np.int32), deep=True)
            level.SetName("level")
            mesh.GetCellData().AddArray(level)
            normals_world = numpy_to_vtk(np.ascontiguousarray(leaves.normal[face_leaf] @ pose[:3, :3].T, dtype=np.float32), deep=True)
            normals_world.SetName("Normals")
            mesh.GetCellData().SetNormals(normals_world)
            if frame.colour is not None:  # each vertex: the colour of the pixel it projects into
                mesh.GetPointData().AddArray(colour_point_array(colours_at(frame.colour, intrinsics, vertices)))
        return mesh

