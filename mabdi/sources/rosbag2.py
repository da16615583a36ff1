"""ROS bags as a frame source, ROS 2 (sqlite3 and MCAP storage) and ROS 1 (``.bag``); frames written as a ROS 2 bag.

Reading and writing use the pure-Python ``rosbags`` package (imported when a
bag is first opened or written, :func:`_rosbags`); message layouts are
ROS 2 Humble's, and a ROS 1 bag's those its own message definitions give
(CameraInfo's ``K``; ``tf/tfMessage`` on /tf as ``tf2_msgs/TFMessage``;
frame names with a leading ``/`` as tf2 names them, without).

* **Depth**: ``sensor_msgs/msg/Image``, ``16UC1`` (millimetres, 0 = no
  return) or ``32FC1`` (metres, NaN or 0 = no return); or, where no Image
  topic holds depth, a ``CompressedImage`` one as image_transport's
  ``compressed`` / ``compressedDepth`` write it (:mod:`mabdi.sources.compressed_depth`).
* **LiDAR**: ``sensor_msgs/msg/PointCloud2`` scans (``cloud_topic``), each
  turned into a range image by :func:`mabdi.sources.range_images.range_image`
  (fields ``x``, ``y``, ``z`` in metres, ``ring`` when present; the
  geometry from the ``[lidar]`` table of a ``mabdi.toml`` beside the bag,
  else the first scan, or the first scans where a cloud has no rings).
* **Colour** (optional): an ``rgb8`` or ``bgr8`` Image topic registered to
  the depth, matched by nearest header stamp.
* **Intrinsics**: the first ``CameraInfo``: fx = K[0], fy = K[4],
  cx = K[2] + 0.5, cy = K[5] + 0.5 (ROS puts pixel centres at integers);
  distortion is ignored.
* **Poses** (``world_from_camera``; the image's ``header.frame_id`` is an
  optical frame, x right, y down, z forward, as mabdi's): a
  ``PoseStamped`` topic, or ``/tf`` and ``/tf_static`` chained from the
  world frame to the image's frame as tf2 does (interpolated in time).

Topics are found by message type when there is one candidate, else named
(``--depth-topic``, ``--info-topic``, ``--pose-topic``). Frames and poses
are matched by header stamps within ``tolerance`` (20 ms); frames without a
pose are skipped and counted. ``read(i)`` decodes frame i only.
The rules in full: docs/architecture.md (``mabdi.sources.rosbag2``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import shutil
import tempfile
import warnings
from types import SimpleNamespace
from pathlib import Path

import numpy as np

from mabdi.camera import Intrinsics, quaternions_from_rotations
from mabdi.depth import DepthFrame
from mabdi.interrupts import interrupts_held
from mabdi.io.atomic import write_text
from mabdi.io.toml_writer import toml_lines
from mabdi.spherical import SphericalGeometry
from mabdi.sources.compressed_depth import decode_compressed_depth, depth_encoding
from mabdi.sources.frames import FrameSource
from mabdi.sources.range_images import (
    KITTI_GEOMETRY,
    OUTSIDE_SHARE_WARNING,
    LidarGeometryWarning,
    geometry_from_table,
    learn_geometry,
    learnt_columns,
    learnt_settings,
    lidar_table,
    range_image_and_returns,
    range_image_points,
    rows_from_rings,
    table_advice,
)
from mabdi.sources.sequence_files import (
    SequenceError,
    bad_quaternions,
    camera_table,
    frame_timestamps,
    interpolate_poses,
    metadata_path,
    nearest_within,
    poses_from_translations_quaternions,
    METADATA_FILE,
    metadata_toml,
    read_sequence_metadata,
)

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
#: The transform messages read on /tf and /tf_static: tf2's, and tf's of older ROS 1 bags (the same layout).
TF_MESSAGES = (TF_MESSAGE, "tf/msg/tfMessage")
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
#: Compressed images (image_transport's compressed / compressedDepth): depth read (:mod:`mabdi.sources.compressed_depth`).
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"

#: Depth encodings read: name -> (dtype of one pixel, metres per unit).
DEPTH_ENCODINGS = {"16UC1": (np.uint16, 1e-3), "32FC1": (np.float32, 1.0)}
#: Colour encodings read: name -> the channel order that gives R, G, B.
COLOUR_ENCODINGS = {"rgb8": [0, 1, 2], "bgr8": [2, 1, 0]}

#: Topics and frames :func:`write_rosbag2` uses.
DEPTH_TOPIC = "/camera/depth/image"
COLOUR_TOPIC = "/camera/color/image_raw"
INFO_TOPIC = "/camera/depth/camera_info"
POSE_TOPIC = "/camera/pose"
WORLD_FRAME = "world"
CAMERA_LINK_FRAME = "camera_link"
OPTICAL_FRAME = "camera_depth_optical_frame"

#: Topics and frames :func:`write_lidar_rosbag2` uses.
CLOUD_TOPIC = "/lidar/points"
LIDAR_POSE_TOPIC = "/lidar/pose"
LIDAR_FRAME = "lidar"
#: Columns of the range image of an unorganised cloud whose ``mabdi.toml`` does not say.
DEFAULT_COLUMNS = 1024
#: The scans an unorganised cloud without rings and without a stated vertical field has its geometry learnt from.
LEARN_SCANS = 10
#: PointField datatypes (sensor_msgs/msg/PointField constants) as numpy types.
POINT_FIELD_TYPES = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32, 6: np.uint32, 7: np.float32, 8: np.float64}

#: camera_link (x forward, y left, z up) from the optical frame (x right, y down, z forward), REP 103.
LINK_FROM_OPTICAL = np.array(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@functools.cache
def _rosbags() -> SimpleNamespace:
    """The ``rosbags`` names this module uses and the ROS 2 Humble type store, imported on first use."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    return SimpleNamespace(
        AnyReader=AnyReader,
        AnyReaderError=AnyReaderError,
        Reader=Reader,
        ReaderError=ReaderError,
        StoragePlugin=StoragePlugin,
        Writer=Writer,
        WriterError=WriterError,
        typestore=get_typestore(Stores.ROS2_HUMBLE),
    )


def __getattr__(name: str):
    if name == "_TYPESTORE":
        return _rosbags().typestore
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def seconds_to_ns(seconds) -> np.ndarray:
    """int64 nanoseconds of times in seconds, exact to the nanosecond (whole seconds split off before scaling)."""
    seconds = np.asarray(seconds, dtype=np.float64)
    whole = np.floor(seconds)
    return whole.astype(np.int64) * 1_000_000_000 + np.rint((seconds - whole) * 1e9).astype(np.int64)


def ns_to_seconds(stamps_ns) -> np.ndarray:
    """float64 seconds of int64 nanoseconds (whole seconds and the rest converted apart: no 256 ns rounding)."""
    whole, rest = np.divmod(np.asarray(stamps_ns, dtype=np.int64), 1_000_000_000)
    return whole.astype(np.float64) + rest / 1e9


def _pose_matrix(position, orientation, what: str = "") -> np.ndarray:
    """The 4x4 pose of a ROS position and quaternion; ``what`` names it in the error a NaN or zero quaternion gets."""
    translation = [[position.x, position.y, position.z]]
    quaternion = [[orientation.x, orientation.y, orientation.z, orientation.w]]
    if bad_quaternions(quaternion)[0] or not np.isfinite(translation).all():
        shown = ", ".join(f"{v:g}" for v in quaternion[0])
        raise SequenceError(
            f"{what}: the quaternion (x, y, z, w = {shown}) is not finite or has zero length"
            if bad_quaternions(quaternion)[0]
            else f"{what}: the translation ({', '.join(f'{v:g}' for v in translation[0])}) is not finite"
        )
    return poses_from_translations_quaternions(translation, quaternion)[0]


def _compressed(message) -> bool:
    """Whether an image message is a CompressedImage (it has a ``format``, not an ``encoding``)."""
    return hasattr(message, "format") and not hasattr(message, "encoding")


def _holds_depth(message) -> bool:
    """Whether an Image or CompressedImage message holds depth (:data:`DEPTH_ENCODINGS`, raw or compressed)."""
    return depth_encoding(message.format) is not None if _compressed(message) else message.encoding in DEPTH_ENCODINGS


def _option(name: str) -> str:
    """How a reader option is given: on the command line and in Python."""
    return f"--{name.replace('_', '-')} (Python: {name}=)"


def _list(names) -> str:
    names = sorted(names)
    return ", ".join(names) if names else "(none)"


def cloud_array(message, where: str) -> np.ndarray:
    """(height, width) structured view of a PointCloud2's points, one field per PointField of a known datatype
    (byte order, offsets, padding and ``row_step`` as the message says); a message that lacks x, y, z or
    holds too few bytes is a :class:`SequenceError` naming ``where``."""
    order = ">" if message.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for field in message.fields:
        if field.datatype in POINT_FIELD_TYPES and field.name not in names:
            dtype = np.dtype(POINT_FIELD_TYPES[field.datatype]).newbyteorder(order)
            count = max(int(field.count), 1)
            names.append(field.name)
            formats.append(dtype if count == 1 else np.dtype((dtype, (count,))))
            offsets.append(int(field.offset))
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise SequenceError(f"{where}: a point cloud needs fields x, y, z; it has {_list(f.name for f in message.fields)}")
    for name in ("x", "y", "z"):
        if formats[names.index(name)].kind != "f":
            raise SequenceError(f"{where}: field {name} is {formats[names.index(name)]}, expected float32 or float64")
    height, width = int(message.height), int(message.width)
    point_step, row_step = int(message.point_step), int(message.row_step)
    end = max(offset + dtype.itemsize for offset, dtype in zip(offsets, formats, strict=True))
    if end > point_step or row_step < width * point_step:
        raise SequenceError(f"{where}: fields end at byte {end} of a point_step of {point_step} (row_step {row_step}, width {width})")
    data = np.asarray(message.data, dtype=np.uint8)
    if height * width and data.size < row_step * (height - 1) + width * point_step:
        raise SequenceError(f"{where}: {height}x{width} points of {point_step} bytes, but only {data.size} bytes of data")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    return np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))


def cloud_points(message, where: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A PointCloud2's points (N, 3) float64 (metres, its frame), their ``ring`` (N,) int64 (None without the
    field) and, for an organised cloud (height > 1), their row in it (N,) (else None)."""
    cloud = cloud_array(message, where)
    points = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=-1).reshape(-1, 3).astype(np.float64)
    rings = None
    if "ring" in cloud.dtype.names and cloud.dtype["ring"].kind in "iu" and cloud.dtype["ring"].shape == ():
        rings = cloud["ring"].reshape(-1).astype(np.int64)
    height, width = cloud.shape
    organised = np.repeat(np.arange(height, dtype=np.int64), width) if height > 1 else None
    return points, rings, organised


class Rosbag2Sequence(FrameSource):
    """A ROS 2 bag (a bag folder, or one ``.db3`` / ``.mcap`` file) as a :class:`FrameSource` (see the module docs).

    Parameters: ``depth_topic``, ``info_topic``, ``pose_topic`` (a
    PoseStamped topic, or ``"/tf"`` for the transform tree), each found by type
    when left out; ``cloud_topic``: a PointCloud2 topic to read instead of
    depth images (LiDAR scans as range images); ``frame_id``: the world frame (the root of the chain for
    /tf; for a PoseStamped topic, the ``header.frame_id`` its messages must
    have); ``tolerance``: seconds between a depth image and its pose (and each
    dynamic transform).
    """

    def __init__(
        self,
        path,
        depth_topic: str | None = None,
        info_topic: str | None = None,
        pose_topic: str | None = None,
        frame_id: str | None = None,
        tolerance: float = 0.02,
        colour_topic: str | None = None,
        cloud_topic: str | None = None,
        time_offset: float = 0.0,
    ) -> None:
        self.path = Path(path)
        #: A ROS 1 bag (one ``.bag`` file) or a ROS 2 one, for messages.
        self.ros1 = self.path.suffix == ".bag"
        self.kind = "ROS 1 bag" if self.ros1 else "ROS 2 bag"
        if not self.path.exists():
            raise SequenceError(f"{self.kind} {self.path} does not exist")
        if not (np.isfinite(tolerance) and tolerance >= 0):
            raise SequenceError(f"{self.kind} {self.path}: tolerance must be >= 0 seconds, got {tolerance!r}")
        if not np.isfinite(time_offset):
            raise SequenceError(f"{self.kind} {self.path}: time offset must be a number of seconds, got {time_offset!r}")
        self.tolerance = float(tolerance)
        self.time_offset = float(time_offset)
        self._options = {
            "depth_topic": depth_topic, "info_topic": info_topic, "pose_topic": pose_topic, "frame_id": frame_id,
            "tolerance": tolerance, "colour_topic": colour_topic, "cloud_topic": cloud_topic,
        }  # fmt: skip
        self._reader = None  # a rosbags Reader once open
        self.geometry_note = ""  # how the LiDAR geometry was learnt, where it was (:meth:`_learnt_geometry`)
        reader = self._open()
        self.topics = {c.topic: c.msgtype for c in reader.connections}
        self.metadata = read_sequence_metadata(self.path)

        #: The PointCloud2 topic of a LiDAR's scans (None: the frames are depth images).
        self.cloud_topic = self._choose_cloud_topic(cloud_topic, depth_topic)
        if self.cloud_topic is None:
            self.depth_topic = self._choose_depth_topic(depth_topic)
            self.info_topic = self._choose_info_topic(info_topic)
            self._index_depth()
            self._intrinsics = self._read_intrinsics()
        else:
            for name, value in (("info_topic", info_topic), ("colour_topic", colour_topic)):
                if value is not None:
                    raise SequenceError(f"{self.kind} {self.path}: {_option(name)} is for depth images, not the point clouds of {self.cloud_topic}")
            self.depth_topic = self.cloud_topic  # the topic the frames come from
            self.info_topic = None
            first = self._index_clouds()
            self._intrinsics = self._cloud_geometry(first)
        self.pose_source = self._choose_pose_source(pose_topic)
        stamps, poses = self._poses_from_tf(frame_id) if self.pose_source == "/tf" else self._poses_from_topic(frame_id)

        keep = np.isfinite(poses[:, 0, 0])
        self.skipped = int((~keep).sum())
        self._poses = poses[keep]
        self._stamps = stamps[keep]
        self._log_times = self._all_log_times[keep]
        self._occurrence = self._all_occurrence[keep]
        self.colour_topic = self._choose_colour_topic(colour_topic) if self.cloud_topic is None else None
        far_colour = self._index_colour() if self.colour_topic is not None else 0
        self.description = f"{self.kind} {self.path} ({self.depth_topic}, poses from {self.pose_source}, {len(self._poses)} frames"
        if self.time_offset:
            self.description += f", poses taken {1000 * self.time_offset:+.1f} ms from the image stamps"
        if self.colour_topic is not None:
            self.description += f", colour from {self.colour_topic}"
            if far_colour:
                self.description += f" ({far_colour} more than {self.tolerance * 1000:g} ms from their colour image)"
        if self.geometry_note:
            self.description += f", {self.geometry_note}"
        self.description += (
            f", {self.skipped} without a pose within {self.tolerance * 1000:g} ms skipped)" if self.skipped else ")"
        )
        spans = getattr(self, "_link_spans", {})
        if spans and self.skipped:
            self.description = self.description[:-1] + f"; not reached by {_list(spans)})"
        if not len(self._poses):
            raise SequenceError(
                f"{self.kind} {self.path}: no image on {self.depth_topic} has a pose from {self.pose_source} "
                f"within {self.tolerance * 1000:g} ms ({self.skipped} images)"
                + (f"; the links that do not reach them: {'; '.join(spans.values())}" if spans else "")
            )

    # -- opening --------------------------------------------------------------

    def _open(self):
        if self._reader is None:
            rosbags = _rosbags()
            try:
                if self.ros1:  # the bag carries its message definitions (ROS 1 field names: CameraInfo's K)
                    reader = rosbags.AnyReader([self.path])
                    reader.open()
                    self._deserialize = reader.deserialize
                else:
                    reader = rosbags.Reader(self.path)
                    reader.open()
                    self._deserialize = rosbags.typestore.deserialize_cdr
            except (rosbags.ReaderError, rosbags.AnyReaderError, FileNotFoundError, OSError, ValueError, KeyError) as exc:
                raise SequenceError(f"{self.kind} {self.path}: cannot open: {exc}") from None
            self._reader = reader
        return self._reader

    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def _connections(self, topic: str):
        return [c for c in self._open().connections if c.topic == topic]

    def _messages(self, topic: str, start: int | None = None, stop: int | None = None):
        """(bag time ns, deserialised message) of ``topic``, in bag-time order."""
        connections = self._connections(topic)
        for connection, log_time, raw in self._open().messages(connections, start=start, stop=stop):
            try:
                yield log_time, self._deserialize(raw, connection.msgtype)
            except Exception as exc:  # noqa: BLE001 (rosbags raises several kinds for a corrupt message)
                raise SequenceError(f"{self.kind} {self.path}: topic {topic}: cannot decode a message: {exc}") from None

    def _check_topic(self, topic: str, msgtype: str, argument: str) -> str:
        if topic not in self.topics:
            raise SequenceError(
                f"{self.kind} {self.path}: no topic {topic!r} ({argument}); the bag has: "
                + _list(f"{t} [{m}]" for t, m in self.topics.items())
            )
        if self.topics[topic] != msgtype:
            raise SequenceError(
                f"{self.kind} {self.path}: topic {topic} ({argument}) is {self.topics[topic]}, expected {msgtype}"
            )
        return topic

    def _of_type(self, msgtype: str) -> list[str]:
        return sorted(t for t, m in self.topics.items() if m == msgtype)

    def _choose_cloud_topic(self, topic: str | None, depth_topic: str | None) -> str | None:
        """The PointCloud2 topic: ``cloud_topic``; else, when ``depth_topic`` is not given and no Image topic holds
        depth, the only PointCloud2 topic (several are an error naming them); else None (depth images)."""
        if topic is not None:
            if depth_topic is not None:
                raise SequenceError(f"{self.kind} {self.path}: give {_option('depth_topic')} or {_option('cloud_topic')}, not both")
            return self._check_topic(topic, POINT_CLOUD2, _option("cloud_topic"))
        clouds = self._of_type(POINT_CLOUD2)
        if depth_topic is not None or not clouds:
            return None
        for name in self._of_type(IMAGE) + self._of_type(COMPRESSED_IMAGE):
            if self._first_is_depth(name):
                return None
        if len(clouds) > 1:
            raise SequenceError(f"{self.kind} {self.path}: several point cloud topics ({_list(clouds)}); choose one with {_option('cloud_topic')}")
        return clouds[0]

    def _index_clouds(self):
        """One pass over the cloud topic (as :meth:`_index_depth` for images); returns its first message."""
        frame_ids, first = set(), []

        def check(message) -> None:
            frame_ids.add(message.header.frame_id)
            if len(first) < LEARN_SCANS:
                first.append(message)

        self._all_stamps, self._all_log_times, self._all_occurrence = self._index_images(self.cloud_topic, check)
        if len(frame_ids) != 1:
            raise SequenceError(f"{self.kind} {self.path}: topic {self.cloud_topic}: clouds in several frames ({_list(frame_ids)})")
        self.camera_frame = frame_ids.pop()
        self._time_origin = int(self._all_stamps.min())
        return first

    def _cloud_geometry(self, messages) -> SphericalGeometry:
        """The range images' geometry: the ``[lidar]`` table of ``mabdi.toml``, the rest from the first scan, or for
        an unorganised cloud without rings, learnt from the first scans (module docs)."""
        file = metadata_path(self.path)
        table = self.metadata.get("lidar", {})
        if not isinstance(table, dict):
            raise SequenceError(f"{file}: 'lidar' must be a table")
        where = f"{self.kind} {self.path}: topic {self.cloud_topic}"
        message = messages[0]
        points, rings, organised = cloud_points(message, f"{where}: first message")
        index = rings if rings is not None else organised
        derived: dict = {"columns": int(message.width) if organised is not None else DEFAULT_COLUMNS}
        if index is None:
            vertical = ("beams", "fov_up", "fov_down", "beam_elevations")
            if not any(k in table for k in vertical):
                return self._learnt_geometry(messages, table, where)
            missing = [k for k in ("beams", "fov_up", "fov_down") if k not in table]
            if missing:
                raise SequenceError(
                    f"{where}: an unorganised cloud without a ring field is binned by elevation: give the LiDAR's "
                    f"{', '.join(missing)} in the [lidar] table of {file} (or none of beams, fov_up, fov_down to "
                    "have them learnt from the first scans)"
                )
        else:
            beams = table.get("beams", int(index.max()) + 1 if len(index) else 1)
            derived["beams"] = beams
            if "beam_elevations" not in table and not ("fov_up" in table or "fov_down" in table) and isinstance(beams, int):
                derived.update(_beam_table(points, self._rows(index, points, beams, f"{where}: first message"), beams))
        geometry = geometry_from_table({**derived, **table}, file)
        if organised is None and "columns" not in table:  # an unorganised cloud: as many columns as its firings allow
            geometry = dataclasses.replace(geometry, columns=learnt_columns(points, geometry))
        return geometry

    def _learnt_geometry(self, messages, table: dict, where: str) -> SphericalGeometry:
        """The geometry of clouds without rings whose ``[lidar]`` table (``table``, perhaps empty) states no vertical
        field: the default one (:data:`~mabdi.sources.range_images.KITTI_GEOMETRY`, ``table``'s keys over it), or
        where the first scan misses it, the one learnt from the first :data:`LEARN_SCANS` scans
        (:func:`~mabdi.sources.range_images.learn_geometry`), said once as for a KITTI folder."""
        file = metadata_path(self.path)
        default = geometry_from_table({**lidar_table(KITTI_GEOMETRY), "columns": DEFAULT_COLUMNS, **table}, file)
        scans = [cloud_points(message, f"{where}: scan {i}")[0] for i, message in enumerate(messages)]
        learnt, fit = learn_geometry(scans, default)
        fix = table_advice(file)
        if learnt is None:
            if fit.share > OUTSIDE_SHARE_WARNING:
                warnings.warn(f"{where}: the first scan does not fit the default geometry (KITTI's Velodyne HDL-64E; the "
                              f"clouds have no ring field): {fit.describe(default)}; the map will miss those points; {fix}",
                              LidarGeometryWarning, stacklevel=4)
            return default
        settings = learnt_settings(learnt)
        self.geometry_note = f"LiDAR geometry learnt from the first {len(scans)} scans: {settings}"
        warnings.warn(f"{where}: the first scan does not fit the default geometry (KITTI's Velodyne HDL-64E; the clouds "
                      f"have no ring field): {fit.describe(default)}; mabdi learnt {settings} from the first {len(scans)} "
                      f"scans (range_min, range_max kept) and uses them; {fix}", LidarGeometryWarning, stacklevel=4)
        return learnt

    def _rows(self, index: np.ndarray, points: np.ndarray, beams: int, where: str) -> np.ndarray:
        try:
            return rows_from_rings(index, points, beams)
        except ValueError as exc:
            raise SequenceError(f"{where}: {exc}") from None

    def _first_is_depth(self, topic: str) -> bool:
        """Whether the first message of an Image or CompressedImage topic holds depth."""
        first = next(self._messages(topic), None)
        return first is not None and _holds_depth(first[1])

    def _choose_depth_topic(self, topic: str | None) -> str:
        if topic is not None:
            expected = COMPRESSED_IMAGE if self.topics.get(topic) == COMPRESSED_IMAGE else IMAGE
            return self._check_topic(topic, expected, _option("depth_topic"))
        candidates = self._of_type(IMAGE)
        raw_depth = [name for name in candidates if self._first_is_depth(name)]
        packed = self._of_type(COMPRESSED_IMAGE)
        packed_depth = [name for name in packed if self._first_is_depth(name)] if not raw_depth else []
        # raw depth first, else compressed depth (image_transport's), else every Image topic (the errors name them)
        candidates = raw_depth or packed_depth or candidates
        if not candidates and packed:
            raise SequenceError(
                f"{self.kind} {self.path}: no depth image topic; the compressed images ({_list(packed)}) hold no depth "
                f"(16UC1 or 32FC1): choose the depth topic with {_option('depth_topic')}"
            )
        if len(candidates) != 1:
            raise SequenceError(
                f"{self.kind} {self.path}: "
                + (f"several depth image topics ({_list(candidates)})" if candidates else f"no {IMAGE} topic")
                + f"; choose one with {_option('depth_topic')} (topics: "
                + _list(f"{t} [{m}]" for t, m in self.topics.items())
                + ")"
            )
        return candidates[0]

    def _choose_colour_topic(self, topic: str | None) -> str | None:
        """The colour Image topic: ``colour_topic``, else the only Image topic whose first message is rgb8 / bgr8
        (None when there is none; several are an error naming them)."""
        if topic is not None:
            return self._check_topic(topic, IMAGE, _option("colour_topic"))
        candidates = []
        for name in self._of_type(IMAGE):
            first = next(self._messages(name), None) if name != self.depth_topic else None
            if first is not None and first[1].encoding in COLOUR_ENCODINGS:
                candidates.append(name)
        if len(candidates) > 1:
            raise SequenceError(
                f"{self.kind} {self.path}: several colour image topics ({_list(candidates)}); choose one with {_option('colour_topic')}"
            )
        return candidates[0] if candidates else None

    def _index_colour(self) -> int:
        """Pair each frame with the colour image nearest in header stamp; returns how many are further than the tolerance."""
        def check(message) -> None:
            if message.encoding not in COLOUR_ENCODINGS:
                raise SequenceError(
                    f"{self.kind} {self.path}: topic {self.colour_topic}: colour encoding {message.encoding!r} is not read "
                    f"(known: {', '.join(COLOUR_ENCODINGS)})"
                )

        stamps, log_times, occurrence = self._index_images(self.colour_topic, check)
        nearest = nearest_within(self._seconds(self._stamps), self._seconds(stamps), np.inf)
        self._colour_log_times = log_times[nearest]
        self._colour_occurrence = occurrence[nearest]
        return int((np.abs(stamps[nearest] - self._stamps) > self.tolerance * 1e9).sum())

    @property
    def has_colour(self) -> bool:
        return self.colour_topic is not None

    def _choose_info_topic(self, topic: str | None) -> str:
        if topic is not None:
            return self._check_topic(topic, CAMERA_INFO, _option("info_topic"))
        candidates = self._of_type(CAMERA_INFO)
        # beside the image topic (/camera/depth/image_raw -> /camera/depth/camera_info), or beside the topic a
        # compressed one is a transport of (/camera/depth/image_raw/compressedDepth)
        for levels in (1, 2):
            beside = self.depth_topic.rsplit("/", levels)[0] + "/camera_info"
            if beside in candidates:
                return beside
        if len(candidates) != 1:
            raise SequenceError(
                f"{self.kind} {self.path}: "
                + (f"several {CAMERA_INFO} topics ({_list(candidates)})" if candidates else f"no {CAMERA_INFO} topic")
                + f" for the depth images on {self.depth_topic}; choose one with {_option('info_topic')} (topics: "
                + _list(f"{t} [{m}]" for t, m in self.topics.items())
                + ")"
            )
        return candidates[0]

    def _choose_pose_source(self, topic: str | None) -> str:
        if topic is not None:
            if topic in ("/tf", "/tf_static") or self.topics.get(topic) in TF_MESSAGES:
                if "/tf" not in self.topics and "/tf_static" not in self.topics:
                    raise SequenceError(
                        f"{self.kind} {self.path}: pose topic {topic!r} ({_option('pose_topic')}) but the bag has no /tf or /tf_static"
                    )
                return "/tf"
            return self._check_topic(topic, POSE_STAMPED, _option("pose_topic"))
        candidates = self._of_type(POSE_STAMPED)
        if len(candidates) == 1:
            return candidates[0]
        if len(candidates) > 1:
            raise SequenceError(
                f"{self.kind} {self.path}: several {POSE_STAMPED} topics ({_list(candidates)}); "
                f"choose one with {_option('pose_topic')} (or /tf)"
            )
        if self.topics.get("/tf") in TF_MESSAGES or self.topics.get("/tf_static") in TF_MESSAGES:
            return "/tf"
        raise SequenceError(
            f"{self.kind} {self.path}: no pose source for {self.depth_topic}: no {POSE_STAMPED} topic and no /tf "
            "(topics: " + _list(f"{t} [{m}]" for t, m in self.topics.items()) + ")"
        )

    def _index_depth(self) -> None:
        """One pass over the depth topic: header stamps, bag times, position among equal bag times, frame id."""
        frame_ids = set()
        self._image_size = None

        def check(message) -> None:
            if not _holds_depth(message):
                shown = message.format if _compressed(message) else message.encoding
                raise SequenceError(
                    f"{self.kind} {self.path}: topic {self.depth_topic}: unknown depth encoding {shown!r} "
                    f"(known: {', '.join(DEPTH_ENCODINGS)}, raw or compressed)"
                )
            frame_ids.add(message.header.frame_id)
            if not _compressed(message):
                self._image_size = (int(message.width), int(message.height))
            elif self._image_size is None:  # a compressed image's size is its PNG's: the first one decoded
                height, width = self.decode_depth(message).shape
                self._image_size = (width, height)

        self._all_stamps, self._all_log_times, self._all_occurrence = self._index_images(self.depth_topic, check)
        if len(frame_ids) != 1:
            raise SequenceError(f"{self.kind} {self.path}: topic {self.depth_topic}: images in several frames ({_list(frame_ids)})")
        self.camera_frame = frame_ids.pop()
        self._time_origin = int(self._all_stamps.min())

    def _index_images(self, topic: str, check) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One pass over an image topic, ``check(message)`` on each: (header stamps (ns), bag times (ns),
        position among messages of equal bag time), int64 arrays; an error when the topic has none."""
        stamps, log_times, occurrence = [], [], []
        previous, count = None, 0
        for log_time, message in self._messages(topic):
            check(message)
            count = count + 1 if log_time == previous else 0
            previous = log_time
            stamps.append(_stamp_ns(message.header.stamp))
            log_times.append(log_time)
            occurrence.append(count)
        if not stamps:
            raise SequenceError(f"{self.kind} {self.path}: topic {topic} has no messages")
        return (np.array(stamps, dtype=np.int64), np.array(log_times, dtype=np.int64), np.array(occurrence, dtype=np.int64))

    def _seconds(self, stamps_ns) -> np.ndarray:
        """Seconds since the first depth stamp (float64 keeps nanoseconds there), for matching."""
        return (np.asarray(stamps_ns, dtype=np.int64) - self._time_origin) / 1e9

    def _read_intrinsics(self) -> Intrinsics:
        first = next(self._messages(self.info_topic), None)
        if first is None:
            raise SequenceError(f"{self.kind} {self.path}: topic {self.info_topic} has no {CAMERA_INFO} message")
        info = first[1]
        k = np.asarray(info.k if hasattr(info, "k") else info.K, dtype=np.float64)  # ROS 2's name, ROS 1's
        if (int(info.width), int(info.height)) != self._image_size:
            raise SequenceError(
                f"{self.kind} {self.path}: {self.info_topic} says {info.width}x{info.height}, "
                f"images on {self.depth_topic} are {self._image_size[0]}x{self._image_size[1]}"
            )
        file = metadata_path(self.path)
        table = camera_table(self.metadata, file)
        values = {k_: table[k_] for k_ in ("near", "far") if k_ in table}
        try:
            return Intrinsics(
                fx=float(k[0]), fy=float(k[4]), cx=float(k[2]) + 0.5, cy=float(k[5]) + 0.5,
                width=int(info.width), height=int(info.height), **values,
            )
        except Exception as exc:  # noqa: BLE001 (ConfigError from Intrinsics, or a short K)
            raise SequenceError(f"{self.kind} {self.path}: {self.info_topic}: bad camera info (K = {k.tolist()}): {exc}") from None

    # -- poses ----------------------------------------------------------------

    def _poses_from_topic(self, frame_id: str | None) -> tuple[np.ndarray, np.ndarray]:
        stamps, poses = [], []
        for _, message in self._messages(self.pose_source):
            if frame_id is not None and message.header.frame_id.lstrip("/") != frame_id.lstrip("/"):  # ROS 1 frames may lead with /
                raise SequenceError(
                    f"{self.kind} {self.path}: topic {self.pose_source}: pose in frame {message.header.frame_id!r}, "
                    f"expected frame_id={frame_id!r}"
                )
            stamp = _stamp_ns(message.header.stamp)
            stamps.append(stamp)
            where = f"{self.kind} {self.path}: topic {self.pose_source}: the pose at stamp {float(ns_to_seconds(stamp)):.9f} s"
            poses.append(_pose_matrix(message.pose.position, message.pose.orientation, where))
        if not poses:
            raise SequenceError(f"{self.kind} {self.path}: pose topic {self.pose_source} has no messages")
        self._pose_stream = (ns_to_seconds(np.array(stamps, dtype=np.int64)), np.array(poses))
        # interpolated between the two samples around the image within the tolerance, else the nearest within it,
        # as a TUM ground truth (a pose topic at the camera's rate is up to half a frame from the image)
        times = self._seconds(self._all_stamps) + self.time_offset
        return self._all_stamps, interpolate_poses(times, self._seconds(stamps), np.array(poses), self.tolerance)

    def _read_tf(self) -> tuple[dict, dict]:
        """Every link of /tf_static (child -> (parent, pose)) and /tf (child -> (parent, stamps ns, poses)), checked."""
        static: dict[str, tuple[str, np.ndarray]] = {}
        dynamic: dict[str, tuple[str, list[int], list[np.ndarray]]] = {}
        for topic in ("/tf_static", "/tf"):
            if self.topics.get(topic) not in TF_MESSAGES:
                continue
            for _, message in self._messages(topic):
                for transform in message.transforms:
                    parent, child = transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/")
                    stamp = _stamp_ns(transform.header.stamp)
                    where = (
                        f"{self.kind} {self.path}: {topic}: transform {parent} -> {child} "
                        f"at stamp {float(ns_to_seconds(stamp)):.9f} s"
                    )
                    matrix = _pose_matrix(transform.transform.translation, transform.transform.rotation, where)
                    if topic == "/tf_static":
                        static[child] = (parent, matrix)
                    else:
                        entry = dynamic.setdefault(child, (parent, [], []))
                        if entry[0] != parent:
                            raise SequenceError(
                                f"{self.kind} {self.path}: /tf: frame {child!r} has two parents ({entry[0]!r}, {parent!r})"
                            )
                        entry[1].append(stamp)
                        entry[2].append(matrix)
        return static, dynamic

    def _poses_from_tf(self, frame_id: str | None) -> tuple[np.ndarray, np.ndarray]:
        static, dynamic = self._read_tf()
        frame_id = None if frame_id is None else frame_id.lstrip("/")  # as tf2 names frames (ROS 1's may lead with /)
        parents = {child: value[0] for child, value in {**dynamic, **static}.items()}
        camera = self.camera_frame.lstrip("/")
        if camera not in parents:
            raise SequenceError(
                f"{self.kind} {self.path}: /tf has no transform to the depth images' frame {camera!r}: missing link ? -> {camera} "
                f"(frames with a parent: {_list(parents)})"
            )
        chain = [camera]  # camera, its parent, ..., up to the world frame
        while chain[-1] in parents and chain[-1] != frame_id:
            chain.append(parents[chain[-1]])
            if len(chain) > len(parents) + 1:
                raise SequenceError(f"{self.kind} {self.path}: /tf has a loop through {chain[-1]!r}")
        if frame_id is not None and chain[-1] != frame_id:
            raise SequenceError(
                f"{self.kind} {self.path}: /tf: frame_id={frame_id!r} is not above {camera!r}: missing link ? -> {chain[-1]} "
                f"(chain: {' <- '.join(reversed(chain))})"
            )
        if frame_id is None:
            roots = sorted({p for p in parents.values() if p not in parents} - {chain[-1]})
            if roots:
                # a forest: the camera's part is not linked to the rest, so its root is not the world
                others = sorted(f for f in {*parents, *parents.values()} if self._root(f, parents) in roots)
                raise SequenceError(
                    f"{self.kind} {self.path}: /tf: the images' frame {camera!r} is not connected to "
                    f"{_list(roots)}: missing link ? -> {chain[-1]} (the chain from {camera!r} ends at {chain[-1]!r}: "
                    f"{' <- '.join(reversed(chain))}; no transform has {chain[-1]!r} as its child; the other tree has "
                    f"{_list(others)})"
                )
        self.world_frame = chain[-1]
        self._tf_chain = (chain, static, dynamic)
        times = self._seconds(self._all_stamps) + self.time_offset
        self.missing_links: dict[str, int] = {}  # "parent -> child": images that link does not reach
        self._link_spans: dict[str, str] = {}
        missing: dict[str, np.ndarray] = {}
        poses = self._chained(times, missing)
        for child in chain[:-1]:  # from the camera up, as the messages name them
            gone = missing.get(child)
            if gone is not None and gone.any():
                parent, stamps, _ = dynamic[child]
                name = f"{parent} -> {child}"
                self.missing_links[name] = int(gone.sum())
                seconds = self._seconds(stamps)
                self._link_spans[name] = (
                    f"{name} ({len(stamps)} transforms from {seconds.min():.3f} s to {seconds.max():.3f} s after the "
                    f"first image; it misses {int(gone.sum())} of {len(times)} images)"
                )
        return self._all_stamps, poses

    def _chained(self, times: np.ndarray, missing: dict | None = None) -> np.ndarray:
        """(N, 4, 4) world_from_camera of the /tf chain at ``times`` (seconds since the first depth stamp; NaN where
        a link does not reach): world_from_a @ a_from_b @ ... @ x_from_camera. ``missing``, when given, gets each
        /tf link's child frame -> (N,) bool, the times that link does not reach."""
        chain, static, dynamic = self._tf_chain
        poses = np.tile(np.eye(4), (len(times), 1, 1))
        for child in reversed(chain[:-1]):
            if child in static:
                poses = poses @ static[child][1]
                continue
            _, stamps, matrices = dynamic[child]
            link = self._interpolated(times, self._seconds(stamps), np.array(matrices))
            if missing is not None:
                missing[child] = ~np.isfinite(link[:, 0, 0])
            poses = poses @ link
        return poses

    @property
    def pose_samples(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose stream the images are matched against: (times (s, as :attr:`timestamps`), (N, 4, 4)
        world_from_camera): the pose topic's messages, or the /tf chain every 10 ms over the images' span (and
        0.2 s beyond); None for a LiDAR's clouds. What :mod:`mabdi.stages.time_offset` learns the clocks from."""
        if self.cloud_topic is not None:
            return None
        if self.pose_source != "/tf":
            return self._pose_stream
        first, last = self._seconds(self._all_stamps).min(), self._seconds(self._all_stamps).max()
        times = np.arange(first - 0.2, last + 0.2, 0.01)
        poses = self._chained(times)
        known = np.isfinite(poses[:, 0, 0])
        return times[known] + self._time_origin / 1e9, poses[known]

    def with_time_offset(self, seconds: float) -> Rosbag2Sequence:
        """The same bag read with each image's pose taken ``seconds`` after its stamp (the pose clock's offset
        from the image clock: :mod:`mabdi.stages.time_offset`); the other options as they were."""
        return Rosbag2Sequence(self.path, **self._options, time_offset=seconds)

    @staticmethod
    def _root(frame: str, parents: dict) -> str:
        seen = {frame}
        while frame in parents and parents[frame] not in seen:
            frame = parents[frame]
            seen.add(frame)
        return frame

    def _interpolated(self, times: np.ndarray, stamps: np.ndarray, matrices: np.ndarray) -> np.ndarray:
        """A /tf link at the image ``times`` (see the module docs): interpolated within its span, held within tolerance."""
        return interpolate_poses(times, stamps, matrices, self.tolerance, bridge_gaps=True)

    # -- frames ---------------------------------------------------------------

    @property
    def intrinsics(self) -> Intrinsics | SphericalGeometry:
        """The depth images' intrinsics, or the range images' geometry for a point cloud topic."""
        return self._intrinsics

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def poses(self) -> np.ndarray:
        return self._poses.copy()

    @property
    def timestamps(self) -> np.ndarray:
        """Header stamps of the depth images, seconds."""
        return ns_to_seconds(self._stamps)

    def read_frame(self, index: int) -> DepthFrame:
        log_time = int(self._log_times[index])
        wanted = int(self._occurrence[index])
        for position, (_, message) in enumerate(self._messages(self.depth_topic, start=log_time, stop=log_time + 1)):
            if position == wanted and self.cloud_topic is not None:
                stamp = float(ns_to_seconds(self._stamps[index]))
                depth, return_points = self.decode_cloud(message, stamp)
                return DepthFrame(depth, self._intrinsics, self._poses[index], index, stamp, None, return_points)
            if position == wanted:
                depth = self.decode_depth(message)
                colour = self._read_colour(index) if self.colour_topic is not None else None
                stamp = float(ns_to_seconds(self._stamps[index]))
                return DepthFrame(depth, self._intrinsics, self._poses[index], index, stamp, colour)
        raise SequenceError(f"{self.kind} {self.path}: topic {self.depth_topic}: image {index} vanished since the bag was opened")

    def _read_colour(self, index: int) -> np.ndarray:
        log_time, wanted = int(self._colour_log_times[index]), int(self._colour_occurrence[index])
        for position, (_, message) in enumerate(self._messages(self.colour_topic, start=log_time, stop=log_time + 1)):
            if position == wanted:
                return self.decode_colour(message)
        raise SequenceError(f"{self.kind} {self.path}: topic {self.colour_topic}: image for frame {index} vanished since the bag was opened")

    def decode_colour(self, message) -> np.ndarray:
        """(H, W, 3) uint8 RGB of an rgb8 / bgr8 Image message, which must be registered to the depth (its size)."""
        height, width, step = int(message.height), int(message.width), int(message.step)
        if (width, height) != (self._intrinsics.width, self._intrinsics.height):
            raise SequenceError(
                f"{self.kind} {self.path}: topic {self.colour_topic}: colour image {width}x{height}, depth "
                f"{self._intrinsics.width}x{self._intrinsics.height}: the colour must be registered to the depth"
            )
        data = np.asarray(message.data, dtype=np.uint8)
        if step < 3 * width or data.size < step * (height - 1) + 3 * width:
            raise SequenceError(
                f"{self.kind} {self.path}: topic {self.colour_topic}: image of {width}x{height} {message.encoding} "
                f"with step {step} has only {data.size} bytes"
            )
        pixels = np.ndarray((height, width, 3), dtype=np.uint8, buffer=data, strides=(step, 3, 1))
        return np.ascontiguousarray(pixels[..., COLOUR_ENCODINGS[message.encoding]])

    def decode_cloud(self, message, stamp: float = float("nan")) -> tuple[np.ndarray, np.ndarray]:
        """(beams, columns) float32 range image (m, NaN = no return) of a PointCloud2 message (module docs), and
        each pixel's own return (:func:`mabdi.sources.range_images.range_image_and_returns`)."""
        where = f"{self.kind} {self.path}: topic {self.cloud_topic}: the cloud at stamp {stamp:.9f} s"
        points, rings, organised = cloud_points(message, where)
        index = rings if rings is not None else organised
        geometry = self._intrinsics
        rows = None if index is None else self._rows(index, points, geometry.beams, where)
        return range_image_and_returns(points, geometry, rows)

    def decode_depth(self, message) -> np.ndarray:
        """(H, W) float32 metres of a depth Image message, or a CompressedImage one
        (:mod:`mabdi.sources.compressed_depth`); no return (0, NaN) as NaN."""
        if _compressed(message):
            stamp = float(ns_to_seconds(_stamp_ns(message.header.stamp)))
            where = f"{self.kind} {self.path}: topic {self.depth_topic}: the image at stamp {stamp:.9f} s"
            return decode_compressed_depth(message.format, message.data, where)
        dtype, scale = DEPTH_ENCODINGS[message.encoding]
        dtype = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
        height, width, step = int(message.height), int(message.width), int(message.step)
        data = np.asarray(message.data)
        if step < width * dtype.itemsize or data.size < step * (height - 1) + width * dtype.itemsize:
            raise SequenceError(
                f"{self.kind} {self.path}: topic {self.depth_topic}: image of {width}x{height} {message.encoding} "
                f"with step {step} has only {data.size} bytes"
            )
        pixels = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(step, dtype.itemsize))
        depth = pixels.astype(np.float32)
        if scale != 1.0:
            depth *= np.float32(scale)
        depth[depth == 0] = np.nan
        return depth


def _beam_table(points: np.ndarray, rows: np.ndarray, beams: int) -> dict:
    """``beam_elevations`` (each row's mean elevation in degrees, rows no point reached interpolated) with
    ``fov_up`` / ``fov_down`` half a spacing beyond the outer beams; ``{}`` when they do not decrease strictly
    down the rows or fewer than two rows have points (a uniform geometry then)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        elevation = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
        valid = np.isfinite(elevation) & (np.linalg.norm(points, axis=1) > 0) & (rows >= 0) & (rows < beams)
    sums = np.bincount(rows[valid], elevation[valid], minlength=beams)[:beams]
    counts = np.bincount(rows[valid], minlength=beams)[:beams]
    seen = counts > 0
    if seen.sum() < 2 or beams < 2:
        return {}
    table = np.interp(np.arange(beams), np.nonzero(seen)[0], sums[seen] / counts[seen])
    if np.any(np.diff(table) >= 0):
        return {}
    up = min(90.0, table[0] + 0.5 * (table[0] - table[1]))
    down = max(-90.0, table[-1] - 0.5 * (table[-2] - table[-1]))
    return {"beam_elevations": [float(a) for a in table], "fov_up": float(up), "fov_down": float(down)}


# ---------------------------------------------------------------------------
# Writing


def _time(stamp_ns: int):
    Time = _rosbags().typestore.types["builtin_interfaces/msg/Time"]
    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def _header(stamp_ns: int, frame: str):
    return _rosbags().typestore.types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame)


def _transform_msgs(pose: np.ndarray, quaternion: np.ndarray):
    types = _rosbags().typestore.types
    translation = types["geometry_msgs/msg/Vector3"](x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3]))
    point = types["geometry_msgs/msg/Point"](x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3]))
    rotation = types["geometry_msgs/msg/Quaternion"](
        x=float(quaternion[0]), y=float(quaternion[1]), z=float(quaternion[2]), w=float(quaternion[3])
    )
    return translation, point, rotation


def depth_image_bytes(depth: np.ndarray, encoding: str) -> np.ndarray:
    """The ``data`` of a depth Image (little-endian rows, no padding): 32FC1 metres as float32 (NaN kept),
    16UC1 round(depth * 1000) millimetres with 0 for NaN, <= 0 and beyond 65.535 m."""
    depth = np.asarray(depth)
    if encoding == "32FC1":
        values = depth.astype("<f4")
    elif encoding == "16UC1":
        units = np.rint(depth.astype(np.float64) * 1000.0)
        with np.errstate(invalid="ignore"):
            keep = (units > 0) & (units <= 65535)
        values = np.where(keep, units, 0).astype("<u2")
    else:
        raise SequenceError(f"unknown depth encoding {encoding!r} for a ROS 2 bag (known: {', '.join(DEPTH_ENCODINGS)})")
    return np.ascontiguousarray(values).view(np.uint8).ravel()


@contextlib.contextmanager
def _new_bag(path: Path, storage: str):
    """A rosbags Writer on a new bag for ``path`` (see :func:`write_rosbag2`): yields a namespace with ``writer``,
    ``add(topic, msgtype)`` (a connection) and ``metadata`` (the text of the bag's ``mabdi.toml``, set by the
    body); when the body completes the bag is closed, ``mabdi.toml`` written, and the folder renamed to ``path``."""
    rosbags = _rosbags()
    plugins = {"sqlite3": rosbags.StoragePlugin.SQLITE3, "mcap": rosbags.StoragePlugin.MCAP}
    if storage not in plugins:
        raise SequenceError(f"cannot write ROS 2 bag {path}: unknown storage {storage!r} (known: {', '.join(plugins)})")
    if path.exists() and not (path.is_dir() and not any(path.iterdir())):
        raise SequenceError(f"cannot write ROS 2 bag {path}: it exists already (rosbags writes only new bags)")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise SequenceError(f"cannot write ROS 2 bag {path}: folder {parent} does not exist")
    temporary = None
    try:
        with interrupts_held():  # Ctrl-C between making the folder and holding its name would leave it behind
            temporary = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent))
        folder = temporary / "bag"
        try:
            writer = rosbags.Writer(folder, version=rosbags.Writer.VERSION_LATEST, storage_plugin=plugins[storage])
            writer.open()
        except rosbags.WriterError as exc:
            raise SequenceError(f"cannot write ROS 2 bag {path} ({storage}): {exc}") from None
        bag = SimpleNamespace(
            writer=writer, add=lambda topic, msgtype: writer.add_connection(topic, msgtype, typestore=rosbags.typestore), metadata=None
        )
        try:
            yield bag
        except BaseException:
            writer.abort()
            raise
        writer.close()
        if bag.metadata is not None:
            write_text(folder / METADATA_FILE, bag.metadata)
        if path.is_dir():
            path.rmdir()
        os.replace(folder, path)
    finally:
        if temporary is not None:
            with interrupts_held():
                shutil.rmtree(temporary, ignore_errors=True)


def write_rosbag2(
    source: FrameSource,
    path,
    *,
    storage: str = "sqlite3",
    encoding: str = "32FC1",
    extra: dict | None = None,
) -> Path:
    """Write every frame of ``source`` as a ROS 2 bag folder at ``path``; returns it.

    Topics (stamps = the frames' timestamps, ``index / 30`` s where a frame has none):

    * ``/camera/depth/image``: ``sensor_msgs/msg/Image``, ``encoding``
      ``32FC1`` (metres, NaN = no return, exact) or ``16UC1`` (millimetres,
      rounded, 0 = no return), frame ``camera_depth_optical_frame``;
    * ``/camera/depth/camera_info``: ``CameraInfo`` per frame, K with ROS's
      integer pixel centres (cx - 0.5, cy - 0.5), no distortion;
    * ``/camera/pose``: ``PoseStamped`` of the optical frame in ``world``;
    * ``/camera/color/image_raw``: ``rgb8`` Image of the frame's colour, when
      frames have colour (registered to the depth: same size and frame);
    * ``/tf``: world -> ``camera_link`` (the camera body, x forward, z up) per
      frame, and ``/tf_static``: ``camera_link`` -> ``camera_depth_optical_frame``
      (REP 103's optical rotation), so that chaining /tf gives the same pose as
      ``/camera/pose``.

    ``storage`` is ``"sqlite3"`` or ``"mcap"`` (rosbags >= 0.10 writes both).
    A ``mabdi.toml`` with ``[camera]`` (so near and far survive) and the
    ``extra`` tables goes into the bag folder. The bag is written to a
    temporary folder beside ``path`` and renamed into place when complete;
    ``path`` must not exist (an empty folder is replaced).
    """
    path = Path(path)
    if encoding not in DEPTH_ENCODINGS:
        raise SequenceError(f"cannot write ROS 2 bag {path}: unknown depth encoding {encoding!r} (known: {', '.join(DEPTH_ENCODINGS)})")
    if source.intrinsics.range_image:
        raise SequenceError(f"cannot write ROS 2 bag {path}: the frames are a LiDAR's range images: write them with write_lidar_rosbag2")
    typestore = _rosbags().typestore
    intrinsics = source.intrinsics
    stamps = seconds_to_ns(frame_timestamps(source))
    if (stamps < 0).any():
        raise SequenceError(f"cannot write ROS 2 bag {path}: negative timestamps")
    types = typestore.types
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx - 0.5, intrinsics.cy - 0.5
    k = np.array([fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0])
    p = np.array([fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    _, _, optical_rotation = _transform_msgs(LINK_FROM_OPTICAL, quaternions_from_rotations(LINK_FROM_OPTICAL[:3, :3])[0])
    optical_from_link = np.linalg.inv(LINK_FROM_OPTICAL)

    with _new_bag(path, storage) as bag:
        writer, add = bag.writer, bag.add
        image_conn, info_conn = add(DEPTH_TOPIC, IMAGE), add(INFO_TOPIC, CAMERA_INFO)
        pose_conn, tf_conn, static_conn = add(POSE_TOPIC, POSE_STAMPED), add("/tf", TF_MESSAGE), add("/tf_static", TF_MESSAGE)
        colour_conn = None
        Transform, TransformStamped = types["geometry_msgs/msg/Transform"], types["geometry_msgs/msg/TransformStamped"]
        static = types[TF_MESSAGE](transforms=[
            TransformStamped(
                header=_header(int(stamps[0]), CAMERA_LINK_FRAME),
                child_frame_id=OPTICAL_FRAME,
                transform=Transform(translation=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0), rotation=optical_rotation),
            )
        ])
        writer.write(static_conn, int(stamps[0]), typestore.serialize_cdr(static, TF_MESSAGE))
        for index in range(len(source)):
            frame = source.read(index)
            if frame.depth.shape != intrinsics.shape:
                raise SequenceError(f"cannot write frame {index} to {path}: depth {frame.depth.shape} != intrinsics {intrinsics.shape}")
            stamp = int(stamps[index])
            pose = frame.world_from_camera
            link = pose @ optical_from_link
            quaternions = quaternions_from_rotations(np.stack([pose[:3, :3], link[:3, :3]]))
            _, point, rotation = _transform_msgs(pose, quaternions[0])
            link_translation, _, link_rotation = _transform_msgs(link, quaternions[1])
            messages = [
                (image_conn, IMAGE, types[IMAGE](
                    header=_header(stamp, OPTICAL_FRAME), height=intrinsics.height, width=intrinsics.width,
                    encoding=encoding, is_bigendian=0, step=intrinsics.width * np.dtype(DEPTH_ENCODINGS[encoding][0]).itemsize,
                    data=depth_image_bytes(frame.depth, encoding),
                )),
                (info_conn, CAMERA_INFO, types[CAMERA_INFO](
                    header=_header(stamp, OPTICAL_FRAME), height=intrinsics.height, width=intrinsics.width,
                    distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).ravel(), p=p,
                    binning_x=0, binning_y=0, roi=roi,
                )),
                (pose_conn, POSE_STAMPED, types[POSE_STAMPED](
                    header=_header(stamp, WORLD_FRAME), pose=types["geometry_msgs/msg/Pose"](position=point, orientation=rotation),
                )),
                (tf_conn, TF_MESSAGE, types[TF_MESSAGE](transforms=[
                    TransformStamped(
                        header=_header(stamp, WORLD_FRAME), child_frame_id=CAMERA_LINK_FRAME,
                        transform=Transform(translation=link_translation, rotation=link_rotation),
                    )
                ])),
            ]
            if frame.colour is not None:
                if colour_conn is None:
                    colour_conn = add(COLOUR_TOPIC, IMAGE)
                messages.append((colour_conn, IMAGE, types[IMAGE](
                    header=_header(stamp, OPTICAL_FRAME), height=intrinsics.height, width=intrinsics.width,
                    encoding="rgb8", is_bigendian=0, step=3 * intrinsics.width,
                    data=np.ascontiguousarray(frame.colour, dtype=np.uint8).ravel(),
                )))
            for connection, msgtype, message in messages:
                writer.write(connection, stamp, typestore.serialize_cdr(message, msgtype))
        bag.metadata = metadata_toml(intrinsics, extra)
    return path


#: Point layouts :func:`write_lidar_rosbag2` writes: fields (name, PointField datatype) in order.
CLOUD_LAYOUTS = {
    "velodyne": (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("ring", 4), ("time", 7)),
    "ouster": (("x", 7), ("y", 7), ("z", 7), ("intensity", 7), ("t", 6), ("reflectivity", 4), ("ring", 4), ("range", 6)),
}
#: Seconds a simulated scan takes (the ``time`` / ``t`` fields a writer gives each column).
SCAN_PERIOD = 0.1


def cloud_bytes(depth: np.ndarray, geometry: SphericalGeometry, layout: str) -> tuple[np.ndarray, int, int]:
    """A range image as PointCloud2 data in ``layout`` (:data:`CLOUD_LAYOUTS`): (bytes, height, width).

    ``velodyne``: an unorganised cloud of the returns (height 1), ``ring`` counted from the lowest beam (0) up,
    ``time`` (float32 s) through the turn by column. ``ouster``: an organised cloud (height = beams, width =
    columns, row 0 the top beam), no return as x = y = z = 0 with ``range`` 0, ``ring`` = the row, ``t`` (uint32
    ns) by column, ``range`` in millimetres. Points at the pixel centres' directions; little-endian, packed.
    """
    fields = CLOUD_LAYOUTS[layout]
    dtype = np.dtype([(name, np.dtype(POINT_FIELD_TYPES[kind]).newbyteorder("<")) for name, kind in fields])
    if layout == "velodyne":
        points, rows, columns = range_image_points(depth, geometry)
        cloud = np.zeros(len(points), dtype=dtype)
        cloud["ring"] = geometry.beams - 1 - rows
        cloud["time"] = columns / geometry.columns * SCAN_PERIOD
        height, width = 1, len(points)
    else:
        rows, columns = np.indices(geometry.shape).reshape(2, -1)
        values = np.asarray(depth, dtype=np.float64).reshape(-1)
        hit = np.isfinite(values)
        points = geometry.rays().reshape(-1, 3) * np.where(hit, values, 0.0)[:, None]
        cloud = np.zeros(len(points), dtype=dtype)
        cloud["ring"] = rows
        cloud["t"] = np.rint(columns / geometry.columns * SCAN_PERIOD * 1e9).astype(np.uint32)
        cloud["range"] = np.rint(np.where(hit, values, 0.0) * 1000.0).astype(np.uint32)
        height, width = geometry.beams, geometry.columns
    cloud["x"], cloud["y"], cloud["z"] = points[:, 0], points[:, 1], points[:, 2]
    return cloud.view(np.uint8).reshape(-1), height, width


def write_lidar_rosbag2(
    source: FrameSource, path, *, storage: str = "sqlite3", layout: str = "velodyne", extra: dict | None = None
) -> Path:
    """Write every frame of a LiDAR ``source`` (range images) as a ROS 2 bag folder at ``path``; returns it.

    Topics (stamps as :func:`write_rosbag2`'s): ``/lidar/points``, ``sensor_msgs/msg/PointCloud2`` in frame
    ``lidar`` with the fields of ``layout`` (:func:`cloud_bytes`: ``"velodyne"`` or ``"ouster"``);
    ``/lidar/pose``, ``PoseStamped`` of ``lidar`` in ``world``; ``/tf``, world -> lidar per frame. A
    ``mabdi.toml`` with the ``[lidar]`` geometry and the ``extra`` tables goes into the folder. ``storage`` and
    the atomic write as for :func:`write_rosbag2`.
    """
    path = Path(path)
    geometry = source.intrinsics
    if not geometry.range_image:
        raise SequenceError(f"cannot write ROS 2 bag {path}: point clouds come from a LiDAR's range images, these frames are a camera's")
    if layout not in CLOUD_LAYOUTS:
        raise SequenceError(f"cannot write ROS 2 bag {path}: unknown point layout {layout!r} (known: {', '.join(CLOUD_LAYOUTS)})")
    stamps = seconds_to_ns(frame_timestamps(source))
    if (stamps < 0).any():
        raise SequenceError(f"cannot write ROS 2 bag {path}: negative timestamps")
    typestore = _rosbags().typestore
    types = typestore.types
    PointField = types["sensor_msgs/msg/PointField"]
    offsets = np.cumsum([0] + [np.dtype(POINT_FIELD_TYPES[kind]).itemsize for _, kind in CLOUD_LAYOUTS[layout]])
    fields = [PointField(name=name, offset=int(offset), datatype=kind, count=1) for (name, kind), offset in zip(CLOUD_LAYOUTS[layout], offsets, strict=False)]
    point_step = int(offsets[-1])
    Transform, TransformStamped = types["geometry_msgs/msg/Transform"], types["geometry_msgs/msg/TransformStamped"]
    with _new_bag(path, storage) as bag:
        cloud_conn, pose_conn, tf_conn = bag.add(CLOUD_TOPIC, POINT_CLOUD2), bag.add(LIDAR_POSE_TOPIC, POSE_STAMPED), bag.add("/tf", TF_MESSAGE)
        for index in range(len(source)):
            frame = source.read(index)
            stamp = int(stamps[index])
            data, height, width = cloud_bytes(frame.depth, geometry, layout)
            pose = frame.world_from_camera
            translation, point, rotation = _transform_msgs(pose, quaternions_from_rotations(pose[:3, :3])[0])
            messages = [
                (cloud_conn, POINT_CLOUD2, types[POINT_CLOUD2](
                    header=_header(stamp, LIDAR_FRAME), height=height, width=width, fields=fields, is_bigendian=False,
                    point_step=point_step, row_step=point_step * width, data=data, is_dense=layout == "velodyne",
                )),
                (pose_conn, POSE_STAMPED, types[POSE_STAMPED](
                    header=_header(stamp, WORLD_FRAME), pose=types["geometry_msgs/msg/Pose"](position=point, orientation=rotation),
                )),
                (tf_conn, TF_MESSAGE, types[TF_MESSAGE](transforms=[
                    TransformStamped(
                        header=_header(stamp, WORLD_FRAME), child_frame_id=LIDAR_FRAME,
                        transform=Transform(translation=translation, rotation=rotation),
                    )
                ])),
            ]
            for connection, msgtype, message in messages:
                bag.writer.write(connection, stamp, typestore.serialize_cdr(message, msgtype))
        text = "# The range image's geometry (mabdi.spherical): beams, columns, fov (degrees), range (m).\n"
        bag.metadata = text + "\n".join(toml_lines({"lidar": lidar_table(geometry), **(extra or {})})).lstrip("\n") + "\n"
    return path


__all__ = ["CLOUD_LAYOUTS", "DEPTH_ENCODINGS", "Rosbag2Sequence", "cloud_points", "write_lidar_rosbag2", "write_rosbag2"]
