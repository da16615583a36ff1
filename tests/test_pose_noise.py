"""Pose noise ([sensor.pose_noise]): the frames carry noisy given poses, the sensor renders from the true ones.

Statistical checks state their tolerance: with n independent samples a sample
standard deviation is off by about 1 / sqrt(2 n) (relative), so each bound is
several times that.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mabdi.camera import check_pose, look_at
from mabdi.config import RunConfig, SceneConfig, ObjectConfig, dump_toml, load_run_config, run_config_from_dict, set_value
from mabdi.errors import ConfigError
from mabdi.pose_noise import PoseNoise
from mabdi.simulate.path import path_from_config
from mabdi.simulate.rig import SimulatedRig
from mabdi.sources.scene import SourceScene


def random_poses(count: int, seed: int = 0) -> np.ndarray:
    """``count`` rigid poses with random orientations and positions."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.uniform(-3, 3, (count, 3))
    return poses


def straight_line(count: int, step: float) -> np.ndarray:
    """Poses along the x axis, ``step`` metres apart, looking along +x."""
    pose = look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0])
    poses = np.tile(pose, (count, 1, 1))
    poses[:, 0, 3] = step * np.arange(count)
    return poses


def errors(true_poses, given_poses):
    """Per-frame translation offset (m, world) and rotation vector (degrees, camera frame) of given vs true."""
    tau = given_poses[:, :3, 3] - true_poses[:, :3, 3]
    relative = np.transpose(true_poses[:, :3, :3], (0, 2, 1)) @ given_poses[:, :3, :3]
    omega = np.degrees(Rotation.from_matrix(relative).as_rotvec())
    return tau, omega


def test_zero_noise_gives_the_true_poses_exactly():
    poses = random_poses(50)
    given = PoseNoise().given_poses(poses, seed=3)
    assert np.array_equal(given, poses)
    assert not PoseNoise().enabled and PoseNoise(drift_rotation=0.1).enabled


def test_jitter_standard_deviation_matches_its_sigma():
    """20,000 frames: per-axis sample std within 3% of sigma (expected error ~0.5%)."""
    poses = random_poses(20_000)
    noise = PoseNoise(jitter_translation=0.004, jitter_rotation=0.3)
    tau, omega = errors(poses, noise.given_poses(poses, seed=1))
    np.testing.assert_allclose(tau.std(axis=0), 0.004, rtol=0.03)
    np.testing.assert_allclose(omega.std(axis=0), 0.3, rtol=0.03)
    np.testing.assert_allclose(tau.mean(axis=0), 0.0, atol=3 * 0.004 / np.sqrt(len(poses)))
    # the rotation angle's RMS is sqrt(3) sigma (three axes)
    angle = np.linalg.norm(omega, axis=1)
    assert np.sqrt(np.mean(angle**2)) == pytest.approx(np.sqrt(3) * 0.3, rel=0.03)
    # jitter alone: frames independent (no correlation between consecutive frames)
    assert abs(np.corrcoef(tau[:-1, 0], tau[1:, 0])[0, 1]) < 0.05


def test_drift_spread_grows_as_rate_times_sqrt_distance():
    """1,000 seeds x 3 axes on a straight 4 m path (0.1 m steps): the spread after L = 1, 2.5 and 4 m
    within 6% of rate sqrt(L) (expected error ~1.3%); frame 0 has no drift."""
    poses = straight_line(41, 0.1)
    noise = PoseNoise(drift_translation=0.01, drift_rotation=0.5)
    taus, omegas = [], []
    for seed in range(1000):
        tau, omega = errors(poses, noise.given_poses(poses, seed))
        taus.append(tau)
        omegas.append(omega)
    taus, omegas = np.array(taus), np.array(omegas)  # (seeds, frames, 3)
    assert np.abs(taus[:, 0]).max() == 0.0 and np.abs(omegas[:, 0]).max() < 1e-12
    for frame, length in ((10, 1.0), (25, 2.5), (40, 4.0)):
        assert taus[:, frame].std() == pytest.approx(0.01 * np.sqrt(length), rel=0.06), length
        assert omegas[:, frame].std() == pytest.approx(0.5 * np.sqrt(length), rel=0.06), length
    # a random walk: the step from 1 m to 4 m is independent of the first metre
    later = taus[:, 40] - taus[:, 10]
    assert abs(np.corrcoef(later.ravel(), taus[:, 10].ravel())[0, 1]) < 0.06


def test_drift_follows_distance_travelled_not_frames():
    """A path that stands still for 20 frames gets no drift there."""
    poses = np.concatenate([straight_line(11, 0.1), np.repeat(straight_line(11, 0.1)[-1:], 20, axis=0)])
    given = PoseNoise(drift_translation=0.01, drift_rotation=0.5).given_poses(poses, seed=4)
    np.testing.assert_array_equal(given[11:], np.repeat(given[10:11], 20, axis=0))


def test_same_seed_same_poses_other_seed_other_poses_any_length():
    poses = random_poses(30)
    noise = PoseNoise(0.002, 0.15, 0.01, 0.1)
    first = noise.given_poses(poses, seed=7)
    np.testing.assert_array_equal(first, noise.given_poses(poses, seed=7))
    assert not np.allclose(first, noise.given_poses(poses, seed=8))
    np.testing.assert_array_equal(first[:12], noise.given_poses(poses[:12], seed=7))  # frame i does not depend on N


def test_given_poses_are_rigid_even_with_large_noise():
    poses = random_poses(200)
    given = PoseNoise(0.5, 40.0, 0.2, 20.0).given_poses(poses, seed=2)
    for pose in given:
        check_pose(pose)


def test_negative_or_bad_values_are_errors_naming_the_key():
    with pytest.raises(ConfigError, match="jitter_rotation"):
        PoseNoise(jitter_rotation=-0.1)
    with pytest.raises(ConfigError, match="drift_translation"):
        PoseNoise(drift_translation=float("nan"))


def test_config_round_trip_set_value_and_unknown_key(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("[sensor.pose_noise]\njitter_translation = 0.002\ndrift_rotation = 1\n")
    config = load_run_config(path)
    assert config.sensor.pose_noise == PoseNoise(jitter_translation=0.002, drift_rotation=1.0)
    assert RunConfig().sensor.pose_noise == PoseNoise()  # default: exact poses
    text = dump_toml(config)
    assert "[sensor.pose_noise]" in text
    assert run_config_from_dict(tomllib.loads(text)) == config
    set_value(config, "sensor.pose_noise.jitter_rotation", 0.15)
    assert config.sensor.pose_noise.jitter_rotation == 0.15
    assert run_config_from_dict(tomllib.loads(dump_toml(config))) == config
    with pytest.raises(ConfigError, match="sensor.pose_noise.jitter_rotaton"):
        set_value(config, "sensor.pose_noise.jitter_rotaton", 0.15)
    with pytest.raises(ConfigError, match="sensor.pose_noise.drift_rotation"):
        set_value(config, "sensor.pose_noise.drift_rotation", -1.0)
    path.write_text("[sensor.pose_noise]\njitter = 0.002\n")
    with pytest.raises(ConfigError, match=r"run.toml: unknown key 'jitter' in \[sensor.pose_noise\]"):
        load_run_config(path)
    path.write_text("[sensor.pose_noise]\njitter_translation = -0.002\n")
    with pytest.raises(ConfigError, match=r"run.toml: \[sensor.pose_noise\] .*jitter_translation"):
        load_run_config(path)


SMALL = {"width": 64, "height": 48, "fx": 52.5, "fy": 52.5, "cx": 32.0, "cy": 24.0}


def floor_scene() -> SceneConfig:
    """A 20 m x 20 m horizontal plane at z = 0."""
    return SceneConfig(objects=[ObjectConfig(type="plane", size=[20.0, 20.0], position=[0.0, 0.0, 0.0])])


def test_the_rig_renders_from_the_true_pose_and_gives_the_noisy_one():
    """A camera 2 m above a floor, looking straight down, with 5 cm translation jitter: the depth is the
    true 2 m everywhere, while the frame's pose is the noisy one."""
    from mabdi.camera import Intrinsics

    true_pose = look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    true_poses = np.stack([true_pose, true_pose, true_pose])
    noise = PoseNoise(jitter_translation=0.05)
    rig = SimulatedRig(
        SourceScene(floor_scene(), frames=3), true_poses, intrinsics=Intrinsics(**SMALL), seed=1, pose_noise=noise
    )
    try:
        given = noise.given_poses(true_poses, seed=1)
        np.testing.assert_array_equal(rig.poses, given)
        np.testing.assert_array_equal(rig.true_poses, true_poses)
        for i in range(3):
            frame = rig.read(i)
            offset = given[i, :3, 3] - true_pose[:3, 3]
            assert abs(offset[2]) > 0.005  # rendered from the given pose, the depth would be off by this
            assert np.isfinite(frame.depth).all()
            np.testing.assert_allclose(frame.depth, 2.0, atol=1e-3)
            np.testing.assert_array_equal(frame.world_from_camera, given[i])
    finally:
        rig.close()


def test_rig_from_config_applies_the_pose_noise_with_the_run_seed():
    config = RunConfig()
    config.scene = floor_scene()
    config.run.frames = 4
    config.run.seed = 9
    set_value(config, "sensor.pose_noise.jitter_rotation", 0.2)
    rig = SimulatedRig.from_config(config)
    path = path_from_config(4, config.path)
    np.testing.assert_array_equal(rig.true_poses, path)
    np.testing.assert_array_equal(rig.poses, PoseNoise(jitter_rotation=0.2).given_poses(path, seed=9))
    assert not np.allclose(rig.poses, path)
    config.sensor.pose_noise = PoseNoise()
    np.testing.assert_array_equal(SimulatedRig.from_config(config).poses, path)


def small_table(frames: int = 2):
    from conftest import SCENES

    config = load_run_config(SCENES / "table.toml")
    set_value(config, "run.frames", frames)
    for key, value in SMALL.items():
        set_value(config, f"sensor.{key}", value)
    set_value(config, "sensor.pose_noise.jitter_translation", 0.01)
    set_value(config, "sensor.pose_noise.jitter_rotation", 0.2)
    return config


def test_a_run_writes_the_true_poses_beside_the_given_ones(tmp_path):
    from mabdi.evaluate.metrics import sensor_poses
    from mabdi.loop import MappingRun

    config = small_table()
    simulation = MappingRun(config)
    simulation.run(tmp_path / "run")
    given, true_poses = np.load(tmp_path / "run" / "poses_given.npy"), np.load(tmp_path / "run" / "poses_true.npy")
    np.testing.assert_array_equal(true_poses, path_from_config(2, config.path))
    np.testing.assert_array_equal(given, simulation.rig.poses)
    assert not np.allclose(given, true_poses)
    np.testing.assert_array_equal(sensor_poses(simulation), true_poses)  # what the evaluation judges visibility by


def test_a_recording_carries_the_given_poses_and_keeps_the_true_ones(tmp_path):
    from mabdi.loop.mapping_run import recorded_simulation
    from mabdi.simulate.recording import TRUE_POSES, record
    from mabdi.sources.tum import TumSequence

    config = small_table(3)
    out = record(config, tmp_path / "recording", "tum")
    rig = SimulatedRig.from_config(config)
    true_poses = np.load(out / TRUE_POSES)
    np.testing.assert_array_equal(true_poses, rig.true_poses)
    recorded = TumSequence(out)
    np.testing.assert_allclose(recorded.poses, rig.poses, atol=1e-9)  # the recording's poses are the noisy ones
    assert not np.allclose(recorded.poses, true_poses, atol=1e-4)
    simulation, note = recorded_simulation(config, out)
    assert note is None
    np.testing.assert_array_equal(simulation.true_poses, true_poses)
