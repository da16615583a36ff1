"""FilterPixelGrid: the pixel grid against known geometry."""

from __future__ import annotations

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy

from mabdi.camera import Intrinsics, backproject, look_at
from mabdi.depth import depth_image
from mabdi.surfaces.pixel_grid import FilterPixelGrid, PixelGridParameters, pixel_grid_triangles

SMALL = Intrinsics(fx=52.5, fy=52.5, cx=32.0, cy=24.0, width=64, height=48)


def surface_of(depth, pose=None, max_jump=0.05):
    surface = FilterPixelGrid(PixelGridParameters(max_jump=max_jump))
    surface.SetInputDataObject(depth_image(depth, SMALL, np.eye(4) if pose is None else pose, frame=2))
    surface.Update()
    mesh = surface.GetOutput()
    points = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64) if mesh.GetNumberOfPoints() else np.zeros((0, 3))
    triangles = vtk_to_numpy(mesh.GetPolys().GetConnectivityArray()).reshape(-1, 3) if mesh.GetNumberOfCells() else np.zeros((0, 3), int)
    return mesh, points, triangles


def test_full_plane_gives_two_triangles_per_square_on_the_plane():
    pose = look_at([1.0, -2.0, 1.5], [0.0, 0.0, 0.5])
    depth = np.full(SMALL.shape, 2.5, np.float32)
    mesh, points, triangles = surface_of(depth, pose)
    assert len(triangles) == 2 * 63 * 47
    assert len(points) == 64 * 48
    np.testing.assert_allclose(np.sort(points, axis=0), np.sort(backproject(depth, SMALL, pose), axis=0), atol=1e-5)
    camera_axis = pose[:3, 2]
    a, b, c = (points[triangles[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert (normals @ camera_axis < 0).all()  # every triangle faces the sensor
    assert int(mesh.GetFieldData().GetArray("frame").GetTuple1(0)) == 2


def test_invalid_pixels_and_discontinuities_are_not_bridged():
    depth = np.full(SMALL.shape, 2.0, np.float32)
    depth[:, 32:] = 3.0  # a step of 50%: no triangle across it
    depth[10, 10] = np.nan
    _, points, triangles = surface_of(depth)
    z = points[:, 2]
    spread = z[triangles].max(1) - z[triangles].min(1)
    assert spread.max() < 1e-5
    expected = 2 * (31 * 47) * 2 - 6  # two halves, minus the 6 triangles touching the hole
    assert len(triangles) == expected


def test_oblique_plane_within_the_jump_is_kept():
    # Kinect intrinsics, a plane turned 55 degrees: depth 1.2-5.7 m over the image, at most 0.8% per pixel
    # (under the 1% limit); turned 60 degrees it reaches 1.6% at the far corner, where triangles go.
    intrinsics = Intrinsics(far=10.0)  # every depth inside the range: all are returns
    normal = np.array([0.0, -np.sin(np.radians(55)), -np.cos(np.radians(55))])
    depth = (normal @ [0, 0, 2.0]) / (intrinsics.rays() @ normal)
    assert depth.min() > 1.0 and depth.max() > 5.5
    surface = FilterPixelGrid()
    from mabdi.depth import depth_image as make_image

    surface.SetInputDataObject(make_image(depth, intrinsics, np.eye(4)))
    surface.Update()
    assert surface.GetOutput().GetNumberOfCells() == 2 * 639 * 479


def test_all_nan_gives_an_empty_mesh():
    mesh, _, _ = surface_of(np.full(SMALL.shape, np.nan, np.float32))
    assert mesh.GetNumberOfCells() == 0 and mesh.GetNumberOfPoints() == 0


def test_triangle_ids_follow_the_square_layout():
    depth = np.ones((3, 4), np.float32)
    triangles = pixel_grid_triangles(depth, 0.05)
    assert triangles.tolist()[:2] == [[0, 4, 1], [1, 5, 2]]
    assert [1, 4, 5] in triangles.tolist()


def test_parameters_are_checked():
    import pytest

    from mabdi.errors import ConfigError

    assert FilterPixelGrid(0.1).max_jump == 0.1 and FilterPixelGrid().parameters == PixelGridParameters()
    with pytest.raises(ConfigError, match="max_jump must be > 0"):
        FilterPixelGrid(PixelGridParameters(max_jump=0.0))


def test_straight_edges_from_a_wider_image_never_reach_a_pixel_without_depth():
    """The flat-ground masks may come from the whole measured image; a triangle still needs three valid corners."""
    from mabdi.surfaces.pixel_grid import pixel_grid_triangles

    depth = np.full((6, 8), 2.0, dtype=np.float32)
    depth[2:4, 3:5] = np.nan
    everywhere = (np.ones((5, 8), bool), np.ones((6, 7), bool), np.ones((5, 7), bool))
    triangles = pixel_grid_triangles(depth, 0.01, everywhere)
    assert len(triangles) > 0 and np.isfinite(depth.ravel()[triangles]).all()
    assert len(triangles) == len(pixel_grid_triangles(depth, 0.01))
