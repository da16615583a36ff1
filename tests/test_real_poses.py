"""Run 2 with the poses a robot gives: jitter and drift on the given poses, the map registered frame by
frame stays as right, as small and as static as with exact poses. Full runs: marked slow (CI runs them)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import simulation
from mabdi.evaluate import evaluate_run
from mabdi.stages.map_anchor import MapAnchor
from mabdi.stages.registration import transform_size
from mabdi.polydata import polydata_area

pytestmark = pytest.mark.slow


def alignment(true: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """The one rigid motion (4x4) that best takes the ``true`` trajectory onto ``poses``."""
    rotation = Rotation.from_matrix(np.einsum("nij,nkj->nik", poses[:, :3, :3], true[:, :3, :3])).mean().as_matrix()
    align = np.eye(4)
    align[:3, :3] = rotation
    align[:3, 3] = np.mean(poses[:, :3, 3] - true[:, :3, 3] @ rotation.T, axis=0)
    return align


def aligned_errors(true: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(N, 2) pose errors (m, degrees) after the one rigid motion that best aligns the two trajectories."""
    align = alignment(true, poses)
    return np.array([transform_size(np.linalg.inv(align @ t) @ p) for t, p in zip(true, poses, strict=True)])


def placed_with_exact_registration(sim) -> np.ndarray:
    """(N, 2) errors (m, degrees) of the poses the run would mesh with were every frame registered exactly: the
    loop's map anchor, told the pose accuracy the simulator states, given each frame's given pose and its true
    pose in the frame of the map the first given pose started. What the given poses allow of the map's
    placement, whatever the registration."""
    true, given = sim.true_poses, sim.poses
    anchor = MapAnchor(stated=sim.source.pose_accuracy.variances())
    map_from_world = given[0] @ np.linalg.inv(true[0])
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(given[:, :3, 3], axis=0), axis=1))])
    for g, t, s in zip(given, true, travelled, strict=True):
        anchor.add(g, map_from_world @ t, float(s))
    placed = anchor.world_from_map @ map_from_world @ true
    return np.array([transform_size(np.linalg.inv(t) @ p) for t, p in zip(true, placed, strict=True)])


def noisy_run(given_sigma: str = "source", **pose_noise):
    """Run 2 with ``pose_noise``; ``given_sigma``: "source" (the simulator states its pose noise, the default)
    or "learnt" (as a recording of unknown accuracy is run)."""
    overrides = {f"sensor__pose_noise__{k}": v for k, v in pose_noise.items()}
    sim = simulation("bunnies", "quadtree", registration__given_sigma=given_sigma, **overrides)
    result = sim.run()
    return sim, result, evaluate_run(sim, result)


def check_jitter_run(static_runs, jitter_translation: float, jitter_rotation: float) -> tuple[np.ndarray, np.ndarray]:
    """A jittered Run 2 against exact poses: F@1cm within 0.005, at most 0.2% of the map removed, the second
    circle adds at most 15% of the first, 90% of the frames registered. Returns the meshed poses' errors from
    the true ones (N, 2: m, degrees) and the same after the one rigid motion that best aligns the two
    trajectories, with the checks that the registration takes out at least three quarters of the given
    poses' rotation error."""
    _, exact = static_runs("bunnies", "quadtree")
    sim, result, metrics = noisy_run(jitter_translation=jitter_translation, jitter_rotation=jitter_rotation)
    assert metrics.fscore_1cm >= exact.fscore_1cm - 0.005, (metrics.fscore_1cm, exact.fscore_1cm)
    removed = sum(r.area_removed for r in result.records)
    assert removed <= 0.002 * polydata_area(result.mesh), removed
    growth = metrics.growth_per_circle
    assert growth[1] <= 0.15 * growth[0], growth
    records = result.records
    assert sum(r.registered for r in records) >= 0.9 * len(records)
    true, meshed = sim.true_poses, sim.meshed_poses()
    given = np.array([transform_size(np.linalg.inv(t) @ g) for t, g in zip(true, sim.poses, strict=True)])
    errors = np.array([transform_size(np.linalg.inv(t) @ p) for t, p in zip(true, meshed, strict=True)])
    assert np.median(errors[:, 1]) <= 0.25 * np.median(given[:, 1]), (np.median(errors, axis=0), np.median(given, axis=0))
    # the map's placement: no pose source tells more of it than the given poses' mean (white jitter), and the
    # meshed poses' constant part is within half a millimetre of that mean's own error
    placed, mean_given = transform_size(alignment(true, meshed)), transform_size(alignment(true, sim.poses))
    assert placed[0] <= mean_given[0] + 0.0005, (placed, mean_given)
    # and within half a millimetre of what exact registration would give (median)
    exact_registration = placed_with_exact_registration(sim)
    assert np.median(errors[:, 0]) <= np.median(exact_registration[:, 0]) + 0.0005, (
        np.median(errors, axis=0), np.median(exact_registration, axis=0))
    return errors, aligned_errors(true, meshed)


def test_run2_with_pose_jitter_is_mapped_as_with_exact_poses(static_runs):
    """Jitter of 2 mm / 0.15 degrees per axis (3.2 mm / 0.26 degrees median): the checks of
    :func:`check_jitter_run`, and the meshed poses within 1.5 mm / 0.05 degrees of the true ones (median;
    measured 1.08 mm / 0.016 degrees)."""
    errors, aligned = check_jitter_run(static_runs, 0.002, 0.15)
    assert np.median(errors[:, 0]) <= 0.0015 and np.median(errors[:, 1]) <= 0.05, np.median(errors, axis=0)
    assert np.median(aligned[:, 0]) <= 0.0015, np.median(aligned, axis=0)


def test_run2_with_large_pose_jitter_is_placed_as_well_as_the_given_poses_allow(static_runs):
    """Jitter of 5 mm / 0.3 degrees per axis: the checks of :func:`check_jitter_run`; the frames agree with
    each other within 1.5 mm / 0.05 degrees (median after the one rigid alignment; measured 0.78 mm). Against
    the true poses they are 2.1 mm off, most of it the map's placement, which is the given poses' mean here
    (1.7 mm off the truth in this run: 5 mm over the square root of 50 frames is 0.7 mm per axis). Exactly
    registered frames would be placed 1.83 mm off (median; 1.1-2.4 mm over ten draws of the jitter): the
    1.5 mm asked of this jitter is below what 50 such given poses tell."""
    errors, aligned = check_jitter_run(static_runs, 0.005, 0.3)
    assert np.median(aligned[:, 0]) <= 0.0015 and np.median(aligned[:, 1]) <= 0.05, np.median(aligned, axis=0)
    assert np.median(errors[:, 1]) <= 0.05, np.median(errors, axis=0)


def test_run2_with_drift_is_mapped_as_with_exact_poses(static_runs):
    """Drift of 1 cm and 0.5 degrees per sqrt(metre travelled) (centimetres and degrees over the run), its
    size learnt from the run (not stated by the source, as with a recording): F@1cm within 0.01 of exact
    poses."""
    _, exact = static_runs("bunnies", "quadtree")
    sim, result, metrics = noisy_run("learnt", drift_translation=0.01, drift_rotation=0.5)
    assert metrics.fscore_1cm >= exact.fscore_1cm - 0.01, (metrics.fscore_1cm, exact.fscore_1cm)
    removed = sum(r.area_removed for r in result.records)
    assert removed <= 0.002 * polydata_area(result.mesh), removed


def test_run2_with_large_jitter_of_unknown_size_keeps_its_static_map():
    """Jitter of 1 cm / 0.5 degrees per axis that the source does not state (learnt, as a recording's): a frame
    keeps the last frame's slow correction only where it fits D to the map at least ``CARRY_FROM`` times better
    than the given pose, so a correction one jittered frame took is not carried on as if it were drift. Removal
    takes at most 1% of the static map's area (measured 0.6%; 1.4% while any better fit carried it on)."""
    _, result, _ = noisy_run("learnt", jitter_translation=0.01, jitter_rotation=0.5)
    removed = sum(r.area_removed for r in result.records)
    assert removed <= 0.01 * polydata_area(result.mesh), (removed, polydata_area(result.mesh))
