"""Atomic writes, the `mabdi run` command and its outputs."""

from __future__ import annotations

import json

import tomllib

import numpy as np
import pytest
from vtkmodules.vtkIOXML import vtkXMLImageDataReader, vtkXMLPolyDataReader

from mabdi.cli import main
from mabdi.config import load_run_config, run_config_from_dict
from mabdi.depth import DepthFrame
from mabdi.stages.registration import given_pose, image_world_from_map
from mabdi.sources.tum import read_groundtruth
from mabdi.io.atomic import atomic_output, write_text


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "map.txt"
    target.write_text("good map")
    with pytest.raises(RuntimeError):
        with atomic_output(target) as temporary:
            temporary.write_text("half a m")
            raise RuntimeError("disk full")
    assert target.read_text() == "good map"
    assert list(tmp_path.iterdir()) == [target]  # no temporary left behind


@pytest.mark.parametrize("moment", ["after the file is made", "while it is removed"])
def test_ctrl_c_while_the_temporary_file_is_made_or_removed_leaves_none_behind(tmp_path, monkeypatch, moment):
    """A SIGINT that lands between creating the temporary file and owning it (or while removing it) still
    removes it: the interrupt is raised once the file is in the writer's hands."""
    import os
    import signal

    import mabdi.io.atomic as atomic
    from mabdi import interrupts

    def interrupt_after(function):
        def wrapped(*args, **kwargs):
            result = function(*args, **kwargs)
            # to this (the main) thread, not the process: Python runs the handler at its next function call
            signal.raise_signal(signal.SIGINT)
            return result

        return wrapped

    target = tmp_path / "checkpoint.npz"
    # the handler a Python program starts with (a test run before this one in the same worker may have left its own)
    handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        if moment == "after the file is made":
            monkeypatch.setattr(atomic.os, "close", interrupt_after(os.close))
            with pytest.raises(KeyboardInterrupt):
                with atomic_output(target) as temporary:
                    temporary.write_bytes(b"never reached")
        else:
            with pytest.raises(KeyboardInterrupt):
                with atomic_output(target) as temporary:
                    monkeypatch.setattr(atomic.Path, "exists", interrupt_after(atomic.Path.exists))
                    raise KeyboardInterrupt
    finally:
        signal.signal(signal.SIGINT, handler)
    monkeypatch.undo()
    interrupts.clear()  # the SIGINT noted (where the command line's handler took it) is this test's alone
    assert list(tmp_path.iterdir()) == []


def test_write_into_a_missing_folder_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_text(blocker / "sub" / "out.txt", "data")


def test_run_writes_depth_images_labels_and_resolved_config(tmp_path, scenes_dir, capsys):
    out = tmp_path / "run"
    status = main(
        ["run", str(scenes_dir / "table.toml"), "--frames", "3", "--noise", "kinect", "--out", str(out), "--quiet", "--depth-images"]
    )
    assert status == 0
    printed = capsys.readouterr().out
    assert "3 frames in" in printed
    # the simulator states its poses exact: used as given, no ICP run
    assert "poses: stated exact by the source, used as given" in printed
    summary = json.loads((out / "summary.json").read_text())["registration"]
    assert summary["statuses"] == {"exact": 3} and summary["registered"] == summary["not_registered"] == 0
    images = sorted((out / "depth").glob("D_*.vti"))
    assert [p.name for p in images] == ["D_000000.vti", "D_000001.vti", "D_000002.vti"]
    assert len(list((out / "depth").glob("E_*.vti"))) == 3
    labels_reader = vtkXMLImageDataReader()
    labels_reader.SetFileName(str(out / "depth" / "labels_000001.vti"))
    labels_reader.Update()
    assert labels_reader.GetOutput().GetPointData().GetArray("label") is not None
    poses = np.load(out / "poses.npy")
    assert poses.shape == (3, 4, 4)
    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(images[1]))
    reader.Update()
    frame = DepthFrame.from_image(reader.GetOutput())
    assert frame.frame == 1
    # D carries the pose the frame was given and the one it was meshed with (registered, in the map's frame,
    # with where that frame lay in the world then); poses.npy has the same in the world, by the final anchor
    np.testing.assert_allclose(given_pose(reader.GetOutput()), np.load(out / "poses_given.npy")[1])
    in_world = image_world_from_map(reader.GetOutput()) @ frame.world_from_camera
    np.testing.assert_allclose(in_world, poses[1], atol=2e-3)
    times, trajectory = read_groundtruth(out / "trajectory.txt")  # the same poses as a TUM trajectory
    np.testing.assert_allclose(trajectory, poses, atol=1e-12)
    np.testing.assert_allclose(times, np.arange(3) / 30.0, atol=1e-6)
    assert 0.5 <= np.nanmin(frame.depth) and np.nanmax(frame.depth) <= 4.2
    resolved = run_config_from_dict(tomllib.loads((out / "config.toml").read_text()))
    original = load_run_config(scenes_dir / "table.toml")
    assert resolved.run.frames == 3 and resolved.sensor.noise == "kinect"
    assert resolved.scene == original.scene
    scene_reader = vtkXMLPolyDataReader()
    scene_reader.SetFileName(str(out / "scene.vtp"))
    scene_reader.Update()
    assert scene_reader.GetOutput().GetCellData().GetArray("object_id") is not None


def test_run_with_a_bad_config_prints_one_line_and_exits_2(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text("[path]\nradius = 2.0\n")
    status = main(["run", str(config), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert status == 2
    assert "unknown key 'radius'" in err and str(config) in err
    assert "Traceback" not in err


def test_run_with_a_bad_override_is_named(tmp_path, scenes_dir, capsys):
    status = main(["run", str(scenes_dir / "table.toml"), "--noise", "speckle", "--out", str(tmp_path / "o")])
    assert status == 2
    assert "sensor.noise" in capsys.readouterr().err


def test_importing_mabdi_selects_egl_unless_the_user_chose():
    import subprocess
    import sys

    code = "import os, mabdi, vtkmodules.vtkRenderingOpenGL2; print(os.environ['VTK_DEFAULT_OPENGL_WINDOW'])"
    env = {k: v for k, v in __import__("os").environ.items() if k != "VTK_DEFAULT_OPENGL_WINDOW"}
    chosen = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert chosen.stdout.strip() == "vtkEGLRenderWindow"
    env["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"
    kept = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert kept.stdout.strip() == "vtkOSOpenGLRenderWindow"


def test_console_script_runs(tmp_path, scenes_dir):
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    script = Path(sys.executable).parent / "mabdi"
    script = str(script) if script.exists() else shutil.which("mabdi")
    assert script, "the mabdi console script is not installed"
    result = subprocess.run(
        [script, "run", str(scenes_dir / "table.toml"), "--frames", "2", "--out", str(tmp_path / "r"), "--quiet"],
        capture_output=True,
        text=True,
        env={k: v for k, v in __import__("os").environ.items() if k != "DISPLAY"},
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "r" / "world_mesh.ply").is_file()
    assert "2 frames in" in result.stdout


def test_run_h5_then_info_export_and_plan(tmp_path, scenes_dir, capsys):
    out = tmp_path / "run"
    status = main(
        ["run", str(scenes_dir / "table.toml"), "--frames", "12", "--surface", "voxel_planes", "--out", str(out), "--quiet", "--no-eval", "--h5"]
    )
    assert status == 0
    capsys.readouterr()
    assert main(["info", str(out / "world_mesh.h5")]) == 0
    info = capsys.readouterr().out
    assert "mesh_tools layout" in info and "floor:" in info and "12 poses, intrinsics" in info
    for layer in ("roughness", "height_difference", "cost", "lethal", "rgb_colors", "frame"):
        assert f"    {layer} (" in info
    assert main(["export", str(out / "world_mesh.h5"), str(tmp_path / "lvr2.h5"), "--layout", "lvr2"]) == 0
    assert main(["export", str(tmp_path / "lvr2.h5"), str(tmp_path / "map.ply")]) == 0
    assert main(["info", str(tmp_path / "lvr2.h5")]) == 0
    assert "lvr2 layout" in capsys.readouterr().out
    path = tmp_path / "path.vtp"
    assert main(["plan", str(out / "world_mesh.h5"), "--start=-2,-1.5,0", "--goal=2,1.5,0", "--out", str(path)]) == 0
    printed = capsys.readouterr().out
    assert "fmm: path of" in printed and path.is_file()
    length = float(printed.split("length ")[1].split(" m")[0])
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    points = np.array([reader.GetOutput().GetPoint(i) for i in range(reader.GetOutput().GetNumberOfPoints())])
    straight = np.linalg.norm(points[-1] - points[0])  # between the free vertices nearest start and goal
    assert straight > 2.0 and straight - 1e-6 <= length <= 1.15 * straight
    assert np.abs(points[:, 2]).max() < 0.05  # on the floor
    # the table top is a lethal island for a floor robot: unreachable, exit status 1
    assert main(["plan", str(out / "world_mesh.h5"), "--start=-2,-1.5,0", "--goal=0,0,1", "--planner", "dijkstra"]) == 1
    assert "goal unreachable" in capsys.readouterr().out
    assert main(["plan", str(out / "world_mesh.h5"), "--start=-2,-1.5,0", "--goal=0,0,3"]) == 2
    assert "from the nearest free vertex" in capsys.readouterr().err
    assert main(["plan", str(out / "world_mesh.h5"), "--start=1,2", "--goal=0,0,0"]) == 2
    assert "--start must be three numbers" in capsys.readouterr().err
    # the run's folder stands for its map (the HDF5 file: the richest), as `mabdi view` takes it
    assert main(["info", str(out)]) == 0
    assert f"{out / 'world_mesh.h5'} (mesh_tools layout)" in capsys.readouterr().out
    assert main(["export", str(out), str(tmp_path / "from_folder.ply")]) == 0
    assert (tmp_path / "from_folder.ply").is_file()
    assert main(["info", str(tmp_path)]) == 2  # a folder that is not a run's
    assert "holds none of world_mesh.h5, world_mesh.vtp, world_mesh.ply" in capsys.readouterr().err
