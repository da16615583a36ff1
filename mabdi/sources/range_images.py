"""LiDAR scans as range images: points (and their ring index, when the data has one) to a range image.

A recording holds a spinning LiDAR's scans as points in the sensor frame
(x forward, y left, z up): KITTI's ``velodyne/*.bin`` files
(:mod:`mabdi.sources.kitti`), ``sensor_msgs/msg/PointCloud2`` messages in a
ROS 2 bag (:mod:`mabdi.sources.rosbag2`). :func:`range_image` turns one scan
into the range image of a :class:`~mabdi.spherical.SphericalGeometry` (the
one convention, :mod:`mabdi.spherical`), the one place this is done:

* the column of a point is its azimuth, by :meth:`SphericalGeometry.pixels`;
* its row is its ring (beam) index when the scan has one
  (:func:`rows_from_rings`: top beam first), else its elevation;
* a pixel holds the range (m, along the point's own direction) of the
  nearest point that falls in it; non-returns (NaN, at the origin, outside
  ``range_min < range < range_max``) are left out; an empty pixel is NaN.

Rows by elevation: each pixel's range is carried to its centre's ray (the
straight segment between two returns of one surface, within
:data:`SURFACE_STEP` and :data:`SURFACE_INCIDENCE`), and a pixel left empty
between two returns of one surface takes their mean.

A recording carries its geometry in the ``[lidar]`` table of its
``mabdi.toml`` (:func:`lidar_table`, :func:`geometry_from_table`);
:func:`scan_fit` counts a scan's points outside the image, for a
:class:`LidarGeometryWarning`, and :func:`learn_geometry` learns the vertical
field of view (and, where clear, the beam count) of a scan that does not fit.
Why the centre rule: docs/architecture.md (``mabdi.sources.range_images``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit

from mabdi.errors import ConfigError
from mabdi.sources.sequence_files import SequenceError
from mabdi.spherical import SphericalGeometry

#: KITTI's Velodyne HDL-64E as a range image: 64 beams from +3 to -25 degrees (the field of view range-image
#: segmentation uses for KITTI, RangeNet++; the sensor's own is +2 to -24.8 with the beams unevenly spread,
#: so a uniform 64-row image a little larger than it keeps one beam a row), 1024 columns (at 10 Hz each laser
#: fires about 2000 times a turn, so nearly every pixel gets a point; 2048 would leave holes), returns from
#: 1 m (closer ones hit the car) to 120 m (the sensor's range).
KITTI_GEOMETRY = SphericalGeometry(beams=64, columns=1024, fov_up=3.0, fov_down=-25.0, range_min=1.0, range_max=120.0)

#: Keys of a ``[lidar]`` table: the fields of :class:`SphericalGeometry`.
LIDAR_KEYS = tuple(f.name for f in dataclasses.fields(SphericalGeometry))

#: A scan with more than this share of its points outside the range image is warned of (:class:`LidarGeometryWarning`):
#: a sensor of +15 to -25 degrees (a VLP-32C's, a Pandar64's) leaves an eighth of its points above the default image.
OUTSIDE_SHARE_WARNING = 0.05
#: A first scan with more than this share outside the default geometry has its geometry learnt (:func:`learn_geometry`):
#: the warning's share, so a map does not miss what a sensor of a wider field than the default's saw.
OUTSIDE_SHARE_LEARN = OUTSIDE_SHARE_WARNING
#: A row of a range image holds returns when at least this share of the median row's do (:func:`rows_without_returns`);
#: a scan whose image has more than :data:`EMPTY_ROWS_WARNING` of the rows between its outer beams without is warned of.
ROW_HELD_SHARE = 0.1
EMPTY_ROWS_WARNING = 0.1
ROWS_MIN_RETURNS = 1000
#: The percentiles of a scan's elevations :func:`learn_geometry` takes as its outer beams when it cannot count them.
LEARNT_PERCENTILES = (0.5, 99.5)
#: Counted rings are evenly spread (:func:`uniform_spacing_of`) when each lies within this share of a spacing of
#: the straight line through them (a deskewed sweep smears a ring by a tenth of a spacing or two), and there are
#: at least :data:`MIN_RINGS_FOR_SPACING` of them (an uneven sensor's, a VLP-32C's, lie several spacings off).
UNIFORM_TOLERANCE_ROWS = 0.75
MIN_RINGS_FOR_SPACING = 4
#: A learnt image of a sensor that fires fewer times a turn than the default's columns has this share of its
#: firings as columns (:func:`learnt_columns`), from the rings of at least :data:`MIN_RING_RETURNS` returns.
COLUMNS_PER_FIRING = 0.9
MIN_RING_RETURNS = 50

#: Two returns of a column on either side of a pixel centre's elevation are one surface when their ranges differ
#: by at most this (m) plus what a surface at :data:`SURFACE_INCIDENCE` from the rays changes over their gap ...
SURFACE_STEP = 0.02
#: ... (degrees); a steeper pair is one surface only when a third return continues its straight line, within
#: :data:`LINE_TOLERANCE`: metres plus a share of the range (a gently curved surface, the column's width).
SURFACE_INCIDENCE = 70.0
LINE_TOLERANCE = (0.02, 0.01)
#: The widest elevation gap (in row spacings) a pixel centre is carried across: a beam that missed between two;
#: for a pixel no return fell in, returns off their rows only (a missed beam leaves a gap of two rows).
WIDEST_GAP_ROWS = 2.5
WIDEST_GAP_EMPTY_ROWS = 1.5


class LidarGeometryWarning(UserWarning):
    """Many of a LiDAR scan's points fall outside the range image: the recording's ``[lidar]`` table is missing or wrong."""


@dataclasses.dataclass(frozen=True)
class ScanFit:
    """How a scan's points fit a geometry: its returns (finite, off the origin) and those outside the image."""

    returns: int
    above: int  # above the image's top edge
    below: int  # below its bottom edge
    beyond: int  # between the edges, at or beyond range_max
    elevation_high: float  # the returns' 99.5th percentile elevation, degrees (NaN: no return)
    elevation_low: float  # their 0.5th percentile

    @property
    def outside(self) -> int:
        return self.above + self.below + self.beyond

    @property
    def share(self) -> float:
        """The share of the returns outside the image (0 for a scan of none)."""
        return self.outside / self.returns if self.returns else 0.0

    def describe(self, geometry: SphericalGeometry) -> str:
        """The numbers in words: the share outside, why, and the points' elevations against the image's."""
        top, bottom = image_edges(geometry)
        return (
            f"{100 * self.share:.0f}% of its {self.returns} points fall outside the range image ({self.above} above its "
            f"top edge, {self.below} below its bottom edge, {self.beyond} at or beyond range_max {geometry.range_max:g} m): "
            f"the points' elevations span {self.elevation_high:+.1f} to {self.elevation_low:+.1f} degrees "
            f"(0.5-99.5 percentiles), the image's {top:+.1f} to {bottom:+.1f}"
        )


def learnt_settings(geometry: SphericalGeometry) -> str:
    """The ``[lidar]`` keys a learnt ``geometry`` sets, as a run says them."""
    return f"fov_up = {geometry.fov_up:g}, fov_down = {geometry.fov_down:g}, beams = {geometry.beams}, columns = {geometry.columns}"


def table_advice(file) -> str:
    """What to put in the ``[lidar]`` table of ``file`` (a recording's ``mabdi.toml``) where the geometry misses."""
    return (
        f"put the sensor's own geometry in the [lidar] table of {file}: fov_up, fov_down (degrees, the image's top "
        "and bottom edges), beams, and as needed columns, range_min, range_max (m), beam_elevations (degrees, one a "
        "beam, top first)"
    )


def rows_without_returns(return_points) -> tuple[int, int]:
    """(rows that hold no returns, rows spanned) between the top and the bottom row of a range image's returns
    (``return_points`` (H, W, 3), NaN where no return fell: :func:`range_image_and_returns`). A row holds returns
    when at least :data:`ROW_HELD_SHARE` of the median such row's do; a row between two that hold returns and
    none of its own is one the image has and the sensor has no beam for: nothing is meshed across it. A scan of
    fewer than :data:`ROWS_MIN_RETURNS` returns is too sparse to tell: (0, 0)."""
    held = np.isfinite(np.asarray(return_points)).all(axis=-1).sum(axis=1)
    if held.sum() < ROWS_MIN_RETURNS:
        return 0, 0
    holds = held >= ROW_HELD_SHARE * np.median(held[held > 0])
    rows = np.flatnonzero(holds)
    spanned = holds[rows[0] : rows[-1] + 1]
    return int((~spanned).sum()), len(spanned)


def image_edges(geometry: SphericalGeometry) -> tuple[float, float]:
    """The elevations (degrees) of a range image's top and bottom edges, as :meth:`SphericalGeometry.pixels` bounds them."""
    rays = geometry.rays_at(np.zeros(2), np.array([0.0, geometry.beams]))
    top, bottom = np.degrees(np.arcsin(np.clip(rays[:, 2], -1.0, 1.0)))
    return float(top), float(bottom)


def _returns(points, range_min: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The finite returns of ``points`` (N, 3) m farther than ``range_min`` m, and their elevations (degrees)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(points).all(axis=1) & (np.linalg.norm(points, axis=1) > max(range_min, 0.0))
    points = points[keep]
    return points, np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def scan_fit(points, geometry: SphericalGeometry) -> ScanFit:
    """How sensor-frame ``points`` (N, 3) m fit the range image of ``geometry`` (:class:`ScanFit`); returns at or
    within its ``range_min`` (the vehicle or person carrying the sensor) are no returns of the scene, left out."""
    points, elevation = _returns(points, geometry.range_min)
    uv, distance = geometry.pixels(points)
    above, below = uv[:, 1] < 0, uv[:, 1] >= geometry.beams
    beyond = ~above & ~below & (distance >= geometry.range_max)
    high, low = (np.percentile(elevation, LEARNT_PERCENTILES[::-1]) if len(elevation) else (np.nan, np.nan))
    return ScanFit(len(points), int(above.sum()), int(below.sum()), int(beyond.sum()), float(high), float(low))


def beam_elevations_of(elevation, step: float = 0.05) -> np.ndarray | None:
    """The beams' elevations (degrees, top first) of a scan's point elevations (degrees) when its rings stand
    clearly apart, else None.

    A histogram of ``step``-degree bins whose filled runs are the rings (runs one empty bin apart joined: a ring
    smeared by deskewing); a run holding under a quarter of the median run's points is no beam (stray returns
    between rings), and runs closer than half the median spacing are one beam. Taken only when the beams hold
    90% of the points, fill at most half the span, and number 2 to 512.
    """
    elevation = np.asarray(elevation, dtype=np.float64)
    if len(elevation) < 100 or np.ptp(elevation) < 4 * step:
        return None
    index = np.floor((elevation - elevation.min()) / step).astype(np.int64)
    counts = np.bincount(index)
    filled = counts >= max(2, 0.01 * counts.max())
    before = np.concatenate([[False], filled[:-1]])
    after = np.concatenate([filled[1:], [False]])
    filled |= before & after
    start = filled & ~np.concatenate([[False], filled[:-1]])
    runs = int(start.sum())
    if not (2 <= runs and filled.sum() <= 0.5 * len(filled)):
        return None
    run = (np.cumsum(start) - 1)[index]
    in_runs = filled[index]
    held = np.bincount(run[in_runs], minlength=runs)
    sums = np.bincount(run[in_runs], weights=elevation[in_runs], minlength=runs)
    beam = held >= 0.25 * np.median(held)
    held, sums = held[beam], sums[beam]
    if len(held) >= 2:
        centres = sums / held
        spacing = np.median(np.diff(centres))
        group = np.concatenate([[0], np.cumsum(np.diff(centres) >= 0.5 * spacing)])
        held, sums = np.bincount(group, weights=held), np.bincount(group, weights=sums)
    beams = len(held)
    if not (2 <= beams <= 512 and held.sum() >= 0.9 * len(elevation)):
        return None
    return (sums / held)[::-1]


def uniform_spacing_of(centres, tolerance: float = UNIFORM_TOLERANCE_ROWS) -> float | None:
    """The spacing (degrees) of beams at ``centres`` (degrees, top first) when they are evenly spread: each within
    ``tolerance`` of a spacing of the straight line through them; else None (an uneven sensor, or rings merged)."""
    if centres is None or len(centres) < MIN_RINGS_FOR_SPACING:
        return None
    index = np.arange(len(centres))
    slope, offset = np.polyfit(index, centres, 1)
    if slope >= 0 or np.abs(offset + slope * index - centres).max() > tolerance * abs(slope):
        return None
    return float(-slope)


def learn_geometry(scans, default: SphericalGeometry) -> tuple[SphericalGeometry | None, ScanFit]:
    """The geometry of a recording whose first scan does not fit ``default`` (more than :data:`OUTSIDE_SHARE_LEARN`
    of its points above or below the image), and how that scan fit ``default``; None when it fits, or misses by
    range only. ``scans``: the first scan's sensor-frame points (N, 3) m, or a list of the first few scans' (a
    moving sensor smears its rings in some scans). Returns within ``default.range_min`` (the carrier) are left out.

    Uniform beams, the edges half a beam spacing beyond the outer beams (so each beam lies on a row's centre):

    1. the rings of the first scan whose rings stand apart and are evenly spread (:func:`beam_elevations_of`,
       :func:`uniform_spacing_of`);
    2. else, the spacing of the first evenly spread rings of returns beyond a scan's median range (far away, a
       ring keeps its elevation: near ones are smeared by deskewing and the lasers' offsets from the sensor's
       origin), over the span between the :data:`LEARNT_PERCENTILES` of the first scan's elevations;
    3. else (rings uneven, or smeared in every scan), ``default``'s beam count over that span.

    Columns: ``default``'s, fewer where the sensor fires fewer times a turn (:func:`learnt_columns`); range:
    ``default``'s.
    """
    scans = [scans] if isinstance(scans, np.ndarray) else list(scans)
    fit = scan_fit(scans[0], default)
    if not fit.returns or fit.above + fit.below <= OUTSIDE_SHARE_LEARN * fit.returns:
        return None, fit
    top, bottom = fit.elevation_high, fit.elevation_low
    if not top > bottom:
        return None, fit
    returns = [_returns(points, default.range_min) for points in scans]
    learnt = _uniform(default, default.beams, top, bottom)
    for _, elevation in returns:
        centres = beam_elevations_of(elevation)
        if uniform_spacing_of(centres) is not None:
            learnt = _uniform(default, len(centres), float(centres[0]), float(centres[-1]))
            break
    else:
        for points, elevation in returns:
            distance = np.linalg.norm(points, axis=1)
            far = elevation[distance > np.median(distance)] if len(distance) else elevation
            if len(far) and (spacing := uniform_spacing_of(beam_elevations_of(far))):
                learnt = _uniform(default, int(round((top - bottom) / spacing)) + 1, top, bottom)
                break
    return dataclasses.replace(learnt, columns=learnt_columns(returns[0][0], learnt)), fit


def learnt_columns(points, geometry: SphericalGeometry) -> int:
    """The columns of an image of ``geometry`` for a scan's returns ``points`` (N, 3): ``geometry.columns``, or
    where the sensor fires fewer times a turn than that (the median azimuth step between a ring's neighbouring
    returns), :data:`COLUMNS_PER_FIRING` of its firings a turn: a column for every firing leaves columns empty
    where the firings drift across column edges, and nothing meshes across an empty column."""
    uv, _ = geometry.pixels(points)
    row = np.floor(uv[:, 1]).astype(np.int64)
    inside = (row >= 0) & (row < geometry.beams)
    azimuth = np.arctan2(points[inside, 1], points[inside, 0])
    steps = []
    for beam in np.unique(row[inside]):
        ring = np.sort(azimuth[row[inside] == beam])
        if len(ring) >= MIN_RING_RETURNS:
            steps.append(np.median(np.diff(ring)))
    if not steps or not np.median(steps) > 0:
        return geometry.columns
    per_turn = 2.0 * np.pi / float(np.median(steps))
    return geometry.columns if per_turn >= geometry.columns else max(int(COLUMNS_PER_FIRING * per_turn), 1)


def _uniform(default: SphericalGeometry, beams: int, top: float, bottom: float) -> SphericalGeometry:
    """``default`` with ``beams`` uniform beams from ``top`` to ``bottom`` (degrees), the edges half a spacing
    beyond."""
    half = (top - bottom) / (2 * (beams - 1)) if beams > 1 else 0.5
    fov_up, fov_down = min(90.0, round(top + half, 3)), max(-90.0, round(bottom - half, 3))
    return dataclasses.replace(default, beams=beams, fov_up=fov_up, fov_down=fov_down, beam_elevations=())


def range_image(points, geometry: SphericalGeometry, rows=None, centred: bool = True) -> np.ndarray:
    """(beams, columns) float32 range image (m, NaN = no point) of sensor-frame ``points`` (N, 3) m.

    ``rows`` (N,) integers: each point's row (top beam 0), from its ring index (:func:`rows_from_rings`);
    None: the row follows from the point's elevation, and with ``centred`` each pixel holds the range along its
    centre's ray where the returns around it allow (module docs). Otherwise the nearest point of a pixel wins.
    """
    return range_image_and_returns(points, geometry, rows, centred)[0]


def range_image_and_returns(points, geometry: SphericalGeometry, rows=None, centred: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`range_image`, and (beams, columns, 3) float32 the sensor-frame point (m) of the return each pixel
    took its range from: the nearest that fell in it (NaN: none fell in it). The range image says where each
    pixel centre's ray meets the surface, for comparing with the map's image; the returns say where the sensor
    measured it, for meshing (``returns`` of :class:`mabdi.depth.DepthFrame`)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uv, distance = geometry.pixels(points)
    binned, fell, chosen = _binned(uv, distance, geometry, rows)
    returns = np.full((*geometry.shape, 3), np.nan, dtype=np.float32)
    held = chosen >= 0
    returns[held] = points[chosen[held]]
    if rows is None and centred:
        return _carried_to_centres(points, uv, distance, geometry, binned, fell, chosen), returns
    return binned, returns


def _binned(uv, distance, geometry: SphericalGeometry, rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The range image whose pixels hold the nearest of the points (their pixel coordinates ``uv`` and ranges)
    that fall in them, (H, W) how many fell in each, and (H, W) the index of the one each holds (-1: none)."""
    with np.errstate(invalid="ignore"):
        keep = (distance > geometry.range_min) & (distance < geometry.range_max)
    if rows is None:
        v = uv[:, 1]
        with np.errstate(invalid="ignore"):
            keep &= (v >= 0) & (v < geometry.beams)
        row = np.where(keep, np.floor(np.where(keep, v, 0.0)), 0).astype(np.int64)
    else:
        row = np.asarray(rows).reshape(-1).astype(np.int64)
        if row.shape != (len(distance),):
            raise ValueError(f"range_image: {len(distance)} points but {row.shape[0]} rows")
        keep &= (row >= 0) & (row < geometry.beams)
    column = np.minimum(np.floor(np.where(keep, uv[:, 0], 0.0)).astype(np.int64), geometry.columns - 1)
    pixel = (row * geometry.columns + column)[keep]
    distance = distance[keep]
    index = np.flatnonzero(keep)
    image = np.full(geometry.beams * geometry.columns, np.nan, dtype=np.float32)
    chosen = np.full(image.size, -1, dtype=np.int64)
    fell = np.bincount(pixel, minlength=image.size).astype(np.int32).reshape(geometry.shape)
    if len(pixel):
        order = np.lexsort((distance, pixel))  # by pixel, nearest first
        pixel, distance, index = pixel[order], distance[order], index[order]
        first = np.ones(len(pixel), dtype=bool)
        first[1:] = pixel[1:] != pixel[:-1]
        image[pixel[first]] = distance[first]
        chosen[pixel[first]] = index[first]
    return image.reshape(geometry.shape), fell, chosen.reshape(geometry.shape)


def _carried_to_centres(points, uv, distance, geometry: SphericalGeometry, binned, fell, chosen) -> np.ndarray:
    """``binned`` with each pixel's range carried to its centre's ray where the returns around it show one
    surface (module docs): along its column (elevation), then along its row (azimuth)."""
    with np.errstate(invalid="ignore"):
        keep = (distance > geometry.range_min) & (distance < geometry.range_max) & np.isfinite(uv).all(axis=1)
    if keep.sum() < 3:
        return binned
    kept = np.flatnonzero(keep)
    centres = geometry.elevations()  # (beams,) radians, decreasing down the image
    spacing = abs(float(centres[0] - centres[-1])) / (geometry.beams - 1) if geometry.beams > 1 else np.radians(1.0)
    column = np.minimum(np.floor(uv[kept, 0]).astype(np.int64), geometry.columns - 1)
    elevation = np.arctan2(points[kept, 2], np.hypot(points[kept, 0], points[kept, 1]))
    low = min(float(elevation.min()), float(centres.min())) - 1e-6
    span = max(float(elevation.max()), float(centres.max())) + 1e-6 - low
    key = column + (elevation - low) / span  # in [column, column + 1): by column, then by elevation
    order = np.argsort(key, kind="stable")
    key, sorted_index = key[order], kept[order]
    upper = np.searchsorted(key, np.arange(geometry.columns)[None, :] + ((centres - low) / span)[:, None], side="left")
    image = binned.copy()
    _carry_kernel(image, fell, chosen, upper.astype(np.int64), key, column[order], elevation[order], sorted_index, points,
                  centres, geometry.azimuths(), spacing / span, spacing)
    return image


@njit(cache=True)
def _one_surface(ra, rb, angle, steep, pax, pay, pbx, pby, pox, poy, tolerance):
    """Whether returns a and b (ranges ``ra``, ``rb`` m, ``angle`` radians apart) are one surface: their ranges
    within SURFACE_STEP plus a ``steep`` surface's change, or the 2-D point o (``pox``, ``poy``: a third return
    beyond a) continuing the line b-a in the plane of a, b and o within ``tolerance`` (NaN ``pox``: none)."""
    if abs(rb - ra) <= SURFACE_STEP + 0.5 * (ra + rb) * angle * steep:
        return True
    if not np.isfinite(pox):
        return False
    lx, ly = pox - pbx, poy - pby
    sx, sy = pax - pbx, pay - pby
    length = np.hypot(lx, ly)
    return length > 1e-9 and abs(lx * sy - ly * sx) / length <= tolerance


@njit(cache=True)
def _carry_kernel(image, fell, chosen, upper, key, column, elevation, index, points, centres, azimuths, row_key, spacing):
    """In place (module docs): (1) each pixel whose centre elevation lies between the sorted returns
    ``upper[r, c] - 1`` and ``upper[r, c]`` of its column, one surface in the column's vertical plane, takes
    the point where their segment passes that elevation, else its own nearest return (``chosen``); (2) each
    pixel's point and the next one's in its row on the other side of the centre's azimuth, one surface in
    the horizontal plane, give the point at the centre's azimuth; (3) a pixel still empty between two of its
    row's, one holding two or more returns (``fell``), takes their mean. ``index`` maps the sorted returns to
    ``points``; ``row_key`` is a row spacing in units of ``key``; ``spacing`` in radians."""
    rows, columns = image.shape
    n = len(key)
    steep = np.tan(np.radians(SURFACE_INCIDENCE))
    carried = np.full((rows, columns, 3), np.nan)
    for r in range(rows):
        for c in range(columns):
            if chosen[r, c] >= 0:
                carried[r, c] = points[chosen[r, c]]
            hi = upper[r, c]
            lo = hi - 1
            if lo < 0 or hi >= n or column[lo] != c or column[hi] != c:
                continue
            gap = elevation[hi] - elevation[lo]
            widest = WIDEST_GAP_ROWS if chosen[r, c] >= 0 else WIDEST_GAP_EMPTY_ROWS
            if gap > widest * spacing:
                continue
            a, b = points[index[lo]], points[index[hi]]
            ra = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
            rb = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
            pax, pay = np.hypot(a[0], a[1]), a[2]
            pbx, pby = np.hypot(b[0], b[1]), b[2]
            one = False
            for side in range(2):  # a third return at least half a row beyond either end
                if side == 0:
                    outer = np.searchsorted(key, key[lo] - 0.5 * row_key, side="right") - 1
                else:
                    outer = np.searchsorted(key, key[hi] + 0.5 * row_key, side="left")
                pox, poy = np.nan, np.nan
                if 0 <= outer < n and column[outer] == c:
                    o = points[index[outer]]
                    pox, poy = np.hypot(o[0], o[1]), o[2]
                near_range = ra if side == 0 else rb
                tolerance = LINE_TOLERANCE[0] + LINE_TOLERANCE[1] * near_range
                if (side == 0 and _one_surface(ra, rb, gap, steep, pax, pay, pbx, pby, pox, poy, tolerance)) or (
                    side == 1 and _one_surface(rb, ra, gap, steep, pbx, pby, pax, pay, pox, poy, tolerance)
                ):
                    one = True
                    break
            if not one:
                continue
            t = min(max((centres[r] - elevation[lo]) / gap if gap > 0 else 0.0, 0.0), 1.0)
            for i in range(3):
                carried[r, c, i] = a[i] + t * (b[i] - a[i])
    # along the rows: to the centre's azimuth (column c's azimuth falls as c grows)
    step = 2.0 * np.pi / columns
    for r in range(rows):
        for c in range(columns):
            p = carried[r, c]
            if not np.isfinite(p[0]):
                continue
            az = np.arctan2(p[1], p[0])
            off = np.angle(np.exp(1j * (az - azimuths[c])))  # radians, wrapped
            value = np.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
            other = (c + 1) % columns if off > 0 else (c - 1) % columns  # the neighbour across the centre
            beyond = (c - 1) % columns if off > 0 else (c + 1) % columns
            q = carried[r, other]
            if off != 0.0 and np.isfinite(q[0]):
                qaz = np.arctan2(q[1], q[0])
                qoff = np.angle(np.exp(1j * (qaz - azimuths[c])))
                if qoff * off < 0:
                    rq = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
                    o = carried[r, beyond]
                    pox, poy = (o[0], o[1]) if np.isfinite(o[0]) else (np.nan, np.nan)
                    tolerance = LINE_TOLERANCE[0] + LINE_TOLERANCE[1] * value
                    if _one_surface(value, rq, abs(qoff - off), steep, p[0], p[1], q[0], q[1], pox, poy, tolerance):
                        t = off / (off - qoff)
                        x0, x1, x2 = p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]), p[2] + t * (q[2] - p[2])
                        value = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            image[r, c] = np.float32(value)
    # a pixel still empty between its row's neighbours, one surface: a return that slid into the next column
    filled = image.copy()
    for r in range(rows):
        for c in range(columns):
            if np.isfinite(image[r, c]):
                continue
            left, right = image[r, (c - 1) % columns], image[r, (c + 1) % columns]
            slid = fell[r, (c - 1) % columns] >= 2 or fell[r, (c + 1) % columns] >= 2
            if slid and np.isfinite(left) and np.isfinite(right):
                if abs(left - right) <= SURFACE_STEP + 0.5 * (left + right) * 2.0 * step * steep:
                    filled[r, c] = 0.5 * (left + right)
    image[:, :] = filled


def range_image_points(depth, geometry: SphericalGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The returns of a range image as sensor-frame points: (N, 3) float64 range times each pixel's unit ray
    (m), and (N,) their rows and columns (row-major order); the inverse of :func:`range_image` for points at
    pixel centres."""
    depth = np.asarray(depth)
    if depth.shape != geometry.shape:
        raise ValueError(f"range image has shape {depth.shape}, the geometry says {geometry.shape}")
    rows, columns = np.nonzero(np.isfinite(depth))
    points = geometry.rays()[rows, columns] * depth[rows, columns, None].astype(np.float64)
    return points, rows, columns


def rows_from_rings(rings, points, beams: int) -> np.ndarray:
    """(N,) image rows (0 = the top beam) of points by their ring index (N,) and sensor-frame ``points`` (N, 3).

    Sensors number their beams either way (Velodyne's ``ring`` 0 is the lowest beam, Ouster's the highest):
    when the lowest-numbered ring of the scan looks lower than the highest-numbered one (mean elevation of its
    points), rings are counted from the bottom and the row is ``beams - 1 - ring``; otherwise the row is the ring.
    A ring outside 0 .. beams - 1 is a ValueError.
    """
    rings = np.asarray(rings).reshape(-1).astype(np.int64)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(rings) and (rings.min() < 0 or rings.max() >= beams):
        bad = int(rings[(rings < 0) | (rings >= beams)][0])
        raise ValueError(f"ring {bad} is outside 0 .. {beams - 1} (the range image has {beams} beams)")
    with np.errstate(invalid="ignore", divide="ignore"):
        elevation = np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1]))
        valid = np.isfinite(elevation) & (np.linalg.norm(points, axis=1) > 0)
    seen = np.unique(rings[valid])
    if len(seen) >= 2:
        low = elevation[valid & (rings == seen[0])].mean()
        high = elevation[valid & (rings == seen[-1])].mean()
        if low < high:
            return beams - 1 - rings
    return rings


def lidar_table(geometry: SphericalGeometry) -> dict:
    """The ``[lidar]`` table of a recording's ``mabdi.toml`` for ``geometry`` (the beam table only when it has one)."""
    table = {name: getattr(geometry, name) for name in LIDAR_KEYS}
    table["beam_elevations"] = list(geometry.beam_elevations)
    if not table["beam_elevations"]:
        del table["beam_elevations"]
    return table


def geometry_from_table(table, file, default: SphericalGeometry | None = None) -> SphericalGeometry:
    """The :class:`SphericalGeometry` of a recording's ``[lidar]`` table (keys :data:`LIDAR_KEYS`; the others from
    ``default``, else the class defaults); a bad table is a :class:`SequenceError` naming ``file`` and the key."""
    if not isinstance(table, dict):
        raise SequenceError(f"{file}: 'lidar' must be a table")
    values = dataclasses.asdict(default) if default is not None else {}
    for key, value in table.items():
        if key not in LIDAR_KEYS:
            raise SequenceError(f"{file}: unknown key 'lidar.{key}' (known: {', '.join(LIDAR_KEYS)})")
        numbers = value if key == "beam_elevations" and isinstance(value, list) else [value]
        if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in numbers):
            raise SequenceError(f"{file}: 'lidar.{key}' must be {'a list of numbers' if key == 'beam_elevations' else 'a number'}, got {value!r}")
        values[key] = tuple(value) if key == "beam_elevations" else value
    try:
        return SphericalGeometry(**values)
    except (ConfigError, TypeError) as exc:
        raise SequenceError(f"{file}: [lidar]: {exc}") from None


__all__ = [
    "KITTI_GEOMETRY",
    "LIDAR_KEYS",
    "OUTSIDE_SHARE_LEARN",
    "OUTSIDE_SHARE_WARNING",
    "LidarGeometryWarning",
    "ScanFit",
    "beam_elevations_of",
    "geometry_from_table",
    "image_edges",
    "learn_geometry",
    "learnt_columns",
    "learnt_settings",
    "table_advice",
    "rows_without_returns",
    "EMPTY_ROWS_WARNING",
    "uniform_spacing_of",
    "lidar_table",
    "range_image",
    "range_image_and_returns",
    "range_image_points",
    "rows_from_rings",
    "scan_fit",
]
