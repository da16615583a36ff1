"""The structured-light noise model: disparity noise (correlated, quantised), sigma(z) ~ z^2, no returns at
depth edges and grazing incidence, reproducibility, config keys.

Tolerances: the noise is correlated over ~2.5 px, so a 640 x 480 image holds a few thousand independent
samples and a sample standard deviation is good to ~1-2%; the bounds are several times that.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from conftest import merged, plane_mesh
from mabdi.camera import Intrinsics, depth_to_zbuffer
from mabdi.config import load_run_config
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.render.depth_image import FilterDepthImage
from mabdi.sensor_noise import SensorNoise, correlated_field, noise_rng

K = Intrinsics()
SL = SensorNoise("structured_light", focal=K.fx)  # as a [sensor] section builds it: focal = fx


def render(mesh, noise, pose=None, intrinsics=K, seed=3, frame=0) -> np.ndarray:
    sensor = FilterDepthImage(intrinsics=intrinsics, noise=noise, seed=seed)
    sensor.SetInputDataObject(mesh)
    sensor.pose = np.eye(4) if pose is None else pose
    sensor.frame = frame
    sensor.Update()
    depth = DepthFrame.from_image(sensor.GetOutput()).depth
    sensor.renderer.close()
    return depth


def tilted_normal(degrees: float, axis: str = "x") -> np.ndarray:
    """The normal of a plane facing the camera, turned by ``degrees`` about the camera's x or y axis."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([0.0, s, -c]) if axis == "x" else np.array([s, 0.0, -c])


def errors_on_plane(z: float, noise: SensorNoise, tilt: float = 20.0, seed: int = 3):
    """(true depth, measured - true) where both have a return, for a plane through (0, 0, z) tilted ``tilt``
    degrees (so its disparity sweeps many quantisation steps)."""
    mesh = plane_mesh([0, 0, z], tilted_normal(tilt))
    true = render(mesh, "none")
    measured = render(mesh, noise, seed=seed)
    both = np.isfinite(true) & np.isfinite(measured)
    return true, np.where(both, measured - true, np.nan)


def test_sigma_is_z_squared_times_the_effective_disparity_error():
    z = np.array([1.0, 2.0, 3.0])
    effective = np.sqrt(0.05**2 + 0.125**2 / 12)
    np.testing.assert_allclose(SL.sigma(z, K.near, K.far), z**2 * effective / (K.fx * 0.075))
    assert SL.disparity_sigma_effective == pytest.approx(effective)
    # the defaults reproduce Khoshelham & Elberink's 1.425e-3 z^2 at the Kinect's f = 580 px
    assert SensorNoise("structured_light").sigma(1.0, K.near, K.far) == pytest.approx(1.425e-3, rel=0.01)
    assert SL.sigma(np.float32(2.0), K.near, K.far).dtype == np.float32


@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_error_std_matches_sigma_and_grows_with_z_squared(z):
    """The error divided by sigma(true z) has std 1 within 8% and mean 0; more than 99% of the plane returns."""
    true, error = errors_on_plane(z, SL)
    valid = np.isfinite(error)
    assert valid.sum() > 0.99 * np.isfinite(true).sum()
    normalised = error[valid] / SL.sigma(true[valid].astype(np.float64), K.near, K.far)
    assert normalised.std() == pytest.approx(1.0, rel=0.08)
    assert abs(normalised.mean()) < 0.1


def test_error_grows_as_z_squared_between_distances():
    """On the same tilted plane moved from 1 to 3 m, the error's std grows ninefold (within 10%)."""
    stds = {z: np.nanstd(errors_on_plane(z, SL)[1]) for z in (1.0, 3.0)}
    assert stds[3.0] / stds[1.0] == pytest.approx(9.0, rel=0.10)


def test_errors_are_spatially_correlated_unless_white():
    def neighbour_correlation(noise):
        _, error = errors_on_plane(2.0, noise)
        a, b = error[:, :-1].ravel(), error[:, 1:].ravel()
        both = np.isfinite(a) & np.isfinite(b)
        return np.corrcoef(a[both], b[both])[0, 1]

    assert neighbour_correlation(SL) > 0.5
    assert neighbour_correlation(SensorNoise("structured_light", focal=K.fx, correlation_length=4.0)) > 0.7
    assert abs(neighbour_correlation(SensorNoise("structured_light", focal=K.fx, correlation_length=0.0))) < 0.05


@pytest.mark.parametrize("length", [0.0, 2.5])
def test_the_noise_left_in_a_mean_of_pixels_is_what_the_correlated_field_leaves(length):
    """SensorNoise.mean_share against the field itself: the standard deviation of the mean of a 2 x 2 block
    over the field's, 1 / 2 for white noise and near 1 for a correlation over 2.5 pixels; one pixel keeps all."""
    noise = SensorNoise("structured_light", focal=K.fx, correlation_length=length)
    field = np.stack([correlated_field((480, 640), length, noise_rng(3, i)) for i in range(4)]).astype(np.float64)
    block = (field[:, :-1:2, :-1:2] + field[:, 1::2, :-1:2] + field[:, :-1:2, 1::2] + field[:, 1::2, 1::2]) / 4
    share = noise.mean_share([(0, 0), (0, 1), (1, 0), (1, 1)])
    assert block.std() / field.std() == pytest.approx(share, rel=0.06)
    assert noise.mean_share([(0, 0)]) == 1.0
    assert (share == pytest.approx(0.5)) if length == 0 else (0.9 < share < 1.0)
    assert noise.noisy and not SensorNoise("none").noisy


@pytest.mark.parametrize("length", [0.0, 1.0, 2.5, 4.0])
def test_correlated_field_has_unit_variance(length):
    field = np.stack([correlated_field((480, 640), length, noise_rng(1, i)) for i in range(8)])
    assert field.shape == (8, 480, 640) and field.dtype == np.float32
    assert field.var() == pytest.approx(1.0, rel=0.04)
    # every pixel of the interpolated field too, not only the coarse grid's
    assert field[:, 1::2, 1::2].var() == pytest.approx(1.0, rel=0.05)


def test_depths_lie_on_the_disparity_lattice():
    measured = render(plane_mesh([0, 0, 2.0], tilted_normal(20.0)), SL)
    z = measured[np.isfinite(measured)].astype(np.float64)
    steps = SL.focal * SL.baseline / (z * SL.disparity_step)
    assert np.abs(steps - np.round(steps)).max() < 1e-3


def true_incidence(intrinsics: Intrinsics, normal) -> np.ndarray:
    rays = intrinsics.rays()
    cosine = np.abs(rays @ normal) / np.linalg.norm(rays, axis=2)
    return np.degrees(np.arccos(cosine))


def test_no_returns_at_grazing_incidence_and_full_returns_head_on():
    narrow = Intrinsics(fx=525.0, fy=525.0, cx=32.0, cy=24.0, width=64, height=48)  # +-3.5 degrees of view
    grazing = render(plane_mesh([0, 0, 2.0], tilted_normal(80.0, "y")), SL, intrinsics=narrow)
    assert np.isfinite(render(plane_mesh([0, 0, 2.0], tilted_normal(80.0, "y")), "none", intrinsics=narrow)).all()
    assert not np.isfinite(grazing).any()  # every pixel beyond 75 degrees: no return
    steep = render(plane_mesh([0, 0, 2.0], tilted_normal(70.0, "y")), SL, intrinsics=narrow)
    assert np.isfinite(steep).mean() > 0.99
    head_on = render(plane_mesh([0, 0, 2.0], [0, 0, -1]), SL)
    assert np.isfinite(head_on).mean() > 0.99


def test_grazing_limit_follows_each_pixels_own_ray():
    """A plane turned 55 degrees, 1 m ahead: across the 63-degree wide view its incidence runs from ~25 to
    ~85 degrees (the far side beyond 4 m)."""
    normal = tilted_normal(55.0, "y")
    mesh = plane_mesh([0, 0, 1.0], normal)
    true = render(mesh, "none")
    measured = render(mesh, SL)
    angle = true_incidence(K, normal)
    returns = np.isfinite(true) & ~binary_dilation(~np.isfinite(true), iterations=3)
    beyond, within = returns & (angle > 76.0), returns & (angle < 74.0)
    assert beyond.sum() > 1000 and within.sum() > 1000
    assert not np.isfinite(measured[beyond]).any()
    assert np.isfinite(measured[within]).mean() > 0.99


def test_pixels_beside_a_depth_step_are_dropped():
    """A 0.6 m square at 1.5 m in front of a wall at 3 m: the pixels within edge_dropout (2) of its outline
    have no return, those 4 or more pixels away keep theirs."""
    mesh = merged(plane_mesh([0, 0, 1.5], [0, 0, -1], size=0.6), plane_mesh([0, 0, 3.0], [0, 0, -1]))
    true = render(mesh, "none")
    assert np.isfinite(true).all()
    jump = np.zeros(true.shape, dtype=bool)
    step = np.abs(np.diff(true, axis=1)) > 0.05 * np.fmin(true[:, 1:], true[:, :-1])
    jump[:, 1:] |= step
    jump[:, :-1] |= step
    step = np.abs(np.diff(true, axis=0)) > 0.05 * np.fmin(true[1:], true[:-1])
    jump[1:] |= step
    jump[:-1] |= step
    assert jump.sum() > 400  # the square's outline
    near = binary_dilation(jump, np.ones((3, 3), dtype=bool))  # distance <= 2 pixels (square)
    far = ~binary_dilation(jump, np.ones((3, 3), dtype=bool), iterations=3)
    measured = render(mesh, SL)
    assert not np.isfinite(measured[near]).any()
    assert np.isfinite(measured[far]).mean() > 0.999
    kept = render(mesh, SensorNoise("structured_light", focal=K.fx, edge_dropout=0, max_incidence=90.0))
    assert np.isfinite(kept).all()


def test_noise_is_reproducible_per_seed_and_frame():
    mesh = plane_mesh([0, 0, 2.0], tilted_normal(20.0))
    first = render(mesh, SL, seed=4, frame=2)
    np.testing.assert_array_equal(first, render(mesh, SL, seed=4, frame=2))
    assert not np.array_equal(first, render(mesh, SL, seed=4, frame=3), equal_nan=True)
    assert not np.array_equal(first, render(mesh, SL, seed=5, frame=2), equal_nan=True)


def test_the_model_needs_the_intrinsics():
    zbuffer = depth_to_zbuffer(np.full(K.shape, 2.0), K.near, K.far).astype(np.float32)
    with pytest.raises(ValueError, match="intrinsics"):
        SL.depth_from_zbuffer(zbuffer, K.near, K.far, noise_rng(0, 0))
    depth = SL.depth_from_zbuffer(zbuffer, K.near, K.far, None, intrinsics=K)  # no rng: losses and quantisation only
    fb = SL.focal * SL.baseline
    np.testing.assert_allclose(depth, fb / (np.round(fb / 2.0 / SL.disparity_step) * SL.disparity_step), rtol=1e-5)
    exact = SensorNoise("structured_light", focal=K.fx, disparity_step=0.0)
    np.testing.assert_allclose(exact.depth_from_zbuffer(zbuffer, K.near, K.far, None, intrinsics=K), 2.0, rtol=1e-5)


def test_config_key_loads_and_bad_values_name_the_key(tmp_path):
    path = tmp_path / "sensor.toml"
    path.write_text(
        '[sensor]\nnoise = "structured_light"\n[sensor.camera]\nfx = 580.0\nfy = 580.0\n'
        '[sensor.noise_parameters]\nbaseline = 0.05\ndisparity_sigma = 0.08\n'
    )
    noise = load_run_config(path).sensor.sensor_noise()
    assert (noise.model, noise.focal, noise.baseline, noise.disparity_sigma) == ("structured_light", 580.0, 0.05, 0.08)
    for text, key in (
        ("disparity_step = -0.125", "disparity_step"),
        ("max_incidence = 0.0", "max_incidence"),
        ("baseline = 0.0", "baseline"),
        ("edge_dropout = -1", "edge_dropout"),
        ("correlation_length = -2.0", "correlation_length"),
    ):
        path.write_text(f'[sensor]\nnoise = "structured_light"\n[sensor.noise_parameters]\n{text}\n')
        with pytest.raises(ConfigError, match=rf"sensor.toml: \[sensor.noise_parameters\] .*{key}"):
            load_run_config(path)
    path.write_text('[sensor]\nnoise = "structured_lite"\n')
    with pytest.raises(ConfigError, match="structured_light"):
        load_run_config(path)


def test_a_camera_that_loses_returns_casts_no_free_space_votes_from_them():
    """A pixel without a return is free space only for a sensor that returns every surface in range: the
    structured-light model (edge and grazing dropouts) and a real camera ("auto") lose returns on real
    surfaces, so the loop does not let those pixels vote faces out; without its dropouts the
    structured-light model loses none, and the simulator's other models never do."""
    import mabdi
    from mabdi.sources.frames import FrameList

    assert SensorNoise("structured_light").loses_returns
    assert SensorNoise("auto").loses_returns
    assert not SensorNoise("structured_light", edge_dropout=0, max_incidence=90.0).loses_returns
    assert not any(SensorNoise(model).loses_returns for model in ("none", "zbuffer", "kinect"))
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    frames = FrameList([DepthFrame(depth, Intrinsics(width=64, height=48, fx=50, fy=50, cx=32, cy=24), np.eye(4), 0, 0.0)])
    for noise, free in (("structured_light", False), ("auto", False), ("zbuffer", True)):
        assert mabdi.MabdiLoop(frames, noise=noise).removal_parameters.no_return_is_free is free, noise


def test_refinement_auto_follows_whether_the_noise_is_correlated(tmp_path):
    """``refinement.enabled = "auto"`` (the default) refines where one look's errors are correlated
    (structured light, a real camera under "auto"), not where each pixel errs on its own; true and false
    decide outright; anything else names the key."""
    import mabdi
    from mabdi.stages.classifier import ClassifierParameters
    from mabdi.stages.refinement import RefinementParameters
    from mabdi.sources.frames import FrameList

    assert SensorNoise("structured_light").correlated and SensorNoise("auto").correlated
    assert not SensorNoise("structured_light", correlation_length=0.0, disparity_step=0.0).correlated
    assert not any(SensorNoise(model).correlated for model in ("none", "zbuffer", "kinect"))
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    frames = FrameList([DepthFrame(depth, Intrinsics(width=64, height=48, fx=50, fy=50, cx=32, cy=24), np.eye(4), 0, 0.0)])
    for noise, setting, refining in (
        ("structured_light", "auto", True),
        ("auto", "auto", True),
        ("kinect", "auto", False),
        ("structured_light", False, False),
        ("kinect", True, True),
        ("none", True, False),  # nothing to average without noise
    ):
        loop = mabdi.MabdiLoop(frames, refinement=RefinementParameters(enabled=setting), noise=noise)
        assert bool(loop.refining) is refining, (noise, setting)
        # the rim's known pixels carry the map's depth where the map is refined ("auto"), unless set outright
        assert loop.classifier.parameters.rim_on_map is refining, (noise, setting)
        for outright in (True, False):
            chosen = mabdi.MabdiLoop(
                frames, classifier=ClassifierParameters(rim_on_map=outright), refinement=RefinementParameters(enabled=setting), noise=noise
            )
            assert chosen.classifier.parameters.rim_on_map is outright
    assert RefinementParameters().enabled == "auto"
    path = tmp_path / "rim.toml"
    path.write_text("[classifier]\nrim_on_map = false\n")
    assert load_run_config(path).classifier.rim_on_map is False
    with pytest.raises(ConfigError, match="refinement: enabled"):
        RefinementParameters(enabled="sometimes")
    path = tmp_path / "run.toml"
    path.write_text("[refinement]\nenabled = false\n")
    assert load_run_config(path).refinement.enabled is False
    path.write_text("[refinement]\nenabled = 1\n")
    with pytest.raises(ConfigError, match="refinement"):
        load_run_config(path)


@pytest.mark.slow
@pytest.mark.parametrize("scene", ["table", "bunnies"])
def test_structured_light_scenes_are_mapped_at_least_as_well_as_the_tuned_tsdf(scene):
    """The table and Run 2 with the structured-light model, quad-tree, `mabdi run` defaults: F@1cm at least that
    of Open3D's TSDF at 1 cm and at 2 cm with its tuned settings (``TsdfSettings.tuned``) on the same frames,
    with fewer triangles, and at most 0.2%
    of the map removed (the margins, over draws of the noise, are in docs/benchmarks.md)."""
    from test_evaluate import open3d_or_skip
    from conftest import simulation
    from mabdi.evaluate import evaluate_run
    from mabdi.evaluate.metrics import evaluate_map, observed_ground_truth, scenes_per_pose
    from mabdi.evaluate.tsdf import TsdfSettings, run_tsdf
    from mabdi.polydata import polydata_area

    open3d_or_skip()
    sim = simulation(scene, "quadtree", sensor__noise="structured_light")
    result = sim.run()
    mabdi_f = evaluate_run(sim, result).fscore_1cm
    removed = sum(r.area_removed for r in result.records)
    assert removed <= 0.002 * polydata_area(result.mesh), removed
    rig = sim.rig
    frames = len(rig)
    truth = rig.scene.mesh_at(frames - 1)
    observed = observed_ground_truth(truth, scenes_per_pose(rig.scene, frames), rig.true_poses, rig.intrinsics)
    for voxel in (0.01, 0.02):
        settings = TsdfSettings.tuned(voxel)
        tsdf = run_tsdf(rig, settings, mesh_every=None, noise=rig.sensor.noise)
        tsdf_f = evaluate_map(tsdf.mesh, truth, observed).fscore_1cm
        assert mabdi_f >= tsdf_f, (voxel, mabdi_f, tsdf_f)
        assert result.mesh.GetNumberOfCells() < tsdf.mesh.GetNumberOfCells()
