"""HDF5 mesh maps: round trips in both layouts, a reader written from the layout description, bad files."""

import h5py  # a required dependency: its absence is a failure, not a skip
import numpy as np
import pytest

from mabdi.io.hdf5 import MapFileError, map_layout, read_map, write_map
from mabdi.io.mesh_map_files import load_map, save_map
from mabdi.mesh_maps.mesh_map import MeshMap, MeshMapError


def sample_map(n=500, seed=0) -> MeshMap:
    rng = np.random.default_rng(seed)
    vertices = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    faces = rng.integers(0, n, (2 * n, 3))
    return MeshMap(
        vertices,
        faces,
        vertex_layers={
            "normals": rng.normal(size=(n, 3)).astype(np.float32),
            "rgb_colors": rng.integers(0, 256, (n, 3)).astype(np.uint8),
            "roughness": rng.uniform(0, 1, n).astype(np.float32),
            "height_difference": rng.uniform(0, 0.3, n).astype(np.float32),
            "cost": rng.uniform(0, 1, n).astype(np.float32),
        },
        face_layers={"frame": rng.integers(0, 30, 2 * n).astype(np.int32), "face_cost": rng.uniform(0, 1, 2 * n).astype(np.float32)},
        labels={"tree_1": np.array([3, 5, 8]), "tree_2": np.array([0]), "floor": np.arange(10, 40)},
        clustersets={"planar": {"0": np.arange(0, 20), "1": np.arange(20, 25)}},
        poses=np.stack([np.eye(4)] * 3),
        intrinsics=np.array([570.0, 570.0, 320.0, 240.0, 640, 480, 0.1, 10.0]),
    )


def assert_same(a: MeshMap, b: MeshMap) -> None:
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert a.vertices.dtype == b.vertices.dtype == np.float32
    np.testing.assert_array_equal(a.faces, b.faces)
    for mine, theirs in ((a.vertex_layers, b.vertex_layers), (a.face_layers, b.face_layers)):
        assert sorted(mine) == sorted(theirs)
        for name in mine:
            np.testing.assert_array_equal(mine[name], theirs[name], err_msg=name)
            assert mine[name].dtype == theirs[name].dtype, name
    assert sorted(a.labels) == sorted(b.labels)
    for name in a.labels:
        np.testing.assert_array_equal(a.labels[name], b.labels[name])
    assert a.clustersets.keys() == b.clustersets.keys()
    for name in a.clustersets:
        for cluster in a.clustersets[name]:
            np.testing.assert_array_equal(a.clustersets[name][cluster], b.clustersets[name][cluster])
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.intrinsics, b.intrinsics)


@pytest.mark.parametrize("layout", ["mesh_tools", "lvr2"])
def test_round_trip_is_exact(tmp_path, layout):
    original = sample_map()
    path = write_map(original, tmp_path / "map.h5", layout)
    assert map_layout(path) == layout
    assert_same(original, read_map(path))


def test_a_reader_written_from_the_mesh_tools_description_reads_our_files(tmp_path):
    """Accesses the datasets as hdf5_map_io::HDF5MapIO does: five groups, flat 1-D arrays."""
    original = sample_map()
    path = write_map(original, tmp_path / "map.h5")
    with h5py.File(path, "r") as f:
        for group in ("geometry", "attributes", "clustersets", "textures", "labels"):
            assert group in f  # the reader throws "No valid map h5 file" otherwise
        vertices = f["geometry/vertices"][()]
        faces = f["geometry/faces"][()]
        assert vertices.dtype == np.float32 and vertices.ndim == 1
        assert faces.dtype == np.uint32 and faces.ndim == 1
        np.testing.assert_array_equal(vertices.reshape(-1, 3), original.vertices)
        np.testing.assert_array_equal(faces.reshape(-1, 3), original.faces)
        assert f["attributes/normals"].dtype == np.float32 and f["attributes/normals"].shape == (3 * 500,)
        assert f["attributes/rgb_colors"].dtype == np.uint8 and f["attributes/rgb_colors"].shape == (3 * 500,)
        np.testing.assert_array_equal(f["attributes/roughness"][()], original.vertex_layers["roughness"])
        np.testing.assert_array_equal(f["attributes/height_difference"][()], original.vertex_layers["height_difference"])
        assert sorted(f["labels"]) == ["floor", "tree"]  # getLabelGroups()
        assert sorted(f["labels/tree"]) == ["1", "2"]  # getAllLabelsOfGroup("tree")
        assert f["labels/tree/1"].dtype == np.uint32  # getFaceIdsOfLabel("tree", "1")
        np.testing.assert_array_equal(f["labels/tree/1"][()], [3, 5, 8])
        assert f["geometry/vertices"].compression == "gzip"


def test_a_reader_written_from_the_lvr2_description_reads_our_files(tmp_path):
    original = sample_map()
    path = write_map(original, tmp_path / "map.h5", "lvr2")
    with h5py.File(path, "r") as f:
        mesh = f["mesh"]
        assert mesh.attrs["IO"] == "MeshIO" and mesh.attrs["CLASS"] == "MeshBuffer"  # isMesh()
        channels = mesh["channels"]
        assert channels["vertices"].shape == (500, 3) and channels["vertices"].dtype == np.float32
        assert channels["face_indices"].shape == (1000, 3) and channels["face_indices"].dtype == np.uint32
        assert channels["vertex_normals"].shape == (500, 3)
        assert channels["vertex_colors"].dtype == np.uint8
        assert channels["roughness"].shape == (500, 1)  # Channel<T>(dim[0], dim[1])
        assert "textures" in mesh and "materials" in mesh


def test_quads_are_triangulated_and_vtk_round_trip(tmp_path):
    from vtkmodules.vtkFiltersSources import vtkPlaneSource

    plane = vtkPlaneSource()
    plane.SetResolution(3, 2)
    plane.Update()
    quads = MeshMap.from_polydata(plane.GetOutput())
    assert quads.number_of_faces == 12 and quads.number_of_vertices == 12
    assert "Normals" in quads.vertex_layers
    save_map(quads, tmp_path / "quads.h5")
    save_map(quads, tmp_path / "quads.vtp")
    assert_same(quads, load_map(tmp_path / "quads.h5"))
    back = load_map(tmp_path / "quads.vtp")
    np.testing.assert_array_equal(back.faces, quads.faces)


def test_corrupt_truncated_and_incomplete_files_are_named(tmp_path):
    good = write_map(sample_map(), tmp_path / "good.h5")
    data = good.read_bytes()
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapFileError, match="truncated.h5"):
        read_map(truncated)
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an hdf5 file at all" * 100)
    with pytest.raises(MapFileError, match="not a readable HDF5 file"):
        read_map(garbage)
    with pytest.raises(MapFileError, match="does not exist"):
        read_map(tmp_path / "missing.h5")
    missing_group = tmp_path / "no_labels.h5"
    missing_group.write_bytes(data)
    with h5py.File(missing_group, "a") as f:
        del f["labels"]
    with pytest.raises(MapFileError, match="/labels"):
        read_map(missing_group)
    wrong_length = tmp_path / "wrong_length.h5"
    wrong_length.write_bytes(data)
    with h5py.File(wrong_length, "a") as f:
        del f["attributes/roughness"]
        f["attributes"].create_dataset("roughness", data=np.zeros(499, dtype=np.float32))
    with pytest.raises(MapFileError, match="roughness.*499"):
        read_map(wrong_length)
    bad_faces = tmp_path / "bad_faces.h5"
    bad_faces.write_bytes(data)
    with h5py.File(bad_faces, "a") as f:
        f["geometry/faces"][0] = 10_000
    with pytest.raises(MapFileError, match="vertex 10000"):
        read_map(bad_faces)


def test_a_layer_of_the_wrong_length_is_refused_before_writing(tmp_path):
    broken = sample_map()
    broken.vertex_layers["roughness"] = np.zeros(3, dtype=np.float32)
    with pytest.raises(MeshMapError, match="roughness"):
        write_map(broken, tmp_path / "map.h5")
    assert not list(tmp_path.iterdir())


def test_unwritable_path_fails_cleanly(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(MapFileError, match="cannot write"):
        write_map(sample_map(), blocker / "map.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_an_overwrite_that_fails_part_way_keeps_the_old_map(tmp_path, monkeypatch):
    import mabdi.io.hdf5 as hdf5

    path = write_map(sample_map(seed=1), tmp_path / "map.h5")
    before = path.read_bytes()

    def fail_half_way(group, name, values, **attributes):
        if name == "faces":
            raise OSError("No space left on device")
        return original_dataset(group, name, values, **attributes)

    original_dataset = hdf5._dataset
    monkeypatch.setattr(hdf5, "_dataset", fail_half_way)
    with pytest.raises(MapFileError, match="No space left"):
        write_map(sample_map(seed=2), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.h5"]
    assert_same(read_map(path), sample_map(seed=1))
