"""SourceScene: placement, schedules, object ids, the bunny, errors."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from mabdi.config import ObjectConfig, SceneConfig, load_run_config
from mabdi.errors import AssetNotFoundError, ConfigError
from mabdi.sources.assets import bunny_path, read_mesh
from mabdi.sources.scene import SourceScene, axis_to_z_rotation, place, schedule_frame


def object_ids(scene: SourceScene) -> set[int]:
    scene.Update()
    return set(vtk_to_numpy(scene.GetOutput().GetCellData().GetArray("object_id")).tolist())


def test_schedule_by_frame_number_and_fraction():
    config = SceneConfig(
        objects=[
            ObjectConfig(type="box", size=[1, 1, 1]),
            ObjectConfig(type="sphere", radius=0.2, appear_at=3),
            ObjectConfig(type="box", size=[1, 1, 1], position=[2, 0, 0], disappear_at=0.5),
            ObjectConfig(type="box", size=[1, 1, 1], position=[4, 0, 0], appear_at=0.2, disappear_at=8),
        ]
    )
    scene = SourceScene(config, frames=10)
    expected = {
        0: {0, 2},
        2: {0, 2, 3},
        3: {0, 1, 2, 3},
        4: {0, 1, 2, 3},
        5: {0, 1, 3},
        7: {0, 1, 3},
        8: {0, 1},
        9: {0, 1},
    }
    for frame, ids in expected.items():
        scene.set_frame(frame)
        assert object_ids(scene) == ids, frame


def test_fractions_resolve_to_the_nearest_frame():
    assert schedule_frame(0.5, 50) == 25
    assert schedule_frame(0.5, 51) == 26
    assert schedule_frame(1.0, 30) == 30
    assert schedule_frame(7, 30) == 7
    assert schedule_frame(None, 30) is None


def test_set_frame_modifies_only_when_the_object_set_changes():
    config = SceneConfig(objects=[ObjectConfig(type="box", size=[1, 1, 1], appear_at=5)])
    scene = SourceScene(config, frames=10)
    scene.Update()
    before = scene.GetMTime()
    scene.set_frame(3)
    assert scene.GetMTime() == before
    scene.set_frame(5)
    assert scene.GetMTime() > before
    after = scene.GetMTime()
    scene.set_frame(9)
    assert scene.GetMTime() == after
    with pytest.raises(ValueError, match="frame"):
        scene.set_frame(-1)


def test_placement_anchor_yaw_and_up_axis():
    box = ObjectConfig(type="box", size=[2.0, 1.0, 0.5], position=[1.0, 2.0, 3.0], yaw=90.0)
    points = place(np.array([[-1, -0.5, -0.25], [1, 0.5, 0.25]]), box)
    np.testing.assert_allclose(points.min(0), [0.5, 1.0, 3.0], atol=1e-12)  # bottom centre at position
    np.testing.assert_allclose(points.max(0), [1.5, 3.0, 3.5], atol=1e-12)  # yaw 90: x extent -> y
    centre = ObjectConfig(type="box", size=[2.0, 1.0, 0.5], anchor="center", position=[0.0, 0.0, 1.0])
    placed = place(np.array([[-1, -0.5, -0.25], [1, 0.5, 0.25]]), centre)
    np.testing.assert_allclose(placed.mean(0), [0.0, 0.0, 1.0])
    for axis in ("x", "y", "-y", "-z", "+z"):
        r = axis_to_z_rotation(axis)
        a = np.zeros(3)
        a["xyz".index(axis[-1])] = -1.0 if axis.startswith("-") else 1.0
        np.testing.assert_allclose(r @ a, [0, 0, 1], atol=1e-12)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_full_rotation_matrix():
    rotation = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    obj = ObjectConfig(type="box", size=[2.0, 1.0, 1.0], rotation=rotation, anchor="origin")
    placed = place(np.array([[1.0, 0.0, 0.0]]), obj)
    np.testing.assert_allclose(placed, [[0.0, 1.0, 0.0]], atol=1e-12)


def test_bunnies_scene_has_three_bunnies_1_5_m_tall_1_5_m_apart(scenes_dir):
    scene = SourceScene.from_file(scenes_dir / "bunnies.toml")
    bunnies = [o for o in scene.objects if o.name.startswith("bunny")]
    assert len(bunnies) == 3
    for bunny in bunnies:
        assert bunny.points[:, 2].min() == pytest.approx(0.0, abs=1e-9)
        assert bunny.points[:, 2].max() == pytest.approx(1.5, abs=1e-9)
    centres = sorted(0.5 * (b.points[:, 0].min() + b.points[:, 0].max()) for b in bunnies)
    np.testing.assert_allclose(np.diff(centres), [1.5, 1.5], atol=1e-9)
    # y-up model turned z-up: the ears (the model's top) are the highest points
    model = read_mesh(bunny_path())
    model_points = vtk_to_numpy(model.GetPoints().GetData())
    top = np.argmax(model_points[:, 1])
    assert bunnies[0].points[top, 2] == pytest.approx(1.5, abs=1e-9)


def test_dynamic_bunny_appears_half_way(scenes_dir):
    scene = SourceScene.from_file(scenes_dir / "bunnies_dynamic.toml")
    middle = [i for i, o in enumerate(scene.objects) if o.name == "bunny_middle"][0]
    config = load_run_config(scenes_dir / "bunnies_dynamic.toml")
    half = config.run.frames // 2
    assert middle not in scene.active_objects(half - 1)
    assert middle in scene.active_objects(half)


def test_table_scene_dimensions(scenes_dir):
    scene = SourceScene.from_file(scenes_dir / "table.toml")
    by_name = {o.name: o for o in scene.objects}
    assert by_name["table_top"].points[:, 2].max() == pytest.approx(1.0)
    for cup in ("cup_1", "cup_2"):
        assert by_name[cup].points[:, 2].min() == pytest.approx(1.0)
    assert sum(name.startswith("leg") for name in by_name) == 4


def test_mesh_file_path_is_relative_to_the_config(tmp_path, scenes_dir):
    from vtkmodules.vtkFiltersSources import vtkSphereSource
    from vtkmodules.vtkIOPLY import vtkPLYWriter

    sphere = vtkSphereSource()
    writer = vtkPLYWriter()
    writer.SetInputConnection(sphere.GetOutputPort())
    writer.SetFileName(str(tmp_path / "ball.ply"))
    writer.Write()
    (tmp_path / "run.toml").write_text('[[scene.objects]]\ntype = "mesh"\nmesh = "ball.ply"\nheight = 2.0\n')
    scene = SourceScene.from_file(tmp_path / "run.toml")
    assert np.ptp(scene.objects[0].points[:, 2]) == pytest.approx(2.0)


def test_missing_mesh_file_names_the_path(tmp_path):
    (tmp_path / "run.toml").write_text('[[scene.objects]]\ntype = "mesh"\nmesh = "nowhere/rabbit.ply"\n')
    with pytest.raises(AssetNotFoundError, match="nowhere/rabbit.ply"):
        SourceScene.from_file(tmp_path / "run.toml")


def test_unknown_mesh_format_is_an_error(tmp_path):
    (tmp_path / "model.dae").write_text("<xml/>")
    with pytest.raises(ConfigError, match="unknown mesh format"):
        read_mesh(tmp_path / "model.dae")


def test_output_has_object_id_per_triangle(scenes_dir):
    scene = SourceScene.from_file(scenes_dir / "table.toml")
    scene.Update()
    mesh = scene.GetOutput()
    ids = vtk_to_numpy(mesh.GetCellData().GetArray("object_id"))
    assert len(ids) == mesh.GetNumberOfCells() == sum(len(o.triangles) for o in scene.objects)
    assert set(ids.tolist()) == set(range(len(scene.objects)))
