"""FilterVoxelPlanes: incremental voxel-plane meshing of points (seed 000), ``voxel_planes`` in configs.

Points in (a depth image's valid pixels back-projected with its pose, or a
vtkPolyData of world points; metres, world frame), a mesh of small planar
polygons out. The filter keeps a :class:`~mabdi.voxels.voxel_map.VoxelMap`
across updates:

1. every point is added to its voxel's statistics;
2. every grid vertex is the centre of a ``window``^3 neighbourhood whose
   Gaussians combine by eqs. (2)-(3); it is planar when it holds at least
   ``min_points`` points and its eigenvalues pass l1 > lambda_large and
   l2 < epsilon^2 (epsilon the point noise, 0.02 m by default);
3. the plane is cut with the voxel-sized cube around the vertex (eq. 4),
   and the 3-6 points make a convex polygon;
4. only the blocks whose neighbourhoods changed are re-meshed; the output
   is the changed patches (``output="changed"``) or the whole map;
5. with colour input, each vertex takes the mean colour of its voxel.

For range images ``between_beams`` adds samples of the pixel grid between
a LiDAR's rings (across gaps up to ``max_bridge``), and ``refine``
meshes creases at half the voxel size.

Output cell data: ``Normals``, ``rgb`` (seed 000 eqs. 5-7) and
``patch_key``; point data ``rgb_colors`` with colour input; a depth
image's field data is passed on.

The reasoning behind the thresholds and options: docs/architecture.md
(``mabdi.surfaces.voxel_planes``).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkImageData, vtkPointSet, vtkPolyData

from mabdi.algorithm import MabdiAlgorithm
from mabdi.camera import at_returns, pixel_rays
from mabdi.depth import COLOUR_ARRAY, FRAME_ARRAY, measured_depth
from mabdi.frame_values import Measured
from mabdi.errors import ConfigError, check_switch
from mabdi.voxels.voxel_map import VoxelMap, moments_to_gaussian, pack_keys, unpack_keys
from mabdi.world_map import PATCH_KEY_ARRAY, REMOVED_KEYS_ARRAY
from mabdi.mesh_maps.colours import colours_by_normal
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER, colour_point_array
from mabdi.polydata import triangles_polydata
from mabdi.surfaces.pixel_grid import PixelGridParameters, pixel_grid_surface
from mabdi.spherical import BEAM_ELEVATIONS_ARRAY, SPHERICAL_ARRAY, on_for_range_images

OUTPUTS = ("changed", "full")
#: Voxels on a side that a patch of the output spans at least (2 m of 5 cm voxels; docs/architecture.md).
PATCH_VOXELS = 40
#: The least share of its window a plane's points must span along each in-plane axis (their variance at least
#: (MIN_SPAN * window * voxel_size)^2 / 12: a uniform strip that wide); module docs, and docs/architecture.md.
MIN_SPAN = 0.5
#: The colour of a polygon whose voxels hold no coloured point (in a map that has colour: points added without it).
NO_COLOUR = (128, 128, 128)

# The cube's 8 corners (unit offsets in {-1, 1}) and its 12 edges as corner pairs.
_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
_EDGES = np.array(
    [(a, b) for a in range(8) for b in range(a + 1, 8) if np.abs(_CORNERS[a] - _CORNERS[b]).sum() == 2]
)


@dataclass(frozen=True)
class VoxelPlanesParameters:
    """Parameters of :class:`FilterVoxelPlanes` (see the module docs); lengths in metres."""

    voxel_size: float = 0.05
    epsilon: float = 0.02
    window: int = 2
    min_points: int = 10
    block_size: float = 1.0
    #: Add points on the surface between neighbouring samples more than half a voxel apart (see the module
    #: docs, "Between beams"): true, false, or "auto" (range images only).
    between_beams: bool | str = "auto"
    #: The widest gap (m) between neighbouring samples that ``between_beams`` fills: pixel-grid triangles with
    #: a longer edge are not sampled (docs/architecture.md, "Between beams"); "none" (the default): every gap.
    max_bridge: float | str = "none"
    #: Fill the cubes of neighbourhoods that are not planar (a crease: a wall's foot) from windows of half-size
    #: voxels (see the module docs, "Creases"): true, false, or "auto" (where half-size windows still tell a
    #: plane from a crease by the same test, :attr:`refines`).
    refine: bool | str = "auto"

    def __post_init__(self) -> None:
        check_switch("between_beams", self.between_beams)
        check_switch("refine", self.refine)
        if self.max_bridge != "none" and (
            isinstance(self.max_bridge, bool) or not isinstance(self.max_bridge, (int, float)) or not self.max_bridge > 0
        ):
            raise ConfigError(f'max_bridge must be a length > 0 (metres) or "none" (every gap), got {self.max_bridge!r}')
        if not self.voxel_size > 0 or not self.epsilon > 0:
            raise ConfigError(
                f"need voxel_size > 0 and epsilon > 0 (metres), got voxel_size={self.voxel_size}, epsilon={self.epsilon}"
            )
        if not isinstance(self.window, (int, np.integer)) or not 1 <= self.window <= 6:
            raise ConfigError(f"window must be an integer from 1 to 6, got {self.window!r}")
        if not isinstance(self.min_points, (int, np.integer)) or self.min_points < 3:
            raise ConfigError(f"min_points must be an integer >= 3, got {self.min_points!r}")

    @property
    def lambda_small(self) -> float:
        """Largest variance across the plane (m^2): epsilon^2, the seed's lambda_t."""
        return self.epsilon**2

    @property
    def lambda_large(self) -> float:
        """Smallest variance along the plane (m^2): min(epsilon^2, (MIN_SPAN * window * voxel_size)^2 / 12)."""
        return min(self.epsilon**2, span_variance(self.window * self.voxel_size))

    @property
    def refines(self) -> bool:
        """Whether creases are filled from half-size voxels: ``refine`` true, or "auto" and a half-size window
        spans enough for the planarity test to hold as it is (its lambda_large still epsilon^2)."""
        if self.refine == "auto":
            return span_variance(self.window * self.voxel_size / 2.0) >= self.epsilon**2
        return bool(self.refine)

    @property
    def bridge(self) -> float:
        """The widest gap (m) between-beams samples fill: ``max_bridge``, infinite for "none"."""
        return math.inf if self.max_bridge == "none" else float(self.max_bridge)

    def halved(self) -> VoxelPlanesParameters:
        """The same parameters at half the voxel size (the refinement's)."""
        return dataclasses.replace(self, voxel_size=self.voxel_size / 2.0, refine=False)


def span_variance(width: float) -> float:
    """The variance (m^2) along an axis of points spread uniformly over :data:`MIN_SPAN` of ``width`` (m)."""
    return (MIN_SPAN * width) ** 2 / 12.0


@dataclass
class PlanePatches:
    """Planar neighbourhoods: anchor index (vertex, or centre voxel for odd windows), plane and cube."""

    anchors: np.ndarray  # (M, 3) int64
    normals: np.ndarray  # (M, 3) unit, n_z >= 0
    centroids: np.ndarray  # (M, 3) world
    centres: np.ndarray  # (M, 3) world centre of each neighbourhood's cube
    counts: np.ndarray  # (M,) points in the neighbourhood
    #: (K, 3) int64: anchors whose neighbourhood holds ``min_points`` but is not planar (a crease, a corner)
    unresolved: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))


def anchor_range(window: int) -> int:
    """Offset of a neighbourhood's lowest voxel from its anchor: -(window // 2)."""
    return -(window // 2)


def plane_patches(voxels: VoxelMap, anchors: np.ndarray, parameters: VoxelPlanesParameters) -> PlanePatches:
    """The planar neighbourhoods among ``anchors`` (eqs. 2-3, batched PCA, the eigenvalue test)."""
    w = parameters.window
    s = voxels.voxel_size
    anchors = np.asarray(anchors, dtype=np.int64).reshape(-1, 3)
    lowest = anchors + anchor_range(w)
    n, mean, cov = moments_to_gaussian(voxels.neighbourhood_moments(lowest, w))
    enough = n >= parameters.min_points
    values, vectors = np.linalg.eigh(cov[enough]) if enough.any() else (np.zeros((0, 3)), np.zeros((0, 3, 3)))
    # eigh sorts ascending: values[:, 0] = l2 (smallest), values[:, 1] = l1
    planar = (values[:, 0] < parameters.lambda_small) & (values[:, 1] > parameters.lambda_large)
    keep = np.flatnonzero(enough)[planar]
    normals = vectors[planar, :, 0]
    normals = np.where(normals[:, 2:3] < 0, -normals, normals)
    centroids = mean[keep] + lowest[keep] * s
    centres = (anchors[keep] + 0.5 * (w % 2)) * s
    unresolved = anchors[np.flatnonzero(enough)[~planar]]
    return PlanePatches(anchors[keep], normals, centroids, centres, n[keep].astype(np.int64), unresolved)


def longest_edges(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(M,) the longest edge (m) of each of ``triangles`` (M, 3, indices into ``vertices`` (N, 3))."""
    corners = vertices[triangles]
    return np.sqrt(np.max([((corners[:, (k + 1) % 3] - corners[:, k]) ** 2).sum(axis=1) for k in range(3)], axis=0))


def triangle_samples(vertices: np.ndarray, triangles: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points inside the triangles (M, 3, indices into ``vertices`` (N, 3)) at most ``spacing`` (m) apart, their
    corners left out, and for each the vertex it lies nearest (by barycentric weight). Each triangle is spanned
    from the corner opposite its longest edge, a + (i / n) (b - a) + (j / m) (c - a) for i / n + j / m <= 1,
    with n and m the two shorter edges' lengths over ``spacing``, rounded up: a long thin triangle gets a row
    of points, not a square grid. A triangle whose two shorter edges are within ``spacing`` gives none (every
    point of it is that close to the corner between them)."""
    if len(triangles) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    corners = vertices[triangles]  # (M, 3, 3)
    opposite = np.stack([np.linalg.norm(corners[:, (k + 2) % 3] - corners[:, (k + 1) % 3], axis=1) for k in range(3)], axis=1)
    first = np.argmax(opposite, axis=1)  # the corner opposite the longest edge: between the two shortest
    order = (first[:, None] + np.arange(3)[None, :]) % 3
    ids = np.take_along_axis(triangles, order, axis=1)
    a, b, c = vertices[ids[:, 0]], vertices[ids[:, 1]], vertices[ids[:, 2]]
    n = np.ceil(np.linalg.norm(b - a, axis=1) / spacing).astype(np.int64)
    m = np.ceil(np.linalg.norm(c - a, axis=1) / spacing).astype(np.int64)
    large = np.flatnonzero(np.maximum(n, m) >= 2)
    points, nearest = [], []
    pairs = np.stack([n[large], m[large]], axis=1)
    for (steps_b, steps_c), rows in _grouped(pairs, large):
        i, j = np.meshgrid(np.arange(steps_b + 1), np.arange(steps_c + 1), indexing="ij")
        s_b, s_c = (i / steps_b).ravel(), (j / steps_c).ravel()
        inside = s_b + s_c <= 1.0 + 1e-9
        corner = ((s_b == 0) & (s_c == 0)) | ((s_b == 1) & (s_c == 0)) | ((s_b == 0) & (s_c == 1))
        s_b, s_c = s_b[inside & ~corner], s_c[inside & ~corner]
        weights = np.stack([1.0 - s_b - s_c, s_b, s_c], axis=1)  # (K, 3)
        points.append((weights @ np.stack([a[rows], b[rows], c[rows]], axis=1)).reshape(-1, 3))
        nearest.append(ids[rows][:, np.argmax(weights, axis=1)].reshape(-1))
    if not points:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    return np.concatenate(points), np.concatenate(nearest)


def _grouped(keys: np.ndarray, rows: np.ndarray):
    """(key, rows) for each distinct row of ``keys`` (K, 2), ``rows`` (K,) the values grouped."""
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(unique) + 1))
    for g, key in enumerate(unique):
        yield (int(key[0]), int(key[1])), rows[order[bounds[g] : bounds[g + 1]]]


def cube_colours(voxels: VoxelMap, anchors: np.ndarray, window: int) -> np.ndarray:
    """(M, 3) uint8: the colour of the polygons of neighbourhoods anchored at (M, 3) ``anchors``.

    A polygon lies in the voxel-sized cube of its anchor, so it takes the count-weighted mean colour of the
    points in the voxels that cube overlaps: for even windows the 2 x 2 x 2 voxels around the anchor vertex
    (the whole window at the default 2), for odd windows the centre voxel. Where those hold no coloured point,
    the whole window's; where it holds none either, :data:`NO_COLOUR`.
    """
    anchors = np.asarray(anchors, dtype=np.int64).reshape(-1, 3)

    def summed(lowest: np.ndarray, side: int) -> np.ndarray:
        return sum(voxels.colour_sums(lowest + np.array(step, dtype=np.int64)) for step in np.ndindex(side, side, side))

    sums = summed(anchors - 1, 2) if window % 2 == 0 else voxels.colour_sums(anchors)
    empty = sums[:, 0] == 0
    if empty.any() and window > 2:
        sums[empty] = summed(anchors[empty] + anchor_range(window), window)
    colours = np.empty((len(anchors), 3), dtype=np.uint8)
    coloured = sums[:, 0] > 0
    colours[coloured] = np.clip(np.rint(sums[coloured, 1:] / sums[coloured, :1]), 0, 255).astype(np.uint8)
    colours[~coloured] = NO_COLOUR
    return colours


def vertex_colours(voxels: VoxelMap, vertices: np.ndarray, sizes: np.ndarray, polygon_colours: np.ndarray) -> np.ndarray:
    """(K, 3) uint8: each polygon vertex's colour, the mean colour of the voxel it lies in, or its polygon's
    (``polygon_colours``, (P, 3), :func:`cube_colours`) where that voxel holds no coloured point.

    ``vertices`` (K, 3) are the rings of :func:`cube_polygons` (``sizes`` vertices each). A vertex on a
    voxel face is taken a hair towards its polygon's centre, into the voxel the polygon covers there.
    """
    sizes = np.asarray(sizes, dtype=np.int64)
    polygon = np.repeat(np.arange(len(sizes)), sizes)
    centres = np.zeros((len(sizes), 3))
    for axis in range(3):
        centres[:, axis] = np.bincount(polygon, weights=vertices[:, axis], minlength=len(sizes))
    centres /= np.maximum(sizes, 1)[:, None]
    inside = vertices + 1e-6 * (centres[polygon] - vertices)
    sums = voxels.colour_sums(voxels.voxel_indices(inside))
    colours = np.asarray(polygon_colours, dtype=np.uint8)[polygon].copy()
    coloured = sums[:, 0] > 0
    colours[coloured] = np.clip(np.rint(sums[coloured, 1:] / sums[coloured, :1]), 0, 255).astype(np.uint8)
    return colours


def cube_polygons(normals: np.ndarray, points: np.ndarray, centres: np.ndarray, half: float):
    """Convex polygons where planes cut axis-aligned cubes (seed 000 eq. 4).

    Plane i has unit normal ``normals[i]`` and passes through ``points[i]``; cube i is centred on
    ``centres[i]`` with half side ``half``. Returns ``(vertices, sizes, owner)``: the polygons'
    vertices (K, 3) in order (counter-clockwise seen from the normal's side), the vertex count of
    each polygon (3-6) and the index of the plane each polygon comes from. Planes that miss their
    cube or only touch it (fewer than 3 distinct points) give no polygon.
    """
    normals = np.asarray(normals, dtype=np.float64)
    m = len(normals)
    corners = centres[:, None, :] + half * _CORNERS[None]  # (M, 8, 3)
    p1 = corners[:, _EDGES[:, 0]]  # (M, 12, 3)
    p2 = corners[:, _EDGES[:, 1]]
    denominator = np.einsum("mk,mek->me", normals, p2 - p1)
    numerator = np.einsum("mk,mek->me", normals, points[:, None, :] - p1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = numerator / denominator  # eq. (4)
    hit = (np.abs(denominator) > 1e-12 * half) & (t >= 0.0) & (t <= 1.0)
    crossings = p1 + np.where(hit, t, 0.0)[..., None] * (p2 - p1)
    # a plane through a cube corner crosses up to three edges there (t = 0 or 1): keep the first
    tolerance = 1e-9
    corner = np.where(t <= tolerance, _EDGES[:, 0], np.where(t >= 1 - tolerance, _EDGES[:, 1], -1))
    corner = np.where(hit, corner, -1)
    at_corner = corner[:, :, None] == np.arange(8)[None, None, :]  # (M, 12, 8)
    hit &= ~((np.cumsum(at_corner, axis=1) > 1) & at_corner).any(axis=2)
    sizes = hit.sum(axis=1)
    polygon = (sizes >= 3) & (sizes <= 6)
    hit, crossings, sizes = hit[polygon], crossings[polygon], sizes[polygon]
    owner = np.flatnonzero(polygon)
    n = normals[owner]
    centre = (crossings * hit[..., None]).sum(axis=1) / np.maximum(sizes, 1)[:, None]
    # in-plane basis (u, v = n x u) so increasing angle runs counter-clockwise seen from +n
    helper = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    offset = crossings - centre[:, None, :]
    angle = np.arctan2(np.einsum("mek,mk->me", offset, v), np.einsum("mek,mk->me", offset, u))
    angle = np.where(hit, angle, np.inf)
    order = np.argsort(angle, axis=1)
    ordered = np.take_along_axis(crossings, order[..., None], axis=1)
    keep = np.arange(12)[None, :] < sizes[:, None]
    return ordered[keep], sizes, owner if m else np.zeros(0, dtype=np.int64)


def fan_triangles(sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (T, 3) fanning polygons stored one after another, and each triangle's polygon."""
    sizes = np.asarray(sizes, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]) if len(sizes) else np.zeros(0, dtype=np.int64)
    per = np.maximum(sizes - 2, 0)
    polygon = np.repeat(np.arange(len(sizes)), per)
    k = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per) + 1
    base = starts[polygon]
    return np.stack([base, base + k, base + k + 1], axis=1), polygon


@dataclass
class BlockPolygons:
    """The polygons of one block, sorted by anchor key: one per planar neighbourhood anchored in it.

    ``anchors`` (P,) packed anchor keys, ``sizes`` (P,) vertex counts, ``vertices`` (sum sizes, 3)
    the rings one after another, ``normals`` (P, 3), ``colours`` (sum sizes, 3) uint8, one per vertex
    (:func:`vertex_colours`; :data:`NO_COLOUR` in a map without colour).
    """

    anchors: np.ndarray
    sizes: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    colours: np.ndarray

    @property
    def number_of_triangles(self) -> int:
        return int((self.sizes - 2).sum())


def ring_indices(sizes: np.ndarray, selected: np.ndarray) -> np.ndarray:
    """Indices of the vertices of the ``selected`` polygons (in that order) among rings stored one after another."""
    sizes = np.asarray(sizes, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    chosen = sizes[selected]
    offsets = np.concatenate([[0], np.cumsum(chosen)[:-1]])
    return np.repeat(starts[selected] - offsets, chosen) + np.arange(chosen.sum())


def _block_offsets() -> np.ndarray:
    return np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)


#: The eight half-size anchors of an anchor V are 2 V + these (see :class:`HalvedGrid`).
_OCTANTS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int64)


@dataclass(frozen=True)
class HalvedGrid:
    """Where the half-size voxels of the crease refinement lie (module docs, "Creases").

    The half-size map indexes points shifted by ``shift`` (metres, on every axis): a quarter voxel for even
    windows, nothing for odd ones, so that the cubes of the half-size anchors 2 V + {0, 1}^3 are exactly
    the eight octants of anchor V's cube.
    """

    voxel_size: float  # the full voxel size s (m)
    window: int

    @property
    def shift(self) -> float:
        return self.voxel_size / 4.0 if self.window % 2 == 0 else 0.0

    def anchors_of(self, anchors: np.ndarray) -> np.ndarray:
        """(8 M, 3): the half-size anchors whose cubes tile the cubes of (M, 3) ``anchors``, eight per anchor."""
        return (2 * np.asarray(anchors, dtype=np.int64)[:, None, :] + _OCTANTS[None]).reshape(-1, 3)

    def voxels_within(self, voxels: np.ndarray) -> np.ndarray:
        """The half-size voxels whose centres lie in (M, 3) full-size ``voxels``: 2 c + {0, 1}^3 for voxel c (with the
        quarter-voxel shift, half-size voxel j's centre is at j s / 2), so every half-size voxel belongs to one."""
        voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        return np.unique((2 * voxels[:, None, :] + _OCTANTS[None]).reshape(-1, 3), axis=0)

    def voxels_around(self, halved: np.ndarray) -> np.ndarray:
        """The full-size voxels that (M, 3) half-size voxels ``halved`` overlap."""
        halved = np.asarray(halved, dtype=np.int64).reshape(-1, 3)
        if not self.shift:
            return np.unique(np.floor_divide(halved, 2), axis=0)
        # half-size voxel j spans [j s / 2 - s / 4, (j + 1) s / 2 - s / 4): full voxels (j - 1) // 2 and j // 2
        low, high = np.floor_divide(halved - 1, 2), np.floor_divide(halved, 2)
        corners = [np.where(np.array(pick, dtype=bool), high, low) for pick in itertools.product((0, 1), repeat=3)]
        return np.unique(np.concatenate(corners), axis=0)


class FilterVoxelPlanes(MabdiAlgorithm):
    """Incremental voxel-plane mesh (depth image or points -> vtkPolyData), see the module docs.

    Python use without a pipeline: :meth:`add_points` then :meth:`mesh` or :meth:`changed_mesh`.
    """

    def __init__(self, parameters: VoxelPlanesParameters | None = None, output: str = "changed") -> None:
        super().__init__(nInputPorts=1, inputType="vtkDataObject", nOutputPorts=1, outputType="vtkPolyData")
        self._parameters = parameters if parameters is not None else VoxelPlanesParameters()
        self._output = self._check_output(output)
        self.map = VoxelMap(self._parameters.voxel_size, self._parameters.block_size)
        self.halved_map = self._new_halved_map()
        self._blocks: dict[int, BlockPolygons] = {}
        self._changed = np.zeros(0, dtype=np.int64)
        self._pending_cleared = np.zeros((0, 3), dtype=np.int64)
        self._last_input: tuple[str, int] | None = None
        self._meshed_with = self._parameters

    # -- parameters --------------------------------------------------------
    @staticmethod
    def _check_output(output: str) -> str:
        if output not in OUTPUTS:
            raise ConfigError(f"FilterVoxelPlanes: output must be one of {OUTPUTS}, got {output!r}")
        return output

    def _new_halved_map(self) -> VoxelMap | None:
        """An empty half-size map for the crease refinement, or None when the parameters do not refine."""
        p = self._parameters
        # blocks of half the size hold as many voxels as the full-size map's, so memory grows with the surface
        return VoxelMap(p.voxel_size / 2.0, p.block_size / 2.0) if p.refines else None

    @property
    def _halved_grid(self) -> HalvedGrid:
        return HalvedGrid(self._parameters.voxel_size, self._parameters.window)

    @property
    def parameters(self) -> VoxelPlanesParameters:
        return self._parameters

    @parameters.setter
    def parameters(self, value: VoxelPlanesParameters) -> None:
        """New parameters; a new voxel or block size, or turning the crease refinement on or off, empties the map
        (its statistics are per voxel, and the refinement's half-size statistics must hold every point)."""
        old = self._parameters
        if (value.voxel_size, value.block_size, value.refines) != (old.voxel_size, old.block_size, old.refines):
            self._parameters = value
            self.reset()
            return
        self._set("_parameters", value)

    @property
    def output(self) -> str:
        """``"changed"``: the blocks re-meshed by the last update; ``"full"``: the whole mesh."""
        return self._output

    @output.setter
    def output(self, value: str) -> None:
        self._set("_output", self._check_output(value))

    def state(self) -> dict:
        """What the filter keeps across updates (the voxel statistics and the polygons per block), for checkpoints."""
        keys = np.array(list(self._blocks), dtype=np.int64)
        blocks = [self._blocks[int(k)] for k in keys]

        def joined(name: str, shape: tuple, dtype) -> np.ndarray:
            parts = [np.asarray(getattr(b, name)) for b in blocks]
            return np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)

        return {
            "map": self.map.state(),
            "halved_map": None if self.halved_map is None else self.halved_map.state(),
            "blocks": {  # every block's polygons one after another; "polygons" says how many are each block's
                "keys": keys,
                "polygons": np.array([len(b.anchors) for b in blocks], dtype=np.int64),
                "anchors": joined("anchors", (0,), np.int64),
                "sizes": joined("sizes", (0,), np.int64),
                "vertices": joined("vertices", (0, 3), np.float64),
                "normals": joined("normals", (0, 3), np.float64),
                "colours": joined("colours", (0, 3), np.uint8),
            },
            "meshed_with": dataclasses.asdict(self._meshed_with),
            "pending": self._pending_cleared.copy(),
        }

    def set_state(self, state: dict) -> None:
        """Restore what :meth:`state` returned (the next update goes on from there; with the crease refinement
        on or off as the state was made, since the half-size statistics must hold every point)."""
        self.map = VoxelMap.from_state(state["map"])
        halved = state.get("halved_map")
        self.halved_map = None if halved is None else VoxelMap.from_state(halved)
        # a state written before the crease refinement existed was meshed without it
        self._meshed_with = VoxelPlanesParameters(**{"refine": False, **state["meshed_with"]})
        if self._parameters.refines != (self.halved_map is not None):  # go on as the state was made
            self._parameters = dataclasses.replace(self._parameters, refine=self.halved_map is not None)
        blocks = state["blocks"]
        polygons = np.asarray(blocks["polygons"], dtype=np.int64)
        sizes = np.asarray(blocks["sizes"])
        cuts = np.cumsum(polygons)[:-1]
        colours = blocks.get("colours")  # states written before colour have none
        colours = np.full((int(sizes.sum()), 3), NO_COLOUR, dtype=np.uint8) if colours is None else np.asarray(colours, dtype=np.uint8)
        vertex_cuts = np.concatenate([[0], np.cumsum(sizes)])[np.cumsum(polygons)][:-1]
        self._blocks = {} if not len(polygons) else {
            int(key): BlockPolygons(anchors, block_sizes, vertices, normals, block_colours)
            for key, anchors, block_sizes, vertices, normals, block_colours in zip(
                blocks["keys"],
                np.split(np.asarray(blocks["anchors"]), cuts),
                np.split(sizes, cuts),
                np.split(np.asarray(blocks["vertices"]), vertex_cuts),
                np.split(np.asarray(blocks["normals"]), cuts),
                np.split(colours, vertex_cuts),
                strict=True,
            )
        }
        self._pending_cleared = np.asarray(state["pending"], dtype=np.int64).reshape(-1, 3).copy()
        self._changed = np.zeros(0, dtype=np.int64)
        self._last_input = None
        self.Modified()

    def reset(self) -> None:
        """Forget every point and face."""
        self.map = VoxelMap(self._parameters.voxel_size, self._parameters.block_size)
        self.halved_map = self._new_halved_map()
        self._blocks.clear()
        self._changed = np.zeros(0, dtype=np.int64)
        self._pending_cleared = np.zeros((0, 3), dtype=np.int64)
        self._last_input = None
        self._meshed_with = self._parameters
        self.Modified()

    # -- the map -----------------------------------------------------------
    @property
    def number_of_triangles(self) -> int:
        return sum(b.number_of_triangles for b in self._blocks.values())

    @property
    def changed_blocks(self) -> np.ndarray:
        """Keys of the blocks re-meshed by the last update."""
        return self._changed.copy()

    @property
    def patch_blocks(self) -> int:
        """Blocks on a side of an output patch: 1, or as many as make :data:`PATCH_VOXELS` voxels (module docs)."""
        return max(1, -(-PATCH_VOXELS // self.map.block_voxels))

    def patch_keys(self, block_keys) -> np.ndarray:
        """The keys of the patches holding blocks ``block_keys`` (the block's own key where a patch is a block)."""
        block_keys = np.asarray(block_keys, dtype=np.int64)
        g = self.patch_blocks
        return block_keys if g == 1 else pack_keys(np.floor_divide(unpack_keys(block_keys), g))

    def clear_free_space(self, origins: np.ndarray, ends: np.ndarray, margins) -> int:
        """Empty the voxels that rays from ``origins`` to ``ends`` (world, metres) saw through, stopping
        ``margins`` (m) short of the ends (:meth:`VoxelMap.clear_free_space`); the neighbourhoods that
        change are re-meshed with the next points. Returns the number of points removed."""
        removed = self._cleared(self.map.clear_free_space(origins, ends, margins))
        if self.halved_map is not None:  # the same rays through the half-size voxels
            shift = self._halved_grid.shift
            self._halved_cleared(self.halved_map.clear_free_space(np.asarray(origins) + shift, np.asarray(ends) + shift, margins))
        return removed

    def _cleared(self, cleared) -> int:
        """Queue the emptied voxels of a :class:`VoxelMap` clearing for re-meshing; returns the points removed."""
        if len(cleared.voxels):
            self._pending_cleared = np.concatenate([self._pending_cleared, cleared.voxels])
            self.Modified()
        return int(cleared.points)

    def _halved_cleared(self, cleared) -> None:
        """Queue the full-size voxels around the emptied half-size ones for re-meshing."""
        if len(cleared.voxels):
            self._pending_cleared = np.concatenate([self._pending_cleared, self._halved_grid.voxels_around(cleared.voxels)])
            self.Modified()

    @property
    def face_overhang(self) -> float:
        """How far (metres) a face may reach past a real edge: a voxel's plane polygon fills the voxel, so
        object removal widens its edge mask by a voxel (see :mod:`mabdi.stages.removal`)."""
        return float(self._parameters.voxel_size)

    def clear_faces_at(self, points: np.ndarray) -> int:
        """Empty the neighbourhoods whose planes made the faces at ``points`` (world, metres; e.g. the
        centroids of faces object removal took out), so that re-meshing does not bring them back.

        A face lies in the cube of its neighbourhood's anchor: for even windows the grid vertex nearest
        to it, whose window of voxels is emptied; for odd windows the voxel holding it and its window.
        A face of the crease refinement lies in an octant of the same cube: the half-size voxels within
        the emptied window are emptied too (every half-size window they are in lies in a full-size window
        re-meshed with the emptied voxels). Returns the number of points removed.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if not len(points):
            return 0
        window = self._parameters.window
        s = self._parameters.voxel_size
        low = anchor_range(window)
        anchors = np.rint(points / s).astype(np.int64) if window % 2 == 0 else np.floor(points / s).astype(np.int64)
        steps = np.array(list(itertools.product(range(low, low + window), repeat=3)), dtype=np.int64)
        voxels = (anchors[:, None, :] + steps[None]).reshape(-1, 3)
        if self.halved_map is not None:
            self.halved_map.clear_voxels(self._halved_grid.voxels_within(np.unique(voxels, axis=0)))
        return self._cleared(self.map.clear_voxels(voxels))

    def add_points(self, points: np.ndarray, colours: np.ndarray | None = None) -> np.ndarray:
        """Add (M, 3) world points (with their (M, 3) uint8 RGB ``colours``, when known) and re-mesh the blocks
        they touch (and those emptied by :meth:`clear_free_space` since the last call); returns the re-meshed
        block keys."""
        changed = self.map.add_points(points, colours)
        if self.halved_map is not None:  # a point in a half-size voxel is in a full-size window around it too
            self.halved_map.add_points(np.asarray(points, dtype=np.float64) + self._halved_grid.shift)
        if len(self._pending_cleared):
            changed = np.concatenate([np.asarray(changed, dtype=np.int64).reshape(-1, 3), self._pending_cleared])
            self._pending_cleared = np.zeros((0, 3), dtype=np.int64)
        window = self._parameters.window
        low = anchor_range(window)
        # voxel v lies in the neighbourhoods of anchors v - low - (window - 1) ... v - low
        steps = np.array(list(itertools.product(range(-low - window + 1, -low + 1), repeat=3)), dtype=np.int64)
        anchors = unpack_keys(np.unique(pack_keys((changed[:, None, :] + steps[None]).reshape(-1, 3))))
        self._remesh_anchors(anchors)
        self.Modified()
        return self._changed.copy()

    def remesh_all(self) -> None:
        """Re-mesh every block (after a change of epsilon, window or min_points)."""
        self._blocks.clear()
        self._remesh_anchors(self.candidate_anchors(self.map.block_keys()))
        self._meshed_with = self._parameters

    def candidate_anchors(self, blocks: np.ndarray) -> np.ndarray:
        """(M, 3) anchors in ``blocks`` (sorted keys) whose neighbourhood holds any point."""
        blocks = np.asarray(blocks, dtype=np.int64)
        if len(blocks) == 0:
            return np.zeros((0, 3), dtype=np.int64)
        coords = unpack_keys(blocks)
        around = np.unique(pack_keys((coords[:, None, :] + _block_offsets()[None]).reshape(-1, 3)))
        occupied = self.map.occupied_voxels(around)
        window = self._parameters.window
        low = anchor_range(window)
        steps = np.array(list(itertools.product(range(-low - window + 1, -low + 1), repeat=3)), dtype=np.int64)
        anchors = (occupied[:, None, :] + steps[None]).reshape(-1, 3)
        b = self.map.block_voxels
        anchor_blocks = np.floor_divide(anchors, b)
        where = np.minimum(np.searchsorted(blocks, pack_keys(anchor_blocks)), len(blocks) - 1)
        inside = blocks[where] == pack_keys(anchor_blocks)
        local = anchors[inside] - anchor_blocks[inside] * b
        flat = where[inside] * b**3 + (local[:, 0] * b + local[:, 1]) * b + local[:, 2]
        mask = np.zeros(len(blocks) * b**3, dtype=bool)
        mask[flat] = True
        flat = np.flatnonzero(mask)
        block, rest = flat // b**3, flat % b**3
        local = np.stack([rest // (b * b), (rest // b) % b, rest % b], axis=1)
        return coords[block] * b + local

    def _remesh_anchors(self, anchors: np.ndarray) -> None:
        """Recompute the polygons of ``anchors`` (M, 3) (their neighbourhoods changed) in their blocks."""
        p = self._parameters
        anchors = np.asarray(anchors, dtype=np.int64).reshape(-1, 3)
        patches = plane_patches(self.map, anchors, p)
        vertices, sizes, owner = cube_polygons(patches.normals, patches.centroids, patches.centres, 0.5 * p.voxel_size)
        polygon_anchor = patches.anchors[owner]
        polygon_normals = patches.normals[owner]
        if self.halved_map is not None and len(patches.unresolved):
            grid = self._halved_grid
            halved = plane_patches(self.halved_map, grid.anchors_of(patches.unresolved), p.halved())
            more, more_sizes, more_owner = cube_polygons(
                halved.normals, halved.centroids - grid.shift, halved.centres - grid.shift, 0.25 * p.voxel_size
            )
            vertices, sizes = np.concatenate([vertices, more]), np.concatenate([sizes, more_sizes])
            polygon_anchor = np.concatenate([polygon_anchor, np.floor_divide(halved.anchors[more_owner], 2)])
            polygon_normals = np.concatenate([polygon_normals, halved.normals[more_owner]])
        if self.map.has_colour:
            colours = vertex_colours(self.map, vertices, sizes, cube_colours(self.map, polygon_anchor, p.window))
        else:
            colours = np.empty((len(vertices), 3), dtype=np.uint8)
            colours[:] = NO_COLOUR
        anchor_key = pack_keys(anchors)
        blocks = np.unique(self.map.block_of(anchors))
        # all the blocks at once: their old polygons but those of the re-meshed anchors, and the new ones, sorted by
        # (block, anchor), each polygon's rings following it (an anchor lies in one block: old and new never share one)
        stored = [(key, self._blocks[key]) for key in blocks.tolist() if key in self._blocks]
        old = [polygons for _, polygons in stored]
        old_anchor = np.concatenate([np.zeros(0, np.int64)] + [o.anchors for o in old])
        old_sizes = np.concatenate([np.zeros(0, np.int64)] + [o.sizes for o in old])
        kept = ~np.isin(old_anchor, anchor_key)
        kept_rings = np.repeat(kept, old_sizes)
        block = np.concatenate(
            [self.map.block_of(polygon_anchor)] + [np.full(len(o.anchors), key, np.int64) for key, o in stored]
        )
        every = np.concatenate([np.ones(len(sizes), bool), kept])
        anchor = np.concatenate([pack_keys(polygon_anchor), old_anchor])[every]
        block = block[every]
        all_sizes = np.concatenate([sizes, old_sizes])[every]
        all_normals = np.concatenate([polygon_normals] + [o.normals for o in old])[every]
        ring_kept = np.concatenate([np.ones(len(vertices), bool), kept_rings])
        all_vertices = np.concatenate([vertices] + [o.vertices for o in old])[ring_kept]
        all_colours = np.concatenate([colours] + [o.colours for o in old])[ring_kept]
        order = np.lexsort((anchor, block))
        rings = ring_indices(all_sizes, order)
        anchor, block, all_sizes, all_normals = anchor[order], block[order], all_sizes[order], all_normals[order]
        all_vertices, all_colours = all_vertices[rings], all_colours[rings]
        ring_bounds = np.concatenate([[0], np.cumsum(all_sizes)])
        lo, hi = np.searchsorted(block, blocks), np.searchsorted(block, blocks, side="right")
        for key, a, b in zip(blocks.tolist(), lo.tolist(), hi.tolist(), strict=True):
            if a == b:
                self._blocks.pop(key, None)
                continue
            r = slice(ring_bounds[a], ring_bounds[b])
            self._blocks[key] = BlockPolygons(  # copies: a block keeps no view of the whole update's arrays
                anchor[a:b].copy(), all_sizes[a:b].copy(), all_vertices[r].copy(), all_normals[a:b].copy(), all_colours[r].copy()
            )
        self._changed = blocks

    # -- output ------------------------------------------------------------
    def _polydata(self, block_keys) -> vtkPolyData:
        block_keys = [key for key in block_keys if key in self._blocks]
        meshes = [self._blocks[key] for key in block_keys]
        if not meshes:
            return vtkPolyData()
        sizes = np.concatenate([m.sizes for m in meshes])
        vertices = np.concatenate([m.vertices for m in meshes])
        triangles, polygon = fan_triangles(sizes)
        normals = np.concatenate([m.normals for m in meshes])[polygon]
        patch = np.repeat(self.patch_keys(block_keys), [len(m.sizes) for m in meshes])[polygon]
        mesh = triangles_polydata(vertices, triangles, dtype=np.float32)
        normal_array = numpy_to_vtk(np.ascontiguousarray(normals, dtype=np.float32), deep=True)
        normal_array.SetName("Normals")
        mesh.GetCellData().SetNormals(normal_array)
        rgb = numpy_to_vtk(colours_by_normal(normals), deep=True)
        rgb.SetName("rgb")
        mesh.GetCellData().AddArray(rgb)
        keys_array = numpy_to_vtk(patch, deep=True)
        keys_array.SetName(PATCH_KEY_ARRAY)
        mesh.GetCellData().AddArray(keys_array)
        if self.map.has_colour:  # each vertex: the mean colour of its voxel (vertex_colours)
            colours = np.concatenate([m.colours for m in meshes])
            mesh.GetPointData().AddArray(colour_point_array(colours))
        return mesh

    def mesh(self) -> vtkPolyData:
        """The whole voxel-plane mesh."""
        return self._polydata(sorted(self._blocks))

    def changed_mesh(self) -> vtkPolyData:
        """The patches that hold a block re-meshed by the last update, whole (``removed_patch_keys``: those now
        empty)."""
        changed = np.unique(self.patch_keys(self._changed))
        if self.patch_blocks == 1:
            blocks = self._changed
        else:  # every block of a changed patch, the unchanged ones too: the patch is replaced whole
            stored = np.array(sorted(self._blocks), dtype=np.int64)
            blocks = stored[np.isin(self.patch_keys(stored), changed)]
        blocks = np.array([key for key in blocks.tolist() if key in self._blocks], dtype=np.int64)
        mesh = self._polydata(blocks.tolist())
        removed = np.setdiff1d(changed, self.patch_keys(blocks))
        array = numpy_to_vtk(removed, deep=True)
        array.SetName(REMOVED_KEYS_ARRAY)
        mesh.GetFieldData().AddArray(array)
        return mesh

    def mesh_frame(self, frame: Measured, whole: np.ndarray | None = None) -> vtkPolyData:
        """Add ``frame``'s points (its depth's returns, in the world of its pose) and give the mesh the filter
        outputs (all patches, or those that changed: ``output``). ``whole``: (H, W) all of D where ``frame`` holds only some
        of it (between beams, the samples beyond an edge), None: the frame is all of D."""
        self.add_points(*self._frame_points(frame, whole))
        return self.mesh() if self._output == "full" else self.changed_mesh()

    # -- pipeline ----------------------------------------------------------
    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        data = vtkDataObject.GetData(inInfo[0])
        stamp = (data.GetAddressAsString("vtkObject"), data.GetMTime())
        if stamp != self._last_input:  # a re-execution with the same input adds no points twice
            self._last_input = stamp
            self.add_points(*self._input_points(data))
        elif self._meshed_with != self._parameters:
            self.remesh_all()
        output = vtkPolyData.GetData(outInfo)
        output.ShallowCopy(self.mesh() if self._output == "full" else self.changed_mesh())
        if isinstance(data, vtkImageData):
            for name in ("intrinsics", SPHERICAL_ARRAY, BEAM_ELEVATIONS_ARRAY, "world_from_camera", FRAME_ARRAY):
                array = data.GetFieldData().GetArray(name)
                if array is not None:
                    output.GetFieldData().AddArray(array)
        return 1

    def _frame_points(self, frame: Measured, whole: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """World points (M, 3) of a frame's valid pixels and their uint8 RGB colours (M, 3), None without colour
        (and, between beams, the points on its pixel grid, module docs)."""
        depth, k, pose, colour = frame.depth, frame.geometry, frame.pose, frame.colour
        v, u = np.nonzero(np.isfinite(depth))  # only the valid (novel) pixels: often a few percent
        z = depth[v, u].astype(np.float64)
        camera = pixel_rays(k)[v, u] * z[:, None]  # a camera's z = 1 rays times depth, or a LiDAR's unit rays times range
        if frame.return_points is not None:  # a LiDAR pixel's own return, where it has one
            camera = at_returns(camera, frame.return_points[v, u])
        points, colours = camera @ pose[:3, :3].T + pose[:3, 3], None if colour is None else colour[v, u]
        if on_for_range_images(self._parameters.between_beams, k):
            vertices, triangles, pixel_ids = pixel_grid_surface(frame, whole, PixelGridParameters(), straight_only=True)
            if math.isfinite(self._parameters.bridge):
                triangles = triangles[longest_edges(vertices, triangles) <= self._parameters.bridge]
            extra, corner = triangle_samples(vertices, triangles, 0.5 * self._parameters.voxel_size)
            points = np.concatenate([points, extra])
            if colours is not None:
                colours = np.concatenate([colours, colour.reshape(-1, 3)[pixel_ids[corner]]])
        return points, colours

    def _input_points(self, data) -> tuple[np.ndarray, np.ndarray | None]:
        """World points (M, 3) of the input and their uint8 RGB colours (M, 3), None when it has no colour:
        a depth image's point array ``colour`` at the valid pixels (and, between beams, the points on its pixel
        grid, module docs); a point set's ``colour`` (or ``rgb_colors``) point array, uint8 with 3 components."""
        if isinstance(data, vtkImageData):
            return self._frame_points(Measured.from_image(data), measured_depth(data))
        if isinstance(data, vtkPointSet):
            if data.GetNumberOfPoints() == 0:
                return np.zeros((0, 3)), None
            from vtkmodules.util.numpy_support import vtk_to_numpy

            points = vtk_to_numpy(data.GetPoints().GetData()).astype(np.float64)
            colour = None
            for name in (COLOUR_ARRAY, COLOUR_LAYER):
                array = data.GetPointData().GetArray(name)
                if array is not None and array.GetNumberOfComponents() == 3 and array.GetDataTypeAsString() == "unsigned char":
                    colour = vtk_to_numpy(array).reshape(-1, 3)
                    break
            return points, colour
        raise TypeError(
            f"FilterVoxelPlanes: input must be a depth image (vtkImageData) or points (vtkPolyData), got {data.GetClassName()}"
        )
