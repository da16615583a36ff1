"""How many frames must see through a face before it goes (``[removal] min_frames``): "auto" asks four of a
real sensor (one that loses returns: a recording, a real camera, structured light with dropouts) and two of
the simulator's, whose sensors return every surface where it lies. A real sensor's contradictions of a static
surface (a mixed pixel, a map edge a beam off, multipath) come back for a frame or two while it passes."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.camera import Intrinsics
from mabdi.errors import ConfigError
from mabdi.loop.loop import resolve_settings
from mabdi.sensor_noise import SensorNoise
from mabdi.spherical import SphericalGeometry
from mabdi.stages.classifier import ClassifierParameters
from mabdi.stages.removal import REAL_SENSOR_MIN_FRAMES, SIMULATED_MIN_FRAMES, RemovalParameters
from mabdi.world_map import update_log_odds


def resolved_removal(geometry, noise: str, loses_returns: bool = False, removal: RemovalParameters | None = None):
    settings = resolve_settings(
        geometry, SensorNoise.of(noise), loses_returns, ClassifierParameters(), "quadtree", None, removal, None, None
    )
    return settings.removal


def test_auto_asks_four_frames_of_a_sensor_that_loses_returns_and_two_of_the_simulators():
    assert (REAL_SENSOR_MIN_FRAMES, SIMULATED_MIN_FRAMES) == (4, 2)
    assert resolved_removal(Intrinsics(), "auto").min_frames == 4  # a real camera's learnt noise
    assert resolved_removal(Intrinsics(), "structured_light").min_frames == 4  # dropouts at edges and grazing
    assert resolved_removal(SphericalGeometry(), "range", loses_returns=True).min_frames == 4  # a LiDAR recording
    assert resolved_removal(Intrinsics(), "zbuffer").min_frames == 2
    assert resolved_removal(Intrinsics(), "kinect").min_frames == 2
    assert resolved_removal(SphericalGeometry(), "range").min_frames == 2  # the simulator's LiDAR
    # a number decides outright, for any sensor
    assert resolved_removal(Intrinsics(), "auto", removal=RemovalParameters(min_frames=3)).min_frames == 3
    assert resolved_removal(Intrinsics(), "zbuffer", removal=RemovalParameters(min_frames=5)).min_frames == 5
    # unresolved (the world map's API used directly): the simulator's rule
    assert RemovalParameters().frames_required == 2 and RemovalParameters(min_frames=6).frames_required == 6


@pytest.mark.parametrize("value", [0, -1, "many", True, 2.5])
def test_min_frames_that_is_not_auto_or_a_whole_number_of_frames_is_an_error_naming_it(value):
    with pytest.raises(ConfigError, match="min_frames"):
        RemovalParameters(min_frames=value)


def run_votes(parameters: RemovalParameters, frames: list[tuple[int, int]], evidence: float = 0.0) -> list[bool]:
    """Whether a face is gone after each frame of (contradicting, confirming) pixel votes, from ``evidence``."""
    e, f = np.full(1, evidence, np.float32), np.zeros(1, np.uint16)
    gone_after = []
    for contradicted, confirmed in frames:
        e, f, gone = update_log_odds(e, f, np.array([contradicted]), np.array([confirmed]), parameters)
        gone_after.append(bool(gone[0]))
    return gone_after


def test_a_static_face_seen_through_for_three_frames_stays_with_a_real_sensor_and_goes_with_the_simulators():
    """A face confirmed all along (at the floor) that three passing frames see through (a misplaced edge's
    recurring contradiction): the simulator's rule removes it at the second, a real sensor's keeps it; frames
    that confirm it again bring it back to the floor."""
    real = resolved_removal(Intrinsics(), "auto")
    simulated = resolved_removal(Intrinsics(), "zbuffer")
    passing = [(5, 0), (5, 0), (5, 0), (0, 5), (0, 5), (0, 5), (0, 5), (0, 5), (0, 5), (0, 5)]
    assert run_votes(simulated, passing, simulated.floor)[:2] == [False, True]
    assert not any(run_votes(real, passing, real.floor))


def test_a_departed_object_still_goes_with_a_real_sensor_two_frames_later():
    """A face every frame sees through from its first vote on (the object left): gone at the second frame with
    the simulator's rule, at the fourth with a real sensor's."""
    real = resolved_removal(Intrinsics(), "auto")
    simulated = resolved_removal(Intrinsics(), "zbuffer")
    left = [(5, 0)] * 6
    assert run_votes(simulated, left, simulated.floor).index(True) == 1
    assert run_votes(real, left, real.floor).index(True) == 3
    # seen again and again before it left (evidence at the floor) or never confirmed: the same four frames
    assert run_votes(real, left, 0.0).index(True) == 3


def test_the_count_starts_again_after_a_frame_that_confirms_the_face():
    """A static face a real sensor sees through in bursts of three frames (each pass of a misplaced edge),
    confirmed between them: it stays however many bursts come, since no four frames see through it without a
    confirmation between; four in a row remove it."""
    real = resolved_removal(Intrinsics(), "auto")
    burst = [(5, 0)] * 3 + [(0, 5)] * 6
    assert not any(run_votes(real, burst * 5, real.floor))
    assert run_votes(real, burst * 2 + [(5, 0)] * 4, real.floor)[-1]
    # frames that give the face no vote (out of view) neither count nor start the count again
    assert run_votes(real, [(5, 0), (0, 0), (5, 0), (0, 0), (5, 0), (5, 0)], real.floor)[-1]
