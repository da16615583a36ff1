"""noise = "auto": sigma(z) learnt online from D - E where the map explains D."""

from __future__ import annotations

import numpy as np
import pytest

import mabdi
from conftest import REPO
from mabdi.config import load_run_config, set_value
from mabdi.errors import ConfigError
from mabdi.sensor_noise import SensorNoise, correlated_field
from mabdi.noise_calibration import PRIOR_COEFFICIENT, PRIOR_CORRELATION, NoiseCalibration
from mabdi.simulate.rig import SimulatedRig
from mabdi.sources.tum import TumSequence, write_tum


def test_the_calibration_fits_the_z_squared_law_and_its_floor():
    """Residuals drawn with sigma(z) = sqrt(2 mm^2 + (3e-3 z^2)^2): the fit recovers the curve within 5%."""
    rng = np.random.default_rng(0)
    calibration = NoiseCalibration()
    assert not calibration.fitted and calibration.sigma(np.float32(2.0)) == pytest.approx(PRIOR_COEFFICIENT * 4, rel=1e-6)
    truth = lambda z: np.sqrt(0.002**2 + (3e-3 * z * z) ** 2)  # noqa: E731
    for _ in range(20):
        expected = rng.uniform(0.6, 4.0, (120, 160))
        measured = expected + truth(expected) * rng.standard_normal(expected.shape)
        measured[:10] = expected[:10] - 0.5  # a new object in front of the map: beyond the gate, not counted
        calibration.observe(measured, expected)
    assert calibration.fitted
    for z in (1.0, 2.0, 3.0, 3.8):
        assert calibration.sigma(z) == pytest.approx(truth(z), rel=0.05), z
    state = calibration.state()
    copy = NoiseCalibration()
    copy.set_state(state)
    assert copy.sigma(2.5) == calibration.sigma(2.5)
    summary = calibration.summary()
    assert summary["fitted"] and len(summary["bins_m"]) == len(summary["bin_sigma_m"]) > 5


@pytest.mark.parametrize("length", [0.0, 1.0, 2.5, 4.0])
def test_the_calibration_learns_how_far_the_errors_are_correlated(length):
    """Residuals drawn as a Gaussian-smoothed field of ``length`` pixels: the learnt correlation length is within
    15% of it (0 for white noise); before enough pairs it is the prior; it survives a checkpoint."""
    rng = np.random.default_rng(1)
    calibration = NoiseCalibration()
    assert calibration.curve.correlation == PRIOR_CORRELATION
    for _ in range(6):
        expected = rng.uniform(1.0, 3.0) * np.ones((240, 320))
        measured = expected + 1.425e-3 * expected**2 * correlated_field(expected.shape, length, rng)
        measured[:20] = expected[:20] - 0.5  # a new object in front of the map: beyond the gate, not counted
        calibration.observe(measured, expected)
    learnt = calibration.curve.correlation
    assert learnt == pytest.approx(length, rel=0.15, abs=1e-9), calibration.correlations()
    copy = NoiseCalibration()
    copy.set_state(calibration.state())
    assert copy.curve.correlation == learnt
    summary = calibration.summary()
    assert summary["correlation_px"] == learnt and len(summary["correlation_at_lags"]) == 4
    assert SensorNoise("auto", calibration=calibration).correlation_px == learnt


def test_auto_is_shared_by_the_filters_and_cannot_simulate():
    noise = SensorNoise("auto")
    assert SensorNoise.of(noise).calibration is noise.calibration
    assert SensorNoise("auto").calibration is not noise.calibration  # each model its own calibration
    config = load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "sensor.noise", "auto")
    set_value(config, "run.frames", 2)
    rig = SimulatedRig.from_config(config)
    with pytest.raises(ConfigError, match="auto"):
        rig.read(0)


@pytest.mark.slow
def test_auto_recovers_the_kinect_noise_of_a_recording(tmp_path):
    """A TUM recording of Run 2 with Kinect noise, run back with noise = "auto": the calibrated sensor
    sigma(z) is within 20% of the Kinect's 1.425e-3 z^2 from 1 to 4 m (the whole curve, the map's floor
    included, lies above it and within 5 mm of it), and summary.json carries the curve."""
    config = load_run_config(REPO / "scenes" / "bunnies.toml")
    set_value(config, "sensor.noise", "kinect")
    set_value(config, "run.frames", 24)
    write_tum(SimulatedRig.from_config(config), tmp_path / "seq")
    set_value(config, "sensor.noise", "auto")
    set_value(config, "surface.method", "quadtree")
    simulation = mabdi.MappingRun(config, source=TumSequence(tmp_path / "seq"))
    result = simulation.run()
    calibration = simulation.loop.noise.calibration
    assert calibration.fitted
    for z in (1.0, 1.5, 2.0, 3.0, 4.0):
        kinect = 1.425e-3 * z * z
        assert calibration.sensor_sigma(z) == pytest.approx(kinect, rel=0.2), (z, calibration.summary())
        assert kinect * 0.8 <= calibration.sigma(z) <= kinect + 0.005
    summary = result.summary()["noise_calibration"]
    assert summary["coefficient_per_m"] == pytest.approx(1.425e-3, rel=0.2)


def test_the_compiled_binning_keeps_what_the_array_version_keeps():
    """Frames of D and E with holes, silhouettes, residuals beyond the gate and a bin that overflows its ring:
    the compiled kernel and the numpy reference leave the same rings and counts, frame after frame."""
    from reference_kernels import add_residuals

    rng = np.random.default_rng(4)
    compiled, reference = NoiseCalibration(samples_per_bin=512), NoiseCalibration(samples_per_bin=512)
    for frame in range(4):
        expected = rng.uniform(0.4, 10.5, (120, 160)).astype(np.float32)
        expected[:40, :60] = np.float32(2.1)  # one bin with more residuals a frame than its ring holds
        measured = expected + rng.normal(0.0, 0.01, expected.shape).astype(np.float32)
        measured[rng.random(expected.shape) < 0.1] += np.float32(0.5)  # beyond the gate
        measured[rng.random(expected.shape) < 0.1] = np.nan
        expected[rng.random(expected.shape) < 0.05] = np.nan
        silhouettes = rng.random(expected.shape) < 0.1 if frame % 2 else None
        counted = compiled.observe(measured, expected, silhouettes)
        reference._observe_pairs(measured, expected, silhouettes)
        assert counted == add_residuals(reference, measured, expected, silhouettes) > 0
        reference._fit()
        np.testing.assert_array_equal(compiled._added, reference._added)
        np.testing.assert_array_equal(compiled._residuals, reference._residuals)  # NaN where empty, in both
        assert compiled.curve == reference.curve
    assert compiled._added.max() > 512  # the crowded bin wrapped around its ring
