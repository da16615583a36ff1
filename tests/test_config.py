"""Run configs: strict TOML loading, clear errors, round trip of the resolved config."""

from __future__ import annotations

import tomllib

import pytest

from mabdi.config import RunConfig, dump_toml, load_run_config, run_config_from_dict
from mabdi.errors import ConfigError


@pytest.mark.parametrize("name", ["table", "bunnies", "bunnies_dynamic"])
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
        ("[sensor]\nfx = -1.0\n", "focal length fx"),
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
    from mabdi.filters import ClassifierParameters, PixelGridParameters, QuadTreeParameters

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
        ("[sensor]\ncx = 1000.0\n", "principal point cx = 1000.0 lies outside the image"),
        ("[run]\nname = '../../escape'\n", "run.name' = '../../escape' must be a plain folder name"),
        ("[run]\nframes = 10\n[[scene.objects]]\ntype = 'sphere'\nappear_at = 0.8\ndisappear_at = 0.2\n", "disappears"),
        ("[run]\nframes = 10\n[[scene.objects]]\ntype = 'sphere'\nappear_at = 12\n", "after the run's last frame 9"),
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
    from mabdi.filters.registry import surface_filter_names, unregister_surface_filter
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
    assert loop.removal_parameters == config.removal and loop.refinement.parameters == config.refinement
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
