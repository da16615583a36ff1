"""Range images of a mesh for a spinning LiDAR: perspective renders for visibility, exact beams for the range.

A :class:`~mabdi.spherical.SphericalGeometry` range image holds, per beam, the range to the first surface
along the beam's unit ray (:mod:`mabdi.spherical` has the convention). :class:`RangeRenderer` makes it in
two steps:

1. **Which triangle**: ``SECTORS`` (4) perspective renders around the sensor's z axis, each 90 degrees of
   azimuth wide and tall enough for every beam, at ``OVERSAMPLE`` (2) render pixels per beam step (the
   smaller of the azimuth step and the closest beams' spacing), draw every triangle flat in the colour of
   its 24-bit identity (the off-screen :class:`~mabdi.render.depth_image.DepthRenderer`, multisampling
   off). Each beam's direction projects into one sector's image; the triangles drawn in the 3 x 3 render
   pixels around that point are its candidates, and the 16 around those next.
2. **Where along the beam**: the beam is intersected with its candidates exactly (Moller-Trumbore, float64,
   :mod:`mabdi.render.range_rendering_kernels`) and takes the nearest of the 3 x 3 it hits inside, else the
   nearest of the ring around them. So the range is exact at every beam, on planes at any slant and at
   silhouettes (a beam that passes a box's edge by a fraction of a pixel reads the wall behind it, or no
   return), whenever the triangle the beam hits is drawn at one of those render pixels: always, unless it
   is thinner than a render pixel there. A fine mesh (a scanned object, a cylinder's facets, a map's
   triangles seen edge-on) has such triangles: a beam that hits none of its candidates inside takes the
   plane of the nearest thin candidate it misses by less than a render pixel's footprint (a sub-pixel
   extrapolation of the surface next to the one hit), or no return.

**Along given directions** (:meth:`RangeRenderer.cast`): a scan's own returns lie anywhere in their pixels,
not on the centre rays. The same drawing can be cast along each return's own direction, its candidates the
render pixels around where that direction falls (:meth:`SectorViews.render_pixels`); the renders reach half a beam
spacing beyond the outermost beams and to the sectors' edges, so every direction of a pixel has its window.

Returns are ranges strictly between ``range_min`` and ``range_max``; anything else is NaN (a surface nearer
than ``range_min`` hides what is behind it, as on a real sensor). The renderer keeps, per triangle, the block
and cell it was drawn for, so E of a map says which face each beam shows with a code and its
:class:`~mabdi.face_identity.FaceIdTable` (:meth:`RangeRenderer.face_ids`), as a camera's E does.

**The map within a beam's footprint** (:meth:`RangeRenderer.footprint_covered`): the 3 x 3 render pixels
around a beam's direction span one beam step (``OVERSAMPLE`` render pixels per step), so a triangle drawn
in any of them means the map reaches into that beam's footprint, whether or not the beam itself hits it.
The classifier reads it to tell a sliver along the map's silhouette from new surface beyond its edge.

Beams must lie within ``MAX_ELEVATION`` (60) degrees of the horizon: the sector renders look horizontally.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkMultiBlockDataSet, vtkPolyData

from mabdi.camera import Intrinsics, boxes_outside, frustum_planes, unit_rays
from mabdi.errors import ConfigError
from mabdi.render.range_rendering_kernels import cast_beams_kernel
from mabdi.face_identity import FaceIdTable, block_address, face_rgb
from mabdi.polydata import named_leaves, triangulated
from mabdi.spherical import SphericalGeometry

#: Cell data the range renderer draws: each triangle's 24-bit identity in its own table, as uint8 RGB.
TRIANGLE_RGB_ARRAY = "range_triangle_rgb"
#: Cell data of a drawn copy: the cell of the map block each of its triangles came from.
_SOURCE_CELL_ARRAY = "range_source_cell"
#: Perspective renders around the azimuth.
SECTORS = 4
#: Render pixels per beam step.
OVERSAMPLE = 3.0
#: Largest beam elevation the sector renders cover (degrees from the horizon).
MAX_ELEVATION = 60.0
#: Candidates per beam tried first: the 3 x 3 render pixels around its direction (then the 5 x 5 ring).
INNER = 9
#: Barycentric tolerance of the inside test (a beam on an edge between two triangles hits either).
BARYCENTRIC_TOLERANCE = 1e-7
#: Identities are 24-bit RGB colours; 0 is "no triangle".
_MAX_IDENTITY = (1 << 24) - 1


@dataclass(frozen=True)
class SectorViews:
    """The perspective renders of one range-image geometry and where each beam falls in them."""

    #: Intrinsics of every sector render (the same for all).
    intrinsics: Intrinsics
    #: (SECTORS, 4, 4) each render camera's pose in the sensor frame (``sensor_from_camera``).
    sensor_from_camera: np.ndarray
    #: (beams * columns,) int64 flat index into the stacked (SECTORS, h, w) identity images of the render
    #: pixel each beam's centre ray falls in.
    centres: np.ndarray
    #: (25,) int64 flat offsets from a beam's render pixel to the 5 x 5 around it, the 3 x 3 nearest first
    #: (:data:`INNER`): its candidates are ``centres + offsets``.
    offsets: np.ndarray
    #: Radians per render pixel at the image centre (the largest footprint; metres per metre of range).
    footprint: float

    def render_pixels(self, directions: np.ndarray) -> np.ndarray:
        """(N,) int64 flat index (as :attr:`centres`) of the render pixel each sensor-frame direction (N, 3)
        falls in, -1 where its 5 x 5 window would leave the renders (or the direction is NaN)."""
        k = self.intrinsics
        with np.errstate(invalid="ignore", divide="ignore"):
            sector, col, row = _project(directions, k.fx, k.cx, k.cy)
            inside = (col >= 2) & (col < k.width - 2) & (row >= 2) & (row < k.height - 2)
        pixels = np.full(len(directions), -1, dtype=np.int64)
        pixels[inside] = sector[inside] * (k.width * k.height) + row[inside] * k.width + col[inside]
        return pixels


def _project(rays: np.ndarray, focal: float, cx: float, cy: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sector each sensor-frame ray (N, 3) is drawn in (the nearest in azimuth), and its render pixel's
    column and row there (int64; garbage where a ray is NaN or not ahead of its sector's camera)."""
    azimuth = np.arctan2(rays[:, 1], rays[:, 0])
    sector = np.mod(np.round(np.nan_to_num(azimuth) / (2.0 * math.pi / SECTORS)).astype(np.int64), SECTORS)
    angles = sector * (2.0 * math.pi / SECTORS)
    # camera x right, y down, z forward (OpenCV), in the sensor frame (x forward, y left, z up)
    x = rays[:, 0] * np.sin(angles) - rays[:, 1] * np.cos(angles)
    y = -rays[:, 2]
    z = rays[:, 0] * np.cos(angles) + rays[:, 1] * np.sin(angles)
    col = np.floor(np.nan_to_num(focal * x / z + cx, nan=-1.0, posinf=-1.0, neginf=-1.0)).astype(np.int64)
    row = np.floor(np.nan_to_num(focal * y / z + cy, nan=-1.0, posinf=-1.0, neginf=-1.0)).astype(np.int64)
    return sector, col, row


@functools.lru_cache(maxsize=4)
def sector_views(geometry: SphericalGeometry) -> SectorViews:
    """The sector renders of ``geometry`` (cached per geometry)."""
    elevations = geometry.elevations()
    if np.degrees(np.abs(elevations)).max() > MAX_ELEVATION:
        raise ConfigError(
            f"lidar: beams must lie within {MAX_ELEVATION:g} degrees of the horizon for the range renderer, "
            f"got elevations from {math.degrees(elevations.min()):.1f} to {math.degrees(elevations.max()):.1f}"
        )
    spacing = np.abs(np.diff(elevations)).min() if len(elevations) > 1 else math.radians(geometry.fov_up - geometry.fov_down)
    step = min(2.0 * math.pi / geometry.columns, spacing)
    focal = OVERSAMPLE / step
    rays = unit_rays(geometry)[0].reshape(-1, 3)
    sector = np.mod(np.round(np.arctan2(rays[:, 1], rays[:, 0]) / (2.0 * math.pi / SECTORS)).astype(np.int64), SECTORS)
    angles = sector * (2.0 * math.pi / SECTORS)
    poses = np.zeros((SECTORS, 4, 4))
    for k in range(SECTORS):
        a = k * 2.0 * math.pi / SECTORS
        # camera x right, y down, z forward (OpenCV), in the sensor frame (x forward, y left, z up)
        poses[k, :3, 0] = (math.sin(a), -math.cos(a), 0.0)
        poses[k, :3, 1] = (0.0, 0.0, -1.0)
        poses[k, :3, 2] = (math.cos(a), math.sin(a), 0.0)
        poses[k, 3, 3] = 1.0
    x = rays[:, 0] * np.sin(angles) - rays[:, 1] * np.cos(angles)
    y = -rays[:, 2]
    z = rays[:, 0] * np.cos(angles) + rays[:, 1] * np.sin(angles)
    # the renders reach the sectors' edges and half a beam spacing beyond the outermost beams (where a scan's
    # own returns may lie; a sector is tallest at its edges), and pad render pixels beyond: the 5 x 5 window
    # around any such direction stays inside the image
    pad = 4
    ends = np.array([elevations[0], elevations[-1]])
    if len(elevations) > 1:
        ends = ends + 0.5 * np.array([elevations[0] - elevations[1], elevations[-1] - elevations[-2]])
    ends = np.clip(ends, -math.radians(MAX_ELEVATION), math.radians(MAX_ELEVATION))
    tallest = float(np.max(np.abs(np.tan(ends)))) / math.cos(math.pi / SECTORS)
    half_width = int(math.ceil(focal * max(float(np.abs(x / z).max()), math.tan(math.pi / SECTORS)))) + pad
    half_height = int(math.ceil(focal * max(float(np.abs(y / z).max()), tallest))) + pad
    width, height = 2 * half_width, 2 * half_height
    near = 0.999 * geometry.range_min * float(z.min())
    intrinsics = Intrinsics(focal, focal, float(half_width), float(half_height), width, height, near, 1.001 * geometry.range_max)
    sector, col, row = _project(rays, focal, float(half_width), float(half_height))
    dr, dc = (a.ravel() for a in np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="ij"))
    order = np.argsort(np.maximum(np.abs(dr), np.abs(dc)), kind="stable")  # the 3 x 3 first
    offsets = dr[order] * width + dc[order]
    centres = sector * (width * height) + row * width + col
    centres.setflags(write=False)
    offsets.setflags(write=False)
    return SectorViews(intrinsics, poses, centres, offsets, 1.0 / focal)


class _TriangleTable:
    """The triangles drawn for the range renderer, by identity: a triangulated copy of each polydata (kept
    while the polydata is unchanged) with cell data :data:`TRIANGLE_RGB_ARRAY`, and per identity the
    triangle's corner, two edges, width (its height over its longest edge), and the block (a serial number of
    the drawn copy) and cell of the map it was drawn for."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        #: id(leaf) -> (leaf, its MTime, the drawn copy, serial, name)
        self._copies: dict[int, tuple[vtkPolyData, int, vtkPolyData, int, str]] = {}
        self._next = 1
        self._serials = 0
        self.corner = np.zeros((1, 3))
        self.edge1 = np.zeros((1, 3))
        self.edge2 = np.zeros((1, 3))
        self.width = np.zeros(1)
        self.block = np.full(1, -1, dtype=np.int64)
        self.cell = np.zeros(1, dtype=np.int64)

    def _grow(self, size: int) -> None:
        if size <= len(self.cell):
            return
        size = max(size, 2 * len(self.cell))
        for name in ("corner", "edge1", "edge2", "width", "block", "cell"):
            old = getattr(self, name)
            new = np.full((size, *old.shape[1:]), -1 if name == "block" else 0, dtype=old.dtype)
            new[: len(old)] = old
            setattr(self, name, new)

    def copies(self, data) -> list[vtkPolyData]:
        """The drawn copies of ``data``'s polydata (new or changed ones added to the table)."""
        leaves = [(name, leaf) for name, leaf in named_leaves(data) if leaf.GetNumberOfPolys()]
        needed = sum(leaf.GetNumberOfPolys() for _, leaf in leaves if not self._current(leaf))
        if self._next + 2 * needed > _MAX_IDENTITY:  # identities run out: start the table afresh
            self.clear()
        copies = {}
        for name, leaf in leaves:
            entry = self._copies.get(id(leaf)) if self._current(leaf) else None
            copies[id(leaf)] = entry if entry is not None else self._add(leaf, name)
        self._copies = copies
        return [entry[2] for entry in copies.values()]

    def faces(self, triangles: np.ndarray) -> tuple[np.ndarray, FaceIdTable]:
        """Face codes of the map cells that ``triangles`` (identities; 0 = none) were drawn for, and their table:
        the blocks drawn last, numbered from code 1 in order."""
        names, bases, counts, addresses = [], [], [], []
        base_of = np.full(self._serials + 1, -1, dtype=np.int64)
        start = 1
        for leaf, _, _, serial, name in self._copies.values():
            names.append(name)
            bases.append(start)
            counts.append(leaf.GetNumberOfCells())
            addresses.append(block_address(leaf))
            base_of[serial] = start
            start += leaf.GetNumberOfCells()
        block = self.block[triangles]
        known = (triangles > 0) & (block >= 0)
        codes = np.where(known, base_of[np.maximum(block, 0)] + self.cell[triangles], 0)
        codes[known & (base_of[np.maximum(block, 0)] < 0)] = 0
        return codes, FaceIdTable(names, np.array(bases, dtype=np.int64), np.array(counts, dtype=np.int64), np.array(addresses, dtype=np.int64))

    def _current(self, leaf: vtkPolyData) -> bool:
        entry = self._copies.get(id(leaf))
        return entry is not None and entry[0] is leaf and entry[1] == leaf.GetMTime()

    def _add(self, leaf: vtkPolyData, name: str) -> tuple[vtkPolyData, int, vtkPolyData, int, str]:
        copy = vtkPolyData()
        copy.ShallowCopy(leaf)
        source_cells = numpy_to_vtk(np.arange(leaf.GetNumberOfCells(), dtype=np.int64), deep=True)
        source_cells.SetName(_SOURCE_CELL_ARRAY)
        copy.GetCellData().AddArray(source_cells)
        copy = triangulated(copy)
        points = vtk_to_numpy(copy.GetPoints().GetData()).astype(np.float64)
        triangles = vtk_to_numpy(copy.GetPolys().GetConnectivityArray()).astype(np.int64).reshape(-1, 3)
        count = len(triangles)
        first = self._next
        self._next += count
        self._grow(self._next)
        rows = slice(first, first + count)
        a, b, c = points[triangles[:, 0]], points[triangles[:, 1]], points[triangles[:, 2]]
        self.corner[rows] = a
        self.edge1[rows] = b - a
        self.edge2[rows] = c - a
        longest = np.sqrt(np.maximum.reduce([((b - a) ** 2).sum(1), ((c - a) ** 2).sum(1), ((c - b) ** 2).sum(1)]))
        doubled_area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        self.width[rows] = np.divide(doubled_area, longest, out=np.zeros(count), where=longest > 0)
        self._serials += 1
        self.block[rows] = self._serials
        self.cell[rows] = vtk_to_numpy(copy.GetCellData().GetArray(_SOURCE_CELL_ARRAY))
        array = numpy_to_vtk(face_rgb(first, count), deep=True)
        array.SetName(TRIANGLE_RGB_ARRAY)
        copy.GetCellData().AddArray(array)
        return (leaf, leaf.GetMTime(), copy, self._serials, name)


class RangeRenderer:
    """Range images of a mesh (a vtkPolyData or a composite dataset of them) for a spinning LiDAR (see the
    module docs). ``depth_renderer`` is a :class:`~mabdi.render.depth_image.DepthRenderer` made with
    ``identity_array`` = :data:`TRIANGLE_RGB_ARRAY`; it keeps its window and mappers across frames."""

    def __init__(self, depth_renderer) -> None:
        if depth_renderer.identity_array != TRIANGLE_RGB_ARRAY:
            raise ValueError(f"RangeRenderer needs a DepthRenderer drawing the identity array {TRIANGLE_RGB_ARRAY!r}")
        self.depth_renderer = depth_renderer
        self._table = _TriangleTable()
        self._hits: np.ndarray | None = None
        self._covered: np.ndarray | None = None
        self._ids: np.ndarray | None = None
        self._along: np.ndarray | None = None
        #: (geometry, world_from_sensor) of the last drawing
        self._drawn: tuple[SphericalGeometry, np.ndarray] | None = None

    def render(self, data, geometry: SphericalGeometry, world_from_sensor) -> np.ndarray:
        """(beams, columns) float32 range (m) along each beam from ``world_from_sensor`` (x forward, y left,
        z up), NaN where no surface lies strictly between ``range_min`` and ``range_max``."""
        views = sector_views(geometry)
        pose = np.asarray(world_from_sensor, dtype=np.float64)
        copies = self._table.copies(data)
        bounds = np.array([copy.GetBounds() for copy in copies]).reshape(-1, 6)
        k = views.intrinsics
        if self._ids is None or self._ids.shape != (SECTORS, k.height, k.width):
            self._ids = np.empty((SECTORS, k.height, k.width), dtype=np.uint32)  # 24-bit identities, kept between frames
        for sector in range(SECTORS):
            camera = pose @ views.sensor_from_camera[sector]
            # each sector draws only the copies whose bounds reach into its frustum (a quarter of a street's)
            blocks = vtkMultiBlockDataSet()
            for index, visible in enumerate(np.flatnonzero(~boxes_outside(bounds, frustum_planes(k, camera)))):
                blocks.SetBlock(index, copies[visible])
            self.depth_renderer.draw(blocks, k, camera)  # the identities alone are read: the rays are cast on them
            self.depth_renderer.render_identity(out=self._ids[sector])
        self._drawn = (geometry, pose)
        self._along = None
        ranges, hits, covered = self._cast(unit_rays(geometry)[0].reshape(-1, 3), views.centres)
        self._hits, self._covered = hits.reshape(geometry.shape), covered.reshape(geometry.shape)
        return ranges.astype(np.float32).reshape(geometry.shape)

    def cast(self, directions: np.ndarray) -> np.ndarray:
        """(beams, columns) float32 range (m) of the last :meth:`render`'s map along ``directions`` (beams,
        columns, 3: sensor-frame unit vectors, a scan's own returns' directions) instead of the pixels' centre
        rays, each with the render pixels around where it falls as its candidates; NaN where no surface is in
        range, or where a direction is NaN or its window would leave the renders (:meth:`along_directions`
        says which beams were cast; only those are). :meth:`face_ids` and :meth:`footprint_covered` then say
        this cast's (none and False for the beams not cast)."""
        if self._drawn is None:
            raise ValueError("RangeRenderer.cast: nothing rendered yet")
        geometry, _ = self._drawn
        own = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        pixels = sector_views(geometry).render_pixels(own)
        cast = pixels >= 0
        ranges = np.full(len(own), np.nan)
        hits = np.zeros(len(own), dtype=np.int64)
        covered = np.zeros(len(own), dtype=bool)
        ranges[cast], hits[cast], covered[cast] = self._cast(own[cast], pixels[cast])
        self._hits, self._covered = hits.reshape(geometry.shape), covered.reshape(geometry.shape)
        self._along = cast.reshape(geometry.shape)
        return ranges.astype(np.float32).reshape(geometry.shape)

    def _cast(self, rays: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast sensor-frame unit ``rays`` (N, 3) against the last drawing, each with the render pixels around
        ``centres`` (N,) as its candidates (:func:`cast_beams_kernel`): (N,) range (NaN outside the range
        limits), the identity hit and whether the map lies within the footprint."""
        geometry, pose = self._drawn
        views, table = sector_views(geometry), self._table
        directions = np.ascontiguousarray(rays @ pose[:3, :3].T)  # world frame
        ranges, hits, covered = cast_beams_kernel(
            np.ascontiguousarray(pose[:3, 3]), directions, self._ids.reshape(-1), np.ascontiguousarray(centres),
            views.offsets, INNER, table.corner, table.edge1, table.edge2, table.width, views.footprint,
            BARYCENTRIC_TOLERANCE,
        )
        outside = ~((ranges > geometry.range_min) & (ranges < geometry.range_max))
        ranges[outside] = np.nan
        hits[outside] = 0
        return ranges, hits, covered

    @property
    def drawn_pose(self) -> np.ndarray | None:
        """(4, 4) ``world_from_sensor`` of the last :meth:`render`'s drawing (None before one)."""
        return None if self._drawn is None else self._drawn[1]

    def along_directions(self) -> np.ndarray | None:
        """(beams, columns) bool: the last :meth:`cast` cast the beam along its given direction; None after a
        :meth:`render` (the centre rays)."""
        return self._along

    def face_ids(self) -> tuple[np.ndarray, FaceIdTable]:
        """(beams, columns) int64 the code of the map face each beam of the last render or cast hit (0: none), and
        the table that says which block and cell each code is."""
        if self._hits is None:
            raise ValueError("RangeRenderer.face_ids: nothing rendered yet")
        return self._table.faces(self._hits)

    def footprint_covered(self) -> np.ndarray:
        """(beams, columns) bool: a triangle of the last render's mesh was drawn within the beam's footprint
        (the 3 x 3 render pixels around its direction, one beam step), hit by the beam or not."""
        if self._covered is None:
            raise ValueError("RangeRenderer.footprint_covered: nothing rendered yet")
        return self._covered

    def describe(self) -> dict:
        return self.depth_renderer.describe()

    def close(self) -> None:
        self.depth_renderer.close()
