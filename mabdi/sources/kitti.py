"""KITTI-style LiDAR folders: read them as a frame source of range images, write any LiDAR frame source so.

The layout (KITTI odometry's ``sequences/NN`` folders, with the sequence's
poses file copied in as ``poses.txt``):

* ``velodyne/NNNNNN.bin``: one scan a file, float32 ``x y z intensity`` per
  point (sensor frame: x forward, y left, z up; metres); frames are the
  files in name order (a file's size is a whole number of 16-byte points,
  else an error). The intensity is not used. Or ``velodyne/NNNNNN.pcd``,
  PCL's files (:mod:`mabdi.sources.pcd`), as many datasets ship their scans.
* ``poses.txt``: one line a scan, the 12 numbers of a 3x4 matrix row-major
  (or 16, a 4x4 whose last row is 0 0 0 1):
  the pose of KITTI's camera 0 (x right, y down, z forward) in the frame of
  the first camera 0 (KITTI's ground truth, ``poses/NN.txt``).
* ``calib.txt`` (optional): lines ``KEY: numbers``; ``Tr:`` is the 3x4
  matrix from the Velodyne frame to camera 0 (``camera0_from_velodyne``).
  Without ``calib.txt`` the poses are the LiDAR's own (Tr = identity), unless the scans
  say they are a camera's (:mod:`mabdi.sources.pose_axes`: then turned, and said).
* ``times.txt`` (optional): one timestamp (s) a scan; without it the
  timestamps are unknown (NaN).
* ``mabdi.toml`` (optional): a ``[lidar]`` table, the range image's
  geometry (:mod:`mabdi.sources.range_images`: beams, columns, fov_up,
  fov_down, range_min, range_max, beam_elevations); without it
  :data:`~mabdi.sources.range_images.KITTI_GEOMETRY` (the HDL-64E), unless
  the first scan misses it: then the geometry learnt from the first
  :data:`LEARN_SCANS` scans (:func:`~mabdi.sources.range_images.learn_geometry`;
  more than 5% of the first scan's points above or below it). A scan with
  more than 5% of its points outside the image (above, below, beyond
  range_max) is said once, as a
  :class:`~mabdi.sources.range_images.LidarGeometryWarning` with the numbers
  and the ``[lidar]`` keys to set.

The pose of scan i is ``world_from_sensor = Tr^-1 P_i Tr`` (SemanticKITTI's
reading of the poses): the LiDAR's motion in a world that is the first
camera 0 frame turned back into the LiDAR's axes, so the world has z up
(the first scan's LiDAR frame when P_0 is the identity, as in KITTI).
Each scan becomes a range image by
:func:`~mabdi.sources.range_images.range_image` (rows by elevation: KITTI's
files have no ring index).
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from mabdi.camera import PoseRepairs
from mabdi.depth import DepthFrame
from mabdi.errors import PoseError, PoseFileWarning
from mabdi.io.atomic import atomic_output, write_text
from mabdi.io.toml_writer import toml_lines
from mabdi.sources.frames import FrameSource
from mabdi.sources.pose_axes import AXES_WORDS, pose_axes, turned
from mabdi.sources.pcd import read_pcd
from mabdi.sources.range_images import (
    EMPTY_ROWS_WARNING,
    KITTI_GEOMETRY,
    OUTSIDE_SHARE_WARNING,
    LidarGeometryWarning,
    geometry_from_table,
    learn_geometry,
    learnt_settings,
    lidar_table,
    range_image_and_returns,
    range_image_points,
    rows_without_returns,
    scan_fit,
    table_advice,
)
from mabdi.sources.sequence_files import SequenceError, metadata_path, prepare_folder, read_sequence_metadata
from mabdi.spherical import SphericalGeometry

SCAN_FOLDER = "velodyne"
#: A scan file's suffixes: KITTI's float32 x y z intensity, or a PCD file (:mod:`mabdi.sources.pcd`).
SCAN_SUFFIXES = (".bin", ".pcd")
POSES_FILE = "poses.txt"
CALIB_FILE = "calib.txt"
TIMES_FILE = "times.txt"
#: The scans a recording without a ``[lidar]`` table has its geometry learnt from (their rings counted in turn,
#: :func:`~mabdi.sources.range_images.learn_geometry`): a moving sensor smears its rings in some scans.
LEARN_SCANS = 10
#: float32 values per point in a scan file: x, y, z, intensity.
POINT_FIELDS = 4
#: Bytes per point in a scan file.
POINT_BYTES = 4 * POINT_FIELDS
#: The Tr of the folders :func:`write_kitti` writes: KITTI's axes (camera 0 = x right, y down, z forward from the
#: LiDAR's x forward, y left, z up) and a lever arm (m) like KITTI's, so a reader that skips Tr is caught by a test.
WRITTEN_TR = np.array([[0.0, -1.0, 0.0, -0.004], [0.0, 0.0, -1.0, -0.076], [1.0, 0.0, 0.0, -0.272], [0.0, 0.0, 0.0, 1.0]])


def is_kitti(path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / SCAN_FOLDER).is_dir() and (path / POSES_FILE).is_file()


def read_matrix_rows(path: Path, what: str) -> np.ndarray:
    """(N, 4, 4) poses of a file of 3x4 row-major matrices, one a line (blank lines skipped; a line of 16 numbers,
    a 4x4 whose last row is 0 0 0 1, as some tools write them, is read too), or a SequenceError naming the file
    and line."""
    matrices = []
    repairs = PoseRepairs()
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            fields = line.split()
            if not fields:
                continue
            try:
                values = [float(f) for f in fields]
            except ValueError:
                raise SequenceError(f"{path}:{number}: {what}: a field is not a number: {line.strip()!r}") from None
            if len(values) == 16 and np.isfinite(values).all():
                if not np.allclose(values[12:], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
                    raise SequenceError(f"{path}:{number}: {what}: a 4x4 matrix's last row must be 0 0 0 1, got {fields[12:]}")
                values = values[:12]
            if len(values) != 12 or not np.isfinite(values).all():
                raise SequenceError(
                    f"{path}:{number}: {what}: expected 12 finite numbers (a 3x4 matrix row-major; or 16, a 4x4), got {len(values)}"
                )
            matrices.append(_homogeneous(values, f"{path}:{number}", repairs))
    if (note := repairs.note(str(path))) is not None:
        warnings.warn(note, PoseFileWarning, stacklevel=2)
    return np.array(matrices, dtype=np.float64).reshape(-1, 4, 4)


def read_calibration(path: Path) -> np.ndarray:
    """The 4x4 ``Tr`` (Velodyne to camera 0) of a KITTI ``calib.txt``, or a SequenceError naming the file."""
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            key, colon, rest = line.partition(":")
            if colon and key.strip() == "Tr":
                try:
                    values = [float(f) for f in rest.split()]
                except ValueError:
                    raise SequenceError(f"{path}:{number}: Tr: a field is not a number") from None
                if len(values) != 12:
                    raise SequenceError(f"{path}:{number}: Tr: expected 12 numbers (a 3x4 matrix row-major), got {len(values)}")
                return _homogeneous(values, f"{path}:{number}: Tr")
    raise SequenceError(f"{path}: no 'Tr:' line (the Velodyne-to-camera-0 transform)")


def _homogeneous(values, where: str, repairs: PoseRepairs | None = None) -> np.ndarray:
    """The 4x4 of a 3x4 row-major matrix, its rotation made rigid (:func:`mabdi.camera.pose_from_file`; counted
    in ``repairs`` when given), or a SequenceError naming ``where``."""
    matrix = np.eye(4)
    matrix[:3, :] = np.asarray(values, dtype=np.float64).reshape(3, 4)
    try:
        return (repairs or PoseRepairs()).read(matrix, where)
    except PoseError as exc:
        raise SequenceError(f"{where}: not a rigid transform: {exc}") from None


def scan_files(folder: Path) -> list[Path]:
    """A KITTI folder's scan files in frame order, by their numbers (``000009`` before ``000010``, and ``9``
    before ``10`` where the names are not padded): ``velodyne/NNNNNN.bin``, or ``.pcd`` (not both); a name that
    is not a number, or both kinds, is a SequenceError naming the file."""
    scans = sorted(p for p in (folder / SCAN_FOLDER).iterdir() if p.suffix in SCAN_SUFFIXES)
    if not scans:
        raise SequenceError(f"KITTI folder {folder}: no .bin or .pcd scan in {SCAN_FOLDER}/")
    kinds = sorted({p.suffix for p in scans})
    if len(kinds) > 1:
        raise SequenceError(f"KITTI folder {folder}: {SCAN_FOLDER}/ holds both .bin and .pcd scans; keep one kind")
    odd = [p for p in scans if not re.fullmatch(r"\d+", p.stem)]
    if odd:
        raise SequenceError(f"{odd[0]}: a scan's name must be its number (NNNNNN{kinds[0]})")
    numbers = [int(p.stem) for p in scans]
    if len(set(numbers)) < len(numbers):
        twice = next(n for n in numbers if numbers.count(n) > 1)
        raise SequenceError(f"KITTI folder {folder}: two scans are number {twice} ({', '.join(p.name for p in scans if int(p.stem) == twice)})")
    return sorted(scans, key=lambda p: int(p.stem))


def read_scan(path: Path) -> np.ndarray:
    """(N, 3) float32 sensor-frame points of a KITTI ``.bin`` scan (float32 x y z intensity), or a SequenceError
    naming the file when it cannot be read or its size is not a whole number of 16-byte points; a ``.pcd`` scan's
    by :func:`~mabdi.sources.pcd.read_pcd`."""
    path = Path(path)
    if path.suffix == ".pcd":
        return read_pcd(path)
    try:
        size = os.stat(path).st_size
        raw = np.fromfile(path, dtype="<f4")
    except OSError as exc:
        raise SequenceError(f"{path}: cannot read the scan: {exc}") from None
    if size % POINT_BYTES or raw.size * 4 != size:
        raise SequenceError(
            f"{path}: {size} bytes is not a whole number of points: a scan holds {POINT_BYTES}-byte points "
            f"(float32 x y z intensity), so its size is a multiple of {POINT_BYTES} ({size % POINT_BYTES} bytes left over)"
        )
    return raw.reshape(-1, POINT_FIELDS)[:, :3]


class KittiSequence(FrameSource):
    """A KITTI-style folder (module docs) as range-image frames; ``geometry`` replaces the ``[lidar]`` table's."""

    #: How messages name a folder of this layout.
    label = "KITTI folder"

    def __init__(self, path, geometry: SphericalGeometry | None = None) -> None:
        path = Path(path)
        self.path = path
        self.description = f"{self.label} {path}"
        self._axes_stated = False  # a calib.txt relates the poses' axes to the LiDAR's (_read_layout)
        self._scans, self._poses, self._times = self._read_layout(path)
        if not self._axes_stated:
            self._poses = self._poses_in_lidar_axes(self._poses)
        self._warned = False
        self._rows_checked = False  # the first scan read is checked for rows without returns (read_frame)
        if geometry is not None:
            self._geometry_from = "the geometry given"
        elif (table := read_sequence_metadata(path).get("lidar")) is not None:
            geometry = geometry_from_table(table, metadata_path(path), KITTI_GEOMETRY)
            self._geometry_from = f"the [lidar] table of {metadata_path(path)}"
        else:
            geometry = self._learn_geometry()
        self.geometry = geometry

    def _read_layout(self, path: Path) -> tuple[list[Path], np.ndarray, np.ndarray]:
        """The folder's scan files in frame order, their (N, 4, 4) world-from-LiDAR poses and timestamps (s, NaN
        where unknown), or a SequenceError naming the file (module docs)."""
        if not is_kitti(path):
            raise SequenceError(f"KITTI folder {path}: needs a {SCAN_FOLDER}/ folder of .bin (or .pcd) scans and {POSES_FILE}")
        scans = scan_files(path)
        poses = read_matrix_rows(path / POSES_FILE, "pose")
        if len(poses) != len(scans):
            raise SequenceError(f"{path / POSES_FILE}: {len(poses)} poses, but {SCAN_FOLDER}/ holds {len(scans)} scans")
        self._axes_stated = (path / CALIB_FILE).is_file()
        tr = read_calibration(path / CALIB_FILE) if self._axes_stated else np.eye(4)
        times = np.full(len(scans), np.nan)
        if (path / TIMES_FILE).is_file():
            times = read_times(path / TIMES_FILE)
            if len(times) != len(scans):
                raise SequenceError(f"{path / TIMES_FILE}: {len(times)} timestamps, but {SCAN_FOLDER}/ holds {len(scans)} scans")
        return scans, np.linalg.inv(tr) @ poses @ tr, times

    def _poses_in_lidar_axes(self, poses: np.ndarray) -> np.ndarray:
        """``poses`` as written, or turned into the LiDAR's world-from-sensor poses where the scans say they are
        written another way (a camera's axes, inverted; :mod:`mabdi.sources.pose_axes`), said once."""
        found = pose_axes(poses, self.scan_points, "lidar")
        if not found.turned:
            return poses
        warnings.warn(
            f"{self.label} {self.path}: {found.describe()}: mabdi reads the poses so and turns them into the LiDAR's "
            f"world-from-sensor poses (a KITTI folder's {CALIB_FILE} states how a camera's poses relate, and is then "
            "used instead)",
            PoseFileWarning,
            stacklevel=4,
        )
        self.description += f" (poses read as {AXES_WORDS[found.axes]})"
        return turned(poses, found.axes)

    @property
    def scan_paths(self) -> list[Path]:
        """The scan files in frame order."""
        return list(self._scans)

    def scan_points(self, index: int) -> np.ndarray:
        """(N, 3) float32 points of scan ``index`` as its file holds them (the LiDAR's frame, metres)."""
        return read_scan(self._scans[index])

    def _learn_geometry(self) -> SphericalGeometry:
        """The default geometry (the HDL-64E), or, when the first scan misses it, the one learnt from the first
        :data:`LEARN_SCANS` scans, said once (:class:`LidarGeometryWarning`)."""
        self._geometry_from = "the default geometry (KITTI's Velodyne HDL-64E; the recording has no [lidar] table)"
        first = read_scan(self._scans[0])
        learnt, fit = learn_geometry(first, KITTI_GEOMETRY)
        if learnt is None:
            if fit.share > OUTSIDE_SHARE_WARNING:
                self._warn(0, fit)
            return KITTI_GEOMETRY
        read = self._scans[:LEARN_SCANS]
        learnt, fit = learn_geometry([first] + [read_scan(scan) for scan in read[1:]], KITTI_GEOMETRY)
        names = read[0].name if len(read) == 1 else f"{read[0].name}..{read[-1].name}"
        settings = learnt_settings(learnt)
        self.description += f" (LiDAR geometry learnt from {names}: {settings})"
        self._warn(0, fit, f"mabdi learnt {settings} from {names} (range_min, range_max kept) and uses them")
        self._geometry_from = f"the geometry learnt from {names}"
        return learnt

    def _warn(self, index: int, fit, done: str = "") -> None:
        """Say once that scan ``index`` mostly misses the geometry (``fit`` against :attr:`geometry`, or the default)."""
        geometry = getattr(self, "geometry", KITTI_GEOMETRY)
        fix = table_advice(metadata_path(self.path))
        warnings.warn(
            f"{self.label} {self.path}: scan {self._scans[index].name} does not fit {self._geometry_from}: "
            f"{fit.describe(geometry)}; " + (f"{done}; " if done else "the map will miss those points; ") + fix,
            LidarGeometryWarning,
            stacklevel=4,
        )
        self._warned = True

    @property
    def intrinsics(self) -> SphericalGeometry:
        return self.geometry

    def __len__(self) -> int:
        return len(self._scans)

    @property
    def poses(self) -> np.ndarray:
        return self._poses.copy()

    @property
    def timestamps(self) -> np.ndarray:
        return self._times.copy()

    def read_frame(self, index: int) -> DepthFrame:
        points = self.scan_points(index)
        if not self._warned and (fit := scan_fit(points, self.geometry)).share > OUTSIDE_SHARE_WARNING:
            self._warn(index, fit)
        depth, return_points = range_image_and_returns(points, self.geometry)
        if not self._rows_checked:
            self._rows_checked = True
            empty, spanned = rows_without_returns(return_points)
            if empty > EMPTY_ROWS_WARNING * spanned:
                warnings.warn(
                    f"{self.label} {self.path}: scan {self._scans[index].name}: {empty} of the range image's {spanned} rows "
                    f"between its top and bottom beams hold no returns ({self._geometry_from}: beams = "
                    f"{self.geometry.beams}): the image has more rows than the sensor has beams there, and no surface is "
                    f"meshed across such a row; put the sensor's beams, or its beam_elevations (degrees, one a beam, top "
                    f"first), in the [lidar] table of {metadata_path(self.path)}",
                    LidarGeometryWarning,
                    stacklevel=3,
                )
        return DepthFrame(depth, self.geometry, self._poses[index], index, float(self._times[index]), None, return_points)


def read_times(path: Path) -> np.ndarray:
    """The timestamps (s) of a file of one number a line (blank lines skipped), or a SequenceError naming the line."""
    times = []
    with open(path, encoding="utf-8", errors="replace") as stream:
        for number, line in enumerate(stream, start=1):
            if not line.strip():
                continue
            try:
                times.append(float(line))
            except ValueError:
                raise SequenceError(f"{path}:{number}: timestamp {line.strip()!r} is not a number") from None
    return np.array(times, dtype=np.float64)


def write_kitti(source: FrameSource, folder, *, overwrite: bool = False, extra: dict | None = None) -> Path:
    """Write every frame of a LiDAR ``source`` (range images) as a KITTI-style folder; returns the folder.

    Each frame's returns go to ``velodyne/NNNNNN.bin`` as points (float32 x y z, intensity 0): a pixel's own
    return where the frame carries it (``return_points``), else its range along the pixel centre's ray;
    ``poses.txt`` holds ``Tr P Tr^-1`` with ``Tr`` = :data:`WRITTEN_TR` in ``calib.txt``
    (so :class:`KittiSequence` reads the source's poses back), ``times.txt`` the timestamps (index / 10 where
    unknown), and ``mabdi.toml`` the ``[lidar]`` geometry and the tables of ``extra``. Atomic file by file.
    """
    if not source.intrinsics.range_image:
        raise SequenceError(
            f"{source.description}: a KITTI folder holds a LiDAR's scans, but these frames are a camera's depth images "
            "(use [sensor] kind = \"lidar\", or another format)"
        )
    folder = Path(folder)
    prepare_folder(folder, overwrite, "a KITTI folder")
    (folder / SCAN_FOLDER).mkdir(exist_ok=True)
    lines, times = [], []
    tr, tr_inverse = WRITTEN_TR, np.linalg.inv(WRITTEN_TR)
    geometry = None
    for index in range(len(source)):
        frame = source.read(index)
        geometry = frame.intrinsics if geometry is None else geometry
        xyz, rows, columns = range_image_points(frame.depth, frame.intrinsics)
        if frame.return_points is not None:  # the returns as measured, not their pixel centres' estimates
            own = frame.return_points[rows, columns].astype(np.float64)
            xyz = np.where(np.isfinite(own).all(axis=1)[:, None], own, xyz)
        points = np.zeros((len(xyz), POINT_FIELDS), dtype="<f4")
        points[:, :3] = xyz
        with atomic_output(folder / SCAN_FOLDER / f"{index:06d}.bin") as temporary:
            points.tofile(temporary)
        pose = tr @ frame.world_from_camera @ tr_inverse
        lines.append(" ".join(f"{v:.17g}" for v in pose[:3].ravel()))
        times.append(frame.timestamp if np.isfinite(frame.timestamp) else index / 10.0)
    write_text(folder / POSES_FILE, "\n".join(lines) + "\n")
    write_text(folder / CALIB_FILE, "Tr: " + " ".join(f"{v:.17g}" for v in tr[:3].ravel()) + "\n")
    write_text(folder / TIMES_FILE, "".join(f"{t:.6f}\n" for t in times))
    text = "# The range image's geometry (mabdi.spherical): beams, columns, fov (degrees), range (m).\n"
    write_text(folder / "mabdi.toml", text + "\n".join(toml_lines({"lidar": lidar_table(geometry), **(extra or {})})).lstrip("\n") + "\n")
    return folder


__all__ = ["KittiSequence", "is_kitti", "read_calibration", "read_matrix_rows", "read_scan", "read_times", "scan_files", "write_kitti"]
