"""A loop's "auto" settings are decided in one function, from the sensor, its noise model and its source."""

from __future__ import annotations

from mabdi.camera import Intrinsics
from mabdi.stages.classifier import ClassifierParameters
from mabdi.stages.refinement import RefinementParameters
from mabdi.stages.removal import RemovalParameters
from mabdi.loop.loop import resolve_settings
from mabdi.noise_calibration import NoiseCurve
from mabdi.sensor_noise import SensorNoise
from mabdi.spherical import SphericalGeometry


def _settings(geometry, noise, loses_returns=False, surface="quadtree", **given):
    return resolve_settings(
        geometry, SensorNoise.of(noise), loses_returns, given.pop("classifier", ClassifierParameters()), surface, None,
        given.pop("removal", None), given.pop("refinement", None), given.pop("registration", None),
    )  # fmt: skip


def test_a_structured_light_camera_refines_and_meshes_its_rim_on_the_map():
    settings = _settings(Intrinsics(), "structured_light")
    assert settings.refining and settings.removing
    assert settings.classifier.rim_on_map is True and settings.classifier.rim == 3  # the quad-tree's 3 x 3 block
    assert settings.removal.no_return_is_free is False  # structured light loses returns on real surfaces
    assert settings.registration.enabled


def test_independent_noise_does_not_refine_and_the_switches_decide_outright():
    settings = _settings(Intrinsics(), "zbuffer", surface="pixel_grid")
    assert not settings.refining and settings.classifier.rim_on_map is False and settings.classifier.rim == 1
    assert settings.removal.no_return_is_free is True
    assert _settings(Intrinsics(), "zbuffer", refinement=RefinementParameters(enabled=True)).refining
    assert not _settings(Intrinsics(), "zbuffer", removal=RemovalParameters(enabled=False)).removing
    black_box = _settings(Intrinsics(), "structured_light", classifier=ClassifierParameters(enabled=False))
    assert not black_box.removing and not black_box.refining


def test_a_lidar_recording_is_registered_not_refined_and_its_misses_are_no_free_space():
    settings = _settings(SphericalGeometry(), "range", loses_returns=True, refinement=RefinementParameters(enabled=True))
    assert not settings.refining  # a camera-only stage: off for a LiDAR
    assert settings.registration.enabled  # scans are fitted to the map (mabdi.stages.scan_registration)
    assert settings.removing and settings.removal.no_return_is_free is False


def test_the_run_folder_s_config_states_what_every_auto_became(tmp_path):
    """A run's config.toml ends with ``[resolved]``, the loop's settings (:func:`resolve_settings`) where they
    differ from the config; loading the file skips it and gives back the config the run was given."""
    import tomllib

    from conftest import SCENES
    from mabdi.cli import main
    from mabdi.config import load_run_config, settings_overrides, with_overrides

    out = tmp_path / "run"
    small = ["sensor.camera.width=80", "sensor.camera.height=60", "sensor.camera.fx=65.625", "sensor.camera.fy=65.625",
             "sensor.camera.cx=40.0", "sensor.camera.cy=30.0"]  # fmt: skip
    options = ["--frames", "2", "--noise", "structured_light", "--surface", "quadtree", "--no-eval", "--quiet"]
    assert main(["run", str(SCENES / "table.toml"), *options, "--out", str(out), *[a for s in small for a in ("--set", s)]]) == 0
    text = (out / "config.toml").read_text()
    assert '# [resolved] is written by the run and not read' in text
    resolved = tomllib.loads(text)["resolved"]
    assert resolved["removing"] is True and resolved["refining"] is True  # correlated noise: refined
    # "auto": the quad-tree's block, the map's depth, and nothing waits at the rim (a model of the simulator's)
    # and a look in front of the map is novel beyond k_sigma, refinement's gate being no wider, and meshed at once
    assert resolved["classifier"] == {"rim": 3, "rim_on_map": True, "outer_radius": 1.0, "front_k": 3.0, "front_frames": 1}
    # structured light loses returns on real surfaces: no free space where it has none, four frames to remove a face
    assert resolved["removal"] == {"no_return_is_free": False, "min_frames": 4}
    assert resolved["refinement"] == {"gate_k": 3.0}  # "auto": a model of the simulator's, not a learnt one
    assert "registration" not in resolved  # as the config says
    config = load_run_config(out / "config.toml")
    given = with_overrides(
        load_run_config(SCENES / "table.toml"),
        {"run.frames": 2, "sensor.noise": "structured_light", "surface.method": "quadtree", "output.dir": str(out),
         **settings_overrides(small)},
    )  # fmt: skip
    assert config == given and config.classifier.rim == "auto"  # the file's "auto" stays: resolved again when run
    assert config.sensor.camera.width == 80 and "[sensor.camera]\nwidth = 80" in text


def test_a_real_cameras_look_in_front_of_the_map_within_refinements_gate_refines_it():
    """front_k "auto": refinement's gate where the loop refines and that is wider than k_sigma (a real camera's
    learnt noise: 5), else k_sigma; a LiDAR (no refinement) and the simulator's models keep k_sigma."""
    learnt = SensorNoise("auto", calibration=NoiseCurve(0.0, 1.4e-3, 2.0))  # correlated: refined
    settings = _settings(Intrinsics(), learnt)
    assert settings.refining and settings.refinement.gate_k == 5.0 and settings.classifier.front_k == 5.0
    assert _settings(Intrinsics(), "structured_light").classifier.front_k == 3.0
    assert _settings(Intrinsics(), "zbuffer").classifier.front_k == 3.0  # not refined
    assert _settings(SphericalGeometry(), "range", loses_returns=True).classifier.front_k == 3.0
    stated = _settings(Intrinsics(), learnt, classifier=ClassifierParameters(front_k=4.0))
    assert stated.classifier.front_k == 4.0  # the config's word stands
