"""The viewer frames the map: its projected bounds fill the picture, a run folder adds the path, --from-frame
looks from a frame's pose; the picture's title and scale bar."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from mabdi.cli import main
from mabdi.viz.viewer import FILL, scale_bar_length


def map_pixels(png) -> np.ndarray:
    """Mask of the pixels that show the map coloured by frame (viridis: saturated), not the white background,
    the grey scene, the black path, title and scale bar."""
    picture = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
    return (picture.max(axis=2) - picture.min(axis=2)) > 40


def dark_pixels(png) -> int:
    picture = np.asarray(Image.open(png).convert("RGB"))
    return int((picture.max(axis=2) < 60).sum())


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory, scenes_dir):
    out = tmp_path_factory.mktemp("view") / "table"
    assert main(["run", str(scenes_dir / "table.toml"), "--frames", "4", "--out", str(out), "--quiet", "--no-eval"]) == 0
    return out


def test_the_map_fills_the_picture(run_folder, tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    png = tmp_path / "x.png"
    assert main(["view", str(run_folder), "--out", str(png)]) == 0
    mask = map_pixels(png)
    height, width = mask.shape
    rows, columns = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    fill = max((columns[-1] - columns[0] + 1) / width, (rows[-1] - rows[0] + 1) / height)
    # the box's corners fill FILL of the binding side; the map inside its box reaches at least half of it
    assert fill >= 0.5, fill
    centre = np.array([(columns[0] + columns[-1]) / 2 / width, (rows[0] + rows[-1]) / 2 / height])
    np.testing.assert_allclose(centre, [0.5, 0.5], atol=0.15)  # centred, not off to a side


def test_a_run_folder_shows_the_path_and_the_map_file_alone_does_not(run_folder, tmp_path):
    folder_png, map_png = tmp_path / "folder.png", tmp_path / "map.png"
    assert main(["view", str(run_folder), "--out", str(folder_png)]) == 0
    assert main(["view", str(run_folder / "world_mesh.vtp"), "--out", str(map_png)]) == 0
    # the same framing (the map's bounds) for both: only the path (black) and the scene (grey) differ
    assert np.mean(map_pixels(folder_png) == map_pixels(map_png)) > 0.9
    assert dark_pixels(folder_png) > dark_pixels(map_png) + 300


def test_from_frame_looks_from_the_sensor_and_checks_the_frame(run_folder, tmp_path, capsys):
    png = tmp_path / "frame.png"
    assert main(["view", str(run_folder), "--from-frame", "2", "--out", str(png)]) == 0
    picture = Image.open(png)
    assert picture.size == (1280, 960)  # the sensor's 4:3
    assert map_pixels(png).mean() > 0.3  # the sensor looked at the table: the map fills much of its view
    assert main(["view", str(run_folder), "--from-frame", "4", "--out", str(png)]) == 2
    assert "poses.npy holds frames 0 .. 3" in capsys.readouterr().err
    assert main(["view", str(run_folder / "world_mesh.vtp"), "--from-frame", "0", "--out", str(png)]) == 2
    assert "needs a run folder" in capsys.readouterr().err


def test_scale_bar_lengths_are_round():
    assert scale_bar_length(10.0) == 2.0
    assert scale_bar_length(25.0) == 5.0
    assert scale_bar_length(0.4) == pytest.approx(0.1)
    assert 0.5 < FILL < 1.0


# -- which way is up ------------------------------------------------------------------------------------------------

#: y-down world from z-up world (x' = x, y' = -z, z' = y): a z-up scene as 7-Scenes and 3DMatch store one.
Y_DOWN = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def kitchen(world_from_z_up=np.eye(4)):
    """(vertices, faces, poses) of a floor 4 x 3 m and a counter 1 m high with cameras at 1.5 m walking along it,
    looking 20 degrees down and turning from +x to -x through +y (their mean up 13 degrees off z, towards +y),
    built z up and moved into a world by ``world_from_z_up`` (4 x 4)."""
    from mabdi.camera import look_at

    floor = [[-2, -1.5, 0], [2, -1.5, 0], [2, 1.5, 0], [-2, 1.5, 0]]
    counter = [[-1, 1, 0], [1, 1, 0], [1, 1, 1], [-1, 1, 1], [-1, 0.4, 1], [1, 0.4, 1]]
    vertices = np.array(floor + counter, dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [7, 6, 9], [7, 9, 8]])
    down = np.tan(np.radians(20))
    poses = np.array(
        [
            look_at([x, -0.5, 1.5], [x + np.cos(heading), -0.5 + np.sin(heading), 1.5 - down])
            for x, heading in zip(np.linspace(-1.5, 1.5, 12), np.linspace(0, np.pi, 12))
        ]
    )
    vertices = vertices @ world_from_z_up[:3, :3].T + world_from_z_up[:3, 3]
    return vertices, faces, world_from_z_up @ poses


def write_run(folder, vertices, faces, poses):
    """A run folder by hand: ``world_mesh.vtp`` (face layer ``frame``) and ``poses.npy``."""
    from mabdi.io.mesh_map_files import save_map
    from mabdi.mesh_maps.mesh_map import MeshMap

    folder.mkdir(parents=True)
    frames = np.arange(len(faces), dtype=np.int32)
    save_map(MeshMap(vertices, faces, face_layers={"frame": frames}), folder / "world_mesh.vtp")
    np.save(folder / "poses.npy", np.asarray(poses))
    return folder


def rotation_about_x(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])


def assert_camera_up(up, expected):
    """The default framing with ``up`` looks down on the map at VIEW_ELEVATION degrees, screen-up along ``expected``."""
    from vtkmodules.vtkRenderingCore import vtkCamera

    from mabdi.viz.viewer import VIEW_ELEVATION, fit_parallel_camera

    camera = vtkCamera()
    fit_parallel_camera(camera, (-1, 1, -1, 1, -1, 1), 1.6, up=up)
    expected = np.asarray(expected, dtype=np.float64) / np.linalg.norm(expected)
    elevation = np.radians(VIEW_ELEVATION)
    assert np.dot(camera.GetViewUp(), expected) == pytest.approx(np.cos(elevation), abs=1e-6)
    assert np.dot(camera.GetDirectionOfProjection(), expected) == pytest.approx(-np.sin(elevation), abs=1e-6)


def test_a_y_down_run_is_seen_with_the_cameras_up(tmp_path, capsys, monkeypatch):
    from mabdi.viz.viewer import view_up

    folder = write_run(tmp_path / "kitchen", *kitchen(Y_DOWN))
    up, line = view_up(folder)
    np.testing.assert_array_equal(up, [0.0, -1.0, 0.0])  # the cameras' mean up is 13 degrees off -y: snapped
    assert line.startswith("up: -y") and "cameras' mean up" in line
    assert_camera_up(up, [0.0, -1.0, 0.0])
    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["view", str(folder), "--out", str(tmp_path / "y_down.png")]) == 0
    assert "up: -y" in capsys.readouterr().out
    z_up = write_run(tmp_path / "z_up", *kitchen())
    assert main(["view", str(z_up), "--out", str(tmp_path / "z_up.png")]) == 0
    assert "up: +z" in capsys.readouterr().out
    # the same kitchen in the two worlds, seen the same way (not the y-down floor stood up as a wall);
    # only the title (the box's x y z size) differs
    y_down_png, z_up_png = (np.asarray(Image.open(tmp_path / f"{n}.png").convert("RGB")) for n in ("y_down", "z_up"))
    differs = np.abs(y_down_png.astype(np.int16) - z_up_png).max(axis=2) > 30
    assert differs[40:].mean() < 0.01, differs[40:].mean()


def test_a_tilted_world_is_seen_with_the_cameras_mean_up(tmp_path):
    from mabdi.viz.viewer import view_up

    world = rotation_about_x(-45) @ Y_DOWN  # the first camera's frame of a camera held 45 degrees down
    folder = write_run(tmp_path / "tilted", *kitchen(world))
    up, line = view_up(folder)
    true_up = world[:3, :3] @ [0.0, 0.0, 1.0]
    assert np.degrees(np.arccos(np.clip(up @ true_up, -1, 1))) < 15  # the cameras' 20 degree pitch, partly undone
    assert "the cameras' mean up" in line and line.startswith("up: (")
    assert_camera_up(up, up)


def test_a_simulated_z_up_run_keeps_z(tmp_path):
    from mabdi.simulate import helical_path
    from mabdi.viz.viewer import view_up

    poses = helical_path(4)  # four frames of the helix: its cameras' mean up tilts some degrees off z
    tilt = -poses[:, :3, 1].mean(axis=0)
    assert 2 < np.degrees(np.arccos(tilt[2] / np.linalg.norm(tilt))) < 20
    vertices, faces, _ = kitchen()
    up, line = view_up(write_run(tmp_path / "helix", vertices, faces, poses))
    np.testing.assert_array_equal(up, [0.0, 0.0, 1.0])
    assert line.startswith("up: +z")
    assert_camera_up(up, [0.0, 0.0, 1.0])


def test_a_lidar_run_takes_up_from_the_lidars_z(tmp_path):
    from mabdi.simulate.routes import CAMERA_FROM_LIDAR
    from mabdi.viz.viewer import view_up

    vertices, faces, poses = kitchen(Y_DOWN)
    folder = write_run(tmp_path / "lidar", vertices, faces, poses @ CAMERA_FROM_LIDAR)  # world_from_lidar
    (folder / "config.toml").write_text('[sensor]\nkind = "lidar"\n')
    up, line = view_up(folder)
    np.testing.assert_array_equal(up, [0.0, -1.0, 0.0])
    assert "LiDAR's mean up" in line


def test_up_falls_back_to_z_and_can_be_set(tmp_path, capsys, monkeypatch):
    from mabdi.camera import look_at
    from mabdi.viz.viewer import parse_up, view_up

    vertices, faces, _ = kitchen()
    # cameras rolled every way about their axis: their up vectors cancel
    rolls = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    rolled = [look_at([0, -3, 1], [0, 0, 1], up=(np.cos(a), 0.0, np.sin(a))) for a in rolls]
    up, line = view_up(write_run(tmp_path / "rolled", vertices, faces, rolled))
    np.testing.assert_array_equal(up, [0.0, 0.0, 1.0])
    assert "+z (the world's" in line
    folder = write_run(tmp_path / "kitchen", *kitchen(Y_DOWN))
    np.testing.assert_array_equal(view_up(folder, up="z")[0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(parse_up("0, -2, 0"), [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(parse_up("-x"), [-1.0, 0.0, 0.0])
    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["view", str(folder), "--up", "0,0,1", "--out", str(tmp_path / "z.png")]) == 0
    assert "up: +z, given" in capsys.readouterr().out
    assert main(["view", str(folder), "--up=-y", "--out", str(tmp_path / "y.png")]) == 0
    assert "up: -y, given" in capsys.readouterr().out
    assert main(["view", str(folder), "--up", "sideways", "--out", str(tmp_path / "z.png")]) == 2
    assert "--up" in capsys.readouterr().err


def test_a_map_file_takes_up_from_its_own_poses(tmp_path):
    from mabdi.io.mesh_map_files import save_map
    from mabdi.mesh_maps.mesh_map import MeshMap
    from mabdi.viz.viewer import view_up

    vertices, faces, poses = kitchen(Y_DOWN)
    mesh_map = MeshMap(vertices, faces, face_layers={"frame": np.zeros(len(faces), dtype=np.int32)})
    save_map(mesh_map, tmp_path / "alone.vtp")  # no poses: the world's z
    up, line = view_up(tmp_path / "alone.vtp")
    np.testing.assert_array_equal(up, [0.0, 0.0, 1.0])
    assert "no poses" in line
    mesh_map.poses = poses
    save_map(mesh_map, tmp_path / "posed.h5")  # an HDF5 map carries the run's poses
    np.testing.assert_array_equal(view_up(tmp_path / "posed.h5")[0], [0.0, -1.0, 0.0])
