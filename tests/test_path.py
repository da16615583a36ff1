"""Sensor paths: the helix (geometry, look-at, coverage of the seed's scenes), waypoints and trajectories."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mabdi.camera import check_pose, in_view, look_at, project
from mabdi.config import PathConfig, dump_toml, load_run_config, run_config_from_dict, set_value
from mabdi.errors import ConfigError
from mabdi.simulate.path import (
    CAMERA_FROM_LIDAR,
    heading_poses,
    helical_path,
    path_frame_count,
    path_from_config,
    path_targets,
    path_timestamps,
)
from mabdi.sources.tum import write_tum_trajectory
from mabdi.sources.scene import SourceScene


def test_poses_are_rigid_and_look_at_their_targets(scenes_dir):
    config = load_run_config(scenes_dir / "bunnies.toml")
    poses = path_from_config(50, config.path)
    targets = path_targets(50, config.path)
    intrinsics = config.sensor.intrinsics()
    assert poses.shape == (50, 4, 4)
    for pose, target in zip(poses, targets, strict=True):
        check_pose(pose)
        uv, z = project(target, intrinsics, pose)
        assert z[0] > 0
        np.testing.assert_allclose(uv[0], [intrinsics.cx, intrinsics.cy], atol=1e-9)
        assert pose[:3, 1] @ np.array([0, 0, 1.0]) < 0  # image down is world down-ish (no roll)
        assert abs(pose[:3, 0][2]) < 1e-12  # camera x stays horizontal


def test_helix_geometry_two_circles_rising():
    poses = helical_path(41, center=(0.5, -0.2), radius_x=3.0, radius_y=2.0, z0=1.0, z1=2.0, turns=2.0)
    eye = poses[:, :3, 3]
    np.testing.assert_allclose(((eye[:, 0] - 0.5) / 3.0) ** 2 + ((eye[:, 1] + 0.2) / 2.0) ** 2, 1.0)
    np.testing.assert_allclose(eye[:, 2], np.linspace(1.0, 2.0, 41))
    angle = np.unwrap(np.arctan2((eye[:, 1] + 0.2) / 2.0, (eye[:, 0] - 0.5) / 3.0))
    assert angle[-1] - angle[0] == pytest.approx(4 * np.pi)  # two full circles, counter-clockwise
    assert np.all(np.diff(angle) > 0)


def test_more_frames_are_finer_steps_of_the_same_helix():
    coarse = helical_path(11)
    fine = helical_path(101)
    np.testing.assert_allclose(coarse, fine[::10], atol=1e-12)


def test_bad_frame_count():
    with pytest.raises(ConfigError, match="frames"):
        helical_path(0)


@pytest.mark.parametrize("name", ["bunnies", "bunnies_dynamic", "table"])
def test_every_object_fully_in_view_from_some_pose(scenes_dir, name):
    config = load_run_config(scenes_dir / f"{name}.toml")
    scene = SourceScene(config.scene, frames=config.run.frames)
    poses = path_from_config(config.run.frames, config.path)
    intrinsics = config.sensor.intrinsics()
    for obj in scene.objects:
        if obj.name == "floor":
            continue
        seen = [i for i, pose in enumerate(poses) if obj.exists_at(i) and in_view(obj.points, intrinsics, pose).all()]
        assert seen, f"{name}: {obj.name} is never fully in view"


# ---------------------------------------------------------------------------
# The helix, pinned: the poses of the default path, frame 0 and half way


def test_helix_default_poses_are_the_look_at_poses():
    poses = path_from_config(5, PathConfig())
    start = math.radians(-90.0)
    np.testing.assert_array_equal(poses[0], look_at([2.5 * math.cos(start), 2.5 * math.sin(start), 1.2], [0.0, 0.0, 0.5]))
    half = start + 2.0 * math.pi * 2.0 * 0.5
    np.testing.assert_array_equal(poses[2], look_at([2.5 * math.cos(half), 2.5 * math.sin(half), 1.5], [0.0, 0.0, 0.65]))
    np.testing.assert_array_equal(helical_path(5), poses)


def test_helix_for_a_lidar_looks_along_the_camera_axis():
    camera = path_from_config(7, PathConfig())
    lidar = path_from_config(7, PathConfig(), axes="lidar")
    for c, s in zip(camera, lidar, strict=True):
        check_pose(s)
        np.testing.assert_allclose(s[:3, 0], c[:3, 2])  # LiDAR forward = camera optical axis
        np.testing.assert_allclose(s[:3, 2], -c[:3, 1])  # LiDAR up = image up
        np.testing.assert_allclose(s[:3, 3], c[:3, 3])
    np.testing.assert_allclose(CAMERA_FROM_LIDAR[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------
# Waypoints


def _waypoints(points, speed=1.0, rate=2.0, **keys) -> PathConfig:
    return PathConfig(kind="waypoints", points=points, speed=speed, rate=rate, **keys)


def test_waypoints_are_driven_at_the_speed_and_rate():
    path = _waypoints([[0, 0, 1], [4, 0, 1], [4, 3, 1]], speed=1.0, rate=2.0)  # 7 m at 0.5 m per frame
    assert path_frame_count(path) == 15
    poses = path_from_config(15, path)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.5, atol=1e-12)  # no corner inside a step here
    np.testing.assert_allclose(poses[0, :3, 3], [0, 0, 1])
    np.testing.assert_allclose(poses[8, :3, 3], [4, 0, 1])
    np.testing.assert_allclose(poses[-1, :3, 3], [4, 3, 1])
    np.testing.assert_allclose(poses[3, :3, 3], [1.5, 0, 1])
    np.testing.assert_allclose(poses[11, :3, 3], [4, 1.5, 1])


def test_waypoint_frame_count_follows_length_speed_and_rate():
    path = _waypoints([[0, 0, 0], [3.3, 0, 0]], speed=2.0, rate=10.0)  # 0.2 m per frame: 16.5 steps
    assert path_frame_count(path) == 17
    poses = path_from_config(17, path)
    np.testing.assert_allclose(poses[-1, 0, 3], 3.2)  # the last whole step before the end
    corner = _waypoints([[0, 0, 0], [1, 0, 0], [1, 1, 0]], speed=0.3, rate=1.0)  # a step across the corner
    positions = path_from_config(path_frame_count(corner), corner)[:, :3, 3]
    np.testing.assert_allclose(positions[4], [1.0, 0.2, 0.0], atol=1e-12)  # 1.2 m along the polyline


def test_headings_follow_the_direction_of_travel():
    path = _waypoints([[0, 0, 1], [2, 0, 1], [2, 2, 1], [0, 0, 1]], speed=1.0, rate=1.0)
    lidar = path_from_config(path_frame_count(path), path, axes="lidar")
    heading = np.degrees(np.arctan2(lidar[:, 1, 0], lidar[:, 0, 0]))
    np.testing.assert_allclose(heading[:2], 0.0, atol=1e-12)  # along +x
    np.testing.assert_allclose(heading[2:4], 90.0)  # from the corner at (2, 0) on: +y
    np.testing.assert_allclose(heading[4:], -135.0)  # back to the start
    for pose in lidar:
        check_pose(pose)
        np.testing.assert_allclose(pose[:3, 2], [0, 0, 1], atol=1e-12)  # LiDAR z = world up


def test_camera_looks_along_the_heading_with_image_up_world_up():
    poses = heading_poses([[1, 2, 3], [0, 0, 0]], np.radians([0.0, 90.0]))
    np.testing.assert_allclose(poses[0, :3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(poses[1, :3, 2], [0, 1, 0], atol=1e-12)  # z (optical axis) along +y
    np.testing.assert_allclose(poses[1, :3, 1], [0, 0, -1], atol=1e-12)  # image down = world down
    np.testing.assert_allclose(poses[0, :3, 3], [1, 2, 3])
    lidar = heading_poses([[1, 2, 3]], [0.3], axes="lidar")[0]
    camera = heading_poses([[1, 2, 3]], [0.3])[0]
    np.testing.assert_allclose(camera @ CAMERA_FROM_LIDAR, lidar, atol=1e-12)


def test_given_headings_turn_the_shorter_way():
    path = _waypoints([[0, 0, 0, 170.0], [4, 0, 0, -170.0], [8, 0, 0, 80.0]], speed=1.0, rate=1.0)
    lidar = path_from_config(path_frame_count(path), path, axes="lidar")
    heading = np.degrees(np.arctan2(lidar[:, 1, 0], lidar[:, 0, 0]))
    np.testing.assert_allclose(heading[:5], [170, 175, 180, -175, -170], atol=1e-9)  # through 180, not 0
    np.testing.assert_allclose(heading[5:], [162.5, 135.0, 107.5, 80.0], atol=1e-9)  # -170 -> 80: clockwise 110


def test_full_pose_waypoints_are_slerped_and_kept_as_given():
    q0 = Rotation.from_euler("z", 0.0).as_quat()
    q1 = Rotation.from_euler("zy", [90.0, 30.0], degrees=True).as_quat()
    path = _waypoints([[0, 0, 0, *q0], [2, 0, 0, *q1]], speed=1.0, rate=2.0)
    poses = path_from_config(path_frame_count(path), path, axes="lidar")
    assert len(poses) == 5
    np.testing.assert_allclose(poses[0, :3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(poses[-1, :3, :3], Rotation.from_quat(q1).as_matrix(), atol=1e-12)
    half = Rotation.from_matrix(poses[2, :3, :3])
    total = Rotation.from_quat(q1).magnitude()
    assert half.magnitude() == pytest.approx(total / 2)  # half way along: half the rotation
    np.testing.assert_allclose(poses[2, :3, 3], [1, 0, 0])
    np.testing.assert_allclose(path_from_config(5, path, axes="camera"), poses)  # full poses are not turned


# ---------------------------------------------------------------------------
# Trajectories and the config


def test_trajectory_poses_are_taken_as_they_are(tmp_path):
    poses = helical_path(6, radius_x=3.0)
    write_tum_trajectory(tmp_path / "poses.txt", np.arange(6) * 0.1, poses)
    (tmp_path / "run.toml").write_text('[path]\nkind = "trajectory"\nfile = "poses.txt"\n')
    config = load_run_config(tmp_path / "run.toml")
    assert config.run.frames == 6
    got = path_from_config(6, config.path, base_dir=tmp_path, axes="lidar")
    np.testing.assert_allclose(got, poses, atol=1e-12)
    np.testing.assert_allclose(path_from_config(4, config.path, base_dir=tmp_path), poses[:4], atol=1e-12)
    np.testing.assert_allclose(path_timestamps(4, config.path, base_dir=tmp_path), [0.0, 0.1, 0.2, 0.3])
    assert path_timestamps(4, PathConfig()) is None  # the helix: the sensor's own rate


def test_config_takes_the_frames_of_a_waypoint_path_unless_given():
    text = '[path]\nkind = "waypoints"\npoints = [[0, 0, 1], [10, 0, 1, ]]\nspeed = 2.0\nrate = 5.0\n'
    config = run_config_from_dict(tomllib.loads(text))
    assert config.run.frames == 26  # 10 m / 2 m/s * 5 frames/s + 1
    set_value(config, "path.speed", 5.0)
    assert config.run.frames == 11  # taken again from the changed path
    set_value(config, "run.frames", 4)
    set_value(config, "path.speed", 1.0)
    assert config.run.frames == 4  # given: kept
    given = run_config_from_dict(tomllib.loads("[run]\nframes = 7\n" + text))
    assert given.run.frames == 7
    np.testing.assert_allclose(path_from_config(7, given.path)[-1, :3, 3], [2.4, 0, 1])  # the first 7 frames
    again = run_config_from_dict(tomllib.loads(dump_toml(config)))
    assert again == config
    assert "radius_x" not in dump_toml(config) and "points" not in dump_toml(PathConfig())


def test_more_frames_than_the_path_has_is_an_error():
    path = _waypoints([[0, 0, 0], [1, 0, 0]], speed=1.0, rate=2.0)
    with pytest.raises(ConfigError, match=r"run.frames = 4 .*gives 3 frames \(1 m at 1 m/s and 2 frames/s\)"):
        path_from_config(4, path)


@pytest.mark.parametrize(
    ("path", "message"),
    [
        ('kind = "spiral"', r"'path.kind' = 'spiral' is not one of: helix, waypoints, trajectory"),
        ('kind = "waypoints"\npoints = [[0, 0, 0]]', r"'path.points' needs at least two waypoints"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0]]', r"'path.points\[1\]' has 2 numbers"),
        ('kind = "waypoints"\npoints = [[0, 0, 0, 9], [1, 0, 0]]', r"'path.points\[1\]' has 3 numbers.*all of one form"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0, 0], [1, 0, 0]]', r"'path.points\[1\]' and 'path.points\[2\]' are at the same position"),
        ('kind = "waypoints"\npoints = [[0, 0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0, 1]]', r"'path.points\[0\]' has a zero quaternion"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0, 0]]\nspeed = 0.0', r"'path.speed' must be positive"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0, 0]]\nrate = -1.0', r"'path.rate' must be positive"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0, 0]]\nradius_x = 3.0', r"'path.radius_x' belongs to kind = \"helix\""),
        ('speed = 2.0', r"'path.speed' belongs to kind = \"waypoints\", but this path is kind = \"helix\""),
        ('kind = "trajectory"', r"'path.file' is required"),
        ('kind = "trajectory"\nfile = "missing.txt"', r"'path.file' = 'missing.txt': trajectory file .*missing.txt not found"),
        ('kind = "waypoints"\npoints = [[0, 0, 0], [1, 0, "a"]]', r"'path.points\[1\]\[2\]' must be a number"),
    ],
)
def test_bad_paths_name_the_key(tmp_path, path, message):
    (tmp_path / "run.toml").write_text("[path]\n" + path + "\n")
    with pytest.raises(ConfigError, match=message):
        load_run_config(tmp_path / "run.toml")


def test_bad_trajectory_names_the_file_and_line(tmp_path):
    (tmp_path / "poses.txt").write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0\n")
    (tmp_path / "run.toml").write_text('[path]\nkind = "trajectory"\nfile = "poses.txt"\n')
    with pytest.raises(ConfigError, match=r"path.file.*poses.txt:2: expected 8 fields"):
        load_run_config(tmp_path / "run.toml")


def test_the_simulated_camera_drives_the_waypoints(tmp_path):
    """A wall at x = 5 m seen from a camera driving along +x: the centre pixel reads 5 m minus the distance driven."""
    from mabdi.simulate.rig import SimulatedRig

    (tmp_path / "run.toml").write_text(
        '[sensor.camera]\nwidth = 40\nheight = 30\nfx = 30.0\nfy = 30.0\ncx = 20.0\ncy = 15.0\nfar = 10.0\n'
        '[path]\nkind = "waypoints"\npoints = [[0, 0, 1], [2, 0, 1]]\nspeed = 1.0\nrate = 2.0\n'
        '[[scene.objects]]\nname = "wall"\ntype = "box"\nsize = [0.2, 10.0, 4.0]\nposition = [5.1, 0.0, -1.0]\n'
    )
    config = load_run_config(tmp_path / "run.toml")
    assert config.run.frames == 5
    rig = SimulatedRig.from_config(config)
    try:
        np.testing.assert_allclose(rig.poses, path_from_config(5, config.path))
        np.testing.assert_allclose(rig.timestamps, [0.0, 0.5, 1.0, 1.5, 2.0])  # a frame every 1 / rate seconds
        assert rig.read(3).timestamp == pytest.approx(1.5)
        for i in (0, 2, 4):
            depth = rig.read(i).depth
            assert depth[14:16, 19:21] == pytest.approx(5.0 - 0.5 * i, abs=1e-3)
    finally:
        rig.close()
