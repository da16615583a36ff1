"""FilterWorldMesh: appending patches, keyed replacement, the merged mesh; per-block rendering of the map."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from conftest import plane_mesh
from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.render.depth_image import FilterDepthImage
from mabdi.face_identity import FaceIdTable
from mabdi.stages.world_mesh import FilterWorldMesh


def with_frame(mesh, frame):
    array = numpy_to_vtk(np.array([frame], dtype=np.int64), deep=True)
    array.SetName("frame")
    mesh.GetFieldData().AddArray(array)
    return mesh


def append(world, mesh):
    world.SetInputDataObject(mesh)
    world.Update()
    return world.cells_added


def test_appends_patches_and_stamps_frames():
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    assert append(world, with_frame(plane_mesh([0, 0, 0], [0, 0, 1], subdivisions=2), 0)) == 8
    first_block = world.map.GetBlock(0)
    assert append(world, with_frame(plane_mesh([0, 0, 1], [0, 0, 1], subdivisions=3), 5)) == 18
    assert world.map.GetBlock(0) is first_block  # old patches are never rebuilt
    assert world.number_of_cells == 26 and world.patch_keys == ["frame_0", "frame_5"]
    merged = world.mesh()
    frames = vtk_to_numpy(merged.GetCellData().GetArray("frame"))
    assert sorted(set(frames.tolist())) == [0, 5] and (frames == 5).sum() == 18


def test_re_execution_for_the_same_frame_appends_nothing():
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    mesh = with_frame(plane_mesh([0, 0, 0], [0, 0, 1]), 3)
    append(world, mesh)
    world.Modified()
    world.Update()
    assert world.number_of_cells == 2


def test_re_execution_behind_a_vtk_filter_appends_nothing():
    """The input is recognised by its VTK object, not by a Python wrapper that may be new each time."""
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter
    from vtkmodules.vtkFiltersSources import vtkPlaneSource

    source = vtkPlaneSource()
    source.SetResolution(3, 3)
    triangles = vtkTriangleFilter()
    triangles.SetInputConnection(source.GetOutputPort())
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    world.SetInputConnection(triangles.GetOutputPort())
    world.Update()
    for _ in range(3):
        world.Modified()
        world.Update()
    assert world.number_of_cells == 18 and len(world.patch_keys) == 1


def test_keyed_patches_replace_instead_of_stacking():
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    mesh = with_frame(plane_mesh([0, 0, 0], [0, 0, 1], subdivisions=2), 0)  # 8 cells
    keys = numpy_to_vtk(np.array([7, 7, 7, 7, 9, 9, 9, 9], dtype=np.int64), deep=True)
    keys.SetName("patch_key")
    mesh.GetCellData().AddArray(keys)
    assert append(world, mesh) == 8
    assert world.patch_keys == ["patch_7", "patch_9"]
    again = with_frame(plane_mesh([0, 0, 0.1], [0, 0, 1], subdivisions=1), 1)  # 2 cells replace patch 7
    keys = numpy_to_vtk(np.array([7, 7], dtype=np.int64), deep=True)
    keys.SetName("patch_key")
    again.GetCellData().AddArray(keys)
    removed = numpy_to_vtk(np.array([9], dtype=np.int64), deep=True)
    removed.SetName("removed_patch_keys")
    again.GetFieldData().AddArray(removed)
    assert append(world, again) == 2 - 8  # net change: 4 -> 2 for key 7, key 9 removed
    assert world.patch_keys == ["patch_7"] and world.number_of_cells == 2
    merged = world.mesh()
    z = vtk_to_numpy(merged.GetPoints().GetData())[:, 2]
    np.testing.assert_allclose(z, 0.1, atol=1e-6)
    assert merged.GetCellData().GetArray("patch_key") is None


def test_reset_empties_the_map():
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    append(world, with_frame(plane_mesh([0, 0, 0], [0, 0, 1]), 0))
    world.reset()
    assert world.number_of_cells == 0 and world.map.GetNumberOfBlocks() == 0
    assert world.mesh().GetNumberOfCells() == 0


def test_expected_image_from_blocks_equals_the_merged_mesh_and_keeps_block_actors():
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    append(world, with_frame(plane_mesh([0, 0, 0], [0, 0, 1], size=3.0), 0))
    pose = look_at([0, -2.5, 1.5], [0, 0, 0.3])
    expected = FilterDepthImage(intrinsics=Intrinsics(width=160, height=120, fx=131.25, fy=131.25, cx=80, cy=60))
    expected.SetInputDataObject(world.map)
    expected.pose = pose
    expected.Update()
    actors_before = dict(expected.renderer._actors)
    append(world, with_frame(plane_mesh([0, 0.5, 0.5], [0, -1, 0], size=0.6), 1))
    expected.Update()
    from_blocks = DepthFrame.from_image(expected.GetOutput()).depth
    for key, entry in actors_before.items():
        assert expected.renderer._actors[key].actor is entry.actor  # the first block's actor (and upload) is reused
    assert len(expected.renderer._actors) == 2
    merged = FilterDepthImage(intrinsics=expected.intrinsics)
    merged.SetInputDataObject(world.mesh())
    merged.pose = pose
    merged.Update()
    np.testing.assert_allclose(from_blocks, DepthFrame.from_image(merged.GetOutput()).depth, atol=1e-5, equal_nan=True)
    assert np.isfinite(from_blocks).mean() > 0.5


def test_removed_blocks_are_hidden_then_lose_their_actors():
    from mabdi.render.depth_image import KEEP_HIDDEN_RENDERS

    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    world.add_patch("a", plane_mesh([0, 0, 0], [0, 0, 1]), 0)
    world.add_patch("b", plane_mesh([0, 0, 1], [0, 0, 1]), 0)
    expected = FilterDepthImage()
    expected.SetInputDataObject(world.map)
    expected.pose = look_at([0, -3, 2], [0, 0, 0])
    expected.Update()
    assert len(expected.renderer._actors) == 2
    assert world.remove_patch("a") == -2
    expected.Update()
    visible = [entry for entry in expected.renderer._actors.values() if entry.actor.GetVisibility()]
    assert len(visible) == 1
    for _ in range(KEEP_HIDDEN_RENDERS):
        expected.Modified()
        expected.Update()
    assert len(expected.renderer._actors) == 1


def test_non_polydata_block_is_an_error():
    from vtkmodules.vtkCommonDataModel import vtkImageData, vtkMultiBlockDataSet

    blocks = vtkMultiBlockDataSet()
    image = vtkImageData()
    image.SetDimensions(2, 2, 1)
    blocks.SetBlock(0, image)
    expected = FilterDepthImage()
    expected.SetInputDataObject(blocks)
    expected.pose = np.eye(4)
    with pytest.raises(TypeError, match="only vtkPolyData"):
        expected.Update()


def test_a_re_meshed_patch_keeps_the_removal_evidence_of_the_faces_it_replaces():
    """Re-meshing a block (voxel planes do it whenever a point lands in it) must not reset removal:
    a face at the same place keeps its evidence, a face somewhere new starts at zero."""
    from mabdi.stages.removal import RemovalParameters

    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    world.add_patch("patch_7", plane_mesh((0, 0, 2), (0, 0, 1), size=1.0, subdivisions=4), frame=0)
    count = world.number_of_cells
    table = FaceIdTable(["patch_7"], [100], [count])  # as an expected image that drew the patch at codes 100..
    ids = np.arange(100, 100 + count)
    contradicted = np.zeros(count, dtype=bool)
    contradicted[:10] = True
    assert not len(world.update_evidence(ids, contradicted, ~contradicted, RemovalParameters(), table))
    before = world.face_evidence_of(ids, table)
    assert (before[:10] > 0).all() and (before[10:] <= 0).all()

    # the same faces, their vertices moved by a millimetre, and one new face 5 m away
    again = plane_mesh((0, 0, 2.001), (0, 0, 1), size=1.0, subdivisions=4)
    world.add_patch("patch_7", again, frame=1)
    np.testing.assert_array_equal(world.face_evidence_of(ids, table), before)
    world.add_patch("patch_7", plane_mesh((5, 0, 2), (0, 0, 1), size=1.0, subdivisions=4), frame=2)
    assert (world.face_evidence_of(ids, table) == 0).all()


def test_moving_points_changes_the_block_and_its_face_normals_only():
    """``move_points``: the moved vertices go where they are told, the faces around them get new normals,
    the rest stay; a wrong shape or vertex id is an error naming the block."""
    world = FilterWorldMesh(chunk_size=1000.0)  # one chunk: these tests are about patches
    append(world, with_frame(plane_mesh([0, 0, 0], [0, 0, 1], subdivisions=2), 0))
    block = world.block("frame_0")
    points = vtk_to_numpy(block.GetPoints().GetData()).copy()
    table = FaceIdTable(["frame_0"], [1], [world.number_of_cells])
    ids = np.arange(1, world.number_of_cells + 1)  # the block's faces drawn as codes 1..8
    normals = world.face_normals_of(ids, table)
    assert np.allclose(normals @ [0, 0, 1], 1.0) or np.allclose(normals @ [0, 0, 1], -1.0)
    centre = int(np.argmin(np.linalg.norm(points[:, :2] - points[:, :2].mean(axis=0), axis=1)))
    world.move_points("frame_0", [centre], [points[centre] + [0.0, 0.0, 5.0]])
    moved = vtk_to_numpy(block.GetPoints().GetData())
    np.testing.assert_allclose(moved[centre], points[centre] + [0.0, 0.0, 5.0], atol=1e-6)
    others = np.arange(len(points)) != centre
    np.testing.assert_array_equal(moved[others], points[others])
    tilted = np.abs(world.face_normals_of(ids, table)[:, 2]) < 0.999
    assert tilted.sum() == 6  # the six triangles around the centre vertex of a 2x2 grid (diagonals one way)
    with pytest.raises(ValueError, match="frame_0"):
        world.move_points("frame_0", [0, 1], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="frame_0"):
        world.move_points("frame_0", [len(points)], np.zeros((1, 3)))


def test_a_frames_moves_at_once_move_each_patch_and_set_each_chunks_bounds():
    """A frame's refinement moves many patches at once (``move_points_of``): the points and normals are what
    moving them one by one gives, and each chunk's bounding box (what the renderer culls by) covers the moved
    points."""
    from vtkmodules.vtkCommonDataModel import vtkDataObject

    worlds = []
    for _ in range(2):
        world = FilterWorldMesh(chunk_size=1.0)
        append(world, with_frame(plane_mesh([0.0, 0.0, 0], [0, 0, 1], subdivisions=2, size=0.5), 0))
        append(world, with_frame(plane_mesh([3.0, 0.0, 0], [0, 0, 1], subdivisions=2, size=0.5), 1))
        worlds.append(world)
    keys = worlds[0].store.patch_keys
    first, last = keys[0], keys[-1]
    assert worlds[0].store.patch(first).chunk != worlds[0].store.patch(last).chunk
    lifted = vtk_to_numpy(worlds[0].block(first).GetPoints().GetData())[:2] + [0.0, 0.0, 2.0]
    lowered = vtk_to_numpy(worlds[0].block(last).GetPoints().GetData())[:1] - [0.0, 0.0, 1.5]
    moves = [(first, [0, 1], lifted), (last, [0], lowered)]
    worlds[0].move_points_of(moves)
    for key, ids, positions in moves:
        worlds[1].move_points(key, ids, positions)
    for key in keys:
        np.testing.assert_array_equal(
            vtk_to_numpy(worlds[0].block(key).GetPoints().GetData()), vtk_to_numpy(worlds[1].block(key).GetPoints().GetData())
        )
        cells = worlds[0].block(key).GetNumberOfCells()
        table = FaceIdTable([key], [1], [cells])
        np.testing.assert_array_equal(worlds[0].face_normals_of(np.arange(1, cells + 1), table), worlds[1].face_normals_of(np.arange(1, cells + 1), table))
    multiblock = worlds[0].store.multiblock
    boxes = [multiblock.GetMetaData(i).Get(vtkDataObject.BOUNDING_BOX()) for i in range(multiblock.GetNumberOfBlocks())]
    assert max(box[5] for box in boxes) == pytest.approx(2.0)  # the lifted corners
    assert min(box[4] for box in boxes) == pytest.approx(-1.5)  # the lowered one, in another chunk


def test_a_surface_split_by_patch_key_in_one_pass_is_what_extracting_each_patch_gives():
    from mabdi.polydata import extract_polys, split_polys, triangles_polydata

    rng = np.random.default_rng(1)
    mesh = triangles_polydata(rng.normal(size=(500, 3)), rng.integers(0, 500, (800, 3)))
    normals = numpy_to_vtk(rng.normal(size=(500, 3)), deep=True)
    normals.SetName("normals")
    mesh.GetPointData().AddArray(normals)
    kind = numpy_to_vtk(rng.integers(0, 9, 800).astype(np.int32), deep=True)
    kind.SetName("kind")
    mesh.GetCellData().AddArray(kind)
    labels = rng.integers(-3, 40, 800)  # shared points between groups, negative labels, labels in no order

    def arrays(patch):
        out = [vtk_to_numpy(patch.GetPoints().GetData()), vtk_to_numpy(patch.GetPolys().GetOffsetsArray()),
               vtk_to_numpy(patch.GetPolys().GetConnectivityArray())]  # fmt: skip
        for data in (patch.GetPointData(), patch.GetCellData()):
            out += [(data.GetArray(i).GetName(), vtk_to_numpy(data.GetArray(i))) for i in range(data.GetNumberOfArrays())]
        return out

    parts = split_polys(mesh, labels)
    assert [label for label, _ in parts] == sorted(set(labels.tolist()))
    for label, patch in parts:
        expected = arrays(extract_polys(mesh, np.flatnonzero(labels == label)))
        got = arrays(patch)
        assert len(got) == len(expected) == 5
        for a, b in zip(got, expected, strict=True):
            if isinstance(a, tuple):
                assert a[0] == b[0] and a[1].dtype == b[1].dtype and np.array_equal(a[1], b[1])
            else:
                assert a.dtype == b.dtype and np.array_equal(a, b)
    with pytest.raises(ValueError, match=r"\(799,\) labels for 800 cells"):
        split_polys(mesh, labels[:-1])


def test_the_faces_beside_and_enclosed_by_removed_ones_are_counted_by_shared_corners():
    """beside: a kept triangle with two corners on removed triangles (an edge shared); enclosed: all three. Checked
    against the array formulation on a random mesh, and on a strip whose answer is known."""
    from mabdi.world_map import beside, enclosed

    rng = np.random.default_rng(3)
    points = 200
    triangles = rng.integers(0, points, size=(1000, 3))
    gone = rng.random(1000) < 0.1
    marked = np.zeros(points, dtype=bool)
    marked[triangles[gone].ravel()] = True
    counts = marked[triangles].sum(axis=1)
    np.testing.assert_array_equal(beside(triangles, points, gone), ~gone & (counts >= 2))
    np.testing.assert_array_equal(enclosed(triangles, points, gone), ~gone & (counts == 3))
    strip = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4], [0, 2, 4]])  # a strip, and a face closing it
    first = np.array([True, False, False, False, False])
    assert beside(strip, 6, first).tolist() == [False, True, False, False, True]
    assert enclosed(strip, 6, np.array([True, True, True, False, False])).tolist() == [False, False, False, False, True]


def test_the_faces_a_move_touches_and_a_patchs_triangles_are_found_as_the_array_formulation_finds_them():
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    from mabdi.polydata import triangles_polydata
    from mabdi.polydata_kernels import triangles_touching
    from mabdi.world_map import patch_triangles

    rng = np.random.default_rng(5)
    triangles = rng.integers(0, 300, size=(2000, 3))
    moved = rng.choice(300, size=20, replace=False)
    mask = np.zeros(300, dtype=bool)
    mask[moved] = True
    np.testing.assert_array_equal(triangles_touching(triangles, 300, moved), np.flatnonzero(mask[triangles].any(axis=1)))
    assert len(triangles_touching(triangles, 300, np.zeros(0, dtype=np.int64))) == 0
    patch = triangles_polydata(rng.random((300, 3)), triangles)
    np.testing.assert_array_equal(patch_triangles(patch), triangles)
    assert patch_triangles(vtkPolyData()) is None
    quads = vtkPolyData()
    quads.SetPoints(patch.GetPoints())
    cells = vtkCellArray()
    for corners in ([0, 1, 2], [3, 4, 5, 6]):
        cells.InsertNextCell(len(corners), corners)
    quads.SetPolys(cells)
    assert patch_triangles(quads) is None  # a polygon of four corners: not all triangles
