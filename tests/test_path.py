"""helical_path: geometry, look-at, and coverage of the seed's scenes."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.camera import check_pose, in_view, project
from mabdi.config import load_run_config
from mabdi.errors import ConfigError
from mabdi.simulate.path import helical_path, path_from_config, path_targets
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
