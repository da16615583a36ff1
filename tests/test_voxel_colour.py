"""Voxel planes in colour: each voxel keeps the sum of its points' colours, clearing a voxel clears it, states
and checkpoints carry it, polygon vertices take their voxel's mean colour, and no colour in gives no colour out."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.depth import COLOUR_ARRAY
from mabdi.voxels.voxel_map import VoxelMap
from mabdi.surfaces.voxel_planes import NO_COLOUR, FilterVoxelPlanes
from mabdi.io.checkpoint import read_tree, write_tree
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER

S = 0.05
RED, BLUE = (220, 30, 30), (40, 40, 200)


def floor_points(count=60_000, half=0.5, z=0.013, sigma=0.003, seed=0):
    """A noisy horizontal square, coloured red for x < 0.012 and blue beyond (the border inside a voxel)."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(-half, half, (count, 2)), z + sigma * rng.standard_normal(count)])
    colours = np.where((points[:, 0] < 0.012)[:, None], np.array(RED, np.uint8), np.array(BLUE, np.uint8)).astype(np.uint8)
    return points, colours


def points_polydata(points, colours=None, name=COLOUR_ARRAY):
    data = vtkPolyData()
    vtk_points = vtkPoints()
    vtk_points.SetData(numpy_to_vtk(points, deep=True))
    data.SetPoints(vtk_points)
    if colours is not None:
        array = numpy_to_vtk(colours, deep=True)
        array.SetName(name)
        data.GetPointData().AddArray(array)
    return data


def expected_sums(voxels: VoxelMap, points, colours):
    """Per occupied voxel of ``voxels``: coloured points and the sums of their r, g, b, from the points directly."""
    index = voxels.voxel_indices(points)
    occupied, inverse = np.unique(index, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    sums = np.column_stack([np.bincount(inverse)] + [np.bincount(inverse, weights=colours[:, c]) for c in range(3)])
    return occupied, sums


@pytest.mark.parametrize("path", ["compiled", "numpy dense", "numpy sparse"])
def test_each_voxel_keeps_the_sum_of_its_points_colours(monkeypatch, path):
    import mabdi.voxels.voxel_map as voxel_map

    rng = np.random.default_rng(4)
    count = 40_000 if path != "numpy sparse" else 300  # few points in big blocks: the sparse numpy sums
    points = rng.normal([-1.2, 0.4, 0.9], 0.5, (count, 3))
    colours = rng.integers(0, 256, (count, 3), dtype=np.uint8)
    if path != "compiled":  # the numpy sums, which add points whose blocks are too spread for the compiled passes
        monkeypatch.setattr(voxel_map.VoxelMap, "_add_compiled", lambda self, columns, colours=None: None)
    voxels = VoxelMap()
    voxels.add_points(points[: count // 2], colours[: count // 2])
    voxels.add_points(points[count // 2 :], colours[count // 2 :])  # incremental: sums add
    occupied, sums = expected_sums(voxels, points, colours)
    np.testing.assert_array_equal(voxels.occupied_voxels()[np.lexsort(voxels.occupied_voxels().T[::-1])], occupied)
    np.testing.assert_allclose(voxels.colour_sums(occupied), sums, rtol=1e-6)
    np.testing.assert_allclose(voxels.colours(occupied), sums[:, 1:] / sums[:, :1], rtol=1e-6)
    assert voxels.has_colour and np.isnan(voxels.colours([[100, 100, 100]])).all()
    with pytest.raises(ValueError, match="colours must be uint8"):
        voxels.add_points(points[:3], colours[:3].astype(np.int64))


def test_colour_survives_a_state_round_trip_and_old_states_load(tmp_path):
    points, colours = floor_points()
    surface = FilterVoxelPlanes(output="full")
    surface.add_points(points[:30_000], colours[:30_000])
    write_tree(tmp_path / "state.npz", {"surface": surface.state()})  # as a checkpoint stores it
    state = read_tree(tmp_path / "state.npz")["surface"]
    assert state["map"]["colour"].dtype == np.float32
    back = FilterVoxelPlanes(output="full")
    back.set_state(state)
    occupied = surface.map.occupied_voxels()
    np.testing.assert_array_equal(back.map.colour_sums(occupied), surface.map.colour_sums(occupied))
    for filter_ in (surface, back):  # going on from the restored state gives the same map, colours and all
        filter_.add_points(points[30_000:], colours[30_000:])
    first, second = surface.mesh(), back.mesh()
    np.testing.assert_array_equal(
        vtk_to_numpy(second.GetPointData().GetArray(COLOUR_LAYER)), vtk_to_numpy(first.GetPointData().GetArray(COLOUR_LAYER))
    )
    np.testing.assert_array_equal(vtk_to_numpy(second.GetPoints().GetData()), vtk_to_numpy(first.GetPoints().GetData()))
    # a state written before colour (no colour sums, no polygon colours) still loads, as a map without colour
    old = surface.state()
    del old["map"]["colour"], old["blocks"]["colours"]
    restored = FilterVoxelPlanes(output="full")
    restored.set_state(old)
    assert not restored.map.has_colour and restored.mesh().GetPointData().GetArray(COLOUR_LAYER) is None
    assert restored.mesh().GetNumberOfCells() == first.GetNumberOfCells()


def test_clearing_a_voxel_clears_its_colour():
    points, colours = floor_points()
    surface = FilterVoxelPlanes(output="full")
    surface.add_points(points, colours)
    voxel = surface.map.voxel_indices(np.array([[0.3, 0.3, 0.013]]))
    assert surface.map.colour_sums(voxel)[0, 0] > 0
    surface.map.clear_voxels(voxel)
    np.testing.assert_array_equal(surface.map.colour_sums(voxel), 0.0)
    # refilled with other colours, the voxel's mean is theirs alone
    inside = (voxel[0] + 0.5) * S + np.random.default_rng(1).uniform(-0.02, 0.02, (50, 3)) * [1, 1, 0.1]
    surface.map.add_points(inside, np.tile(np.array(RED, np.uint8), (50, 1)))
    np.testing.assert_array_equal(surface.map.colours(voxel)[0], RED)
    # free space: rays from above through the floor at x > 0.2 clear those voxels, colour and all
    ends = np.column_stack([np.full(20, 0.3), np.linspace(-0.4, 0.4, 20), np.full(20, -0.5)])
    origin = np.array([0.3, 0.0, 2.0])
    removed = surface.clear_free_space(origin, ends, 0.02)
    crossed = surface.map.voxel_indices(origin + (2.0 - 0.013) / 2.5 * (ends - origin))  # where the rays cross the floor
    assert removed > 0 and (surface.map.counts(crossed) == 0).all()
    np.testing.assert_array_equal(surface.map.colour_sums(crossed), 0.0)
    surface.add_points(np.zeros((0, 3)))  # re-mesh around the cleared voxels
    mesh = surface.mesh()
    assert len(vtk_to_numpy(mesh.GetPointData().GetArray(COLOUR_LAYER))) == mesh.GetNumberOfPoints()


def test_polygon_vertices_take_the_mean_colour_of_their_voxel():
    """A floor red on one side of x = 0.012 and blue on the other: every vertex more than a voxel from the border
    has its side's colour exactly; vertices in the voxels the border crosses have a blend of the two."""
    points, colours = floor_points()
    surface = FilterVoxelPlanes(output="full")
    surface.SetInputDataObject(points_polydata(points, colours))
    surface.Update()
    mesh = surface.GetOutput()
    vertices = vtk_to_numpy(mesh.GetPoints().GetData())
    rgb = vtk_to_numpy(mesh.GetPointData().GetArray(COLOUR_LAYER))
    assert rgb.dtype == np.uint8 and rgb.shape == (len(vertices), 3) and len(vertices) > 1000
    red, blue = vertices[:, 0] < -S, vertices[:, 0] >= 2 * S
    assert red.sum() > 300 and blue.sum() > 300
    assert (rgb[red] == RED).all() and (rgb[blue] == BLUE).all()
    border = (vertices[:, 0] >= 0) & (vertices[:, 0] < S)  # the voxel column the border cuts
    blends = rgb[border].astype(int)
    assert ((blends[:, 0] > BLUE[0]) & (blends[:, 0] < RED[0])).all()
    # the pipeline takes the colour under the name the map uses too
    surface = FilterVoxelPlanes(output="full")
    surface.SetInputDataObject(points_polydata(points, colours, name=COLOUR_LAYER))
    surface.Update()
    np.testing.assert_array_equal(vtk_to_numpy(surface.GetOutput().GetPointData().GetArray(COLOUR_LAYER)), rgb)


def test_no_colour_array_without_colour_input():
    from conftest import plane_mesh
    from mabdi.render.depth_image import FilterDepthImage

    points, colours = floor_points()
    surface = FilterVoxelPlanes(output="full")
    surface.SetInputDataObject(points_polydata(points))
    surface.Update()
    assert surface.GetOutput().GetNumberOfCells() > 0
    assert surface.GetOutput().GetPointData().GetArray(COLOUR_LAYER) is None
    assert not surface.map.has_colour and "colour" not in surface.map.state()
    sensor = FilterDepthImage()  # a depth image without colour
    sensor.SetInputDataObject(plane_mesh([0, 0, 2.0], [0, 0, 1]))
    sensor.pose = np.eye(4)
    surface = FilterVoxelPlanes(output="full")
    surface.SetInputConnection(sensor.GetOutputPort())
    surface.Update()
    assert surface.GetOutput().GetNumberOfCells() > 0
    assert surface.GetOutput().GetPointData().GetArray(COLOUR_LAYER) is None
    # coloured points after uncoloured ones: polygons whose voxels saw no colour are NO_COLOUR
    surface = FilterVoxelPlanes(output="full")
    surface.add_points(points[points[:, 0] < -0.2])
    surface.add_points(points[points[:, 0] > 0.2], colours[points[:, 0] > 0.2])
    mesh = surface.mesh()
    vertices = vtk_to_numpy(mesh.GetPoints().GetData())
    rgb = vtk_to_numpy(mesh.GetPointData().GetArray(COLOUR_LAYER))
    assert (rgb[vertices[:, 0] < -0.3] == NO_COLOUR).all() and (rgb[vertices[:, 0] > 0.3] == BLUE).all()


def test_a_coloured_voxel_planes_run_resumes_with_its_colours(tmp_path):
    """--resume of the coloured table with voxel planes after an interrupt: the same map, colours and all."""
    from test_colour import coloured_table
    from test_run_folder import interrupt_at

    from mabdi.config import load_run_config
    from mabdi.io.run_folder import STAGING
    from mabdi.loop import MappingRun
    from mabdi.loop.run_outputs import CHECKPOINT

    def config():
        config = load_run_config(coloured_table(tmp_path, frames=6))
        config.surface.method = "voxel_planes"
        config.output.checkpoint_every = 2
        return config

    MappingRun(config()).run(tmp_path / "whole")
    with pytest.raises(KeyboardInterrupt):
        MappingRun(config()).run(tmp_path / "cut", progress=interrupt_at(3))
    checkpoint = read_tree(tmp_path / "cut" / STAGING / CHECKPOINT)
    assert checkpoint["loop"]["surface"]["map"]["colour"][..., 0].sum() > 0  # the voxels' colour sums are in it
    _, result = MappingRun.resume(tmp_path / "cut")
    assert result.mesh.GetPointData().GetArray(COLOUR_LAYER) is not None
    for name in ("world_mesh.vtp", "world_mesh.ply"):
        assert (tmp_path / "cut" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
