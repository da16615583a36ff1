"""Object removal on a LiDAR's scans (mabdi.stages.removal with for_geometry): what a real or deskewed scan gets
wrong about a static place is no contradiction, while a surface that left still is.

* A return's direction is uncertain by a fraction of the beam spacing: on a surface seen obliquely, D lies off
  E by E tan(incidence) times that along the ray.
* The map's depth edges, made from earlier scans, lie up to a beam off the sensor's.
* A lone pixel without a return between returns is a return that slid into the next pixel, not free space.
* Every recording a reader opens loses returns (glass, black surfaces, grazing incidence).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mabdi.camera import Intrinsics, unit_rays
from mabdi.stages.classifier import CONTRADICTED, KNOWN, NO_RETURN
from mabdi.stages.removal import RemovalParameters, contradiction_gap, for_geometry, free_space_filled, removal_votes
from mabdi.depth import DepthFrame
from mabdi.loop.loop import MabdiLoop
from mabdi.loop.mapping_run import recorded_simulation
from mabdi.config import RunConfig
from mabdi.sources.frames import FrameList
from mabdi.sources.kitti import write_kitti
from mabdi.sources.sequences import open_sequence
from mabdi.spherical import SphericalGeometry

GEOMETRY = SphericalGeometry(beams=32, columns=256, fov_up=45.0, fov_down=-45.0, range_min=0.5, range_max=60.0)
LIDAR_RULES = for_geometry(RemovalParameters(), GEOMETRY)


def range_sigma(depth):
    """A spinning LiDAR's range noise: 2 cm at every range."""
    return np.full(np.shape(depth), 0.02, dtype=np.float32)


def labelled(measured, expected) -> np.ndarray:
    labels = np.where(measured > expected + 0.05, CONTRADICTED, KNOWN).astype(np.uint8)
    labels[np.isnan(measured)] = NO_RETURN
    return labels


def votes(measured, expected, face_ids, normals: dict, rules=LIDAR_RULES):
    rays, _ = unit_rays(GEOMETRY)

    def normals_of(ids):
        return np.array([normals.get(int(i), [np.nan] * 3) for i in ids], dtype=np.float32)

    faces, contradicted, confirmed, voting = removal_votes(
        labelled(measured, expected), measured, expected, face_ids, rays, np.eye(4), normals_of, rules,
        sigma=range_sigma, far=GEOMETRY.far,
    )
    return dict(zip(faces.tolist(), contradicted.tolist(), strict=True)), voting


def wall_ranges(distance: float) -> np.ndarray:
    """(H, W) range of the plane x = distance (NaN where a ray does not reach it)."""
    rays = GEOMETRY.rays()
    with np.errstate(divide="ignore", invalid="ignore"):
        ranges = distance / rays[..., 0]
    return np.where(rays[..., 0] > 0.2, ranges, np.nan).astype(np.float32)


def test_a_lidar_s_rules_take_its_beam_spacing():
    assert LIDAR_RULES.ray_sigma == pytest.approx(GEOMETRY.pixel_angle() / math.sqrt(12.0))
    assert LIDAR_RULES.misplaced_reach == 1 and LIDAR_RULES.misplaced_edges
    camera = for_geometry(RemovalParameters(), Intrinsics())
    assert camera.ray_sigma == 0.0 and camera.misplaced_reach == "auto"


def test_a_surface_seen_obliquely_is_not_seen_through_within_its_beams_direction():
    # E 10 m along the ray at 70 degrees from the face's normal: a direction off by ray_sigma moves the ray's
    # crossing E ray_sigma tan(70) along it, and a contradiction needs 3 times that (with the range noise).
    cosine = np.float32(np.cos(np.radians(70.0)))
    gap = contradiction_gap(np.float32([10.3]), np.float32([10.0]), LIDAR_RULES, range_sigma, None, np.float32([cosine]))
    lever = 10.0 * LIDAR_RULES.ray_sigma * np.tan(np.radians(70.0))
    expected = 3.0 * math.sqrt(0.02**2 + (0.02 / float(cosine)) ** 2 + lever**2)
    assert gap[0] == pytest.approx(expected, rel=1e-4)
    no_direction = contradiction_gap(np.float32([10.3]), np.float32([10.0]), RemovalParameters(ray_sigma=0.0), range_sigma, None, np.float32([cosine]))
    assert no_direction[0] < 0.2 < 0.3 < gap[0]  # D 30 cm beyond E: a contradiction only if the direction were exact


def test_a_map_edge_one_beam_off_does_not_vote_and_a_surface_that_left_does():
    # A box face 5 m ahead in front of a wall at 6 m; the map's box reaches one beam higher than the scan's.
    expected, measured = wall_ranges(6.0), wall_ranges(6.0)
    face_ids = np.where(np.isfinite(expected), 1, 0).astype(np.int32)
    box = np.zeros(GEOMETRY.shape, dtype=bool)
    columns = slice(120, 136)
    box[12:20, columns] = True
    expected[12:20, columns] = wall_ranges(5.0)[12:20, columns]
    face_ids[12:20, columns] = 2
    measured[13:20, columns] = wall_ranges(5.0)[13:20, columns]  # the scan's edge a beam lower
    normals = {1: [-1.0, 0.0, 0.0], 2: [-1.0, 0.0, 0.0]}
    counted, voting = votes(measured, expected, face_ids, normals)
    assert counted.get(2, 0) == 0 and not voting.any()
    off = RemovalParameters(misplaced_edges=False)
    counted, _ = votes(measured, expected, face_ids, normals, for_geometry(off, GEOMETRY))
    assert counted.get(2, 0) > 0  # the rule is what holds the edge back
    # The box gone: its face is seen through, away from its edges.
    counted, voting = votes(wall_ranges(6.0), expected, face_ids, normals)
    assert counted.get(2, 0) >= 4 * 14 and voting[14:18, 122:134].all()


def test_a_lone_hole_between_returns_is_not_free_space_and_a_region_without_returns_is():
    expected = wall_ranges(6.0)
    face_ids = np.where(np.isfinite(expected), 1, 0).astype(np.int32)
    measured = expected.copy()
    measured[16, 100] = np.nan  # a hole
    measured[10:20, 140:150] = np.nan  # a region
    filled = free_space_filled(measured, LIDAR_RULES, GEOMETRY.far)
    assert np.isnan(filled[16, 100]) and (filled[11:19, 141:149] == np.float32(GEOMETRY.far)).all()
    _, voting = votes(measured, expected, face_ids, {1: [-1.0, 0.0, 0.0]})
    assert not voting[16, 100] and voting[12:18, 142:148].all()


def test_a_recorded_scan_loses_returns_and_has_a_lidar_s_noise(tmp_path):
    frames = [DepthFrame(wall_ranges(6.0), GEOMETRY, np.eye(4), i, 0.1 * i) for i in range(2)]
    write_kitti(FrameList(frames, "lidar frames"), tmp_path / "seq")
    recording = open_sequence(tmp_path / "seq")
    assert recording.loses_returns  # a pixel without a return says nothing about free space
    loop = MabdiLoop(recording)
    assert not loop.removal_parameters.no_return_is_free
    assert MabdiLoop(FrameList(frames, "simulated")).removal_parameters.no_return_is_free  # the simulator returns every surface
    simulation, _ = recorded_simulation(RunConfig(), tmp_path / "seq", noise_stated=False)
    assert simulation.config.sensor.noise == "range" and simulation.config.sensor.noise_parameters.range_sigma == pytest.approx(0.02)
