"""Recorded sequences: TUM RGB-D folders and ROS 2 bags written from frames in memory and read back."""

from __future__ import annotations

import dataclasses
import tomllib

import numpy as np
import pytest
from PIL import Image
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame, only_returns
from mabdi.errors import ConfigError
from mabdi.sources.frames import FrameList
from mabdi.sources.rosbag2 import _TYPESTORE, Rosbag2Sequence, write_rosbag2
from mabdi.sources.sequences import SequenceError, nearest_within, open_sequence, read_sequence_metadata
from mabdi.sources.tum import PRESETS, TumSequence, write_tum

# Not the defaults, so that a reader falling back to them fails: off-centre principal point, fx != fy, own range.
INTRINSICS = Intrinsics(fx=60.5, fy=58.25, cx=31.75, cy=24.5, width=64, height=48, near=0.3, far=6.0)
TIMES = 1_700_000_000.0 + np.array([0.0, 0.033, 0.066, 0.1, 0.133])  # seconds, like a real clock
EXTRA = {"recorded": {"scene": "scenes/table.toml", "frames": 5, "noise": "kinect"}}


def _frames() -> list[DepthFrame]:
    rng = np.random.default_rng(7)
    v, u = np.mgrid[0:48, 0:64]
    frames = []
    for i, t in enumerate(TIMES):
        depth = 0.8 + 0.02 * u + 0.01 * v + 0.1 * i + rng.uniform(-0.01, 0.01, (48, 64))
        depth[5:9, 10:20] = np.nan  # no return
        depth[0, 0] = 0.0012345  # closer than near: not a return (mabdi.depth.returns), NaN once read
        depth[0, 1] = 0.3005  # just inside near: a return, still a number after the round trip
        pose = look_at([2.0 + 0.1 * i, -1.0, 1.2 + 0.05 * i], [0.0, 0.2 * i, 0.4])  # rotated about every axis
        frames.append(DepthFrame(depth.astype(np.float32), INTRINSICS, pose, i, float(t)))
    return frames


@pytest.fixture(scope="module")
def frames() -> list[DepthFrame]:
    return _frames()


@pytest.fixture(scope="module")
def tum_folder(tmp_path_factory, frames):
    return write_tum(FrameList(frames, "test frames"), tmp_path_factory.mktemp("tum") / "seq", extra=EXTRA)


def _check_depth(read, expected, step):
    """Same no-return pixels (by the one rule, mabdi.depth.returns); depth within half the format's step."""
    expected = only_returns(expected, INTRINSICS.near, INTRINSICS.far)
    np.testing.assert_array_equal(np.isnan(read), np.isnan(expected))
    np.testing.assert_allclose(read, expected, rtol=0, atol=step / 2 + 1e-6, equal_nan=True)


# ---------------------------------------------------------------------------
# TUM


def test_tum_round_trip(tum_folder, frames):
    sequence = TumSequence(tum_folder)
    assert len(sequence) == len(frames) and sequence.skipped == 0
    assert sequence.intrinsics == INTRINSICS
    np.testing.assert_allclose(sequence.timestamps, TIMES, atol=1e-6)
    for i, expected in enumerate(frames):
        frame = sequence.read(i)
        assert frame.frame == i and frame.depth.dtype == np.float32
        _check_depth(frame.depth, expected.depth, 1 / 5000)  # 0.2 mm steps: within 0.1 mm
        np.testing.assert_allclose(frame.world_from_camera, expected.world_from_camera, rtol=0, atol=1e-9)
        np.testing.assert_allclose(sequence.poses[i], expected.world_from_camera, rtol=0, atol=1e-9)
    assert read_sequence_metadata(tum_folder)["recorded"] == EXTRA["recorded"]
    with pytest.raises(IndexError, match="TUM folder"):
        sequence.read(len(frames))


def test_tum_png_is_16_bit_with_5000_units_per_metre(tum_folder, frames):
    name = (tum_folder / "depth.txt").read_text().splitlines()[-1].split()[1]
    values = np.asarray(Image.open(tum_folder / name))
    assert values.dtype == np.uint16 and values[6, 15] == 0  # no return -> 0
    assert values[10, 10] == round(float(frames[-1].depth[10, 10]) * 5000)


def test_tum_writer_clips_out_of_range_depth(tmp_path, frames):
    depth = frames[0].depth.copy()
    depth[1, 1], depth[1, 2], depth[1, 3] = 20.0, -1.0, np.inf  # beyond 65535 / 5000 m, negative, infinite
    far = dataclasses.replace(INTRINSICS, far=30.0)
    write_tum(FrameList([DepthFrame(depth, far, frames[0].world_from_camera, 0, 1.0)]), tmp_path / "seq")
    read = TumSequence(tmp_path / "seq").read(0).depth
    assert np.isnan(read[1, 1:4]).all()


def test_tum_camera_argument_wins_and_presets_shift_pixel_centres(tum_folder):
    sequence = TumSequence(tum_folder, camera=dataclasses.replace(INTRINSICS, fx=70.0))
    assert sequence.intrinsics.fx == 70.0
    fr1 = PRESETS["fr1"]
    assert (fr1.fx, fr1.fy, fr1.cx, fr1.cy) == (517.3, 516.5, 319.1, 255.8)  # TUM's 318.6, 255.3 + 0.5
    assert (fr1.near, fr1.far) == (Intrinsics().near, Intrinsics().far)
    with pytest.raises(SequenceError, match="fr1, fr2, fr3"):
        TumSequence(tum_folder, camera="fr9")


def test_tum_camera_preset_in_toml(tmp_path, frames):
    big = [DepthFrame(np.full((480, 640), 1.0, np.float32), PRESETS["fr2"], f.world_from_camera, i, f.timestamp) for i, f in enumerate(frames[:2])]
    folder = write_tum(FrameList(big), tmp_path / "seq")
    (folder / "mabdi.toml").write_text('[camera]\npreset = "fr3"\nfar = 5.5\n')
    intrinsics = TumSequence(folder).intrinsics
    assert intrinsics == dataclasses.replace(PRESETS["fr3"], far=5.5)


def test_a_benchmark_folder_names_its_camera(tmp_path, frames):
    """A folder as the TUM benchmark publishes it (no mabdi.toml): depth.txt's header, or the folder's name, names
    the Kinect (rgbd_dataset_freiburg2_...) and its calibration is taken, and said; a name without one still asks."""
    big = [DepthFrame(np.full((480, 640), 1.0, np.float32), PRESETS["fr2"], f.world_from_camera, i, f.timestamp) for i, f in enumerate(frames[:2])]
    folder = write_tum(FrameList(big), tmp_path / "seq")
    (folder / "mabdi.toml").unlink()
    with pytest.raises(SequenceError, match="no intrinsics: give --camera"):
        TumSequence(folder)
    depth_list = folder / "depth.txt"
    depth_list.write_text("# depth maps\n# file: 'rgbd_dataset_freiburg2_desk.bag'\n" + depth_list.read_text())
    sequence = TumSequence(folder)
    assert sequence.intrinsics == PRESETS["fr2"]
    assert "camera: TUM's fr2 calibration (named by depth.txt's header)" in sequence.description
    assert TumSequence(folder, camera="fr1").intrinsics == PRESETS["fr1"], "a camera given wins"
    renamed = folder.rename(tmp_path / "rgbd_dataset_freiburg3_long_office_household")
    depth_list = renamed / "depth.txt"
    depth_list.write_text("\n".join(line for line in depth_list.read_text().splitlines() if not line.startswith("#")) + "\n")
    sequence = TumSequence(renamed)
    assert sequence.intrinsics == PRESETS["fr3"] and "(named by the folder)" in sequence.description


def test_a_calibration_file_gives_the_camera(tmp_path, frames):
    """The layout's ETH3D variant: calibration.txt's one line 'fx fy cx cy' (pixel centres at integers) is the
    camera, at the depth images' size; a mabdi.toml [camera] table and camera= win over it; a file that is not
    one line of four numbers is refused naming it."""
    folder = write_tum(FrameList(frames), tmp_path / "seq")
    (folder / "mabdi.toml").unlink()
    (folder / "calibration.txt").write_text("60.5 58.25 31.25 24\n")  # INTRINSICS with OpenCV's pixel centres
    sequence = TumSequence(folder)
    assert sequence.intrinsics == dataclasses.replace(INTRINSICS, near=Intrinsics().near, far=Intrinsics().far)
    assert "camera: calibration.txt" in sequence.description
    np.testing.assert_allclose(sequence.read(1).world_from_camera, frames[1].world_from_camera, atol=1e-6)
    assert TumSequence(folder, camera="fr1").intrinsics == PRESETS["fr1"], "a camera given wins"
    (folder / "mabdi.toml").write_text("[camera]\nfx = 61\nfy = 59\ncx = 32\ncy = 24\nwidth = 64\nheight = 48\n")
    assert TumSequence(folder).intrinsics.fx == 61.0, "the folder's mabdi.toml wins"
    (folder / "mabdi.toml").unlink()
    for text, message in [
        ("60.5 58.25 31.25 24 0.1 -0.02\n", r"calibration\.txt:1: expected one line 'fx fy cx cy'"),
        ("# fx fy cx cy\n60.5 58.25 31.25\n", r"calibration\.txt:2: expected one line 'fx fy cx cy'"),
        ("60.5 58.25 abc 24\n", r"calibration\.txt:1: 'fx fy cx cy' must be numbers"),
        ("", r"calibration\.txt: expected one line 'fx fy cx cy'.*got nothing"),
    ]:
        (folder / "calibration.txt").write_text(text)
        with pytest.raises(SequenceError, match=message):
            TumSequence(folder)


def test_tum_pose_30_ms_away_is_skipped_and_counted(tmp_path, frames):
    folder = write_tum(FrameList(frames), tmp_path / "seq")
    lines = (folder / "groundtruth.txt").read_text().splitlines()
    data = [i for i, line in enumerate(lines) if not line.startswith("#")]
    fields = lines[data[2]].split()
    fields[0] = f"{float(fields[0]) + 0.030:.6f}"  # 30 ms after its depth frame (and 3 ms before the next one's)
    lines[data[2]] = " ".join(fields)
    (folder / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    sequence = TumSequence(folder)
    assert sequence.skipped == 1 and len(sequence) == 4 and "1 without a pose" in sequence.description
    np.testing.assert_allclose(sequence.timestamps, np.delete(TIMES, 2), atol=1e-6)
    np.testing.assert_allclose(sequence.poses[2], frames[3].world_from_camera, atol=1e-9)
    assert len(TumSequence(folder, tolerance=0.031)) == 5


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda f: (f / "groundtruth.txt").unlink(), r"missing groundtruth\.txt"),
        (lambda f: (f / "depth.txt").unlink(), r"missing depth\.txt"),
        (lambda f: (f / "mabdi.toml").unlink(), r"no intrinsics.*camera="),
        (lambda f: (f / "mabdi.toml").write_text("[camera]\nfx = 1\nwidht = 3\n"), r"mabdi\.toml: unknown key 'camera\.widht'"),
        (lambda f: _append(f / "groundtruth.txt", "1.0 2.0 3.0\n"), r"groundtruth\.txt:\d+: expected 8 fields"),
        (lambda f: _append(f / "depth.txt", "abc depth/x.png\n"), r"depth\.txt:\d+: timestamp 'abc'"),
        (lambda f: _first_png(f).write_bytes(b"\x89PNG\r\n\x1a\n garbage"), r"\.png: cannot read depth PNG"),
        (lambda f: Image.fromarray(np.zeros((48, 64), np.uint8)).save(_first_png(f)), r"\.png: not a 16-bit"),
        (lambda f: Image.fromarray(np.zeros((40, 64), np.uint16)).save(_first_png(f)), r"\.png: image is 64x40, intrinsics say 64x48"),
        (lambda f: _first_png(f).unlink(), r"\.png: depth image missing"),
    ],
)
def test_tum_bad_inputs_name_the_file(tmp_path, frames, damage, message):
    folder = write_tum(FrameList(frames), tmp_path / "seq")
    damage(folder)
    with pytest.raises(ConfigError, match=message):
        TumSequence(folder).read(0)


def test_tum_missing_folder_and_writer_refuses_a_full_folder(tmp_path, frames):
    with pytest.raises(ConfigError, match="nowhere"):
        TumSequence(tmp_path / "nowhere", camera="fr1")
    write_tum(FrameList(frames), tmp_path / "seq")
    with pytest.raises(SequenceError, match="not empty"):
        write_tum(FrameList(frames), tmp_path / "seq")
    write_tum(FrameList(frames[:2]), tmp_path / "seq", overwrite=True)


def _append(path, text):
    with open(path, "a") as stream:
        stream.write(text)


def _first_png(folder):
    return folder / (folder / "depth.txt").read_text().splitlines()[2].split()[1]


# ---------------------------------------------------------------------------
# ROS 2 bags


@pytest.fixture(scope="module")
def bags(tmp_path_factory, frames):
    root = tmp_path_factory.mktemp("bags")
    return {
        (storage, encoding): write_rosbag2(
            FrameList(frames), root / f"{storage}_{encoding}", storage=storage, encoding=encoding, extra=EXTRA
        )
        for storage in ("sqlite3", "mcap")
        for encoding in ("32FC1", "16UC1")
    }


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("encoding", ["32FC1", "16UC1"])
def test_bag_round_trip(bags, frames, storage, encoding):
    path = bags[storage, encoding]
    assert (path / "metadata.yaml").is_file() and any(path.glob("*.mcap" if storage == "mcap" else "*.db3"))
    with Rosbag2Sequence(path) as sequence:
        assert sequence.pose_source == "/camera/pose" and sequence.skipped == 0
        assert sequence.intrinsics == INTRINSICS  # K with integer pixel centres, +0.5 on reading; near/far from mabdi.toml
        np.testing.assert_allclose(sequence.timestamps, TIMES, rtol=0, atol=1e-9)
        for i, expected in enumerate(frames):
            frame = sequence.read(i)
            if encoding == "32FC1":
                # exact, NaN where NaN (and where the one rule says no return: closer than near)
                np.testing.assert_array_equal(frame.depth, only_returns(expected.depth, INTRINSICS.near, INTRINSICS.far))
            else:
                _check_depth(frame.depth, np.where(expected.depth >= 0.0005, expected.depth, np.nan), 1e-3)  # mm
            np.testing.assert_allclose(frame.world_from_camera, expected.world_from_camera, rtol=0, atol=1e-9)
            assert frame.timestamp == pytest.approx(TIMES[i], abs=1e-9) and frame.frame == i
        # frames can be read in any order, and again
        np.testing.assert_array_equal(sequence.read(3).depth, sequence.read(3).depth)
    assert read_sequence_metadata(path)["recorded"] == EXTRA["recorded"]


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bag_tf_and_pose_topic_agree(bags, frames, storage):
    path = bags[storage, "32FC1"]
    from_topic = Rosbag2Sequence(path).poses
    from_tf = Rosbag2Sequence(path, pose_topic="/tf")
    assert from_tf.pose_source == "/tf" and from_tf.world_frame == "world" and from_tf.camera_frame == "camera_depth_optical_frame"
    np.testing.assert_allclose(from_tf.poses, from_topic, rtol=0, atol=1e-9)
    np.testing.assert_allclose(from_tf.poses, [f.world_from_camera for f in frames], rtol=0, atol=1e-9)
    # chained only up to an intermediate frame: camera_link_from_optical, the static transform
    link = Rosbag2Sequence(path, pose_topic="/tf", frame_id="camera_link").poses
    np.testing.assert_allclose(link[0][:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)


def test_bag_single_storage_file_and_open_sequence(bags, frames, tum_folder):
    path = bags["mcap", "16UC1"]
    (storage_file,) = path.glob("*.mcap")
    assert len(Rosbag2Sequence(storage_file)) == len(frames)
    assert isinstance(open_sequence(path), Rosbag2Sequence)
    assert isinstance(open_sequence(storage_file), Rosbag2Sequence)
    assert isinstance(open_sequence(tum_folder), TumSequence)
    assert read_sequence_metadata(tum_folder / "nowhere") == {}


def test_open_sequence_refuses_other_folders(tmp_path):
    with pytest.raises(SequenceError, match="not a recorded sequence"):
        open_sequence(tmp_path)
    with pytest.raises(SequenceError, match="does not exist"):
        open_sequence(tmp_path / "nowhere")


def _rewrite(source, target, *, drop=(), change=None, copy=None):
    """Copy a bag, dropping topics, changing messages (change(topic, index, message) -> message) and copying topics."""
    change = change or (lambda topic, index, message: message)
    copy = copy or {}
    with Reader(source) as reader, Writer(target, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        out = {}
        for connection in reader.connections:
            for topic in (connection.topic, copy.get(connection.topic)):
                if topic and topic not in drop:
                    out[topic] = writer.add_connection(topic, connection.msgtype, typestore=_TYPESTORE)
        counts: dict[str, int] = {}
        for connection, time, raw in reader.messages():
            if connection.topic in drop:
                continue
            index = counts[connection.topic] = counts.get(connection.topic, -1) + 1
            message = change(connection.topic, index, _TYPESTORE.deserialize_cdr(raw, connection.msgtype))
            data = _TYPESTORE.serialize_cdr(message, connection.msgtype)
            for topic in (connection.topic, copy.get(connection.topic)):
                if topic:
                    writer.write(out[topic], time, data)
    return target


def test_bag_pose_30_ms_away_is_skipped_and_counted(bags, tmp_path):
    def late(topic, index, message):
        if topic == "/camera/pose" and index == 2:
            message.header.stamp.nanosec += 30_000_000
        return message

    path = _rewrite(bags["sqlite3", "32FC1"], tmp_path / "bag", change=late)
    sequence = Rosbag2Sequence(path)
    assert sequence.skipped == 1 and len(sequence) == 4 and "1 without a pose" in sequence.description
    np.testing.assert_allclose(sequence.timestamps, np.delete(TIMES, 2), atol=1e-9)
    np.testing.assert_array_equal(sequence.read(2).depth, Rosbag2Sequence(path, tolerance=0.031).read(3).depth)
    assert len(Rosbag2Sequence(path, pose_topic="/tf")) == 5  # /tf is untouched


def test_bag_pose_topic_is_interpolated_between_the_samples_around_an_image(bags, frames, tmp_path):
    """A pose topic stamped half a frame after the images (16.5 ms): each image lies between two samples within
    the tolerance and gets the pose between them (slerp, about halfway), not the nearer one; the first keeps its nearest."""
    from scipy.spatial.transform import Rotation, Slerp

    def half_a_frame_late(topic, index, message):
        if topic == "/camera/pose":
            message.header.stamp.nanosec += 16_500_000
        return message

    path = _rewrite(bags["sqlite3", "32FC1"], tmp_path / "bag", change=half_a_frame_late)
    sequence = Rosbag2Sequence(path, pose_topic="/camera/pose")
    assert len(sequence) == 5 and sequence.skipped == 0
    np.testing.assert_allclose(sequence.poses[0], frames[0].world_from_camera, atol=1e-9)
    for i in range(1, 5):
        before, after = frames[i - 1].world_from_camera, frames[i].world_from_camera
        share = (TIMES[i] - TIMES[i - 1] - 0.0165) / (TIMES[i] - TIMES[i - 1])  # about a half
        between = Slerp([0.0, 1.0], Rotation.from_matrix([before[:3, :3], after[:3, :3]]))([share]).as_matrix()[0]
        np.testing.assert_allclose(sequence.poses[i][:3, :3], between, atol=1e-6)
        np.testing.assert_allclose(sequence.poses[i][:3, 3], (1 - share) * before[:3, 3] + share * after[:3, 3], atol=1e-6)


def test_bag_tf_matching_skips_frames_without_a_transform(bags, tmp_path):
    def late(topic, index, message):
        if topic == "/tf" and index == 4:
            message.transforms[0].header.stamp.sec += 1  # the last frame is 1 s past the link's last transform
        return message

    path = _rewrite(bags["sqlite3", "32FC1"], tmp_path / "bag", change=late)
    sequence = Rosbag2Sequence(path, pose_topic="/tf")
    assert sequence.skipped == 0  # a link published late is interpolated across the gap, as tf2 does

    def gone(topic, index, message):
        if topic == "/tf" and index == 4:
            message.transforms[0].header.stamp.sec -= 10  # now the link ends 33 ms before the last frame
        return message

    path = _rewrite(bags["sqlite3", "32FC1"], tmp_path / "bag2", change=gone)
    sequence = Rosbag2Sequence(path, pose_topic="/tf")
    assert sequence.skipped == 1 and "not reached by world -> camera_link" in sequence.description


@pytest.mark.parametrize(
    ("rewrite", "options", "message"),
    [
        ({"drop": ("/camera/pose", "/tf", "/tf_static")}, {}, r"bag.*: no pose source for /camera/depth/image"),
        ({"drop": ("/camera/depth/camera_info",)}, {}, r"bag.*: no sensor_msgs/msg/CameraInfo topic .*--info-topic \(Python: info_topic=\)"),
        ({"change": lambda t, i, m: dataclasses.replace(m, encoding="rgb8") if t.endswith("image") else m}, {"depth_topic": "/camera/depth/image"}, r"topic /camera/depth/image: unknown depth encoding 'rgb8'"),
        ({}, {"depth_topic": "/camera/dept"}, r"no topic '/camera/dept' \(--depth-topic \(Python: depth_topic=\)\); the bag has: /camera/depth/camera_info"),
        ({}, {"pose_topic": "/odom"}, r"no topic '/odom' \(--pose-topic .*\); the bag has:.*/camera/pose"),
        ({}, {"info_topic": "/camera/pose"}, r"topic /camera/pose \(--info-topic .*\) is geometry_msgs/msg/PoseStamped"),
        ({"copy": {"/camera/depth/image": "/other/depth"}}, {}, r"several depth image topics \(/camera/depth/image, /other/depth\); choose one with --depth-topic"),
        ({"copy": {"/camera/pose": "/other/pose"}}, {}, r"several geometry_msgs/msg/PoseStamped topics .*--pose-topic"),
        ({"drop": ("/tf_static",)}, {"pose_topic": "/tf"}, r"/tf has no transform to the depth images' frame 'camera_depth_optical_frame'"),
        ({}, {"pose_topic": "/tf", "frame_id": "map"}, r"frame_id='map' is not above"),
        ({}, {"frame_id": "map"}, r"topic /camera/pose: pose in frame 'world', expected frame_id='map'"),
    ],
)
def test_bag_bad_inputs_name_the_bag_and_topic(bags, tmp_path, rewrite, options, message):
    path = _rewrite(bags["sqlite3", "32FC1"], tmp_path / "bag", **rewrite)
    with pytest.raises(ConfigError, match=message):
        Rosbag2Sequence(path, **options)


def test_bag_writer_refuses_existing_bags_and_unknown_options(bags, frames, tmp_path):
    source = FrameList(frames)
    with pytest.raises(SequenceError, match="exists already"):
        write_rosbag2(source, bags["sqlite3", "32FC1"])
    with pytest.raises(SequenceError, match="unknown storage 'rosbag1'"):
        write_rosbag2(source, tmp_path / "a", storage="rosbag1")
    with pytest.raises(SequenceError, match="unknown depth encoding '8UC1'"):
        write_rosbag2(source, tmp_path / "b", encoding="8UC1")
    assert not (tmp_path / "a").exists() and not list(tmp_path.iterdir())  # nothing half-written
    with pytest.raises(ConfigError, match="does not exist"):
        Rosbag2Sequence(tmp_path / "nowhere")


def test_bag_near_far_from_mabdi_toml(bags, tmp_path):
    path = _rewrite(bags["mcap", "32FC1"], tmp_path / "bag")  # the copy has no mabdi.toml: Intrinsics' defaults
    assert (Rosbag2Sequence(path).intrinsics.near, Rosbag2Sequence(path).intrinsics.far) == (Intrinsics().near, Intrinsics().far)
    (path / "mabdi.toml").write_text("[camera]\nnear = 0.2\nfar = 9.0\n")
    assert (Rosbag2Sequence(path).intrinsics.near, Rosbag2Sequence(path).intrinsics.far) == (0.2, 9.0)
    assert tomllib.loads((bags["mcap", "32FC1"] / "mabdi.toml").read_text())["camera"]["far"] == INTRINSICS.far


def test_nearest_within():
    reference = np.array([0.3, 0.0, 0.1, 0.2])
    np.testing.assert_array_equal(nearest_within([0.0, 0.05, 0.19, 0.5, -0.02, 0.29], reference, 0.02), [1, -1, 3, -1, 1, 0])
    np.testing.assert_array_equal(nearest_within([1.0], [], 0.1), [-1])


def _png_with_every_filter(values: np.ndarray) -> bytes:
    """A 16-bit greyscale PNG of ``values`` whose rows use filter types 0-4 in turn (Pillow picks one for all)."""
    import struct
    import zlib

    rows = values.astype(">u2").view(np.uint8).reshape(values.shape[0], -1).astype(np.int32)
    out = []
    for y, row in enumerate(rows):
        kind = y % 5
        up = rows[y - 1] if y else np.zeros_like(row)
        left = np.concatenate([[0, 0], row[:-2]])
        up_left = np.concatenate([[0, 0], up[:-2]])
        p = left + up - up_left
        pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - up_left)
        paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, up_left))
        predictor = [np.zeros_like(row), left, up, (left + up) // 2, paeth][kind]
        out.append(bytes([kind]) + ((row - predictor) & 0xFF).astype(np.uint8).tobytes())

    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", values.shape[1], values.shape[0], 16, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"".join(out))) + chunk(b"IEND", b"")


def test_fast_png_decoder_equals_pillow_for_every_row_filter(tmp_path):
    from mabdi.sources.png import decode_gray16_png

    values = np.random.default_rng(3).integers(0, 65536, (23, 37)).astype(np.uint16)
    values[5:9] = 4000  # flat rows, as depth has
    data = _png_with_every_filter(values)
    (tmp_path / "x.png").write_bytes(data)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "x.png")), values)  # the test's encoder is right
    np.testing.assert_array_equal(decode_gray16_png(data), values)
    assert decode_gray16_png(data.replace(b"IHDR", b"IHDX")) is None  # not ours: Pillow decides
