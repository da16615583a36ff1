"""A spinning LiDAR that moves during its sweep (``[sensor] sweep = "deskewed"``, :mod:`mabdi.simulate.lidar_sweep`)
and a tilted mount: the deskewed points lie on the scene while their elevations are continuous, a sensor standing
still gives the ideal renderer's range image, a tilted sensor's floor is level in the world, and the config keys."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import SCENES
from mabdi.config import ObjectConfig, SceneConfig, dump_toml, load_run_config, run_config_from_dict, with_overrides
from mabdi.errors import ConfigError
from mabdi.evaluate import distances_to_mesh
from mabdi.polydata import triangles_polydata
from mabdi.simulate import SimulatedRig
from mabdi.simulate.lidar_sweep import SweepSettings, column_times, mount_rotation, poses_at
from mabdi.simulate.routes import heading_poses
from mabdi.sources.range_images import range_image_points
from mabdi.sources.scene import SourceScene
from mabdi.spherical import SphericalGeometry
from test_evaluate import open3d_or_skip

#: A small LiDAR for the tests: 32 beams from +15 to -25 degrees, 512 columns.
GEOMETRY = SphericalGeometry(32, 512, 15.0, -25.0, 0.5, 50.0)
SIGMA = 0.005


def scene() -> SourceScene:
    """A floor, a box beside the path and four walls about it (the path runs along +x at 1.5 m)."""
    objects = [
        ObjectConfig(type="plane", name="floor", size=[60.0, 60.0], position=[5.0, 0.0, 0.0]),
        ObjectConfig(type="box", name="box", size=[2.0, 2.0, 2.0], position=[6.0, 3.0, 0.0]),
        ObjectConfig(type="box", name="wall", size=[0.4, 30.0, 5.0], position=[15.0, 0.0, 0.0]),
        ObjectConfig(type="box", name="back", size=[0.4, 30.0, 5.0], position=[-10.0, 0.0, 0.0]),
        ObjectConfig(type="box", name="left", size=[25.0, 0.4, 5.0], position=[2.5, 12.0, 0.0]),
        ObjectConfig(type="box", name="right", size=[25.0, 0.4, 5.0], position=[2.5, -12.0, 0.0]),
    ]
    return SourceScene(SceneConfig(objects), frames=4)


def truth(source: SourceScene):
    points = np.concatenate([o.points for o in source.objects])
    offsets = np.cumsum([0] + [len(o.points) for o in source.objects[:-1]])
    triangles = np.concatenate([o.triangles + k for o, k in zip(source.objects, offsets, strict=True)])
    return triangles_polydata(points, triangles)


def driving(frames: int = 4, speed: float = 5.0, turn: float = 30.0, rate: float = 10.0):
    """(poses, times): a LiDAR at 1.5 m driving along +x at ``speed`` m/s while turning ``turn`` degrees/s."""
    times = np.arange(frames) / rate
    positions = np.stack([speed * times, 0.2 * speed * times, np.full(frames, 1.5)], axis=1)
    return heading_poses(positions, np.radians(turn) * times, "lidar"), times


def rig(poses, times, sweep: str = "deskewed", noise: str = "range", geometry=GEOMETRY, **mount) -> SimulatedRig:
    from mabdi.sensor_noise import SensorNoise

    return SimulatedRig(
        scene(), poses, intrinsics=geometry, noise=SensorNoise(noise, range_sigma=SIGMA), seed=5, timestamps=times,
        sweep=SweepSettings(sweep, **mount),
    )


def on_floor(world) -> np.ndarray:
    """(N,) the world points low down and away from the walls and the box: the floor's."""
    x, y, z = world.T
    box = (np.abs(x - 6.0) < 1.2) & (np.abs(y - 3.0) < 1.2)
    return (z < 0.3) & (x > -9.5) & (x < 14.5) & (np.abs(y) < 11.5) & ~box


def beam_offsets(points, geometry: SphericalGeometry) -> np.ndarray:
    """(N,) degrees from each sensor-frame point's elevation to the nearest beam's."""
    elevation = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    beams = np.degrees(geometry.elevations())
    return np.abs(elevation[:, None] - beams[None, :]).min(axis=1)


def test_a_moving_sweep_deskewed_lies_on_the_scene_with_continuous_elevations():
    """Moving at 5 m/s and turning at 30 degrees/s (half a metre and 3 degrees a sweep), every deskewed point lies
    on the scene's surfaces once the sweep's end pose is applied (exactly without noise, within the range noise
    with it), while its elevation is no longer its beam's; standing still, every point is on its beam."""
    open3d_or_skip()
    poses, times = driving()
    mesh = truth(scene())
    exact = rig(poses, times, noise="none").read_sweep(2)
    assert len(exact.points) > 0.8 * GEOMETRY.beams * GEOMETRY.columns
    distance = distances_to_mesh(exact.world_points(), mesh)
    assert distance.max() < 1e-6, distance.max()

    noisy = rig(poses, times).read_sweep(2)
    distance = distances_to_mesh(noisy.world_points(), mesh)
    assert np.median(distance) < SIGMA and np.percentile(distance, 99) < 3 * SIGMA, np.percentile(distance, [50, 99])
    assert distance.max() < 6 * SIGMA + 0.001, distance.max()

    spacing = (GEOMETRY.fov_up - GEOMETRY.fov_down) / GEOMETRY.beams
    offset = beam_offsets(exact.points, GEOMETRY)
    assert (offset > 0.1 * spacing).mean() > 0.3, np.percentile(offset, [25, 50, 75])  # continuous, not on the beams
    still = rig(poses[[2, 2, 2, 2]], times, noise="none").read_sweep(2)
    assert beam_offsets(still.points, GEOMETRY).max() < 1e-6

    # The frame: its pose is the sweep's end (the path's pose at its timestamp), its image the points binned.
    moving = rig(poses, times, noise="none")
    frame = moving.read(2)
    np.testing.assert_array_equal(frame.world_from_camera, poses[2])
    assert frame.timestamp == times[2] and frame.intrinsics == GEOMETRY
    assert np.isfinite(frame.depth).mean() > 0.6


def test_each_column_is_measured_at_its_time_and_deskewed_into_the_sweep_end():
    """The sweep ends at the frame's time, column 0 (looking backwards) first: a sensor driving at a wall sees the
    forward column half a sweep before the end, from half a sweep's travel further back, so its deskewed points
    on the wall sit at the elevations its beams had from there."""
    open3d_or_skip()
    speed, rate = 10.0, 10.0
    times = np.arange(3) / rate
    positions = np.stack([speed * times, np.zeros(3), np.full(3, 1.5)], axis=1)
    poses = heading_poses(positions, np.zeros(3), "lidar")
    sensor = rig(poses, times, noise="none")
    sweep = sensor.read_sweep(2)
    duration = 1.0 / rate
    assert sensor.sweep_time() == pytest.approx(duration)
    expected = column_times(GEOMETRY, times[2], duration)
    assert expected[0] == pytest.approx(times[2] - duration + 0.5 * duration / GEOMETRY.columns)
    np.testing.assert_allclose(sweep.times, expected[sweep.columns])
    # the forward column (azimuth 0 lies between the two middle columns), measured when the sensor was
    # speed * (duration / 2) further from the wall (x = 14.8 m, the sensor at x = 2 m at the end)
    forward = (sweep.columns == GEOMETRY.columns // 2) & (sweep.points[:, 2] > -1.0)  # the wall, not the floor
    assert forward.sum() > 5
    points = sweep.points[forward]
    behind = speed * (times[2] - sweep.times[forward])
    np.testing.assert_allclose(points[:, 0], 14.8 - positions[2, 0], atol=1e-6)  # on the wall, in the end frame
    beam = GEOMETRY.elevations()[sweep.beams[forward]]
    azimuth = GEOMETRY.azimuths()[GEOMETRY.columns // 2]
    # measured from `behind` metres back along x: the wall lay that much further along the beam
    reach = (points[:, 0] + behind) / (np.cos(beam) * math.cos(azimuth))
    np.testing.assert_allclose(points[:, 2], reach * np.sin(beam), atol=1e-6)


def test_b_standing_still_the_deskewed_scan_is_the_instant_range_image():
    """With the sensor standing still and no tilt, the deskewed scan's range image is the ideal renderer's at
    the pixels both have (the same noise stream: equal within float32), and they have nearly the same pixels."""
    open3d_or_skip()
    poses = np.repeat(driving()[0][1:2], 3, axis=0)
    times = np.arange(3) / 10.0
    for noise in ("none", "range"):
        deskewed = rig(poses, times, noise=noise).read(1).depth
        instant = rig(poses, times, sweep="instant", noise=noise).read(1).depth
        both = np.isfinite(deskewed) & np.isfinite(instant)
        either = np.isfinite(deskewed) | np.isfinite(instant)
        assert both.sum() >= 0.999 * either.sum(), (both.sum(), either.sum())
        difference = np.abs(deskewed[both] - instant[both])
        assert (difference < 1e-4).mean() >= 0.999, np.sort(difference)[-10:]


@pytest.mark.parametrize("sweep", ["instant", "deskewed"])
def test_c_a_tilted_mount_sees_the_floor_level_in_the_world(sweep):
    """A sensor on a mount tipped 15 degrees forward and rolled 5 degrees, 1.5 m above the floor: in its own frame
    the floor is tilted (its beams are the sensor's), and the frame's pose (the path's times the mount) puts the
    floor back at z = 0 in the world."""
    if sweep == "deskewed":
        open3d_or_skip()
    poses, times = driving(speed=2.0, turn=0.0)
    geometry = SphericalGeometry(32, 512, 20.0, -45.0, 0.5, 12.0)  # the floor and the near walls' feet
    sensor = rig(poses, times, sweep=sweep, noise="none", geometry=geometry, mount_tilt=15.0, mount_roll=5.0)
    mount = mount_rotation(15.0, 5.0)
    np.testing.assert_allclose(sensor.true_poses, poses @ mount)
    forward = sensor.true_poses[1][:3, 0]
    assert forward[2] == pytest.approx(-math.sin(math.radians(15.0)))  # x tips down
    assert sensor.true_poses[1][:3, 1][2] > 0  # the left side is lifted
    frame = sensor.read(1)
    np.testing.assert_allclose(frame.world_from_camera, poses[1] @ mount)
    points, _, _ = range_image_points(frame.depth, geometry)
    world = points @ frame.world_from_camera[:3, :3].T + frame.world_from_camera[:3, 3]
    floor = on_floor(world)
    assert floor.sum() > 1000
    level = np.abs(world[floor, 2])
    if sweep == "instant":  # every return on its pixel's centre ray: exact
        assert level.max() < 1e-4, level.max()
    else:  # a deskewed point binned into a pixel is up to half a row and half a column (in angle) off its centre
        half = math.radians(0.5 * (geometry.fov_up - geometry.fov_down) / geometry.beams + 0.5 * 360.0 / geometry.columns)
        reach = np.linalg.norm(points[floor], axis=1) * half
        assert (level <= reach + 1e-3).all(), np.max(level - reach)
        assert np.median(level) < 0.5 * np.median(reach), (np.median(level), np.median(reach))
    sensor_z = points[floor, 2]
    assert np.ptp(sensor_z) > 0.5  # in the sensor's own frame the floor is not level
    if sweep == "deskewed":
        sweep_points = sensor.read_sweep(1).world_points()
        assert np.abs(sweep_points[on_floor(sweep_points), 2]).max() < 1e-6


def test_poses_between_frames_and_beyond_them():
    poses, times = driving(turn=90.0)
    np.testing.assert_allclose(poses_at(times, times, poses), poses, atol=1e-12)
    middle = poses_at([0.05], times, poses)[0]
    np.testing.assert_allclose(middle[:3, 3], 0.5 * (poses[0, :3, 3] + poses[1, :3, 3]))
    heading = math.degrees(math.atan2(middle[1, 0], middle[0, 0]))
    assert heading == pytest.approx(0.5 * 90.0 * 0.1)
    before = poses_at([-0.1], times, poses)[0]  # the first step's motion goes on backwards
    np.testing.assert_allclose(before[:3, 3], 2 * poses[0, :3, 3] - poses[1, :3, 3])
    np.testing.assert_allclose(poses_at([0.7], times[:1], poses[:1]), poses[:1])


def test_the_sweep_keys_of_a_run_config():
    base = load_run_config(SCENES / "street.toml")
    assert base.sensor.lidar.sweep == "instant" and base.sensor.lidar.sweep_time == 0.0
    text = dump_toml(base)
    assert '[sensor.lidar]\nbeams = 64' in text and '\nsweep = "instant"\n' in text  # a LiDAR's table is written whole
    assert "[sensor.camera]" not in text  # the camera's only where set
    changed = with_overrides(base, {"sensor.lidar.sweep": "deskewed", "sensor.lidar.mount_tilt": 10.0, "sensor.lidar.sweep_time": 0.1})
    assert changed.sensor.sweep_settings() == SweepSettings("deskewed", 0.1, 10.0, 0.0)
    again = run_config_from_dict(__import__("tomllib").loads(dump_toml(changed)))
    assert again.sensor == changed.sensor
    with pytest.raises(ConfigError, match="sensor.lidar.sweep"):
        with_overrides(base, {"sensor.lidar.sweep": "rolling"})
    with pytest.raises(ConfigError, match="mount_tilt"):
        with_overrides(base, {"sensor.lidar.mount_tilt": 120.0})
    with pytest.raises(ConfigError, match="sweep_time"):
        with_overrides(base, {"sensor.lidar.sweep_time": -1.0})
    camera = load_run_config(SCENES / "table.toml")
    with pytest.raises(ConfigError, match="'sensor.lidar.sweep' is a LiDAR's"):
        with_overrides(camera, {"sensor.lidar.sweep": "deskewed"})
    with pytest.raises(ConfigError, match="'sensor.lidar.mount_roll' is a LiDAR's"):
        with_overrides(camera, {"sensor.mount_roll": 3.0})  # the old flat name sets the new key


def test_the_deskewed_street_scene_reads_a_frame():
    """``scenes/street_deskewed.toml``: the street's objects and path, a 128-beam +-45 degree sensor tipped
    12 degrees forward, deskewed sweeps; a frame a reader of its scans would get."""
    open3d_or_skip()
    config = load_run_config(SCENES / "street_deskewed.toml")
    street = load_run_config(SCENES / "street.toml")
    assert config.scene == street.scene and config.path == street.path and config.run.frames == street.run.frames
    lidar = config.sensor.lidar
    assert (lidar.beams, lidar.fov_up, lidar.fov_down) == (128, 45.0, -45.0)
    assert lidar.sweep == "deskewed" and lidar.mount_tilt == 12.0
    street_rig = SimulatedRig.from_config(config)
    try:
        assert street_rig.sweep_time() == pytest.approx(1.0 / config.path.rate)
        frame = street_rig.read(10)
        assert frame.intrinsics == config.sensor.geometry()
        assert 0.4 < np.isfinite(frame.depth).mean() < 0.9
        sweep = street_rig.read_sweep(10)
        spacing = 90.0 / 128
        assert (beam_offsets(sweep.points, frame.intrinsics) > 0.1 * spacing).mean() > 0.2
    finally:
        street_rig.close()
