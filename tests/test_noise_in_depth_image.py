"""The sensor's noise model travels with the frame: D carries it in its field data, the filters read it there."""

from __future__ import annotations

import numpy as np
import pytest

import mabdi
from conftest import REPO
from mabdi.camera import Intrinsics, look_at
from mabdi.config import set_value
from mabdi.depth import DepthFrame, depth_image, image_noise, set_noise
from mabdi.stages.classifier import CONTRADICTED, KNOWN, NOVEL, ClassifierParameters, FilterClassifier, label_array
from mabdi.noise_calibration import PRIOR_CORRELATION, NoiseCalibration, NoiseCurve
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.frames import FrameList, SourceDepthFrames

SMALL = Intrinsics(fx=52.5, fy=52.5, cx=32.0, cy=24.0, width=64, height=48)
POSE = look_at([0, -3, 1], [0, 0, 1])

MODELS = [
    SensorNoise("none"),
    SensorNoise("zbuffer", zbuffer_sigma=0.004),
    SensorNoise("kinect", kinect_coefficient=2.5e-3),
    SensorNoise("structured_light", baseline=0.05, focal=612.0, disparity_sigma=0.08, disparity_step=0.0, edge_dropout=3, max_incidence=80.0),
    SensorNoise("range", range_sigma=0.01),
]


@pytest.mark.parametrize("noise", MODELS, ids=lambda n: n.model)
def test_a_depth_image_carries_its_noise_model_and_its_parameters(noise):
    image = depth_image(np.full(SMALL.shape, 2.0), SMALL, POSE, noise=noise)
    carried = image_noise(image)
    assert carried == noise
    z = np.array([0.7, 2.0, 3.5])
    np.testing.assert_array_equal(carried.sigma(z, SMALL.near, SMALL.far), noise.sigma(z, SMALL.near, SMALL.far))


def test_an_image_without_a_noise_model_is_read_as_noise_free_and_a_malformed_one_is_an_error():
    image = depth_image(np.full(SMALL.shape, 2.0), SMALL, POSE)
    assert image_noise(image) == SensorNoise("none")
    set_noise(image, SensorNoise("kinect"))
    image.GetFieldData().GetArray("noise_parameters").SetNumberOfTuples(3)
    with pytest.raises(ValueError, match=r"noise model 'kinect': expected 11 parameters .* got 3"):
        image_noise(image)


def test_auto_carries_the_curve_as_it_stood_when_the_image_was_made():
    calibration = NoiseCalibration()
    noise = SensorNoise("auto", calibration=calibration)
    calibration.curve = NoiseCurve(0.002, 3e-3, 1.7)
    image = depth_image(np.full(SMALL.shape, 2.0), SMALL, POSE, noise=noise)
    calibration.curve = NoiseCurve(0.0, 1e-3)  # the calibration learns on; the image keeps its curve
    carried = image_noise(image)
    assert carried.model == "auto" and carried.calibration == NoiseCurve(0.002, 3e-3, 1.7)
    assert carried.sigma(2.0, SMALL.near, SMALL.far) == pytest.approx(np.hypot(0.002, 3e-3 * 4))
    assert carried.correlation_px == 1.7
    # an image written before the curve had a correlation length (floor and coefficient only): the prior's
    values = image.GetFieldData().GetArray("noise_parameters")
    values.SetNumberOfTuples(values.GetNumberOfTuples() - 1)
    assert image_noise(image).calibration == NoiseCurve(0.002, 3e-3, PRIOR_CORRELATION)
    # the source stamps each new D with the curve of that moment
    frames = FrameList([DepthFrame(np.full(SMALL.shape, 2.0, np.float32), SMALL, POSE, i) for i in range(2)])
    measured = SourceDepthFrames(frames, noise=noise)
    measured.frame = 1
    measured.Update()
    assert image_noise(measured.GetOutput()).calibration == NoiseCurve(0.0, 1e-3)


def test_the_classifier_judges_d_by_the_noise_model_d_carries():
    """The same D and E (D 2 cm beyond and 2 cm before E at 3 m) with and without a Kinect's noise stated:
    tau = 3 sigma(3 m) = 3.8 cm explains both; noise-free, tau = tau_min = 1 cm does not."""
    expected = np.full(SMALL.shape, 3.0, np.float32)
    measured = expected.copy()
    measured[:24] += 0.02
    measured[24:] -= 0.02
    labels = {}
    for noise in (None, "kinect"):
        classifier = FilterClassifier(ClassifierParameters(tau_min=0.01, k_sigma=3.0, min_width=1, min_region=0, rim=0))
        classifier.SetInputDataObject(0, depth_image(measured, SMALL, POSE, frame=2, noise=noise))
        classifier.SetInputDataObject(1, depth_image(expected, SMALL, POSE, frame=2))
        classifier.Update()
        labels[noise] = label_array(classifier.GetOutput())
        assert image_noise(classifier.GetOutput()) == SensorNoise.of(noise or "none")  # passed on to the surface
    assert (labels[None][:24] == CONTRADICTED).all() and (labels[None][24:] == NOVEL).all()
    assert (labels["kinect"] == KNOWN).all()


def test_the_loop_stamps_d_with_the_sources_noise_or_the_one_it_is_given():
    frames = [DepthFrame(np.full(SMALL.shape, 2.0, np.float32), SMALL, POSE, i) for i in range(2)]
    loop = mabdi.MabdiLoop(FrameList(frames), surface="quadtree", noise="kinect")
    loop.step(0)
    loop.step(1)
    assert loop.last_frame.measured.noise == SensorNoise("kinect")  # the value the stages read
    for image in (loop.measured_image(), loop.classified_image()):  # and the images the pipeline API shows
        assert image_noise(image) == SensorNoise("kinect")
    assert mabdi.MabdiLoop(FrameList(frames)).noise == SensorNoise("none")  # a list of frames states nothing


def test_the_simulated_rig_states_the_noise_it_draws():
    config = mabdi.load_run_config(REPO / "scenes" / "table.toml")
    set_value(config, "sensor.noise", "kinect")
    set_value(config, "run.frames", 2)
    rig = mabdi.SimulatedRig.from_config(config)
    assert rig.noise == config.sensor.sensor_noise()
    measured = SourceDepthFrames(rig)
    measured.Update()
    assert image_noise(measured.GetOutput()) == config.sensor.sensor_noise()
    assert mabdi.MabdiLoop(rig).noise == config.sensor.sensor_noise()
    rig.close()
