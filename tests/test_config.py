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
    path = write(tmp_path, '[[scene.objects]]\ntype = "box"\nsize = [1, 1, 1]\ncolour = "red"\n')
    with pytest.raises(ConfigError, match=r"unknown key 'colour' in \[scene.objects\[0\]\]"):
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
