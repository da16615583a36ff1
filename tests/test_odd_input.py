"""Odd depths and empty maps: what is not a return makes no geometry in any surface filter, and a run
whose map is empty says what is empty and why, with valid files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mabdi.camera import Intrinsics
from mabdi.cli import main
from mabdi.depth import depth_image, returns
from mabdi.surfaces.registry import make_surface_filter
from mabdi.io.vtk_files import read_mesh_file

SMALL = Intrinsics(fx=52.5, fy=52.5, cx=32.0, cy=24.0, width=64, height=48)


@pytest.mark.parametrize("value", [-2.0, 0.0, 1e9, np.inf, -np.inf, np.nan, 0.2, 4.5])
@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree", "voxel_planes"])
def test_depths_that_are_not_returns_give_no_geometry(surface, value):
    # 0.2 m is closer than near (0.5 m), 4.5 m beyond far (4 m): not returns either
    depth = np.full(SMALL.shape, value, dtype=np.float32)
    assert not returns(depth, SMALL.near, SMALL.far).any()
    surface_filter = make_surface_filter(surface)
    surface_filter.SetInputDataObject(depth_image(depth, SMALL, np.eye(4), frame=0))
    surface_filter.Update()
    assert surface_filter.GetOutput().GetNumberOfCells() == 0


@pytest.mark.parametrize("surface", ["pixel_grid", "quadtree"])
def test_odd_pixels_among_good_ones_are_left_out(surface):
    depth = np.full(SMALL.shape, 2.0, dtype=np.float32)
    depth[10:20, 10:20] = -1.0
    depth[30:40, 40:50] = np.inf
    surface_filter = make_surface_filter(surface)
    surface_filter.SetInputDataObject(depth_image(depth, SMALL, np.eye(4), frame=0))
    surface_filter.Update()
    from vtkmodules.util.numpy_support import vtk_to_numpy

    points = vtk_to_numpy(surface_filter.GetOutput().GetPoints().GetData())
    assert np.all(np.isfinite(points)) and np.abs(points[:, 2] - 2.0).max() < 1e-3


def test_an_empty_scene_is_an_error_before_running(tmp_path, capsys):
    config = tmp_path / "empty.toml"
    config.write_text("[run]\nframes = 2\n")
    assert main(["run", str(config), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "nothing to map: the scene has no objects" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_objects_out_of_view_give_an_empty_map_with_a_reason(tmp_path, capsys):
    config = tmp_path / "far.toml"
    config.write_text('[run]\nframes = 3\n[[scene.objects]]\ntype = "box"\nsize = [0.5, 0.5, 0.5]\nposition = [30.0, 0.0, 0.0]\n')
    out = tmp_path / "out"
    assert main(["run", str(config), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "mabdi: warning: the map is empty: no frame had a depth return" in err and "Traceback" not in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cells"] == 0 and summary["evaluation"] == "skipped: the map is empty"
    for name in ("world_mesh.vtp", "world_mesh.ply"):
        assert read_mesh_file(out / name).GetNumberOfCells() == 0  # valid files, holding no triangles
        assert main(["info", str(out / name)]) == 0


@pytest.mark.parametrize(
    "text,message",
    [
        ("[[scene.objects]]\ntype = 'box'\nsize = [1, 1, 1]\nappear_at = 40\n", "after the run's last frame 29"),
        ("[[scene.objects]]\ntype = 'box'\nsize = [1, 1, 1]\nappear_at = 10\ndisappear_at = 5\n", "disappears"),
        ("[sensor.camera]\ncx = 10000.0\n[[scene.objects]]\ntype = 'box'\nsize = [1, 1, 1]\n", "principal point cx = 10000.0"),
        ("[run]\nname = '../../escape'\n[[scene.objects]]\ntype = 'box'\nsize = [1, 1, 1]\n", "plain folder name"),
    ],
)
def test_configs_that_would_map_nothing_or_escape_are_refused(tmp_path, capsys, text, message):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    assert main(["run", str(config), "--quiet"]) == 2
    assert message in capsys.readouterr().err
