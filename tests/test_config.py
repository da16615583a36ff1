"""Run configs: strict TOML loading, clear errors, round trip of the resolved config."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest

from mabdi.config import RunConfig, dump_toml, load_run_config, run_config_from_dict
from mabdi.errors import ConfigError


@pytest.mark.parametrize("name", ["table", "bunnies", "bunnies_dynamic", "door", "street", "street_deskewed"])
def test_scenes_load_and_round_trip(scenes_dir, name):
    config = load_run_config(scenes_dir / f"{name}.toml")
    assert config.run.name == name
    again = run_config_from_dict(tomllib.loads(dump_toml(config)))
    assert again == config


def test_seed_runs_table_ii(scenes_dir):
    table = load_run_config(scenes_dir / "table.toml")
    bunnies = load_run_config(scenes_dir / "bunnies.toml")
    dynamic = load_run_config(scenes_dir / "bunnies_dynamic.toml")
    assert (table.run.frames, table.sensor.noise) == (30, "none")
    assert (bunnies.run.frames, bunnies.sensor.noise) == (50, "zbuffer")
    assert (dynamic.run.frames, dynamic.sensor.noise) == (50, "zbuffer")
    assert not any(o.appear_at is not None for o in bunnies.scene.objects)
    assert [o.appear_at for o in dynamic.scene.objects if o.appear_at is not None] == [0.5]


def test_empty_config_is_all_defaults(tmp_path):
    path = tmp_path / "empty.toml"
    path.write_text("")
    assert load_run_config(path) == RunConfig()


def write(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


def test_unknown_key_names_key_and_file(tmp_path):
    path = write(tmp_path, '[sensor]\nnosie = "kinect"\n')
    with pytest.raises(ConfigError) as info:
        load_run_config(path)
    assert "nosie" in str(info.value) and str(path) in str(info.value)


def test_unknown_key_in_an_object(tmp_path):
    path = write(tmp_path, '[[scene.objects]]\ntype = "box"\nsize = [1, 1, 1]\nmaterial = "wood"\n')
    with pytest.raises(ConfigError, match=r"unknown key 'material' in \[scene.objects\[0\]\]"):
        load_run_config(path)
    path = write(tmp_path, '[[scene.objects]]\ntype = "box"\nsize = [1, 1, 1]\ncolour = "red"\n')  # [r, g, b]
    with pytest.raises(ConfigError, match=r"objects\[0\]\.colour' must be list"):
        load_run_config(path)


def test_unknown_section(tmp_path):
    with pytest.raises(ConfigError, match="unknown key 'sensr'"):
        load_run_config(write(tmp_path, "[sensr]\nnoise = 'none'\n"))


@pytest.mark.parametrize(
    "text,message",
    [
        ("[run]\nframes = 'ten'\n", "run.frames' must be an integer"),
        ("[run]\nframes = 0\n", "run.frames' must be at least 1"),
        ("[sensor]\nnoise = 'gauss'\n", "sensor.noise' = 'gauss' is not one of"),
        ("[sensor.camera]\nfx = -1.0\n", "[sensor.camera] intrinsics: focal length fx"),
        ("[sensor]\nbackend = 'x11'\n", "sensor.backend"),
        ("[path]\ncenter = [0, 0, 0]\n", "path.center' must have 2 numbers"),
        ("[[scene.objects]]\ntype = 'cone'\n", "scene.objects[0].type' = 'cone'"),
        ("[[scene.objects]]\ntype = 'box'\nsize = [1, 1]\n", "scene.objects[0].size' must have 3"),
        ("[[scene.objects]]\ntype = 'cylinder'\nradius = 0.1\n", "height' is required"),
        ("[[scene.objects]]\ntype = 'mesh'\n", "mesh' is required"),
        ("[[scene.objects]]\ntype = 'sphere'\nappear_at = 1.5\n", "fraction of the run"),
        ("[[scene.objects]]\ntype = 'sphere'\nup = 'w'\n", "up' = 'w'"),
        ("[[scene.objects]]\ntype = 'box'\nsize = [1, 1, 1]\nrotation = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]\n", "not a rotation"),
        ("[run\n", "not valid TOML"),
    ],
)
def test_bad_values_are_named(tmp_path, text, message):
    with pytest.raises(ConfigError) as info:
        load_run_config(write(tmp_path, text))
    assert message in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_run_config(tmp_path / "nope.toml")


# --- one home for every parameter: sections are the filters' own parameter dataclasses -------------


def test_sections_are_the_filters_parameter_classes(tmp_path):
    from mabdi.stages.classifier import ClassifierParameters
    from mabdi.surfaces.pixel_grid import PixelGridParameters
    from mabdi.surfaces.quadtree import QuadTreeParameters

    config = load_run_config(write(tmp_path, '[classifier]\ntau_min = 0.02\n[surface]\nmethod = "quadtree"\n[surface.quadtree]\nn_t = 0.05\n'))
    assert isinstance(config.classifier, ClassifierParameters) and config.classifier.tau_min == 0.02
    assert config.surface.parameters_of() == QuadTreeParameters(n_t=0.05)
    assert config.surface.parameters_of("pixel_grid") == PixelGridParameters()  # defaults from the filter's class
    again = run_config_from_dict(tomllib.loads(dump_toml(config)))
    assert again == config and again.surface.parameters_of().n_t == 0.05


@pytest.mark.parametrize(
    "text,message",
    [
        ("[classifier]\ntau_min = 0\n", "[classifier] tau_min must be > 0"),
        ("[classifier]\nmin_width = 0\n", "min_width must be >= 1"),
        ("[surface.quadtree]\nd_t = -1\n", "[surface.quadtree] need n_t >= 0 and d_t > 0"),
        ("[surface.voxel_planes]\nwindow = 9\n", "[surface.voxel_planes] window must be an integer from 1 to 6"),
        ("[surface.pixel_grid]\nmax_jump = 0\n", "[surface.pixel_grid] max_jump must be > 0"),
        ("[surface]\nn_t = 0.1\n", "n_t is a parameter of quadtree: put it in [surface.quadtree]"),
        ("[surface.quadtree]\nn_tt = 0.1\n", "unknown key 'n_tt' in [surface.quadtree]"),
        ("[surface.quadtree]\ntriangles = false\n", "unknown key 'triangles'"),  # not a config key: the loop triangulates
        ("[surface]\nmethod = 'marching_cubes'\n", "surface.method' = 'marching_cubes' is not one of: pixel_grid, quadtree, voxel_planes"),
        ("[sensor.camera]\ncx = 1000.0\n", "principal point cx = 1000.0 lies outside the image"),
        ("[run]\nname = '../../escape'\n", "run.name' = '../../escape' must be a plain folder name"),
        ("[run]\nframes = 10\n[[scene.objects]]\ntype = 'sphere'\nappear_at = 0.8\ndisappear_at = 0.2\n", "disappears"),
        ("[run]\nframes = 10\n[[scene.objects]]\ntype = 'sphere'\nappear_at = 12\n", "after the run's last frame 9"),
        # a sensor sub-table's unknown or bad key, named with its table
        ("[sensor.camera]\nfxx = 1.0\n", "unknown key 'fxx' in [sensor.camera] (known keys: width, height, fx"),
        ("[sensor.lidar]\nfx = 500.0\n", "unknown key 'fx' in [sensor.lidar]"),
        ("[sensor.lidar]\nrange_sigma = 0.01\n", "range_sigma is a key of [sensor.noise_parameters]"),
        ("[sensor.noise_parameters]\nbeams = 8\n", "beams is a key of [sensor.lidar]"),
        ("[sensor.pose_noise]\nfx = 8.0\n", "fx is a key of [sensor.camera]"),
        ("[sensor]\nbeamz = 8\n", "unknown key 'beamz' in [sensor]"),
        ("[sensor.camera]\nwidth = 'wide'\n", "key 'sensor.camera.width' must be an integer"),
        ("[sensor.noise_parameters]\nbaseline = 0.0\n", "[sensor.noise_parameters] noise parameter baseline must be > 0"),
        ("[sensor]\nkind = 'lidar'\n[sensor.lidar]\nrange_min = 9.0\nrange_max = 2.0\n", "[sensor.lidar] lidar: need 0 < range_min"),
        ("[sensor.lidar]\nsweep = 'deskewed'\n", "key 'sensor.lidar.sweep' is a LiDAR's"),
    ],
)
def test_parameter_checks_name_file_section_and_key(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_run_config(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_set_value_checks_and_names_the_key(tmp_path):
    from mabdi.config import set_value

    config = load_run_config(write(tmp_path, ""))
    set_value(config, "surface.quadtree.n_t", 0.25)
    set_value(config, "classifier.enabled", False)
    set_value(config, "run.frames", 7)
    assert config.surface.parameters_of("quadtree").n_t == 0.25
    assert config.classifier.enabled is False and config.run.frames == 7
    with pytest.raises(ConfigError, match="key 'classifier.tau_min': tau_min must be > 0"):
        set_value(config, "classifier.tau_min", -1.0)
    with pytest.raises(ConfigError, match="key 'classifier.tau': unknown key 'tau' in \\[classifier\\]"):
        set_value(config, "classifier.tau", 1.0)
    with pytest.raises(ConfigError, match="must be true or false"):
        set_value(config, "classifier.enabled", "yes")


def test_a_surface_filter_registered_from_outside_runs_by_name(tmp_path):
    """A new surface is one class and one register call: the config section and the loop follow."""
    import dataclasses

    import numpy as np
    from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData

    import mabdi
    from mabdi.depth import depth_array, image_pose
    from mabdi.surfaces.registry import surface_filter_names, unregister_surface_filter
    from mabdi.polydata import triangles_polydata

    @dataclasses.dataclass(frozen=True)
    class CentreTriangleParameters:
        size: float = 0.1

        def __post_init__(self):
            if self.size <= 0:
                raise ConfigError(f"size must be > 0, got {self.size}")

    class FilterCentreTriangle(mabdi.MabdiAlgorithm):
        """One triangle at the centre pixel's point, if it has a return."""

        def __init__(self, parameters):
            super().__init__(nInputPorts=1, inputType="vtkImageData", nOutputPorts=1, outputType="vtkPolyData")
            self.parameters = parameters

        def RequestData(self, request, inInfo, outInfo):  # noqa: N802
            image = vtkImageData.GetData(inInfo[0])
            depth = depth_array(image)
            z = depth[depth.shape[0] // 2, depth.shape[1] // 2]
            output = vtkPolyData.GetData(outInfo)
            if np.isfinite(z):
                pose = image_pose(image)
                centre = pose[:3, :3] @ np.array([0.0, 0.0, z]) + pose[:3, 3]
                s = self.parameters.size
                points = centre + np.array([[0, 0, 0], [s, 0, 0], [0, s, 0]])
                output.ShallowCopy(triangles_polydata(points, np.array([[0, 1, 2]])))
            output.GetFieldData().ShallowCopy(image.GetFieldData())
            return 1

        def reset(self):  # what a filter has is not probed: only declared capabilities are used
            raise AssertionError("the loop called reset() of a filter that does not declare keeps_state")

        def state(self):
            raise AssertionError("the loop called state() of a filter that does not declare keeps_state")

    mabdi.register_surface_filter(
        "centre_triangle", CentreTriangleParameters, FilterCentreTriangle, "one test triangle"
    )
    try:
        assert "centre_triangle" in surface_filter_names()
        path = write(
            tmp_path,
            '[run]\nframes = 3\n[classifier]\nenabled = false\n[surface]\nmethod = "centre_triangle"\n'
            '[surface.centre_triangle]\nsize = 0.2\n[[scene.objects]]\ntype = "box"\nsize = [1.0, 1.0, 2.0]\n',
        )
        config = load_run_config(path)
        assert config.surface.parameters_of().size == 0.2
        simulation = mabdi.MappingRun(config)
        result = simulation.run()
        assert result.mesh.GetNumberOfCells() == 3  # one triangle a frame
        simulation.loop.reset()
        assert "surface" not in simulation.loop.state()
        with pytest.raises(ConfigError, match=r"\[surface.centre_triangle\] size must be > 0"):
            load_run_config(write(tmp_path, "[surface.centre_triangle]\nsize = -1.0\n"))
    finally:
        unregister_surface_filter("centre_triangle")
    with pytest.raises(ConfigError, match="unknown key 'centre_triangle'"):
        load_run_config(path)


def test_removal_and_refinement_sections_reach_the_loop(tmp_path):
    """[removal] and [refinement] are the filters' own parameter classes; their values reach the loop."""
    import mabdi
    from mabdi.sources.frames import FrameList
    from mabdi.depth import DepthFrame
    from mabdi.camera import Intrinsics
    import numpy as np

    path = tmp_path / "run.toml"
    path.write_text("[removal]\nno_return_is_free = false\nedge_margin = 3\n[refinement]\nstride = 2\n")
    config = load_run_config(path)
    assert config.removal.edge_margin == 3 and not config.removal.no_return_is_free
    small = Intrinsics(fx=50, fy=50, cx=20, cy=15, width=40, height=30)
    frames = FrameList([DepthFrame(np.full(small.shape, 2.0, np.float32), small, np.eye(4), 0)])
    loop = mabdi.MabdiLoop.from_config(config, frames)
    # the section's values, with min_frames "auto" resolved for the sensor (frames that return every surface: 2)
    assert loop.removal_parameters == dataclasses.replace(config.removal, min_frames=2)
    # and gate_k "auto" resolved for the noise model (a model of the simulator's: 3)
    assert loop.refinement.parameters == dataclasses.replace(config.refinement, gate_k=3.0)
    assert "edge_margin = 3" in dump_toml(config)
    path.write_text("[removal]\nedge_margin = -1\n")
    with pytest.raises(ConfigError, match=r"run.toml.*\[removal\].*0 <= edge_margin"):
        load_run_config(path)


def test_the_stages_switches_moved_to_their_sections_and_old_configs_keep_loading(tmp_path):
    """``[removal] enabled`` and ``[refinement] enabled`` are the stages' switches; the old names
    (``[classifier] removal`` / ``refinement``, in older configs and run folders) load as the new keys, set
    one by one too; both given and disagreeing is an error naming both."""
    from mabdi.config import load_run_config, set_value

    path = tmp_path / "old.toml"
    path.write_text('[classifier]\nremoval = false\nrefinement = true\n')
    config = load_run_config(path)
    assert config.removal.enabled is False and config.refinement.enabled is True
    assert "removal.enabled" in config.stated and "classifier.removal" not in config.stated
    assert "[removal]\nenabled = false" in dump_toml(config)
    assert "removal = " not in dump_toml(config).split("[classifier]")[1].split("[")[0]
    set_value(config, "classifier.removal", True)
    assert config.removal.enabled is True
    path.write_text("[classifier]\nremoval = false\n[removal]\nenabled = true\n")
    with pytest.raises(ConfigError, match=r"classifier.removal = False and removal.enabled = True disagree"):
        load_run_config(path)
    path.write_text("[classifier]\nremoval = false\n[removal]\nenabled = false\n")
    assert load_run_config(path).removal.enabled is False


# --- [sensor] split by what it describes: camera, lidar, noise_parameters, pose_noise ----------------------

#: One sensor in the flat keys of older configs, and the same in the sub-tables.
OLD_SENSOR = """[sensor]
kind = "lidar"
noise = "range"
fx = 400.0
far = 6.0
beams = 2
beam_elevations = [10.0, -20.0]
range_sigma = 0.01
kinect_coefficient = 0.002
mount_tilt = 5.0
"""
NEW_SENSOR = """[sensor]
kind = "lidar"
noise = "range"
[sensor.camera]
fx = 400.0
far = 6.0
[sensor.lidar]
beams = 2
beam_elevations = [10.0, -20.0]
mount_tilt = 5.0
[sensor.noise_parameters]
range_sigma = 0.01
kinect_coefficient = 0.002
"""


def test_the_sensor_section_has_a_sub_table_for_each_thing_it_describes(tmp_path):
    from mabdi.config import CameraConfig, LidarConfig, NoiseParameters

    config = load_run_config(write(tmp_path, NEW_SENSOR.replace("beam_elevations = [10.0, -20.0]\n", "")))
    sensor = config.sensor
    assert isinstance(sensor.camera, CameraConfig) and (sensor.camera.fx, sensor.camera.far) == (400.0, 6.0)
    assert isinstance(sensor.lidar, LidarConfig) and sensor.lidar.beams == 2 and sensor.lidar.mount_tilt == 5.0
    assert isinstance(sensor.noise_parameters, NoiseParameters) and sensor.noise_parameters.range_sigma == 0.01
    assert sensor.geometry().beams == 2 and sensor.sensor_noise().range_sigma == 0.01
    assert sensor.sensor_noise().focal == 400.0  # the structured-light disparity's focal length is the camera's fx
    assert sensor.sweep_settings().mount_tilt == 5.0
    assert {"sensor.camera.fx", "sensor.lidar.beams", "sensor.noise_parameters.range_sigma"} <= config.stated
    assert CameraConfig().intrinsics() == RunConfig().sensor.geometry()  # the defaults are Intrinsics' own


def test_old_flat_sensor_keys_load_as_their_new_keys_from_files_and_set(tmp_path):
    """Older configs (and older run folders' config.toml) wrote every [sensor] key flat: they load as the
    sub-tables' keys, and ``--set sensor.fx=...`` sets ``sensor.camera.fx``."""
    from mabdi.config import settings_overrides, with_overrides

    old = load_run_config(write(tmp_path, OLD_SENSOR))
    assert old == load_run_config(write(tmp_path, NEW_SENSOR))
    assert old.sensor.camera.fx == 400.0 and old.sensor.lidar.beam_elevations == [10.0, -20.0]
    assert old.sensor.noise_parameters.range_sigma == 0.01 and old.sensor.lidar.mount_tilt == 5.0
    assert "sensor.camera.fx" in old.stated and "sensor.fx" not in old.stated
    text = dump_toml(old)
    assert "[sensor.camera]\nfx = 400.0\nfar = 6.0\n" in text  # the other kind's table: only its keys set
    assert "fx" not in text.split("[sensor]")[1].split("[sensor.")[0]  # nothing flat left under [sensor]
    overrides = settings_overrides(["sensor.fx=500", "sensor.columns=256", "sensor.range_sigma=0.03", "sensor.sweep_time=0.05"])
    changed = with_overrides(old, overrides, where="command line")
    assert (changed.sensor.camera.fx, changed.sensor.lidar.columns) == (500.0, 256)
    assert changed.sensor.noise_parameters.range_sigma == 0.03 and changed.sensor.lidar.sweep_time == 0.05
    assert {"sensor.camera.fx", "sensor.lidar.columns"} <= changed.stated and "sensor.fx" not in changed.stated
    with pytest.raises(ConfigError, match="key 'sensor.fx'.*focal length fx must be positive"):
        with_overrides(old, {"sensor.fx": -1.0}, where="command line")


def test_an_old_sensor_key_and_its_new_key_disagreeing_is_an_error_naming_both(tmp_path):
    path = write(tmp_path, "[sensor]\nfx = 500.0\n[sensor.camera]\nfx = 520.0\n")
    with pytest.raises(ConfigError) as info:
        load_run_config(path)
    assert "sensor.fx = 500.0 and sensor.camera.fx = 520.0 disagree" in str(info.value) and str(path) in str(info.value)
    path = write(tmp_path, "[sensor]\nrange_sigma = 0.01\n[sensor.noise_parameters]\nrange_sigma = 0.02\n")
    with pytest.raises(ConfigError, match="sensor.range_sigma = 0.01 and sensor.noise_parameters.range_sigma = 0.02"):
        load_run_config(path)
    assert load_run_config(write(tmp_path, "[sensor]\nfx = 500\n[sensor.camera]\nfx = 500.0\n")).sensor.camera.fx == 500.0


def test_the_sensor_s_new_layout_round_trips(tmp_path):
    """Every sub-table set away from its defaults, the other kind's table too: dump and load give it back."""
    from mabdi.config import with_overrides

    settings = {
        "sensor.noise": "structured_light", "sensor.fill_pixel_holes": False,
        "sensor.camera.width": 320, "sensor.camera.cx": 160.0, "sensor.camera.fx": 300.0, "sensor.camera.near": 0.3,
        "sensor.lidar.beams": 4, "sensor.lidar.beam_elevations": [3.0, 1.0, -1.0, -3.0], "sensor.lidar.range_max": 30.0,
        "sensor.noise_parameters.baseline": 0.05, "sensor.noise_parameters.edge_dropout": 3,
        "sensor.pose_noise.jitter_rotation": 0.2,
    }  # fmt: skip
    config = with_overrides(RunConfig(), settings)
    text = dump_toml(config)
    again = run_config_from_dict(tomllib.loads(text))
    assert again == config and again.sensor.lidar.beam_elevations == [3.0, 1.0, -1.0, -3.0]
    for table in ("[sensor.camera]", "[sensor.lidar]", "[sensor.noise_parameters]", "[sensor.pose_noise]"):
        assert table in text
    assert "[sensor.lidar]\nbeams = 4\nrange_max = 30.0\nbeam_elevations" in text and "columns" not in text  # set keys only
    assert "[sensor.lidar]" not in dump_toml(RunConfig())  # a camera's config writes no LiDAR table
    lidar = with_overrides(RunConfig(), {"sensor.kind": "lidar", "sensor.noise": "range"})
    assert "[sensor.camera]" not in dump_toml(lidar) and run_config_from_dict(tomllib.loads(dump_toml(lidar))) == lidar


def test_an_unknown_sensor_key_set_from_the_command_line_is_named():
    from mabdi.config import with_overrides

    with pytest.raises(ConfigError, match=r"key 'sensor.camera.fxx': unknown key 'fxx' in \[sensor.camera\]"):
        with_overrides(RunConfig(), {"sensor.camera.fxx": 1.0}, where="command line")


def test_a_run_s_resolved_table_is_skipped_when_its_config_is_loaded(tmp_path):
    """``[resolved]`` (what a run's "auto" settings became) is a record: loading skips it, ``--set`` refuses it."""
    from mabdi.config import with_overrides

    text = dump_toml(RunConfig()) + "\n[resolved]\nrefining = true\n\n[resolved.classifier]\nrim = 3\n"
    config = load_run_config(write(tmp_path, text))
    assert config == RunConfig() and not any(key.startswith("resolved") for key in config.stated)
    with pytest.raises(ConfigError, match=r"key 'resolved.refining': \[resolved\] is what a run's \"auto\" settings became"):
        with_overrides(config, {"resolved.refining": False}, where="command line")


#: The [sensor] section of scenes/street_deskewed.toml as run folders' config.toml held it before the split.
FORMER_STREET_SENSOR = """[sensor]
kind = "lidar"
width = 640
height = 480
fx = 525.0
fy = 525.0
cx = 320.0
cy = 240.0
near = 0.5
far = 4.0
noise = "range"
zbuffer_sigma = 0.001
kinect_coefficient = 0.001425
baseline = 0.075
disparity_sigma = 0.05
disparity_step = 0.125
correlation_length = 2.5
edge_dropout = 2
edge_jump = 0.05
max_incidence = 75.0
beams = 128
columns = 1024
fov_up = 45.0
fov_down = -45.0
range_min = 1.0
range_max = 60.0
beam_elevations = []
range_sigma = 0.005
backend = "egl"
fill_pixel_holes = "auto"
sweep = "deskewed"
mount_tilt = 12.0

[sensor.pose_noise]
jitter_translation = 0.0
jitter_rotation = 0.0
drift_translation = 0.0
drift_rotation = 0.0
"""


def test_an_older_run_folder_s_config_toml_still_loads(scenes_dir, tmp_path):
    """A run folder's config.toml written before [sensor] was split (every key flat) loads as the same config."""
    scene = load_run_config(scenes_dir / "street_deskewed.toml")
    text = dump_toml(scene)
    start, end = text.index("[sensor]\n"), text.index("[path]\n")
    path = write(tmp_path, text[:start] + FORMER_STREET_SENSOR + "\n" + text[end:])
    assert "\nbeams = 128\n" in path.read_text() and "[sensor.lidar]" not in path.read_text()
    assert load_run_config(path) == scene
