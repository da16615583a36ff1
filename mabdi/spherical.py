"""The geometry of a spinning LiDAR's range image: beams by rows, azimuth by columns.

Conventions (every module that reads or writes a range image follows them):

* Sensor frame: x forward, y left, z up (ROS REP 103; Velodyne, Ouster and
  KITTI scans use it). A pose is a 4x4 float64 ``world_from_sensor`` matrix,
  stored in the image's field data under the same name as a camera's pose
  (``world_from_camera``), so every filter finds it in one place.
* Row r (0 = the top beam) looks at elevation ``elevations[r]`` (degrees,
  decreasing down the image). Uniform beams span ``fov_up`` at the top edge
  of row 0 to ``fov_down`` at the bottom edge of the last row, so beam r's
  centre is ``fov_up - (r + 0.5) (fov_up - fov_down) / beams``. A real
  sensor's non-uniform beam table is given instead as ``beam_elevations``.
* Column c looks at azimuth ``pi (1 - 2 (c + 0.5) / columns)`` (radians,
  counter-clockwise from x seen from above): column 0 looks backwards over
  the left, the centre column forwards, the last backwards over the right
  (the convention of range-image LiDAR segmentation, RangeNet++).
* Pixel (c, r) covers [c, c+1) x [r, r+1) like a camera's, and its ray is the
  unit vector (cos el cos az, cos el sin az, sin el).
* The image holds **range** along the ray in metres (not z-depth), NaN where
  there is no return; a return has ``range_min < range < range_max``.

Because a pinhole ray has z = 1 and holds z-depth while a spherical ray is a
unit vector and holds range, ``value * ray`` is the sensor-frame point for
both: :meth:`SphericalGeometry.rays` has the same meaning as
:meth:`mabdi.camera.Intrinsics.rays`, and ``near`` / ``far`` are the range
limits, so code written against a camera's rays and range reads a range
image unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from mabdi.camera import Intrinsics, check_pose
from mabdi.errors import ConfigError


#: Field-data array of a range image: beams, columns, fov_up, fov_down (degrees), range_min, range_max (m).
SPHERICAL_ARRAY = "spherical"
#: Optional field-data array of a range image: the elevation of each beam (degrees, top row first).
BEAM_ELEVATIONS_ARRAY = "beam_elevations"


@dataclass(frozen=True)
class SphericalGeometry:
    """A spinning LiDAR's range image: ``beams`` rows by ``columns`` azimuth steps over 360 degrees.

    ``fov_up`` / ``fov_down`` are the elevations (degrees) of the image's top and bottom edges; ``range_min``
    and ``range_max`` (metres) bound a return. ``beam_elevations`` (degrees, one per beam, strictly decreasing)
    replaces the uniform spacing for sensors whose beams are not evenly spread; empty means uniform.
    """

    #: The image holds range along each beam's ray.
    range_image: ClassVar[bool] = True
    #: 360 degrees of azimuth: the last column meets the first.
    wraps_around: ClassVar[bool] = True

    beams: int = 64
    columns: int = 1024
    fov_up: float = 2.0
    fov_down: float = -24.8
    range_min: float = 0.5
    range_max: float = 80.0
    beam_elevations: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        for name in ("beams", "columns"):
            value = getattr(self, name)
            if isinstance(value, float) and value.is_integer():
                object.__setattr__(self, name, int(value))
                value = int(value)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise ConfigError(f"lidar: {name} must be a positive integer, got {value!r}")
        if not (math.isfinite(self.fov_up) and math.isfinite(self.fov_down) and -90.0 <= self.fov_down < self.fov_up <= 90.0):
            raise ConfigError(f"lidar: need -90 <= fov_down < fov_up <= 90 (degrees), got fov_up={self.fov_up!r}, fov_down={self.fov_down!r}")
        if not (math.isfinite(self.range_min) and math.isfinite(self.range_max) and 0 < self.range_min < self.range_max):
            raise ConfigError(f"lidar: need 0 < range_min < range_max (metres), got {self.range_min!r}, {self.range_max!r}")
        if self.beam_elevations:
            table = np.asarray(self.beam_elevations, dtype=np.float64)
            if table.shape != (self.beams,) or not np.isfinite(table).all():
                raise ConfigError(f"lidar: beam_elevations must hold {self.beams} finite angles (one per beam), got {table.shape[0]}")
            if np.any(np.diff(table) >= 0):
                raise ConfigError("lidar: beam_elevations must decrease strictly from the top beam (row 0) down")
            object.__setattr__(self, "beam_elevations", tuple(float(a) for a in table))

    # -- the shape every image filter reads ---------------------------------
    @property
    def width(self) -> int:
        return self.columns

    @property
    def height(self) -> int:
        return self.beams

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as numpy sees it: (beams, columns)."""
        return (self.beams, self.columns)

    @property
    def near(self) -> float:
        """The smallest range that is a return (metres): the meaning ``near`` has for a camera's depth."""
        return self.range_min

    @property
    def far(self) -> float:
        """The largest range that is a return (metres)."""
        return self.range_max

    # -- angles and rays ------------------------------------------------------
    def elevations(self) -> np.ndarray:
        """(beams,) float64 elevation of each row's centre, radians (row 0 the top beam)."""
        if self.beam_elevations:
            return np.radians(np.asarray(self.beam_elevations, dtype=np.float64))
        step = (self.fov_up - self.fov_down) / self.beams
        return np.radians(self.fov_up - (np.arange(self.beams) + 0.5) * step)

    def azimuths(self) -> np.ndarray:
        """(columns,) float64 azimuth of each column's centre, radians in (-pi, pi)."""
        return math.pi * (1.0 - 2.0 * (np.arange(self.columns) + 0.5) / self.columns)

    def rays(self) -> np.ndarray:
        """(H, W, 3) unit sensor-frame rays through pixel centres (range times ray is the point)."""
        elevation = self.elevations()[:, None]
        azimuth = self.azimuths()[None, :]
        rays = np.empty((self.beams, self.columns, 3))
        rays[..., 0] = np.cos(elevation) * np.cos(azimuth)
        rays[..., 1] = np.cos(elevation) * np.sin(azimuth)
        rays[..., 2] = np.broadcast_to(np.sin(elevation), (self.beams, self.columns))
        return rays

    def rays_at(self, u, v) -> np.ndarray:
        """(..., 3) unit sensor-frame rays at continuous pixel coordinates (u column, v row; pixel corners at
        integers, centres at + 0.5, as :meth:`pixels` returns them). With a beam table, the elevation is linear
        between beam centres and beyond the outer ones."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        azimuth = math.pi * (1.0 - 2.0 * u / self.columns)
        if self.beam_elevations and self.beams > 1:
            centres = np.radians(np.asarray(self.beam_elevations))
            index = np.clip(np.floor(v - 0.5).astype(np.int64), 0, self.beams - 2)
            fraction = v - 0.5 - index
            elevation = centres[index] + fraction * (centres[index + 1] - centres[index])
        else:
            elevation = np.radians(self.fov_up - v * (self.fov_up - self.fov_down) / self.beams)
        return np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1)

    def row_edges(self) -> np.ndarray:
        """(beams + 1,) elevations (radians) of the rows' edges, decreasing from the image's top edge: uniform rows
        span fov_up to fov_down; a beam table's rows meet halfway between beam centres and the outer rows reach
        half their spacing beyond, as :meth:`pixels` reads them (a point lies in row r where
        ``edges[r] >= elevation > edges[r + 1]``)."""
        if not self.beam_elevations or self.beams < 2:
            return np.radians(np.linspace(self.fov_up, self.fov_down, self.beams + 1))
        centres = np.asarray(self.beam_elevations, dtype=np.float64)
        edges = np.empty(self.beams + 1)
        edges[1:-1] = 0.5 * (centres[:-1] + centres[1:])
        edges[0] = centres[0] + 0.5 * (centres[0] - centres[1])
        edges[-1] = centres[-1] - 0.5 * (centres[-2] - centres[-1])
        return np.radians(edges)

    def pixels(self, sensor_points) -> tuple[np.ndarray, np.ndarray]:
        """Continuous pixel coordinates of sensor-frame points (N, 3), and (N,) their range (m).

        Returns ``(uv, range)`` with u the column and v the row, so ``floor(uv)`` is the pixel a point falls in
        (u wraps into [0, columns)). With a beam table, v is piecewise linear between beam centres, and a point
        beyond the outer beams' half spacing gets v outside [0, beams).
        """
        points = np.asarray(sensor_points, dtype=np.float64).reshape(-1, 3)
        horizontal = np.hypot(points[:, 0], points[:, 1])
        distance = np.sqrt(horizontal**2 + points[:, 2] ** 2)
        azimuth = np.arctan2(points[:, 1], points[:, 0])
        u = np.mod(0.5 * (1.0 - azimuth / math.pi) * self.columns, self.columns)
        elevation = np.degrees(np.arctan2(points[:, 2], horizontal))
        if self.beam_elevations:
            centres = np.asarray(self.beam_elevations)[::-1]  # increasing
            rows = np.arange(self.beams, dtype=np.float64)[::-1] + 0.5
            top = centres[-1] + 0.5 * (centres[-1] - centres[-2]) if self.beams > 1 else centres[-1] + 0.5
            bottom = centres[0] - 0.5 * (centres[1] - centres[0]) if self.beams > 1 else centres[0] - 0.5
            v = np.interp(elevation, np.concatenate([[bottom], centres, [top]]), np.concatenate([[self.beams], rows, [0.0]]),
                          left=np.inf, right=-np.inf)
        else:
            v = (self.fov_up - elevation) / (self.fov_up - self.fov_down) * self.beams
        return np.stack([u, v], axis=1), distance

    # -- the questions every sensor geometry answers (the camera's: mabdi.camera.Intrinsics) -----------
    def pixels_per_radian(self) -> float:
        """How many pixels one radian of azimuth spans: columns / 2 pi."""
        return self.columns / (2.0 * math.pi)

    def pixel_angle(self) -> float:
        """The largest angle (radians) between neighbouring pixels' rays: the azimuth step or the widest beam
        spacing."""
        elevations = self.elevations()
        spacing = float(np.abs(np.diff(elevations)).max()) if len(elevations) > 1 else 0.0
        return max(2.0 * math.pi / self.columns, spacing)

    def pair_angles(self) -> np.ndarray:
        """(beams - 1,) the angle (radians) between the rays of each row and the next, or across a row (the
        azimuth step), whichever is larger: :meth:`pixel_angle` for every pair of rows of a uniform image; a beam
        table's own spacing, row by row (an uneven sensor's dense beams are not judged by its widest gap)."""
        if not self.beam_elevations or self.beams < 2:
            return np.full(max(self.beams - 1, 0), self.pixel_angle())
        return np.maximum(2.0 * math.pi / self.columns, np.abs(np.diff(self.elevations())))

    def jump_scale(self) -> float:
        """What a relative depth jump between neighbouring pixels scales by: :meth:`pixel_angle` over the default
        camera's (1 / ``Intrinsics.fx``): the same surface at the same incidence spreads that much more between
        neighbouring beams."""
        return self.pixel_angle() * Intrinsics.fx

    def sensor_values(self, sensor_points) -> np.ndarray:
        """(...) the image's value for sensor-frame points (..., 3): their range (metres)."""
        return np.linalg.norm(np.asarray(sensor_points), axis=-1)

    def project_points(self, points, world_from_sensor) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) to continuous pixel coordinates (N, 2: u column, v row; the pixel is ``floor``)
        and (N,) their range (metres) (:meth:`pixels`)."""
        pose = check_pose(world_from_sensor, "world_from_sensor")
        local = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]
        return self.pixels(local)

    # -- field data ---------------------------------------------------------------
    def to_array(self) -> np.ndarray:
        """float64[6]: beams, columns, fov_up, fov_down, range_min, range_max (the field-data layout)."""
        return np.array([self.beams, self.columns, self.fov_up, self.fov_down, self.range_min, self.range_max], dtype=np.float64)

    @classmethod
    def from_array(cls, values, beam_elevations=None) -> SphericalGeometry:
        """Inverse of :meth:`to_array` (with the beam table, if the image has one)."""
        a = np.asarray(values, dtype=np.float64).ravel()
        if a.shape != (6,):
            raise ConfigError(f"spherical geometry array must have 6 values (beams, columns, fov_up, fov_down, range_min, range_max), got shape {a.shape}")
        table = () if beam_elevations is None else tuple(float(x) for x in np.asarray(beam_elevations).ravel())
        return cls(int(round(a[0])), int(round(a[1])), float(a[2]), float(a[3]), float(a[4]), float(a[5]), table)


def on_for_range_images(switch: bool | str, geometry) -> bool:
    """A true / false / "auto" switch (:func:`mabdi.errors.check_switch`) for an image of ``geometry``: "auto" is
    on for a LiDAR's range image (a :class:`SphericalGeometry`) and off for a camera's."""
    return switch is True or (switch == "auto" and geometry.range_image)
