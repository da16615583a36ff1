"""ROS 1 bags (``.bag``): read as TUM's own bags are laid out (32FC1 depth, CameraInfo's ``K``, the pose on
``/tf`` as ``tf/tfMessage``, frame names with a leading ``/``), the same frames as the recording they were
written from, and run by ``mabdi run --sequence``."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mabdi.camera import quaternions_from_rotations
from mabdi.cli import main
from mabdi.sources.rosbag2 import LINK_FROM_OPTICAL, Rosbag2Sequence
from mabdi.sources.sequences import SequenceError, open_sequence, sequence_format

rosbag1 = pytest.importorskip("rosbags.rosbag1")
typesys = pytest.importorskip("rosbags.typesys")

OPTICAL = "/openni_depth_optical_frame"


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """4 frames of the table scene as a TUM folder, recorded by mabdi."""
    root = tmp_path_factory.mktemp("ros1")
    table = Path(__file__).resolve().parents[1] / "scenes" / "table.toml"
    assert main(["record", str(table), "--frames", "4", "--format", "tum", "--out", str(root / "tum")]) == 0
    return open_sequence(root / "tum")


def _write_ros1_bag(source, path, compressed: bool = False) -> None:
    """``source``'s frames as a ROS 1 bag laid out as TUM's: /camera/depth/image (32FC1, metres),
    /camera/depth/camera_info (K with pixel centres at integers) and /tf (``tf/tfMessage``) carrying
    /world -> /kinect at each image's stamp and /kinect -> the optical frame (a camera link, REP 103).
    ``compressed``: the depth as a robot's driver records it instead, /camera/depth/image_raw/compressedDepth
    (16UC1 millimetres, image_transport's header and PNG), beside a colour image topic."""
    store = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    store.register(typesys.get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf/msg/tfMessage"))
    t = store.types
    k = source.intrinsics
    link_from_optical = LINK_FROM_OPTICAL

    def header(seconds: float, frame: str):
        whole = int(np.floor(seconds))
        return t["std_msgs/msg/Header"](seq=0, stamp=t["builtin_interfaces/msg/Time"](sec=whole, nanosec=int(round((seconds - whole) * 1e9))), frame_id=frame)

    def transform(seconds: float, parent: str, child: str, matrix: np.ndarray):
        x, y, z, w = quaternions_from_rotations(matrix[None, :3, :3])[0]
        return t["geometry_msgs/msg/TransformStamped"](
            header=header(seconds, parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=matrix[0, 3], y=matrix[1, 3], z=matrix[2, 3]),
                rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
            ),
        )  # fmt: skip

    with rosbag1.Writer(path) as writer:
        if compressed:
            depth_topic = writer.add_connection("/camera/depth/image_raw/compressedDepth", "sensor_msgs/msg/CompressedImage", typestore=store)
            colour_topic = writer.add_connection("/camera/rgb/image_raw", "sensor_msgs/msg/Image", typestore=store)
        else:
            depth_topic = writer.add_connection("/camera/depth/image", "sensor_msgs/msg/Image", typestore=store)
        info_topic = writer.add_connection("/camera/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=store)
        tf_topic = writer.add_connection("/tf", "tf/msg/tfMessage", typestore=store)
        for i in range(len(source)):
            frame = source.read(i)
            seconds = 1_300_000_000.0 + 0.25 * i  # a 2011 recording's clock
            stamp = int(round(seconds * 1e9))
            world_from_kinect = frame.world_from_camera @ np.linalg.inv(link_from_optical)
            tf = t["tf/msg/tfMessage"](transforms=[
                transform(seconds, "/world", "/kinect", world_from_kinect),
                transform(seconds, "/kinect", OPTICAL, link_from_optical),
            ])  # fmt: skip
            writer.write(tf_topic, stamp, store.serialize_ros1(tf, "tf/msg/tfMessage"))
            if compressed:
                stream = io.BytesIO()
                Image.fromarray(np.nan_to_num(np.round(frame.depth * 1000.0), nan=0.0).astype(np.uint16)).save(stream, format="PNG")
                payload = struct.pack("<iff", 0, 0.0, 0.0) + stream.getvalue()
                image = t["sensor_msgs/msg/CompressedImage"](
                    header=header(seconds, OPTICAL), format="16UC1; compressedDepth png", data=np.frombuffer(payload, np.uint8),
                )  # fmt: skip
                writer.write(depth_topic, stamp, store.serialize_ros1(image, "sensor_msgs/msg/CompressedImage"))
                colour = t["sensor_msgs/msg/Image"](
                    header=header(seconds, "/openni_rgb_optical_frame"), height=k.height, width=k.width, encoding="rgb8",
                    is_bigendian=0, step=3 * k.width, data=np.zeros(3 * k.width * k.height, dtype=np.uint8),
                )  # fmt: skip
                writer.write(colour_topic, stamp, store.serialize_ros1(colour, "sensor_msgs/msg/Image"))
            else:
                depth = np.nan_to_num(frame.depth, nan=0.0).astype("<f4")
                image = t["sensor_msgs/msg/Image"](
                    header=header(seconds, OPTICAL), height=k.height, width=k.width, encoding="32FC1", is_bigendian=0,
                    step=4 * k.width, data=np.frombuffer(depth.tobytes(), dtype=np.uint8),
                )  # fmt: skip
                writer.write(depth_topic, stamp, store.serialize_ros1(image, "sensor_msgs/msg/Image"))
            info = t["sensor_msgs/msg/CameraInfo"](
                header=header(seconds, OPTICAL), height=k.height, width=k.width, distortion_model="plumb_bob",
                D=np.zeros(5), K=np.array([k.fx, 0, k.cx - 0.5, 0, k.fy, k.cy - 0.5, 0, 0, 1.0]), R=np.eye(3).ravel(),
                P=np.array([k.fx, 0, k.cx - 0.5, 0, 0, k.fy, k.cy - 0.5, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
                roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
            )  # fmt: skip
            writer.write(info_topic, stamp, store.serialize_ros1(info, "sensor_msgs/msg/CameraInfo"))


@pytest.fixture(scope="module")
def bag(recording, tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "small.bag"
    _write_ros1_bag(recording, path)
    return path


def test_a_ros1_bag_reads_as_the_frames_it_was_written_from(recording, bag):
    assert sequence_format(bag) == "rosbag1"
    read = open_sequence(bag)
    assert "ROS 1 bag" in read.description and len(read) == len(recording)
    k = recording.intrinsics
    assert (read.intrinsics.fx, read.intrinsics.fy, read.intrinsics.cx, read.intrinsics.cy) == (k.fx, k.fy, k.cx, k.cy)
    assert read.world_frame == "world"
    for i in range(len(recording)):
        mine, theirs = read.read(i), recording.read(i)
        np.testing.assert_allclose(mine.world_from_camera, theirs.world_from_camera, atol=1e-9)
        np.testing.assert_array_equal(np.isnan(mine.depth), np.isnan(theirs.depth))
        np.testing.assert_allclose(mine.depth, theirs.depth, atol=1e-6, equal_nan=True)
    read.close()


@pytest.mark.parametrize("name", ["world", "/world"])
def test_a_ros1_bags_world_frame_may_be_named_with_or_without_its_slash(bag, name):
    read = Rosbag2Sequence(bag, pose_topic="/tf", frame_id=name)
    assert read.world_frame == "world" and len(read) == 4
    read.close()


def test_mabdi_run_maps_a_ros1_bag(bag, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--sequence", str(bag), "--quiet", "--no-eval", "--surface", "pixel_grid", "--out", str(out)]) == 0
    assert "source: ROS 1 bag" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 4 and summary["cells"] > 0


def test_a_damaged_ros1_bag_is_an_error_naming_it(tmp_path):
    path = tmp_path / "broken.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    with pytest.raises(SequenceError, match=r"ROS 1 bag .*broken\.bag: cannot open"):
        open_sequence(path)


def test_depth_compressed_as_a_robot_records_it_is_read(recording, tmp_path):
    """A bag of image_transport's compressedDepth (16UC1, PNG) and a colour Image topic: the compressed topic is
    the depth (the Image one holds colour), its size its PNG's, and its frames the recording's to the millimetre."""
    path = tmp_path / "compressed.bag"
    _write_ros1_bag(recording, path, compressed=True)
    read = open_sequence(path)
    assert read.depth_topic == "/camera/depth/image_raw/compressedDepth"
    assert (read.intrinsics.width, read.intrinsics.height) == (recording.intrinsics.width, recording.intrinsics.height)
    for i in range(len(recording)):
        mine, theirs = read.read(i), recording.read(i)
        np.testing.assert_array_equal(np.isnan(mine.depth), np.isnan(theirs.depth))
        np.testing.assert_allclose(mine.depth, theirs.depth, atol=0.0005 + 1e-6, equal_nan=True)
        np.testing.assert_allclose(mine.world_from_camera, theirs.world_from_camera, atol=1e-9)
    read.close()
