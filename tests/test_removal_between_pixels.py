"""Removal of faces smaller than the pixels that see them, and contradictions at grazing incidence
(mabdi.stages.removal: gap_along_ray, votes_between_pixels; the loop's removal stage)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import plane_mesh

import mabdi
from mabdi.camera import Intrinsics, look_at, project, unit_rays
from mabdi.depth import DepthFrame, image_pose
from mabdi.face_identity import FaceIdTable
from mabdi.stages.world_mesh import FilterWorldMesh
from mabdi.stages.object_removal import ObjectRemoval
from mabdi.stages.registration import RegistrationParameters
from mabdi.stages.removal import RemovalParameters, gap_along_ray, votes_between_pixels
from mabdi.polydata import polydata_arrays
from mabdi.sources.frames import FrameList

CAMERA = Intrinsics(fx=160, fy=160, cx=80, cy=60, width=160, height=120, far=10.0)
RULES = RemovalParameters()


def test_the_gap_stands_as_it_is_up_to_grazing_and_stretches_beyond():
    cos_grazing = np.cos(np.radians(RULES.grazing_deg))
    cosines = np.array([1.0, 0.5, cos_grazing, np.cos(np.radians(86.0)), 0.0, np.nan])
    gap = gap_along_ray(np.full(6, 0.05), cosines, RULES)
    assert np.allclose(gap[:3], 0.05)  # continuous at grazing_deg
    assert gap[3] == pytest.approx(0.05 * cos_grazing / np.cos(np.radians(86.0)), rel=1e-5)  # 18.5 cm
    assert np.isinf(gap[4]) and np.isinf(gap[5])  # edge-on, or no normal: no contradiction


def _faces_on_plane(z: float, spacing: float, half: float):
    """Centres (M, 3) of square faces ``spacing`` apart tiling [-half, half]^2 at height z, their normals and radii."""
    s = np.arange(-half + spacing / 2, half, spacing)
    x, y = np.meshgrid(s, s)
    centres = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(centres), 1))
    return centres, normals, np.full(len(centres), spacing / np.sqrt(2.0))


def _grazing_view(camera_height: float, distance: float):
    """A camera ``camera_height`` above z = 0, looking along +x at a point ``distance`` away on the ground."""
    return look_at([0.0, 0.0, camera_height], [distance, 0.0, 0.0])


def _between(centres, normals, radii, measured, voting, pose):
    rays, length = unit_rays(CAMERA, np.float32)
    uv, z = project(centres, CAMERA, pose)
    uv[z <= 0] = np.nan
    return votes_between_pixels(
        centres, normals, radii, measured, voting, rays, length, uv, pose[:3, 3], pose[:3, :3], CAMERA.pixel_angle(), RULES
    )


def test_a_small_face_is_seen_through_where_the_ray_crosses_its_plane_short_of_d():
    """A ray that voted a contradiction sees through the small faces around it whose plane it crosses well
    short of D (a car's roof that left, seen at grazing incidence), but not the faces of the surface D hits
    (the ground it reaches), nor faces whose pixel did not vote."""
    pose = _grazing_view(1.9, 8.0)
    rays, length = unit_rays(CAMERA, np.float64)
    world_rays = rays @ pose[:3, :3].T
    # D: the ground (z = 0) where the rays reach it, else a wall 30 m off
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(world_rays[..., 2] < -1e-6, -1.9 / world_rays[..., 2], np.inf)
    distance = np.minimum(t_ground, 30.0)
    measured = (distance / length).astype(np.float32)  # z-depth
    voting = np.ones(CAMERA.shape, dtype=bool)
    # a roof 1.5 m up, 6-9 m ahead, tiled by 2 cm faces (much smaller than a pixel there: 5 cm)
    roof, normals, radii = _faces_on_plane(1.5, 0.02, 1.5)
    roof[:, 0] += 7.5
    seen = _between(roof, normals, radii, measured, voting, pose)
    uv, _ = project(roof, CAMERA, pose)
    in_image = (uv[:, 0] >= 0) & (uv[:, 0] < CAMERA.width) & (uv[:, 1] >= 0) & (uv[:, 1] < CAMERA.height)
    assert in_image.sum() > 1000
    assert seen[in_image].mean() > 0.99, seen[in_image].mean()
    # the same faces on the ground D reaches: nothing seen through
    ground = roof.copy()
    ground[:, 2] = 0.0
    assert not _between(ground, normals, radii, measured, voting, pose).any()
    # no pixel voted: no face is seen through
    assert not _between(roof, normals, radii, measured, np.zeros_like(voting), pose).any()


def _roof_then_gone(close: int = 4, far: int = 8) -> FrameList:
    """A plane at z = 1 m seen from 1 m for ``close`` frames (faces a pixel wide), then gone, seen from 4 m
    (faces a quarter of a pixel) with a wall 6 m away behind it. The camera drifts a fraction of a pixel a
    frame."""
    out = []
    for i in range(close + far):
        pose = np.eye(4)
        pose[:3, 3] = [0.0011 * i, 0.0007 * i, 0.0 if i < close else -3.0]
        depth = np.full(CAMERA.shape, 1.0 if i < close else 6.0, np.float32)
        out.append(DepthFrame(depth, CAMERA, pose, i))
    return FrameList(out)


def _area_at(loop, z: float) -> float:
    mesh = loop.mesh()
    if mesh.GetNumberOfCells() == 0:
        return 0.0
    points, triangles = polydata_arrays(mesh)
    corners = points[triangles]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return float(area[np.abs(corners[:, :, 2].mean(axis=1) - z) < 0.05].sum())


def test_faces_meshed_from_close_go_when_seen_from_afar():
    """Faces a quarter of a pixel wide in the far view are shown by a pixel centre in few frames; they go
    with the contradictions around them all the same."""
    frames = _roof_then_gone()
    loop = mabdi.MabdiLoop(frames, surface="pixel_grid", noise="kinect", registration=RegistrationParameters(enabled=False))
    for i in range(4):
        loop.step(i)
    plane = _area_at(loop, 1.0)
    assert plane > 0.5  # the plane fills the close view: 1 m x 0.75 m
    assert image_pose(loop.measured_image())[2, 3] == 0.0
    for i in range(4, len(frames)):
        loop.step(i)
    assert _area_at(loop, 1.0) <= 0.01 * plane, (_area_at(loop, 1.0), plane)


@pytest.mark.parametrize(("beyond", "counts"), [(3.0, True), (0.1, False)])
def test_a_contradiction_at_grazing_incidence_counts_when_d_is_beyond_the_stretched_gap(beyond, counts):
    """A face 86 degrees from the rays (a roof seen across a street): seen through by metres it is a
    contradiction; by 10 cm (less than 5 cm stretched to 18.5 cm along the ray) it is not. A face facing the
    rays is contradicted by the 10 cm either way."""
    from mabdi.stages.classifier import CONTRADICTED
    from mabdi.stages.removal import removal_votes

    shape = (9, 9)
    rays, _ = unit_rays(Intrinsics(fx=90, fy=90, cx=4.5, cy=4.5, width=9, height=9, far=60.0), np.float32)  # 3 degrees wide
    labels = np.full(shape, CONTRADICTED, dtype=np.uint8)
    expected = np.full(shape, 5.0, np.float32)
    measured = expected + np.float32(beyond)
    face_ids = np.ones(shape, dtype=np.int64)
    face_ids[:, 5:] = 2
    incidence = np.radians(86.0)
    normals = {1: [0.0, np.sin(incidence), np.cos(incidence)], 2: [0.0, 0.0, 1.0]}  # camera frame = world here

    def normals_of(ids):
        return np.array([normals[int(i)] for i in ids], dtype=np.float32)

    faces, contradicted, confirmed, _ = removal_votes(labels, measured, expected, face_ids, rays, np.eye(4), normals_of, RULES)
    by_face = dict(zip(faces.tolist(), contradicted.tolist(), strict=True))
    assert by_face.get(2, 0) > 0
    assert (by_face.get(1, 0) > 0) == counts
    assert not confirmed.any()


def test_a_patch_of_faces_smaller_than_a_pixel_is_looked_at_beside_a_contradicted_one():
    """A departed surface meshed in two patches: one of faces many pixels wide, voted against by the pixels
    that see through it, and beside it a remnant of faces a third of a pixel wide that no pixel shows. The
    remnant's faces are contradicted with its neighbour's, though no pixel voted on that patch; a patch of
    such faces far from the contradicted faces (3 m away, though in view and seen through) is not looked at."""
    world = FilterWorldMesh(chunk_size=100.0)
    world.store.add_patch("frame_0", plane_mesh([0.0, 0.0, 1.0], [0, 0, 1], size=0.4, subdivisions=2), frame=0)
    world.store.add_patch("frame_1", plane_mesh([0.21, 0.0, 1.0], [0, 0, 1], size=0.02, subdivisions=10), frame=1)
    world.store.add_patch("frame_2", plane_mesh([0.9, 0.0, 3.0], [0, 0, 1], size=0.06, subdivisions=10), frame=2)
    counts = [world.block(k).GetNumberOfCells() for k in ("frame_0", "frame_1", "frame_2")]
    table = FaceIdTable(["frame_0", "frame_1", "frame_2"], [1, 1 + counts[0], 1 + counts[0] + counts[1]], counts)
    measured = np.full(CAMERA.shape, 6.0, np.float32)  # seen through everywhere
    voting = np.ones(CAMERA.shape, dtype=bool)  # every pixel voted a contradiction
    faces = np.arange(1, 1 + counts[0])
    removal = ObjectRemoval(RULES, threshold=None)
    found = removal._between_pixels(
        faces, np.ones(len(faces), np.int64), np.zeros(len(faces), np.int64), voting, measured, CAMERA, np.eye(4),
        table, world, RULES, None, None,
    )
    remnant = np.arange(1 + counts[0], 1 + counts[0] + counts[1])
    assert np.isin(remnant, found).mean() > 0.9
    far = np.arange(1 + counts[0] + counts[1], 1 + sum(counts))
    assert not np.isin(far, found).any()
