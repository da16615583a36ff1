"""LiDAR scans in ROS 2 bags: PointCloud2 (Velodyne and Ouster layouts) read as range images, poses from /tf."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, Writer

from mabdi.camera import look_at
from mabdi.depth import DepthFrame
from mabdi.simulate.path import CAMERA_FROM_LIDAR
from mabdi.sources.frames import FrameList
from mabdi.sources.range_images import LidarGeometryWarning
from mabdi.sources.rosbag2 import _TYPESTORE, Rosbag2Sequence, write_lidar_rosbag2, write_rosbag2
from mabdi.sources.sequences import SequenceError, open_sequence, read_sequence_metadata
from mabdi.spherical import SphericalGeometry

GEOMETRY = SphericalGeometry(beams=16, columns=64, fov_up=10.0, fov_down=-20.0, range_min=0.5, range_max=50.0)
EXTRA = {"recorded": {"name": "lidar test", "frames": 3}}


def _room(geometry, half=(6.0, 4.0, 1.5)):
    """Range image inside an axis-aligned box room centred on the sensor."""
    with np.errstate(divide="ignore"):
        t = np.min(np.abs(np.asarray(half) / geometry.rays()), axis=-1)
    return np.where(t < geometry.range_max, t, np.nan).astype(np.float32)


@pytest.fixture(scope="module")
def source():
    frames = []
    for i in range(3):
        depth = _room(GEOMETRY, (6.0 + i, 4.0, 1.5))
        depth[2, 5 + i] = np.nan  # pixels without a return
        pose = look_at([0.3 * i, 0.1 * i, 1.0], [5.0, 1.0 + i, 0.8]) @ CAMERA_FROM_LIDAR
        frames.append(DepthFrame(depth, GEOMETRY, pose, i, 0.1 * i))
    return FrameList(frames, "lidar frames")


@pytest.fixture(scope="module")
def bags(tmp_path_factory, source):
    root = tmp_path_factory.mktemp("lidar_bags")
    return {
        (layout, storage): write_lidar_rosbag2(source, root / f"{layout}_{storage}", storage=storage, layout=layout, extra=EXTRA)
        for layout in ("velodyne", "ouster")
        for storage in ("sqlite3", "mcap")
    }


@pytest.mark.parametrize("layout", ["velodyne", "ouster"])
@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_cloud_bag_reads_back_the_range_images(bags, source, layout, storage):
    with Rosbag2Sequence(bags[layout, storage]) as sequence:
        assert sequence.cloud_topic == "/lidar/points" and sequence.camera_frame == "lidar"
        assert sequence.intrinsics == GEOMETRY and len(sequence) == 3 and sequence.skipped == 0
        np.testing.assert_allclose(sequence.timestamps, [0.0, 0.1, 0.2], atol=1e-9)
        for i in range(3):
            got, want = sequence.read(i), source.read(i)
            np.testing.assert_array_equal(np.isnan(got.depth), np.isnan(want.depth))
            np.testing.assert_allclose(got.depth, want.depth, rtol=2e-7, equal_nan=True)  # float32 points
            np.testing.assert_allclose(got.world_from_camera, want.world_from_camera, atol=1e-9)
    assert read_sequence_metadata(bags[layout, storage])["recorded"] == EXTRA["recorded"]


def test_tf_and_pose_topic_agree(bags, source):
    path = bags["velodyne", "sqlite3"]
    from_tf = Rosbag2Sequence(path, pose_topic="/tf")
    assert from_tf.pose_source == "/tf" and from_tf.world_frame == "world"
    np.testing.assert_allclose(from_tf.poses, source.poses, atol=1e-9)
    assert isinstance(open_sequence(path), Rosbag2Sequence) and open_sequence(path).pose_source == "/lidar/pose"


def test_geometry_from_the_first_scan_without_mabdi_toml(bags, source, tmp_path):
    """Rings give the beams and their elevations; an organised cloud's width the columns, an unorganised one's
    firings a turn (64 here, fewer than the default's 1,024 columns: 0.9 of them, so that no column is empty)."""
    for layout in ("velodyne", "ouster"):
        path = _rewrite_clouds(bags[layout, "sqlite3"], tmp_path / layout, lambda m: m)  # no mabdi.toml
        sequence = Rosbag2Sequence(path)
        geometry = sequence.intrinsics
        assert geometry.beams == 16
        np.testing.assert_allclose(geometry.beam_elevations, np.degrees(GEOMETRY.elevations()), atol=1e-5)
        assert geometry.fov_up == pytest.approx(10.0, abs=1e-5) and geometry.fov_down == pytest.approx(-20.0, abs=1e-5)
        assert geometry.columns == (64 if layout == "ouster" else int(0.9 * 64))
        if layout == "ouster":
            got, want = sequence.read(1).depth, source.read(1).depth
            np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)


def _rewrite_clouds(path, target, change):
    """Copy a bag (not its mabdi.toml) with each PointCloud2 message passed through ``change(message)``."""
    with Reader(path) as reader, Writer(target, version=Writer.VERSION_LATEST) as writer:
        connections = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=_TYPESTORE) for c in reader.connections}
        for connection, time, raw in reader.messages():
            if connection.msgtype == "sensor_msgs/msg/PointCloud2":
                message = change(_TYPESTORE.deserialize_cdr(raw, connection.msgtype))
                raw = _TYPESTORE.serialize_cdr(message, connection.msgtype)
            writer.write(connections[connection.id], time, raw)
    return target


def test_unorganised_cloud_without_rings_is_binned_by_elevation(bags, source, tmp_path):
    def drop_ring(message):
        message.fields = [f for f in message.fields if f.name != "ring"]
        return message

    path = _rewrite_clouds(bags["velodyne", "sqlite3"], tmp_path / "no_ring", drop_ring)
    # No [lidar] table: the geometry learnt from the first scans (before, an error), said once: the 16 rings.
    with pytest.warns(LidarGeometryWarning, match=r"learnt fov_up = \S+, fov_down = \S+, beams = 16, columns = 57 from the first 3 scans"):
        learnt = Rosbag2Sequence(path)
    geometry = learnt.intrinsics
    spacing = 30.0 / 16
    assert geometry.beams == 16 and "LiDAR geometry learnt from the first 3 scans" in learnt.description
    assert geometry.fov_up == pytest.approx(10.0, abs=0.1 * spacing) and geometry.fov_down == pytest.approx(-20.0, abs=0.1 * spacing)
    # Each ring on its row: the learnt image holds the returns where the sensor's own does (columns: the default).
    rows_hit = np.isfinite(learnt.read(2).depth).any(axis=1)
    assert rows_hit.sum() == np.isfinite(source.read(2).depth).any(axis=1).sum()
    # A table that states part of the vertical field is the user's word: the rest must be given too.
    (path / "mabdi.toml").write_text("[lidar]\nbeams = 16\n")
    with pytest.raises(SequenceError, match=r"without a ring field is binned by elevation: give the LiDAR's fov_up, fov_down"):
        Rosbag2Sequence(path)
    (path / "mabdi.toml").write_text("[lidar]\nbeams = 16\ncolumns = 64\nfov_up = 10.0\nfov_down = -20.0\nrange_max = 50.0\n")
    sequence = Rosbag2Sequence(path)
    np.testing.assert_allclose(sequence.read(2).depth, source.read(2).depth, rtol=2e-7, equal_nan=True)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: setattr(m, "fields", [f for f in m.fields if f.name != "y"]) or m, r"needs fields x, y, z; it has intensity, ring, time, x, z"),
        (lambda m: setattr(m, "data", m.data[:-16]) or m, r"only \d+ bytes of data"),
        (lambda m: setattr(m, "point_step", 12) or m, r"fields end at byte 22 of a point_step of 12"),
    ],
)
def test_bad_clouds_name_the_topic(bags, tmp_path, change, message):
    path = _rewrite_clouds(bags["velodyne", "sqlite3"], tmp_path / "bad", change)
    with pytest.raises(SequenceError, match="topic /lidar/points: .*" + message):
        Rosbag2Sequence(path).read(0)


def test_rings_beyond_the_geometry_and_wrong_options(bags, tmp_path):
    path = bags["velodyne", "mcap"]
    (tmp_path / "few").mkdir()
    few = _rewrite_clouds(path, tmp_path / "few" / "bag", lambda m: m)
    (few / "mabdi.toml").write_text("[lidar]\nbeams = 8\n")
    with pytest.raises(SequenceError, match=r"/lidar/points: first message: ring 15 is outside 0 .. 7"):
        Rosbag2Sequence(few)
    with pytest.raises(SequenceError, match=r"--colour-topic \(Python: colour_topic=\) is for depth images"):
        Rosbag2Sequence(path, colour_topic="/lidar/points")
    with pytest.raises(SequenceError, match=r"topic /lidar/pose \(--cloud-topic \(Python: cloud_topic=\)\) is geometry_msgs/msg/PoseStamped"):
        Rosbag2Sequence(path, cloud_topic="/lidar/pose")


def test_writers_refuse_the_other_sensor(source, tmp_path):
    with pytest.raises(SequenceError, match="range images: write them with write_lidar_rosbag2"):
        write_rosbag2(source, tmp_path / "a")
    with pytest.raises(SequenceError, match="unknown point layout 'hesai'"):
        write_lidar_rosbag2(source, tmp_path / "b", layout="hesai")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_organised_cloud_without_rings_takes_its_rows(bags, source, tmp_path):
    def drop_ring(message):
        message.fields = [f for f in message.fields if f.name != "ring"]
        return message

    path = _rewrite_clouds(bags["ouster", "sqlite3"], tmp_path / "no_ring", drop_ring)  # no mabdi.toml
    sequence = Rosbag2Sequence(path)
    assert sequence.intrinsics.beams == 16 and sequence.intrinsics.columns == 64
    np.testing.assert_allclose(sequence.read(0).depth, source.read(0).depth, rtol=1e-6, equal_nan=True)
