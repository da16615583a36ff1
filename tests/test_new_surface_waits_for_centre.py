"""New surface at the image's rim waits for a look nearer the centre (``[classifier] outer_radius``; "auto": a
real camera's, whose noise model is learnt from its frames).

A panning camera first sees new surface at the rim of its image, where a real camera's depth errs most; the
frames after it see the same surface nearer the centre. The classifier leaves such pixels unmeshed while the
camera's motion, carried on one frame, brings them nearer the principal point, and meshes them once it does
not (the camera stopped, turned back, or the pixel drifts along the rim)."""

from __future__ import annotations

import numpy as np
import pytest

import mabdi
from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.evaluate.held_out import map_depth
from mabdi.frame_values import Expected, Measured
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.frames import FrameList
from mabdi.stages.classifier import NOVEL, ClassifierParameters, FilterClassifier, normalised_radius, waiting_for_centre

CAMERA = Intrinsics(fx=80.0, fy=80.0, cx=40.0, cy=30.0, width=80, height=60)


def moved_along_x(metres: float) -> np.ndarray:
    """The last frame's camera from this one's when the camera moved ``metres`` along its own x axis."""
    motion = np.eye(4)
    motion[0, 3] = metres
    return motion


def wall(depth: float = 2.0) -> np.ndarray:
    return np.full(CAMERA.shape, depth, np.float32)


def test_the_normalised_radius_is_zero_at_the_principal_point_and_one_at_the_corners():
    radius = normalised_radius(CAMERA)
    assert radius.shape == CAMERA.shape
    assert radius.min() < 0.02 and radius[CAMERA.shape[0] // 2, CAMERA.shape[1] // 2] < 0.02
    for corner in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
        assert 0.97 < radius[corner] <= 1.0
    assert radius[30, 79] == pytest.approx(np.hypot(39.5 / 40, 0.5 / 30) / np.sqrt(2), rel=1e-6)  # middle of the right edge


def test_new_surface_waits_only_at_the_rim_the_camera_moves_towards():
    """The camera moving 5 cm to its right: the wall's points move left in the image, so new surface at the right
    rim comes nearer the centre next frame and waits; the left rim moves out of view and is meshed now; nothing
    within ``outer_radius`` waits."""
    new = np.ones(CAMERA.shape, dtype=bool)
    radius = normalised_radius(CAMERA)
    waiting = waiting_for_centre(new, wall(), CAMERA, moved_along_x(0.05), 0.7)
    right = np.arange(CAMERA.width)[None, :] + 0.5 > CAMERA.cx
    assert waiting.any()
    assert not waiting[radius <= 0.7].any()
    assert not (waiting & ~right).any()
    # on the right rim every pixel comes nearer the principal point: all of them wait
    assert waiting[(radius > 0.7) & right & (np.abs(np.arange(CAMERA.height)[:, None] + 0.5 - CAMERA.cy) < 20)].all()
    # only pixels of new surface wait
    assert not waiting_for_centre(np.zeros(CAMERA.shape, dtype=bool), wall(), CAMERA, moved_along_x(0.05), 0.7).any()


def test_nothing_waits_while_the_camera_is_still():
    still = waiting_for_centre(np.ones(CAMERA.shape, dtype=bool), wall(), CAMERA, np.eye(4), 0.7)
    assert not still.any()
    # a motion that moves the rim less than half a pixel inwards: no better look is coming soon enough
    assert not waiting_for_centre(np.ones(CAMERA.shape, dtype=bool), wall(), CAMERA, moved_along_x(1e-4), 0.7).any()


def classified(motion, outer_radius: float = 0.7, expected_depth: np.ndarray | None = None):
    measured = Measured(wall(), CAMERA, np.eye(4), SensorNoise("none"), 3)
    depth = np.full(CAMERA.shape, np.nan, np.float32) if expected_depth is None else expected_depth
    expected = Expected(depth, CAMERA, np.eye(4), 3)
    return FilterClassifier(ClassifierParameters(outer_radius=outer_radius, rim=0)).classify(measured, expected, camera_motion=motion)


def test_the_classifier_leaves_waiting_pixels_unmeshed_and_labelled_novel():
    moving = classified(moved_along_x(0.05))
    waiting = np.isnan(moving.depth)
    assert 0 < waiting.mean() < 0.3
    assert (moving.labels == NOVEL).all()  # still novel: only their meshing waits
    assert moving.counts["novel"] == int((~waiting).sum())
    # no last frame, the rule off, or a surface the map already has there: every pixel is meshed as before
    assert np.isfinite(classified(None).depth).all()
    assert np.isfinite(classified(moved_along_x(0.05), outer_radius=1.0).depth).all()
    in_front = classified(moved_along_x(0.05), expected_depth=wall(3.0))  # novel in front of the map: not new surface
    assert np.isfinite(in_front.depth).all()


@pytest.mark.parametrize("value", [0.0, -0.1, 1.5, "half", True])
def test_outer_radius_outside_its_range_is_an_error_naming_it(value):
    with pytest.raises(ConfigError, match="outer_radius"):
        ClassifierParameters(outer_radius=value)


def test_auto_waits_for_a_real_cameras_learnt_noise_only():
    """A noise model learnt from a real camera's frames (``auto``): its depth errs most at the corners, and new
    surface waits beyond 0.7; the simulator's models err alike across the image: nothing waits."""
    parameters = ClassifierParameters()
    assert parameters.outer_radius == "auto"
    assert parameters.outer_radius_for(SensorNoise("auto")) == 0.7
    for model in ("none", "kinect", "structured_light"):
        assert parameters.outer_radius_for(SensorNoise(model)) == 1.0
    assert ClassifierParameters(outer_radius=0.5).outer_radius_for(SensorNoise("kinect")) == 0.5


@pytest.mark.slow
def test_a_camera_whose_depth_errs_at_its_corners_maps_a_room_nearer_the_truth():
    """A camera moving sideways past a room, Kinect noise and a radial depth distortion (1% too far at the
    corners, :func:`test_registration_distorted_depth.distorted`), exact poses: the map's depth at the true poses
    against the undistorted, noise-free room. Measured: median error 8.21 mm with the wait against 8.66 mm with
    every pixel meshed at once (``outer_radius = 1``), from 101,215 against 107,371 triangles."""
    from test_registration import room_frames
    from test_registration_distorted_depth import distorted

    frames_count = 40
    true = np.stack([look_at([-1.5 + 0.04 * i, -1.8, 1.4], [0.8 + 0.04 * i, 0.8, 0.5]) for i in range(frames_count)])
    camera = Intrinsics()
    depths = [distorted(d, camera) for d in room_frames(true, noise="kinect")]
    clean = room_frames(true, noise="none")
    frames = FrameList([DepthFrame(d, camera, t, i, i / 30) for i, (d, t) in enumerate(zip(depths, true, strict=True))])

    def median_error(outer_radius: float) -> tuple[float, int]:
        loop = mabdi.MabdiLoop(frames, surface="quadtree", noise="kinect", classifier=ClassifierParameters(outer_radius=outer_radius))
        for i in range(frames_count):
            loop.step(i)
        mesh = loop.mesh()
        errors = []
        for i in range(2, frames_count, 4):
            error = np.abs(map_depth(mesh, camera, true[i]) - clean[i])
            errors.append(error[np.isfinite(error)])
        return float(np.median(np.concatenate(errors))), mesh.GetNumberOfCells()

    waited, waited_cells = median_error(0.7)
    at_once, at_once_cells = median_error(1.0)
    assert waited < 0.97 * at_once, (waited, at_once)
    assert waited_cells < at_once_cells, (waited_cells, at_once_cells)
