"""Colour: the simulated table with coloured objects gives a map whose vertices carry the colour of the object
they lie on; the colour survives PLY, OBJ and HDF5; config checks; recorded colour; the viewer shows it."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from conftest import REPO
from mabdi.config import load_run_config
from mabdi.errors import ConfigError
from mabdi.evaluate.distance import distances_within
from mabdi.io.hdf5 import read_map
from mabdi.io.mesh_map_files import load_map, save_map
from mabdi.io.vtk_files import read_mesh_file, write_mesh_file
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER, MeshMap
from mabdi.polydata import triangles_polydata
from mabdi.loop import MappingRun
from mabdi.sources.scene import SourceScene

#: Each object of Run 1's table its own colour (no two alike), so a vertex's colour names its object.
COLOURS = {
    "floor": [90, 140, 60],
    "table_top": [150, 100, 50],
    "leg_1": [40, 40, 200],
    "leg_2": [40, 200, 200],
    "leg_3": [200, 40, 200],
    "leg_4": [200, 200, 40],
    "cup_1": [220, 30, 30],
    "cup_2": [250, 250, 250],
}
SMALL_SENSOR = 'noise = "{noise}"\nwidth = 320\nheight = 240\nfx = 262.5\nfy = 262.5\ncx = 160.0\ncy = 120.0\n'


def coloured_table(folder, noise="none", frames=8):
    """Run 1's table with COLOURS, a 320x240 sensor and ``frames`` frames, as a config file in ``folder``."""
    text = (REPO / "scenes" / "table.toml").read_text()
    text = text.replace('noise = "none"\n', SMALL_SENSOR.format(noise=noise)).replace("frames = 30", f"frames = {frames}")
    for name, colour in COLOURS.items():
        text = text.replace(f'name = "{name}"\n', f'name = "{name}"\ncolour = {colour}\n')
    path = folder / "coloured_table.toml"
    path.write_text(text)
    return path


def object_of_vertices(scene: SourceScene, vertices: np.ndarray, cap: float = 0.02) -> np.ndarray:
    """Index of the object each vertex lies on (the nearest within ``cap`` m), -1 where none is that near."""
    distances = np.stack(
        [distances_within(vertices, triangles_polydata(o.points, o.triangles), cap) for o in scene.objects]
    )
    nearest = distances.argmin(axis=0)
    return np.where(distances.min(axis=0) <= cap, nearest, -1)


@pytest.fixture(scope="module")
def coloured_runs(tmp_path_factory):
    """The coloured table run with each surface (pixel grid, quad-tree, voxel planes), Kinect noise: (simulation, result)."""
    folder = tmp_path_factory.mktemp("colour")
    path = coloured_table(folder, noise="kinect")
    runs = {}
    for surface in ("pixel_grid", "quadtree", "voxel_planes"):
        config = load_run_config(path)
        config.surface.method = surface
        simulation = MappingRun(config)
        runs[surface] = (simulation, simulation.run(folder / surface))
    return runs


@pytest.mark.parametrize("surface, near, small", [("pixel_grid", 0.95, 0.8), ("quadtree", 0.8, 0.8), ("voxel_planes", 0.95, 0.3)])
def test_map_vertices_carry_the_colour_of_their_object(coloured_runs, surface, near, small):
    """Of the vertices that lie on an object (within 2 cm), 95% have exactly its colour. Most vertices lie on
    one: a pixel-grid vertex is a pixel's return; a quad-tree corner can stand off a surface by more than 2 cm
    with Kinect noise at 4 m (``near``: the share within 2 cm).

    Voxel planes (measured: 99.4% right overall) colour a vertex with the mean colour of its 5 cm voxel, so
    where a voxel holds two objects' points the vertex has their blend: a leg's lowest voxel holds floor
    points (70-78% of a leg's vertices right) and a cup's lowest the table top's (about 40% of a cup's;
    ``small``: the share asked of the cup, a leg and the table top)."""
    simulation, result = coloured_runs[surface]
    mesh = result.mesh
    colours = vtk_to_numpy(mesh.GetPointData().GetArray(COLOUR_LAYER))
    vertices = vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    assert len(colours) == len(vertices) > 1000
    owner = object_of_vertices(simulation.scene, vertices)
    on_an_object = owner >= 0
    expected = simulation.scene.colours[owner[on_an_object]]
    right = (colours[on_an_object] == expected).all(axis=1)
    print(surface, "within 2 cm", on_an_object.mean(), "right colour", right.mean())
    assert on_an_object.mean() > near, on_an_object.mean()
    assert right.mean() >= 0.95, right.mean()
    # the small objects too, not only the floor: each coloured cup's colour is on its own vertices
    for name in ("cup_1", "table_top", "leg_1"):
        index = [o.name for o in simulation.scene.objects].index(name)
        mine = owner == index
        assert mine.sum() > 20 and (colours[mine] == COLOURS[name]).all(axis=1).mean() > small, name
    if surface == "voxel_planes":  # a leg's blends lie in the voxel layers it shares with the floor or the table top
        legs = np.isin(owner, [i for i, o in enumerate(simulation.scene.objects) if o.name.startswith("leg")])
        blended = legs & ~(colours == simulation.scene.colours[np.maximum(owner, 0)]).all(axis=1)
        z = vertices[blended, 2]
        assert blended.any() and ((z <= 0.05 + 1e-6) | (z >= 0.95)).all(), np.sort(z)


def test_colour_survives_ply_obj_vtp_and_hdf5(coloured_runs, tmp_path):
    simulation, result = coloured_runs["pixel_grid"]
    mesh_map = MeshMap.from_polydata(result.mesh)
    colours = mesh_map.vertex_layers[COLOUR_LAYER]
    assert colours.dtype == np.uint8 and colours.shape == (mesh_map.number_of_vertices, 3)
    for suffix in (".ply", ".obj", ".vtp"):
        write_mesh_file(result.mesh, tmp_path / f"map{suffix}")
        back = read_mesh_file(tmp_path / f"map{suffix}")
        np.testing.assert_array_equal(vtk_to_numpy(back.GetPointData().GetArray(COLOUR_LAYER)), colours, err_msg=suffix)
    for layout in ("mesh_tools", "lvr2"):
        save_map(mesh_map, tmp_path / f"{layout}.h5", layout=layout)
        np.testing.assert_array_equal(read_map(tmp_path / f"{layout}.h5").vertex_layers[COLOUR_LAYER], colours)
    import h5py

    with h5py.File(tmp_path / "mesh_tools.h5") as file:  # where Mesh Tools' reader looks: flat uint8 r g b ...
        stored = file["attributes/rgb_colors"]
        assert stored.dtype == np.uint8 and stored.shape == (3 * len(colours),)
        np.testing.assert_array_equal(stored[:6], colours[:2].ravel())
    # the run's own files
    folder = result.out_dir
    np.testing.assert_array_equal(load_map(folder / "world_mesh.ply").vertex_layers[COLOUR_LAYER], colours)


def test_colour_key_is_checked(tmp_path):
    path = coloured_table(tmp_path)
    text = path.read_text()
    path.write_text(text.replace("colour = [220, 30, 30]", "colour = [220, 30, 300]"))
    with pytest.raises(ConfigError, match=r"cup_1|objects\[6\]\.colour.*0-255"):
        load_run_config(path)
    path.write_text(text.replace("colour = [220, 30, 30]", "color = [220, 30, 30]"))
    with pytest.raises(ConfigError, match="color"):
        load_run_config(path)
    path.write_text(text.replace("colour = [220, 30, 30]", "colour = [220, 30]"))
    with pytest.raises(ConfigError, match="colour"):
        load_run_config(path)


@pytest.fixture(scope="module")
def coloured_frames(tmp_path_factory):
    """Three frames of the coloured table, with their colour images, in memory."""
    from mabdi.simulate.rig import SimulatedRig
    from mabdi.sources.frames import FrameList

    folder = tmp_path_factory.mktemp("frames")
    rig = SimulatedRig.from_config(load_run_config(coloured_table(folder, frames=3)))
    try:
        return FrameList([rig.read(i) for i in range(3)], "coloured table"), folder
    finally:
        rig.close()


def test_the_rig_renders_each_objects_colour(coloured_frames):
    frames, _ = coloured_frames
    colour = frames.read(0).colour
    assert colour.shape == (240, 320, 3) and colour.dtype == np.uint8
    seen = {tuple(c) for c in np.unique(colour.reshape(-1, 3), axis=0)}
    assert seen <= {tuple(c) for c in COLOURS.values()} | {(0, 0, 0)}  # flat colours only: no shading, no blending
    assert tuple(COLOURS["floor"]) in seen and tuple(COLOURS["table_top"]) in seen
    returns = np.isfinite(frames.read(0).depth)
    assert (colour[returns] != 0).any(axis=1).all()  # every return shows an object, in its colour


@pytest.mark.parametrize("layout", ["tum", "3dmatch", "redwood", "scannet", "replica"])
def test_every_layout_writes_and_reads_colour(coloured_frames, tmp_path, layout):
    from mabdi.sources import write_3dmatch, write_redwood, write_replica, write_scannet, write_tum
    from mabdi.sources.sequences import open_sequence

    frames, _ = coloured_frames
    writer = {"tum": write_tum, "3dmatch": write_3dmatch, "redwood": write_redwood, "scannet": write_scannet, "replica": write_replica}
    source = open_sequence(writer[layout](frames, tmp_path / layout))
    assert "with colour" in source.description
    for i in range(3):
        np.testing.assert_array_equal(source.read(i).colour, frames.read(i).colour)


def test_a_coloured_recording_gives_a_coloured_map_and_the_viewer_shows_it(coloured_frames, tmp_path, capsys):
    from PIL import Image

    from mabdi.cli import main
    from mabdi.sources import write_tum

    frames, folder = coloured_frames
    recording = write_tum(frames, tmp_path / "tum")
    out = tmp_path / "run"
    assert main(["run", str(folder / "coloured_table.toml"), "--sequence", str(recording), "--out", str(out), "--quiet", "--no-eval"]) == 0
    assert "with colour" in capsys.readouterr().out
    colours = load_map(out / "world_mesh.vtp").vertex_layers[COLOUR_LAYER]
    assert len({tuple(c) for c in colours}) >= 5  # floor, table top, legs, cups
    png = tmp_path / "rgb.png"
    assert main(["view", str(out / "world_mesh.vtp"), "--colour", "rgb", "--out", str(png)]) == 0
    picture = np.asarray(Image.open(png).convert("RGB")).astype(int)
    greenish = (picture[..., 1] > picture[..., 0] + 30) & (picture[..., 1] > picture[..., 2] + 30)  # the floor, lit
    assert greenish.mean() > 0.05
    assert main(["view", str(out / "world_mesh.vtp"), "--colour", "rgb", "--out", str(png)]) == 0
    bare = tmp_path / "bare.vtp"
    mesh = read_mesh_file(out / "world_mesh.vtp")
    mesh.GetPointData().RemoveArray(COLOUR_LAYER)
    write_mesh_file(mesh, bare)
    assert main(["view", str(bare), "--colour", "rgb", "--out", str(png)]) == 2
    assert "has no vertex colours" in capsys.readouterr().err


def test_the_dashboard_and_rerun_show_the_colours(tmp_path):
    from mabdi.viz.dashboard import Dashboard

    config = load_run_config(coloured_table(tmp_path, frames=3))
    simulation = MappingRun(config)
    dashboard = Dashboard(simulation)
    try:
        for i in range(3):
            simulation.step(i)
        picture = dashboard.render(2).astype(int)
    finally:
        dashboard.close()
    top_left = picture[30 : picture.shape[0] // 2, : picture.shape[1] // 3]
    floor = (top_left[..., 1] > top_left[..., 0] + 25) & (top_left[..., 1] > top_left[..., 2] + 25)  # the green floor
    assert floor.mean() > 0.02, floor.mean()

    rr = pytest.importorskip("rerun")
    from mabdi.viz.rerun_log import RerunLogger

    simulation = MappingRun(config)
    logger = RerunLogger(tmp_path / "run.rrd", frames=1)
    record = simulation.step(0)
    logger.log_frame(simulation.loop, record)
    logger.close()
    from rerun.chunk import RrdReader

    columns = {}
    for chunk in RrdReader(tmp_path / "run.rrd").stream().to_chunks():
        columns.setdefault(chunk.entity_path.lstrip("/"), set()).update(chunk.to_record_batch().schema.names)
    assert any("vertex_colors" in c for name, cs in columns.items() if name.startswith("world/map/") for c in cs), columns
    assert "world/camera/rgb" in columns
    assert rr is not None


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_carries_colour_rgb8_and_bgr8(coloured_frames, tmp_path, storage):
    from types import SimpleNamespace

    from mabdi.sources import Rosbag2Sequence, write_rosbag2

    frames, _ = coloured_frames
    bag = Rosbag2Sequence(write_rosbag2(frames, tmp_path / "bag", storage=storage))
    assert bag.colour_topic == "/camera/color/image_raw" and "colour from /camera/color/image_raw" in bag.description
    for i in range(3):
        np.testing.assert_array_equal(bag.read(i).colour, frames.read(i).colour)
    rgb = frames.read(1).colour
    padded = np.zeros((240, 320 * 3 + 8), dtype=np.uint8)  # rows padded to a step of 968 bytes
    padded[:, : 320 * 3] = rgb[..., ::-1].reshape(240, -1)  # bgr8
    message = SimpleNamespace(height=240, width=320, step=320 * 3 + 8, encoding="bgr8", data=padded.ravel())
    np.testing.assert_array_equal(bag.decode_colour(message), rgb)
    small = SimpleNamespace(height=120, width=160, step=480, encoding="rgb8", data=np.zeros(120 * 480, np.uint8))
    with pytest.raises(Exception, match="registered to the depth"):
        bag.decode_colour(small)
    bag.close()
