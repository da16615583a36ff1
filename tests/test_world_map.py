"""WorldMap: patches in chunks of space, merged frame patches, E drawn from the chunks in view, and a map of
more faces than an image's 24-bit face codes can name at once."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkDataObject, vtkPolyData

from conftest import merged as merged_meshes, plane_mesh
from scipy.spatial import cKDTree

from mabdi.camera import Intrinsics, look_at
from mabdi.face_identity import MAX_FACE_CODE, FaceIdTable, codes_in, rows_by_block, unique_codes
from mabdi.render.depth_image import DepthRenderer
from mabdi.polydata import named_leaves, polydata_arrays
from mabdi.stages.removal import RemovalParameters
from mabdi import world_map
from mabdi.world_map import WorldMap, _chunked_state

SMALL = Intrinsics(fx=160, fy=160, cx=80, cy=60, width=160, height=120, near=0.3, far=4.0)


def test_patches_go_to_the_chunk_of_their_centre_and_chunks_carry_their_bounds():
    world = WorldMap(chunk_size=4.0)
    world.add_patch("frame_0", plane_mesh([1, 1, 0], [0, 0, 1], size=1.0), frame=0)
    world.add_patch("frame_1", plane_mesh([-7, 9, 0.5], [0, 0, 1], size=1.0), frame=1)
    world.add_patch("frame_2", plane_mesh([1.5, 1.5, 0], [0, 0, 1], size=1.0), frame=2)
    assert set(world.chunks) == {(0, 0, 0), (-2, 2, 0)}  # chunk (i, j, k) is centred on 4 (i, j, k) metres
    assert list(world.chunks[(0, 0, 0)].patches) == ["frame_0", "frame_2"]
    top = world.multiblock
    assert top.GetNumberOfBlocks() == 2
    np.testing.assert_allclose(top.GetMetaData(0).Get(vtkDataObject.BOUNDING_BOX()), [0.5, 2.0, 0.5, 2.0, 0, 0])
    assert [name for name, _ in named_leaves(top)] == ["frame_0", "frame_2", "frame_1"]
    assert world.number_of_cells == 6
    # a frame's patch across chunks is split, each face to the chunk of its centre
    world.add_patch("frame_3", plane_mesh([2.0, 0.0, 0], [0, 0, 1], size=2.0, subdivisions=4), frame=3)
    parts = [key for key in world.patch_keys if key.startswith("frame_3")]
    assert parts == ["frame_3@0_0_0", "frame_3@1_0_0"] and world.number_of_cells == 6 + 32
    for key in parts:
        x = polydata_arrays(world.block(key))[0][:, 0]
        assert (x >= 1.0 - 1e-9).all() and (x <= 3.0 + 1e-9).all()
        assert world.patch(key).chunk == ((0, 0, 0) if key.endswith("@0_0_0") else (1, 0, 0))


def test_frame_patches_beyond_the_limit_merge_into_one_with_their_faces_and_evidence():
    world = WorldMap(chunk_size=4.0, patches_per_chunk=3)
    for frame in range(5):
        world.add_patch(f"frame_{frame}", plane_mesh([0.5, 0.5, 0.1 * frame], [0, 0, 1], size=1.0, subdivisions=2), frame=frame)
    world.add_patch("patch_9", plane_mesh([1.5, 1.5, 0], [0, 0, 1], size=0.5), frame=5, keyed=True)
    table = FaceIdTable(["frame_1"], [1], [8])
    world.update_evidence(np.arange(1, 9), np.ones(8, bool), np.zeros(8, bool), RemovalParameters(), table)
    before = world.mesh()
    assert world.number_of_cells == 42 and len(world.patch_keys) == 6
    world.compact()
    chunk = world.chunks[(0, 0, 0)]
    assert list(chunk.patches) == ["patch_9", "merged_0"]  # keyed patches are never merged
    merged = chunk.patches["merged_0"]
    assert merged.cells == 40 and world.number_of_cells == 42
    frames = vtk_to_numpy(merged.polydata.GetCellData().GetArray("frame"))
    assert frames.tolist() == sorted(frames.tolist()) == [f for f in range(5) for _ in range(8)]
    assert (merged.evidence[8:16] > 0).all() and (merged.evidence[:8] == 0).all() and (merged.evidence[16:] == 0).all()
    points, triangles = polydata_arrays(world.mesh())
    old_points, old_triangles = polydata_arrays(before)
    centres = np.sort(points[triangles].mean(axis=1), axis=0)
    np.testing.assert_allclose(centres, np.sort(old_points[old_triangles].mean(axis=1), axis=0))
    # the merged patch keeps vertices apart: removing one layer's face spreads over that layer only
    assert merged.polydata.GetNumberOfPoints() == 5 * 9


def test_a_full_frame_patch_is_not_merged_again_nor_counted_against_the_limit(monkeypatch):
    # a chunk of a large place: once a merged patch holds FULL_PATCH_FACES faces, later frames merge apart from it,
    # so removing a face there rebuilds a patch of bounded size, not the whole chunk
    monkeypatch.setattr(world_map, "FULL_PATCH_FACES", 20)
    world = WorldMap(chunk_size=4.0, patches_per_chunk=2)
    for frame in range(3):  # 8 faces a frame: three frames merge into one of 24, full
        world.add_patch(f"frame_{frame}", plane_mesh([0.5, 0.5, 0.1 * frame], [0, 0, 1], size=1.0, subdivisions=2), frame=frame)
    world.compact()
    chunk = world.chunks[(0, 0, 0)]
    assert list(chunk.patches) == ["merged_0"] and chunk.patches["merged_0"].cells == 24
    assert chunk.frame_patches == 0  # full: not counted
    for frame in range(3, 6):
        world.add_patch(f"frame_{frame}", plane_mesh([0.5, 0.5, 0.1 * frame], [0, 0, 1], size=1.0, subdivisions=2), frame=frame)
    world.compact()
    assert list(chunk.patches) == ["merged_0", "merged_1"]
    assert chunk.patches["merged_0"].cells == 24 and chunk.patches["merged_1"].cells == 24
    assert world.number_of_cells == 48
    # a full patch that a removal brings under the size counts again, and merges with the next ones
    table = FaceIdTable(["merged_0"], [1], [24])
    world.remove_faces(np.arange(1, 9), table)
    assert chunk.patches["merged_0"].cells == 16 and chunk.frame_patches == 1


def test_state_round_trip_and_the_previous_checkpoint_layout():
    world = WorldMap(chunk_size=4.0)
    world.add_patch("frame_0", plane_mesh([0.5, 0.5, 0], [0, 0, 1], size=1.0, subdivisions=2), frame=0)
    world.add_patch("patch_3", plane_mesh([9, 0.5, 0], [0, 0, 1], size=1.0), frame=1, keyed=True)
    world.patch("frame_0").evidence[:] = np.arange(8)
    restored = WorldMap(chunk_size=4.0)
    restored.set_state(world.state())
    assert restored.patch_keys == world.patch_keys and restored.number_of_cells == 10
    np.testing.assert_array_equal(restored.patch("frame_0").evidence, np.arange(8))
    assert restored.patch("patch_3").keyed and restored.patch("patch_3").chunk == (2, 0, 0)
    # a checkpoint of the map kept as blocks with evidence by 24-bit identity range
    state = world.state()
    old = {
        "patches": [[key, polydata] for key, polydata, *_ in state["patches"]],
        "ranges": {"frame_0": [1, 8], "patch_3": [9, 2]},
        "evidence": np.concatenate([[0.0], np.arange(8), [5, 6]]).astype(np.float32),
        "contradicted": np.zeros(11, np.uint16),
        "next_frame": 2,
    }
    converted = WorldMap(chunk_size=4.0)
    converted.set_state(old)
    np.testing.assert_array_equal(converted.patch("patch_3").evidence, [5, 6])
    assert _chunked_state(old, 4.0)["patches"][1][5] is True


def test_expected_image_draws_only_the_chunks_in_view():
    world = WorldMap(chunk_size=2.0)
    for i in range(10):  # ten floor tiles along x, 2 m apart (each in its chunk)
        world.add_patch(f"frame_{i}", plane_mesh([2.0 * i, 0.0, 0.0], [0, 0, 1], size=1.9, subdivisions=4), frame=i)
    renderer = DepthRenderer(face_identity=True)
    pose = look_at([12.0, 0.0, 1.2], [12.0, 0.0001, 0.0])  # straight down over tile 6 (x 11..13)
    zbuffer = renderer.render_zbuffer(world.multiblock, SMALL, pose)
    assert (zbuffer < 1).any()
    assert renderer.identities.names == ["frame_6"]  # the other nine chunks were not drawn
    renderer.render_zbuffer(world.multiblock, SMALL, look_at([2.0, 0.0, 1.2], [2.0, 0.0001, 0.0]))
    assert renderer.identities.names == ["frame_1"]


def _grid(cells_per_side: int, size: float, origin) -> tuple[np.ndarray, vtkCellArray]:
    n = cells_per_side + 1
    s = np.linspace(0.0, size, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    points = np.column_stack([x.ravel() + origin[0], y.ravel() + origin[1], np.zeros(n * n)]).astype(np.float32)
    i, j = np.meshgrid(np.arange(cells_per_side), np.arange(cells_per_side), indexing="ij")
    v0 = (i * n + j).ravel()
    triangles = np.concatenate([np.stack([v0, v0 + n, v0 + n + 1], 1), np.stack([v0, v0 + n + 1, v0 + 1], 1)])
    cells = vtkCellArray()
    cells.SetData(
        numpy_to_vtk(np.arange(0, 3 * len(triangles) + 1, 3, dtype=np.int64), deep=True),
        numpy_to_vtk(triangles.ravel().astype(np.int64), deep=True),
    )
    return points, cells


def test_a_map_of_more_faces_than_24_bit_codes_renders_identities_and_removes_faces():
    """21 patches of 1M faces each (21M faces, more than the 16.7M an image's codes can name): the expected
    image over the last patch names its faces right, and removing faces by those codes removes exactly them."""
    side = 708  # 2 * 708^2 = 1,002,528 triangles per patch
    patches = 21
    world = WorldMap(chunk_size=4.0)
    _, cells = _grid(side, 3.9, (0.0, 0.0))  # the connectivity is shared by every patch (the points differ)
    for k in range(patches):  # patch k fills most of chunk (k, 0, 0): x from 4k - 1.95 to 4k + 1.95
        points, _ = _grid(side, 3.9, (4.0 * k - 1.95, -1.95))
        patch = vtkPolyData()
        vtk_points = vtkPoints()
        vtk_points.SetData(numpy_to_vtk(points, deep=True))
        patch.SetPoints(vtk_points)
        patch.SetPolys(cells)
        world.add_patch(f"frame_{k}", patch, frame=k)
    assert world.number_of_cells == patches * 2 * side * side > MAX_FACE_CODE + 4_000_000

    last = f"frame_{patches - 1}"
    x0, y0 = 4.0 * (patches - 1) - 1.95, -1.95
    renderer = DepthRenderer(face_identity=True)
    pose = look_at([x0 + 1.7, y0 + 1.25, 0.8], [x0 + 1.7, y0 + 1.2501, 0.0])
    zbuffer = renderer.render_zbuffer(world.multiblock, SMALL, pose)
    codes = renderer.render_identity()
    table = renderer.identities
    assert table.names == [last] and (zbuffer < 1).all()
    block, local, keys = world.face_lookup(codes, table)
    assert (block == 0).all() and keys == [last]
    # each pixel's face contains the point its centre ray hits on the floor (z = 0)
    rays = SMALL.rays() @ pose[:3, :3].T
    hits = pose[:3, 3] + rays * (-pose[2, 3] / rays[..., 2])[..., None]
    step = 3.9 / side
    i = np.floor((hits[..., 0] - x0) / step).astype(int)
    j = np.floor((hits[..., 1] - y0) / step).astype(int)
    fx, fy = (hits[..., 0] - x0) / step - i, (hits[..., 1] - y0) / step - j
    quad = i * side + j
    expected = np.where(fy < fx, quad, quad + side * side)  # which of the quad's two triangles
    clear = (np.abs(fx - fy) > 0.05) & (fx > 0.05) & (fx < 0.95) & (fy > 0.05) & (fy < 0.95)
    assert clear.mean() > 0.5
    np.testing.assert_array_equal(local[clear], expected[clear])

    # remove the faces seen by every tenth pixel (5 cm apart: no two touch), every face voted on first so
    # that only they go (faces never voted on would go with their removed neighbours)
    every_code = table.bases[0] + np.arange(table.counts[0])
    world.update_evidence(every_code, np.zeros(len(every_code), bool), np.ones(len(every_code), bool), RemovalParameters(), table)
    chosen = np.unique(codes[::10, ::10])
    gone_local = table.lookup(chosen)[1]
    before = world.number_of_cells
    removed = world.remove_faces(chosen, table)
    assert removed.GetNumberOfCells() == len(chosen) == 192 and world.number_of_cells == before - len(chosen)
    assert world.patch(last).cells == 2 * side * side - len(chosen)
    points, triangles = polydata_arrays(removed)
    quad, upper = gone_local % (side * side), gone_local // (side * side)
    i, j = quad // side, quad % side
    corners = np.stack([np.stack([i, j], 1), np.stack([i + 1, j + upper], 1), np.stack([i + 1 - upper, j + 1], 1)], 1)
    centres = corners.mean(axis=1) * step + [x0, y0]
    distance, _ = cKDTree(points[triangles].mean(axis=1)[:, :2]).query(centres)
    assert distance.max() < 1e-5
    # the next image of the same place sees through where they were
    zbuffer = renderer.render_zbuffer(world.multiblock, SMALL, pose)
    assert (zbuffer[::10, ::10] == 1).all() and (zbuffer < 1).mean() > 0.98


def test_a_view_of_more_faces_than_codes_is_a_clear_error():
    world = WorldMap()
    renderer = DepthRenderer(face_identity=True)
    renderer._codes.allocate("elsewhere", MAX_FACE_CODE - 10)  # as if a huge block were in view already
    world.add_patch("frame_0", plane_mesh([0.5, 0.5, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0)
    with pytest.raises(MemoryError, match="in view"):
        renderer.render_zbuffer(world.multiblock, SMALL, look_at([0.5, 0.5, 1.0], [0.5, 0.5001, 0.0]))


def test_merging_leaves_a_large_patch_apart_until_the_small_ones_add_up_to_it():
    world = WorldMap(chunk_size=8.0, patches_per_chunk=4)
    world.add_patch("frame_0", plane_mesh([0.5, 0.5, 0], [0, 0, 1], size=1.0, subdivisions=10), frame=0)  # 200 faces
    for frame in range(1, 6):
        world.add_patch(f"frame_{frame}", plane_mesh([0.5, 0.5, 0.1 * frame], [0, 0, 1], size=1.0, subdivisions=2), frame=frame)
    world.compact()
    chunk = world.chunks[(0, 0, 0)]
    assert [(key, p.cells) for key, p in chunk.patches.items()] == [("frame_0", 200), ("merged_0", 40)]
    for frame in range(6, 30):  # small patches keep coming: merged among themselves, then into the large one
        world.add_patch(f"frame_{frame}", plane_mesh([0.5, 0.5, 0.1 * frame], [0, 0, 1], size=1.0, subdivisions=5), frame=frame)
        world.compact()
        assert chunk.frame_patches <= 5
    assert world.number_of_cells == 200 + 40 + 24 * 50
    assert "frame_0" not in world.patch_keys  # once the small ones outweighed it


def test_codes_drawn_before_a_patch_changed_its_number_of_faces_find_nothing():
    """Voxel planes re-mesh a block at the append that follows E: the codes of the old faces find the new
    patch's faces only while it holds as many (the same polygons re-fitted), never another patch's."""
    world = WorldMap()
    world.add_patch("patch_1", plane_mesh([0.5, 0.5, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0, keyed=True)
    world.add_patch("patch_2", plane_mesh([1.5, 0.5, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0, keyed=True)
    table = FaceIdTable(["patch_1", "patch_2"], [1, 33], [32, 32])  # E drew both: codes 1..64
    world.add_patch("patch_1", plane_mesh([0.5, 0.5, 0.001], [0, 0, 1], size=1.0, subdivisions=4), frame=1, keyed=True)
    block, local, keys = world.face_lookup(np.arange(1, 65), table)
    assert (block[:32] == 0).all() and local[:32].tolist() == list(range(32))  # re-fitted, the same 32 faces
    world.add_patch("patch_1", plane_mesh([0.5, 0.5, 0.002], [0, 0, 1], size=1.0, subdivisions=2), frame=2, keyed=True)
    block, local, keys = world.face_lookup(np.arange(1, 65), table)
    assert (block[:32] == -1).all() and (local[:32] == -1).all()  # 8 faces now: the old codes mean nothing
    assert [keys[b] for b in block[32:]] == ["patch_2"] * 32 and local[32:].tolist() == list(range(32))


def test_a_block_of_polygons_and_the_same_block_triangulated_show_the_same_faces():
    """A block of triangles draws its codes from the triangles' order in the shader, a block of quads (split into
    triangles by the mapper) from a colour array: pixel for pixel they name the same faces (quad i is
    triangles 2i and 2i + 1 once triangulated)."""
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter
    from vtkmodules.vtkFiltersSources import vtkPlaneSource

    plane = vtkPlaneSource()
    plane.SetResolution(24, 18)
    plane.SetOrigin(-1.2, -0.9, 0.0)
    plane.SetPoint1(1.2, -0.9, 0.0)
    plane.SetPoint2(-1.2, 0.9, 0.0)
    plane.Update()
    quads = plane.GetOutput()
    triangulate = vtkTriangleFilter()
    triangulate.SetInputData(quads)
    triangulate.Update()
    triangles = triangulate.GetOutput()
    assert triangles.GetNumberOfCells() == 2 * quads.GetNumberOfCells()
    pose = look_at([0.1, -0.2, 2.0], [0.1, -0.1999, 0.0])
    local, seen = {}, {}
    for name, mesh in (("quads", quads), ("triangles", triangles)):
        renderer = DepthRenderer(face_identity=True)
        renderer.render_zbuffer(mesh, SMALL, pose)
        codes = renderer.render_identity()
        seen[name] = codes > 0
        local[name] = renderer.identities.lookup(np.where(seen[name], codes, renderer.identities.bases[0]))[1]
    np.testing.assert_array_equal(seen["quads"], seen["triangles"])
    assert seen["quads"].mean() > 0.5
    on = seen["quads"]
    np.testing.assert_array_equal(local["triangles"][on] // 2, local["quads"][on])
    assert len(np.unique(local["triangles"][on])) > 1.8 * len(np.unique(local["quads"][on]))  # both halves of each quad seen


def test_a_contradicted_face_follows_a_neighbour_removed_before_it_was_contradicted():
    """Faces contradicted before go with a removed neighbour; one contradicted only after its neighbour
    went (a departed car's small roof faces, each seen by one beam in one frame) goes at that contradiction,
    while a face elsewhere still needs the two frames; the mark survives a checkpoint."""
    world = WorldMap(chunk_size=100.0)
    world.add_patch("frame_0", plane_mesh([0, 0, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0)
    params = RemovalParameters()
    n = world.number_of_cells

    def vote(against, table_cells):
        table = FaceIdTable(["frame_0"], [1], [table_cells])
        codes = np.arange(1, table_cells + 1)
        contradicted = np.isin(codes - 1, against)
        return world.update_evidence(codes, contradicted, ~contradicted, params, table), table

    vote([], n)  # every face confirmed once: none is "never voted", none follows by that rule
    points, triangles = polydata_arrays(world.block("frame_0"))
    centres = points[triangles].mean(axis=1)
    target = int(np.argmin(np.linalg.norm(centres - [0.05, 0.05, 0], axis=1)))
    for _ in range(3):
        condemned, table = vote([target], n)
    assert condemned.tolist() == [target + 1]
    removed_corners = points[triangles[target]]
    world.remove_faces(condemned, table)
    assert world.number_of_cells == n - 1  # its neighbours were confirmed, not contradicted: they stay
    points, triangles = polydata_arrays(world.block("frame_0"))
    shared = (np.linalg.norm(points[triangles][:, :, None] - removed_corners[None, None], axis=3) < 1e-9).any(axis=2).sum(axis=1)
    beside, far = np.flatnonzero(shared >= 2), int(np.argmax(np.linalg.norm(points[triangles].mean(axis=1), axis=1)))
    assert len(beside) == 3 and far not in beside
    restored = WorldMap(chunk_size=100.0)
    restored.set_state(world.state())
    np.testing.assert_array_equal(restored.patch("frame_0").beside_removed, world.patch("frame_0").beside_removed)
    condemned, _ = vote([beside[0], far], n - 1)
    assert condemned.tolist() == [beside[0] + 1]  # one contradicting frame: the neighbour goes, the far face waits


def test_a_contradicted_face_follows_a_never_voted_neighbour_that_went_with_a_removed_face():
    """Removal spreads to the never-voted direct neighbours of a removed face (no pixel centre showed them),
    and from those on to faces already contradicted; faces confirmed stay."""
    world = WorldMap(chunk_size=100.0)
    world.add_patch("frame_0", plane_mesh([0, 0, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0)
    n = world.number_of_cells
    table = FaceIdTable(["frame_0"], [1], [n])
    _, triangles = polydata_arrays(world.block("frame_0"))

    def neighbours(face):
        return [f for f in range(n) if f != face and len(set(triangles[f]) & set(triangles[face])) == 2]

    def vote(faces, against):
        faces = np.asarray(faces)
        return world.update_evidence(faces + 1, np.full(len(faces), against), np.full(len(faces), not against), RemovalParameters(), table)

    removed = 5
    never_voted = neighbours(removed)[0]
    follower = next(f for f in neighbours(never_voted) if f != removed and f not in neighbours(removed))
    vote([f for f in range(n) if f != never_voted], against=False)
    vote([follower], against=True)
    for _ in range(3):
        condemned = vote([removed], against=True)
    assert condemned.tolist() == [removed + 1]
    gone = world.remove_faces(condemned, table)
    assert gone.GetNumberOfCells() == 3 and world.number_of_cells == n - 3


def test_a_patch_pools_its_faces_evidence_when_nothing_in_it_stands():
    """Each face of a small patch contradicted once, each by another frame (a departed car's roof seen from across
    a street, one beam per scan): once two frames have contradicted the patch and none of its voted faces was
    confirmed since, its contradicted faces go. The same votes on a patch with a confirmed face remove nothing;
    the patch's frame count survives a checkpoint."""
    world = WorldMap(chunk_size=100.0)
    world.add_patch("roof", plane_mesh([0, 0, 1.5], [0, 0, 1], size=0.4, subdivisions=2), frame=0)
    world.add_patch("wall", plane_mesh([5, 0, 1.5], [0, 0, 1], size=0.4, subdivisions=2), frame=0)
    n = world.patch("roof").cells
    table = FaceIdTable(["roof", "wall"], [1, 1 + n], [n, n])
    params = RemovalParameters()

    def vote(patch, face, against=True):
        code = np.array([face + 1 + (n if patch == "wall" else 0)])
        return world.update_evidence(code, np.array([against]), np.array([not against]), params, table).tolist()

    vote("wall", 3, against=False)  # the wall has a face that pixels confirm
    assert vote("roof", 0) == [] and vote("wall", 0) == []  # one frame: nothing goes
    restored = WorldMap(chunk_size=100.0)
    restored.set_state(world.state())
    assert list(restored.patch("roof").pool_frames.values()) == [1] and list(restored.patch("wall").pool_frames.values()) == [1]
    assert vote("roof", 1) == [1, 2]  # a second frame, another face: the roof's contradicted faces go
    assert vote("wall", 1) == []  # the wall's confirmed face stands: each face still needs two frames
    assert vote("wall", 1) == [n + 2]


def test_code_sets_by_table_equal_numpys_sorting_sets():
    """unique_codes, codes_in and rows_by_block (tables over the codes' range) give numpy's answers, dense and sparse."""
    rng = np.random.default_rng(3)
    for codes in (rng.integers(0, 5_000, 20_000), rng.integers(0, MAX_FACE_CODE, 300), np.array([7, 7, 7]), np.zeros(0, np.int64)):
        distinct, inverse = unique_codes(codes)
        expected, expected_inverse = np.unique(codes.astype(np.int64), return_inverse=True)
        assert np.array_equal(distinct, expected) and np.array_equal(inverse, expected_inverse.reshape(-1))
        chosen = np.concatenate([codes[::7], [-5, MAX_FACE_CODE + 9]]).astype(np.int64)
        assert np.array_equal(codes_in(codes, chosen), np.isin(codes, chosen))
    block = rng.integers(-1, 70_000, 50_000)  # over 2^16 blocks: no 16-bit keys
    for blocks in (block, block % 40 - 1, np.full(10, -1)):
        groups = rows_by_block(blocks)
        assert [b for b, _ in groups] == sorted(set(blocks[blocks >= 0].tolist()))
        for b, rows in groups:
            assert np.array_equal(rows, np.flatnonzero(blocks == b))


def test_triangle_centres_and_radii_by_the_compiled_pass_equal_the_corner_formulas():
    """face_centres of a triangle mesh (compiled path) against the corner average and farthest corner, all and some cells."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    from mabdi.world_map import face_centres

    source = vtkSphereSource()
    source.SetThetaResolution(30)
    source.SetPhiResolution(20)
    source.Update()
    sphere = source.GetOutput()
    points = vtk_to_numpy(sphere.GetPoints().GetData()).astype(np.float64)
    triangles = vtk_to_numpy(sphere.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    for cells in (None, np.array([5, 0, 17])):
        rows = np.arange(len(triangles)) if cells is None else cells
        corners = points[triangles[rows]]
        centres, radii = face_centres(sphere, cells)
        assert np.allclose(centres, corners.mean(axis=1), atol=1e-12)
        assert np.allclose(radii, np.linalg.norm(corners - corners.mean(axis=1, keepdims=True), axis=2).max(axis=1), atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_triangle_normals_by_the_compiled_pass_equal_numpys_cross_product_and_norm(dtype):
    """triangle_normals (compiled for float points) against numpy's cross product and norm, to the bit, in the
    points' dtype; a degenerate triangle has normal 0 and area 0, and a mesh without triangles gives empty arrays."""
    from mabdi.polydata import triangle_normals

    rng = np.random.default_rng(3)
    points = (5.0 * rng.standard_normal((500, 3))).astype(dtype)
    triangles = rng.integers(0, 500, (2000, 3)).astype(np.int32)
    triangles[0] = [7, 7, 9]
    corner = points[triangles[:, 0]]
    cross = np.cross(points[triangles[:, 1]] - corner, points[triangles[:, 2]] - corner)
    length = np.linalg.norm(cross, axis=1)
    normals, areas = triangle_normals(points, triangles)
    assert normals.dtype == dtype and areas.dtype == dtype
    assert np.array_equal(normals, cross / np.where(length > 0, length, dtype(1.0))[:, None])
    assert np.array_equal(areas, 0.5 * length)
    assert not normals[0].any() and areas[0] == 0
    empty_normals, empty_areas = triangle_normals(points, np.zeros((0, 3), dtype=np.int64))
    assert empty_normals.shape == (0, 3) and empty_areas.shape == (0,)


def test_a_real_sensors_contradicted_faces_follow_a_removed_neighbour_only_after_two_frames_against_them():
    """With a real sensor's four frames (``min_frames = 4``: ``follow_frames`` 2) a removed face takes along the
    neighbours two frames have contradicted since they were last confirmed, not those one frame contradicted (a
    static surface's passing mixed pixel beside a false removal, which would otherwise chain across the
    surface); such a neighbour, now beside a removed face, goes at its next contradicting frame. The
    simulator's rule (``follow_frames`` 1) takes both at once."""

    def run(params: RemovalParameters):
        world = WorldMap(chunk_size=100.0)
        world.add_patch("frame_0", plane_mesh([0, 0, 0], [0, 0, 1], size=1.0, subdivisions=4), frame=0)
        n = world.number_of_cells
        table = FaceIdTable(["frame_0"], [1], [n])
        _, triangles = polydata_arrays(world.block("frame_0"))
        target = 5
        once, twice = [f for f in range(n) if f != target and len(set(triangles[f]) & set(triangles[target])) == 2][:2]

        def vote(against):
            contradicted = np.isin(np.arange(n), against)
            return world.update_evidence(np.arange(1, n + 1), contradicted, ~contradicted, params, table)

        vote([])  # every face confirmed: none is "never voted"
        for frame in range(params.frames_required):
            condemned = vote([target] + [twice] * (frame >= params.frames_required - 2) + [once] * (frame == params.frames_required - 1))
        gone = world.remove_faces(condemned, table, params.follow_frames)
        return n, condemned.tolist(), gone.GetNumberOfCells(), world

    real = RemovalParameters(min_frames=4)
    assert (real.follow_frames, RemovalParameters(min_frames=2).follow_frames, RemovalParameters(min_frames=1).follow_frames) == (2, 1, 1)
    n, condemned, removed, world = run(real)
    assert condemned == [5 + 1]
    assert removed == 2  # the face and the neighbour two frames saw through; the one seen through once stays

    left = n - 2
    table = FaceIdTable(["frame_0"], [1], [left])
    assert world.number_of_cells == left
    # the face one frame contradicted is now beside a removed face: the next frame against it takes it
    beside = np.flatnonzero(world.patch("frame_0").beside_removed_faces())
    evidence = world.patch("frame_0").evidence
    waiting = int(beside[np.argmax(evidence[beside])])  # the contradicted one among the removed faces' neighbours
    assert evidence[waiting] > 0 and world.patch("frame_0").contradicted[waiting] == 1
    codes = np.arange(1, left + 1)
    against = codes - 1 == waiting
    assert world.update_evidence(codes, against, ~against, real, table).tolist() == [waiting + 1]
    _, condemned, removed, _ = run(RemovalParameters(min_frames=2))  # the second neighbour's two frames condemn it
    assert len(condemned) == 2 and removed == 3  # and the one seen through once follows


def named_multiblock(blocks: dict[str, vtkPolyData]):
    """A multiblock of the named polydata ``blocks``, as the world map hands the renderer its patches."""
    from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkMultiBlockDataSet

    multiblock = vtkMultiBlockDataSet()
    for number, (name, polydata) in enumerate(blocks.items()):
        multiblock.SetBlock(number, polydata)
        multiblock.GetMetaData(number).Set(vtkCompositeDataSet.NAME(), name)
    return multiblock


def test_codes_split_into_gaps_over_a_long_run_are_given_out_afresh(monkeypatch):
    """Blocks that change take new codes while the old ones wait hidden: over a long run the free codes split
    into gaps, until a block in view found none large enough (a real kitchen's pixel-grid map stopped so after
    hundreds of frames, its view holding a quarter of the codes). The renderer then gives the blocks in view
    their codes afresh, and they still name their faces; a view that holds more faces than codes is an error."""
    import mabdi.face_identity as face_identity

    monkeypatch.setattr(face_identity, "MAX_FACE_CODE", 150)
    renderer = DepthRenderer(face_identity=True)
    pose = look_at([0.5, 0.5, 1.0], [0.5, 0.5001, 0.0])
    left = plane_mesh([0.25, 0.5, 0], [0, 0, 1], size=0.5, subdivisions=4)  # 32 faces each
    right = plane_mesh([0.75, 0.5, 0], [0, 0, 1], size=0.5, subdivisions=4)
    renderer.render_zbuffer(named_multiblock({"left": left, "right": right}), SMALL, pose)
    renderer.render_identity()
    for size in (5, 6, 7):  # the left block re-made bigger, three times: its old codes wait hidden
        left = plane_mesh([0.25, 0.5, 0], [0, 0, 1], size=0.5, subdivisions=size)
        renderer.render_zbuffer(named_multiblock({"left": left, "right": right}), SMALL, pose)
    codes = renderer.render_identity()
    table = renderer.identities
    assert sorted(table.names) == ["left", "right"] and table.counts.sum() == 2 * 7 * 7 + 32 <= 150
    block = table.lookup(codes[codes > 0])[0]
    u = np.nonzero(codes > 0)[1]
    shown = np.array(table.names)[block]
    assert (shown[u < SMALL.width // 2 - 2] == "left").all() and (shown[u > SMALL.width // 2 + 2] == "right").all()
    bigger = plane_mesh([0.75, 0.5, 0], [0, 0, 1], size=0.5, subdivisions=8)  # 98 + 128 faces in view: too many
    with pytest.raises(MemoryError, match="in view"):
        renderer.render_zbuffer(named_multiblock({"left": left, "right": bigger}), SMALL, pose)


def test_evidence_pools_are_one_frames_faces_in_a_cube_however_the_map_is_chunked_or_merged():
    """A frame's mesh of a departed car's roof (pooled) and of a wall 5 m away that pixels confirm, in one frame
    patch of one large chunk: with 2 m pools the roof's contradicted faces go once two frames contradicted it, as
    they would in 2 m chunks; pooled with the wall (pools as large as the chunk) they stay. The pools and their
    frame counts survive merging and a checkpoint."""
    both = merged_meshes(plane_mesh([0, 0, 1.5], [0, 0, 1], size=0.4, subdivisions=2), plane_mesh([5, 0, 1.5], [0, 0, 1], size=0.4, subdivisions=2))
    n = both.GetNumberOfCells() // 2
    params = RemovalParameters()

    def run(pool_size, merge):
        world = WorldMap(chunk_size=100.0, patches_per_chunk=1, pool_size=pool_size)
        world.add_patch("frame_0", both, frame=0)
        if merge:  # two more frame patches, then all merged: the codes below name the merged patch (frame 0 first)
            for frame in (1, 2):
                world.add_patch(f"frame_{frame}", plane_mesh([-5, 0, frame], [0, 0, 1], size=0.4, subdivisions=2), frame=frame)
            world.compact()
        (key,) = world.patch_keys
        assert key.startswith("merged_" if merge else "frame_")
        table = FaceIdTable([key], [1], [world.patch(key).cells])

        def vote(face, against=True):
            code = np.array([face + 1])
            return world.update_evidence(code, np.array([against]), np.array([not against]), params, table).tolist()

        vote(n + 3, against=False)  # a wall face confirmed
        first = vote(0)
        restored = WorldMap(chunk_size=100.0, patches_per_chunk=1, pool_size=pool_size)
        restored.set_state(world.state())
        assert sorted(restored.patch(key).pool_frames.values()) == sorted(world.patch(key).pool_frames.values())
        np.testing.assert_array_equal(restored.patch(key).pools, world.patch(key).pools)
        return first, vote(1)

    for merge in (False, True):
        assert run(2.0, merge) == ([], [1, 2])  # the roof's pool: both contradicted faces go
        assert run(None, merge) == ([], [])  # one pool with the confirmed wall: nothing goes yet
