"""LiDAR scans as range images: points (and their ring index, when the data has one) to a range image.

A recording holds a spinning LiDAR's scans as points in the sensor frame
(x forward, y left, z up): KITTI's ``velodyne/*.bin`` files
(:mod:`mabdi.sources.kitti`), ``sensor_msgs/msg/PointCloud2`` messages in a
ROS 2 bag (:mod:`mabdi.sources.rosbag2`). :func:`range_image` turns one scan
into the range image of a :class:`~mabdi.spherical.SphericalGeometry` (the
one convention, :mod:`mabdi.spherical`), the one place this is done:

* the column of a point is its azimuth, by :meth:`SphericalGeometry.pixels`;
* its row is its ring (beam) index when the scan has one (a ``ring`` field,
  or the row of an organised cloud: :func:`rows_from_rings` turns rings into
  rows, top beam first, whichever way the sensor numbers them), else its
  elevation by :meth:`SphericalGeometry.pixels`;
* a pixel holds the range (m, along the point's own direction) of the
  nearest point that falls in it; points that are not returns (NaN,
  at the origin, outside ``range_min < range < range_max``) and points
  outside the image's rows are left out; a pixel no point falls in is NaN.

The image's rays (:meth:`SphericalGeometry.rays`) are the pixel centres'
directions, so a point off a pixel's centre is meshed up to half a pixel
(in angle) from where it was measured: choose the geometry to match the
sensor (:data:`KITTI_GEOMETRY` for KITTI's Velodyne HDL-64E).

A recording carries its geometry in the ``[lidar]`` table of its
``mabdi.toml`` (:func:`lidar_table`, :func:`geometry_from_table`): the keys
of :class:`SphericalGeometry`. A wrong or missing table loses points without
an error: :func:`scan_fit` counts a scan's points outside the image (above its
top edge, below its bottom one, at or beyond ``range_max``), for a
:class:`LidarGeometryWarning`, and :func:`learn_geometry` learns the vertical
field of view (and, where the scan's rings are clearly apart, the beam count)
of a scan that does not fit a default.
"""

from __future__ import annotations

import dataclasses

import numpy as np

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

#: A scan with more than this share of its points outside the range image is warned of (:class:`LidarGeometryWarning`).
OUTSIDE_SHARE_WARNING = 0.25
#: The percentiles of a scan's elevations :func:`learn_geometry` takes as its outer beams when it cannot count them.
LEARNT_PERCENTILES = (0.5, 99.5)


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


def image_edges(geometry: SphericalGeometry) -> tuple[float, float]:
    """The elevations (degrees) of a range image's top and bottom edges, as :meth:`SphericalGeometry.pixels` bounds them."""
    rays = geometry.rays_at(np.zeros(2), np.array([0.0, geometry.beams]))
    top, bottom = np.degrees(np.arcsin(np.clip(rays[:, 2], -1.0, 1.0)))
    return float(top), float(bottom)


def _returns(points) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(points).all(axis=1) & (np.abs(points).sum(axis=1) > 0)
    points = points[keep]
    return points, np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def scan_fit(points, geometry: SphericalGeometry) -> ScanFit:
    """How sensor-frame ``points`` (N, 3) m fit the range image of ``geometry`` (:class:`ScanFit`)."""
    points, elevation = _returns(points)
    uv, distance = geometry.pixels(points)
    above, below = uv[:, 1] < 0, uv[:, 1] >= geometry.beams
    beyond = ~above & ~below & (distance >= geometry.range_max)
    high, low = (np.percentile(elevation, LEARNT_PERCENTILES[::-1]) if len(elevation) else (np.nan, np.nan))
    return ScanFit(len(points), int(above.sum()), int(below.sum()), int(beyond.sum()), float(high), float(low))


def beam_elevations_of(elevation, step: float = 0.05) -> np.ndarray | None:
    """The beams' elevations (degrees, top first) of a scan's point elevations (degrees) when its rings stand
    clearly apart, else None: a histogram of ``step``-degree bins whose filled runs are the rings, taken only
    when they hold 95% of the points, fill at most half the span, and number 2 to 512."""
    elevation = np.asarray(elevation, dtype=np.float64)
    if len(elevation) < 100 or np.ptp(elevation) < 4 * step:
        return None
    index = np.floor((elevation - elevation.min()) / step).astype(np.int64)
    counts = np.bincount(index)
    filled = counts >= max(2, 0.01 * counts.max())
    start = filled & ~np.concatenate([[False], filled[:-1]])
    run = np.cumsum(start) - 1  # each bin's run (ring), meaningful where filled
    beams = int(start.sum())
    in_rings = filled[index]
    if not (2 <= beams <= 512 and in_rings.mean() >= 0.95 and filled.sum() <= 0.5 * len(filled)):
        return None
    ring = run[index[in_rings]]
    centres = np.bincount(ring, weights=elevation[in_rings], minlength=beams) / np.bincount(ring, minlength=beams)
    return centres[::-1]


def learn_geometry(points, default: SphericalGeometry) -> tuple[SphericalGeometry | None, ScanFit]:
    """The geometry of a scan that does not fit ``default`` (more than :data:`OUTSIDE_SHARE_WARNING` of its points
    above or below the image), and how it fit ``default``; None when it fits, or misses by range only.

    Uniform beams: the counted rings (:func:`beam_elevations_of`) when they stand apart, else ``default``'s count
    between the :data:`LEARNT_PERCENTILES` of the elevations; the edges half a beam spacing beyond the outer beams
    (so each beam lies on a row's centre). Columns and range are ``default``'s.
    """
    fit = scan_fit(points, default)
    if not fit.returns or fit.above + fit.below <= OUTSIDE_SHARE_WARNING * fit.returns:
        return None, fit
    centres = beam_elevations_of(_returns(points)[1])
    if centres is not None:
        beams, top, bottom = len(centres), float(centres[0]), float(centres[-1])
    else:
        beams, top, bottom = default.beams, fit.elevation_high, fit.elevation_low
    if not top > bottom:
        return None, fit
    half = (top - bottom) / (2 * (beams - 1)) if beams > 1 else 0.5
    fov_up, fov_down = min(90.0, round(top + half, 3)), max(-90.0, round(bottom - half, 3))
    return dataclasses.replace(default, beams=beams, fov_up=fov_up, fov_down=fov_down, beam_elevations=()), fit


def range_image(points, geometry: SphericalGeometry, rows=None) -> np.ndarray:
    """(beams, columns) float32 range image (m, NaN = no point) of sensor-frame ``points`` (N, 3) m.

    ``rows`` (N,) integers: each point's row (top beam 0), from its ring index (:func:`rows_from_rings`);
    None: the row follows from the point's elevation. The nearest point of a pixel wins (module docs).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uv, distance = geometry.pixels(points)
    with np.errstate(invalid="ignore"):
        keep = (distance > geometry.range_min) & (distance < geometry.range_max)
    if rows is None:
        v = uv[:, 1]
        with np.errstate(invalid="ignore"):
            keep &= (v >= 0) & (v < geometry.beams)
        row = np.where(keep, np.floor(np.where(keep, v, 0.0)), 0).astype(np.int64)
    else:
        row = np.asarray(rows).reshape(-1).astype(np.int64)
        if row.shape != (len(points),):
            raise ValueError(f"range_image: {len(points)} points but {row.shape[0]} rows")
        keep &= (row >= 0) & (row < geometry.beams)
    column = np.minimum(np.floor(np.where(keep, uv[:, 0], 0.0)).astype(np.int64), geometry.columns - 1)
    pixel = (row * geometry.columns + column)[keep]
    distance = distance[keep]
    image = np.full(geometry.beams * geometry.columns, np.nan, dtype=np.float32)
    if len(pixel):
        order = np.lexsort((distance, pixel))  # by pixel, nearest first
        pixel, distance = pixel[order], distance[order]
        first = np.ones(len(pixel), dtype=bool)
        first[1:] = pixel[1:] != pixel[:-1]
        image[pixel[first]] = distance[first]
    return image.reshape(geometry.shape)


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
    "OUTSIDE_SHARE_WARNING",
    "LidarGeometryWarning",
    "ScanFit",
    "beam_elevations_of",
    "geometry_from_table",
    "image_edges",
    "learn_geometry",
    "lidar_table",
    "range_image",
    "range_image_points",
    "rows_from_rings",
    "scan_fit",
]
