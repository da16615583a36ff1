"""Frame-to-map registration: projective point-to-plane ICP of D against E, its checks, the pose's
depth uncertainty, and the loop that meshes and votes with the registered pose."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import mabdi
from conftest import REPO, merged, plane_mesh
from mabdi.camera import Intrinsics, look_at
from mabdi.config import load_run_config, set_value
from mabdi.depth import DepthFrame
from mabdi.errors import ConfigError
from mabdi.render.depth_image import DepthRenderer
from mabdi.sensor_noise import SensorNoise, noise_rng
from mabdi.stages.map_anchor import MapAnchor
from mabdi.pose_noise import PoseNoise
from mabdi.stages.registration import (
    RegistrationParameters,
    fuse_with_given,
    pose_depth_sigma,
    register_depth,
    transform_size,
)
from mabdi.sources.primitives import box
from mabdi.sources.frames import FrameList
from mabdi.sources.scene import SourceScene


def perturbed(pose: np.ndarray, translation, rotation_deg) -> np.ndarray:
    """``pose`` moved by ``translation`` (world, m) and turned by ``rotation_deg`` (rotation vector, camera frame)."""
    out = pose.copy()
    out[:3, :3] = pose[:3, :3] @ Rotation.from_rotvec(np.radians(rotation_deg)).as_matrix()
    out[:3, 3] += translation
    return out


NOISE_FREE = SensorNoise()
ROOM_CAMERA = Intrinsics()


def depth_of(renderer: DepthRenderer, mesh, intrinsics: Intrinsics, pose, noise: SensorNoise = NOISE_FREE, frame: int = 0):
    zbuffer = renderer.render_zbuffer(mesh, intrinsics, pose)
    rng = None if noise.model == "none" else noise_rng(7, frame)
    return noise.depth_from_zbuffer(zbuffer, intrinsics.near, intrinsics.far, rng, intrinsics=intrinsics)


@pytest.fixture(scope="module")
def bunnies():
    """Run 2's scene and four of its poses."""
    config = load_run_config(REPO / "scenes" / "bunnies.toml")
    scene = SourceScene(config.scene, frames=config.run.frames)
    poses = mabdi.simulate.path.path_from_config(config.run.frames, config.path)
    return scene.mesh_at(0), poses[[3, 17, 29, 41]]


def test_icp_recovers_the_true_pose_against_a_known_map(bunnies):
    """D from the true pose (z-buffer noise), E of the true scene from a pose 5-10 mm and 0.3-0.5 degrees
    off: the registered poses are within 1.5 mm and 0.05 degrees of the true ones, 1 mm and 0.03 degrees
    in the median."""
    mesh, poses = bunnies
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("zbuffer")
    rng = np.random.default_rng(3)
    errors = []
    for i, true in enumerate(poses):
        given = perturbed(true, rng.normal(0, 0.005, 3), rng.normal(0, 0.25, 3))
        before = transform_size(np.linalg.inv(true) @ given)
        measured = depth_of(renderer, mesh, intrinsics, true, noise, frame=i)
        expected = depth_of(renderer, mesh, intrinsics, given)
        result = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        assert result.registered, result.status
        assert result.inlier_share > 0.95
        error = transform_size(np.linalg.inv(true) @ given @ result.transform)
        assert error[0] < 0.0015 and error[1] < 0.05, (before, error)
        assert np.all(np.linalg.eigvalsh(result.covariance) >= 0)
        errors.append(error)
    assert np.all(np.median(np.array(errors), axis=0) < [0.001, 0.03]), errors


def test_a_wall_with_a_recess_holds_the_pose_across_it_and_leaves_the_height_as_given():
    """A wall with a recess 3 cm deep (a closed door in its frame) running the whole height of the view: the
    wall holds the distance and the recess's edges the slide along the wall, and nothing holds the height.
    The height stays as given (the normals that the sensor's noise tilts held it at a few hundred-thousandths
    of the wall's information, and moved the pose centimetres up or down), the rest is corrected, and the
    covariance says the height is known far less than the rest (at most what
    :data:`~mabdi.stages.registration_kernels.UNCONSTRAINED` of the information would tell)."""
    wall = merged(
        _moved(box((0.1, 9.5, 20.0)), [2.55, -5.25, 0.0]),
        _moved(box((0.1, 9.5, 20.0)), [2.55, 5.25, 0.0]),
        _moved(box((0.1, 1.0, 20.0)), [2.58, 0.0, 0.0]),  # the recess's back, 3 cm behind the wall's face
    )
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("zbuffer")
    true = look_at([0.0, -0.3, 0.0], [2.5, 0.1, 0.05])
    for frame, offset in enumerate(([0.004, 0.003, 0.006], [-0.003, -0.004, -0.008])):
        given = perturbed(true, offset, [0.0, 0.0, 0.0])
        measured = depth_of(renderer, wall, intrinsics, true, noise, frame=frame)
        expected = depth_of(renderer, wall, intrinsics, given)
        result = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        assert result.registered, result.status
        registered = given @ result.transform
        error = registered[:3, 3] - true[:3, 3]
        assert abs(error[0]) < 0.001 and abs(error[1]) < 0.0015, error  # held by the wall and the recess's edges
        assert registered[2, 3] == pytest.approx(given[2, 3], abs=0.0005), error  # nothing holds the height
        sigma = np.sqrt(np.diag(true[:3, :3] @ result.covariance[3:, 3:] @ true[:3, :3].T))
        assert sigma[2] > 50 * sigma[0], sigma  # the height far less known than the distance to the wall


def _moved(mesh, offset):
    points, triangles = mesh
    return points + np.asarray(offset), triangles


def test_a_plane_alone_fixes_only_what_it_constrains():
    """Seen head-on, a plane fixes the distance to it and the tilt, not a slide along it: the slide is
    left as given (no step along an unconstrained direction), the rest is corrected."""
    mesh = plane_mesh([0, 0, 0], [0, 0, 1], size=20.0)
    intrinsics = Intrinsics()
    true = look_at([0.0, 0.0, 2.0], [0.0, 0.3, 0.0])
    given = perturbed(true, [0.02, 0.0, 0.01], [0.0, 0.0, 0.0])
    renderer = DepthRenderer()
    measured = depth_of(renderer, mesh, intrinsics, true)
    expected = depth_of(renderer, mesh, intrinsics, given)
    result = register_depth(measured, expected, intrinsics, SensorNoise(), RegistrationParameters())
    assert result.registered
    registered = given @ result.transform
    # the height above the plane is corrected, the slide along x stays as given
    assert registered[2, 3] == pytest.approx(2.0, abs=2e-4)
    assert registered[0, 3] == pytest.approx(0.02, abs=2e-4)


def _undulating_wall(amplitude: float, wavelength: float, extent: float = 4.0, n: int = 240):
    """The plane z = 0 as a map that departs from it by up to ``amplitude`` (m) in waves ``wavelength`` (m) long:
    the faces of a real map of a flat wall, tilted a degree or two by their own error."""
    from mabdi.polydata import triangles_polydata

    s = np.linspace(-extent / 2, extent / 2, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    k = 2 * np.pi / wavelength
    z = amplitude * np.sin(k * x + 0.3) * np.sin(0.8 * k * y + 1.1)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    v0 = (i * n + j).ravel()
    v1, v2, v3 = v0 + n, v0 + n + 1, v0 + 1
    triangles = np.concatenate([np.stack([v0, v1, v2], 1), np.stack([v0, v2, v3], 1)])
    return triangles_polydata(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), triangles)


@pytest.mark.parametrize("amplitude, wavelength", [(0.002, 0.3), (0.003, 0.4), (0.004, 0.6)])
def test_a_wall_the_map_holds_with_tilted_faces_keeps_the_slide_and_the_turn_as_given(amplitude, wavelength):
    """A flat wall fills the view; the map's copy of it undulates by a few millimetres (its normals tilted by
    up to 1.6-2.4 degrees), as a real map's faces do. The wall holds the distance and the tilt; only the
    normals' tilts hold the slide along it and the turn about its normal, at a few ten-thousandths of the
    distance's information. Those take no step (they moved the camera 3-18 mm along the wall and 0.08-0.16
    degrees about its normal, or left the frame unconverged), and the distance given 4 mm off is corrected."""
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("zbuffer")
    true = look_at([0.05, -0.02, 1.0], [0.1, 0.05, 0.0])
    given = perturbed(true, [0.0, 0.0, 0.004], [0.0, 0.0, 0.0])
    measured = depth_of(renderer, plane_mesh([0, 0, 0], [0, 0, 1], size=20.0), intrinsics, true, noise, frame=1)
    expected = depth_of(renderer, _undulating_wall(amplitude, wavelength), intrinsics, given)
    result = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
    assert result.registered, result.status
    registered = given @ result.transform
    assert np.abs(registered[:2, 3] - given[:2, 3]).max() < 0.0005  # no slide along the wall
    assert registered[2, 3] == pytest.approx(true[2, 3], abs=0.0005)  # the distance corrected
    turn = Rotation.from_matrix(registered[:3, :3] @ given[:3, :3].T).as_rotvec()
    assert abs(np.degrees(turn[2])) < 0.02  # no turn about the wall's normal (world z)


def test_structure_counts_only_normals_that_lie_across_a_motion():
    """The information a wall gives along a motion, counting only normals more than STRUCTURE_MIN_ANGLE out of
    the plane the motion moves its points in: all of it along the wall's normal; none along the wall or about
    its normal, whether the wall faces the camera or is tilted 5 degrees (its normals then hold those at
    (sin 5 deg)^2 of the normal's information in the normal equations); and what a step across the view holds."""
    from mabdi.stages import registration
    from mabdi.stages.registration_kernels import structure_information

    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    directions = np.eye(6)  # turns about x, y, z, then moves along x, y, z (camera frame)
    sine = float(np.sin(np.radians(registration.STRUCTURE_MIN_ANGLE)))

    def information(mesh):
        pose = np.eye(4)  # camera at the origin looking down +z
        depth = np.ascontiguousarray(depth_of(renderer, mesh, intrinsics, pose), dtype=np.float32)
        points, z, *_ = registration.sample_points(depth, intrinsics, 8, average=False)
        scale, gate = np.full(len(points), 0.01), np.full(len(points), 0.05)
        args = (
            points, scale, gate, np.eye(3), np.zeros(3), depth, np.empty((*depth.shape, 3)), np.zeros(depth.shape, dtype=np.int8),
            intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, registration.NORMAL_STEP, registration.NORMAL_MAX_JUMP,
        )  # fmt: skip
        return structure_information(*args, directions, sine), structure_information(*args, directions, 0.0), len(points)

    for normal in ([0.0, 0.0, -1.0], [np.sin(np.radians(5.0)), 0.0, -np.cos(np.radians(5.0))]):
        held, plain, count = information(plane_mesh([0.0, 0.0, 2.0], normal, size=20.0))
        assert held[5] == pytest.approx(plain[5], rel=0.02) and plain[5] > 0.9 * count / 0.01**2  # the distance
        assert held[3] == held[4] == held[2] == 0.0  # the slide along the wall and the turn about its normal
        if normal[0] != 0.0:
            assert plain[3] == pytest.approx(np.sin(np.radians(5.0)) ** 2 * plain[5], rel=0.05)  # what the tilt holds
    step = merged(  # a wall 2 m away, its part right of x = 0.3 m half a metre nearer: the step's side holds the slide along x
        plane_mesh([-4.7, 0.0, 2.0], [0, 0, -1], size=10.0), plane_mesh([5.3, 0.0, 1.5], [0, 0, -1], size=10.0),
        plane_mesh([0.3, 0.0, 1.75], [-1, 0, 0], size=0.5, subdivisions=4),
    )
    held, plain, _ = information(step)
    assert held[3] > 0.5 * plain[3] > 0.0 and held[4] == 0.0


def test_a_view_the_map_does_not_explain_is_not_registered():
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    pose = np.eye(4)
    wall = depth_of(renderer, plane_mesh([0, 0, 2], [0, 0, -1], size=10), intrinsics, pose)
    far_wall = depth_of(renderer, plane_mesh([0, 0, 3], [0, 0, -1], size=10), intrinsics, pose)
    parameters = RegistrationParameters()
    assert register_depth(wall, np.full_like(wall, np.nan), intrinsics, SensorNoise(), parameters).status == "no_map"
    result = register_depth(wall, far_wall, intrinsics, SensorNoise(), parameters)
    assert not result.registered and result.status in ("few_points", "few_inliers")
    assert np.array_equal(result.transform, np.eye(4))


def test_pose_uncertainty_becomes_depth_uncertainty_by_the_angle_of_incidence():
    """A lateral pose error d reads as d tan(theta) in depth on a surface seen at incidence theta; along
    the optical axis it reads as itself on a surface seen head-on."""
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    sigma = 0.001
    lateral = np.diag([0.0, 0.0, 0.0, 0.0, sigma**2, 0.0])  # translation along the camera's y (image down)
    axial = np.diag([0.0, 0.0, 0.0, 0.0, 0.0, sigma**2])
    head_on = depth_of(renderer, plane_mesh([0, 0, 2], [0, 0, -1], size=10), intrinsics, np.eye(4))
    centre = (240, 320)
    assert pose_depth_sigma(head_on, intrinsics, axial)[centre] == pytest.approx(sigma, rel=0.01)
    assert pose_depth_sigma(head_on, intrinsics, lateral)[centre] == pytest.approx(0.0, abs=1e-5)
    for theta in (30.0, 60.0, 75.0):
        normal = [0.0, -np.sin(np.radians(theta)), -np.cos(np.radians(theta))]  # tilted about the camera's x
        tilted = depth_of(renderer, plane_mesh([0, 0, 2], normal, size=20), intrinsics, np.eye(4))
        expected = sigma * np.tan(np.radians(theta))
        assert pose_depth_sigma(tilted, intrinsics, lateral)[centre] == pytest.approx(expected, rel=0.03), theta
    assert np.isnan(pose_depth_sigma(np.full_like(head_on, np.nan), intrinsics, axial)).all()


def test_pose_depth_sigma_is_the_same_image_on_any_number_of_cores_and_for_a_zero_covariance():
    """The kernel's rows run in parallel threads: the image equals the one-thread kernel's, bit for bit; a zero
    covariance (a pose stated exact) gives 0 wherever E has a surface without the kernel, as the kernel would."""
    from numba import njit

    from mabdi.stages.registration import NORMAL_MAX_JUMP, NORMAL_STEP
    from mabdi.stages.registration_kernels import pose_sigma_image

    one_thread = njit(pose_sigma_image.py_func)
    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:120, 0:160]
    expected = (1.5 + 0.002 * cols + 0.001 * rows + 0.002 * rng.standard_normal((120, 160))).astype(np.float32)
    expected[30:60, 40:80] = np.nan
    expected[80:, :30] += 0.5  # a depth jump: silhouettes take the head-on value
    k = Intrinsics(fx=130.0, fy=130.0, cx=80.0, cy=60.0, width=160, height=120)
    root = rng.standard_normal((6, 6))
    cosine = float(np.cos(np.radians(80.0)))
    for covariance in (root @ root.T * 1e-6, np.zeros((6, 6))):
        args = (expected, k.fx, k.fy, k.cx, k.cy, NORMAL_STEP, NORMAL_MAX_JUMP, covariance, cosine)
        np.testing.assert_array_equal(pose_sigma_image(*args), one_thread(*args))
        np.testing.assert_array_equal(pose_depth_sigma(expected, k, covariance), one_thread(*args))
    assert np.nanmax(pose_depth_sigma(expected, k, root @ root.T * 1e-6)) > 0


def room_frames(poses: np.ndarray, *, extra=None, intrinsics: Intrinsics = ROOM_CAMERA, noise="none") -> list[np.ndarray]:
    """Depth images of a small room (floor, two walls, a box) from ``poses``; ``extra``: a mesh added from frame 4."""
    box_points, box_triangles = box([0.6, 0.6, 0.8])
    room = merged(
        plane_mesh([0, 0, 0], [0, 0, 1], size=8.0),
        plane_mesh([0, 2.5, 0], [0, -1, 0], size=8.0),
        plane_mesh([2.5, 0, 0], [-1, 0, 0], size=8.0),
        (box_points + [0.5, 0.8, 0.4], box_triangles),
    )
    renderer = DepthRenderer()
    noise = SensorNoise.of(noise)
    depths = []
    for i, pose in enumerate(poses):
        mesh = room if extra is None or i < 4 else merged(room, extra)
        depths.append(depth_of(renderer, mesh, intrinsics, pose, noise, frame=i))
    return depths


def room_poses(count: int) -> np.ndarray:
    return np.stack([look_at([-1.5 + 0.05 * i, -1.8, 1.4], [0.8, 0.8, 0.5]) for i in range(count)])


def test_the_loop_meshes_with_the_registered_pose_and_reports_it():
    """Poses 7 mm and 0.5 degrees off (median), that jitter stated (``given_sigma``; eight frames are too few to
    learn it from, :class:`PoseJitter`): the frames fit each other within 1.5 mm and 0.05 degrees (the map's
    frame itself is only as good as the mean of eight given poses: the anchor's test)."""
    true = room_poses(8)
    rng = np.random.default_rng(5)
    given = np.stack([perturbed(p, rng.normal(0, 0.005, 3), rng.normal(0, 0.3, 3)) for p in true])
    depths = room_frames(true, noise="kinect")
    frames = [DepthFrame(d, Intrinsics(), g, i, i / 30) for i, (d, g) in enumerate(zip(depths, given, strict=True))]
    stated = RegistrationParameters(given_sigma=[0.005, 0.3])
    loop = mabdi.MabdiLoop(FrameList(frames), surface="quadtree", noise="kinect", registration=stated)
    records = [loop.step(i) for i in range(len(frames))]
    assert records[0].registration == "no_map" and all(r.registered for r in records[1:])
    trajectory = loop.trajectory()
    relative = np.array(
        [transform_size(np.linalg.inv(np.linalg.inv(true[0]) @ true[i]) @ np.linalg.inv(trajectory[0]) @ trajectory[i]) for i in range(1, 8)]
    )
    assert np.median(relative[:, 0]) < 0.0015 and np.median(relative[:, 1]) < 0.05, relative
    assert relative[:, 0].max() < 0.004 and relative[:, 1].max() < 0.1, relative
    world_from_map = loop.world_from_map()
    for record in records[1:]:  # the corrections of the given poses are reported (mm, degrees, the fit's residual)
        assert 0 < record.correction_mm < 50 and 0 < record.correction_deg < 2
        assert 0 < record.residual_mm < 20 and 0.9 < record.inlier_share <= 1
    mesh = loop.mesh()
    map_points = mabdi.polydata.polydata_arrays(loop.world.mesh())[0]
    assert np.allclose(mabdi.polydata.polydata_arrays(mesh)[0], map_points @ world_from_map[:3, :3].T + world_from_map[:3, 3], atol=1e-5)
    assert sum(r.cells_removed for r in records) == 0

    off = mabdi.MabdiLoop(FrameList(frames), surface="quadtree", noise="kinect", registration=RegistrationParameters(enabled=False))
    assert off.step(1).registration == "off"
    assert np.array_equal(off.trajectory()[1], given[1])


def test_a_pose_source_that_states_its_accuracy_is_weighed_by_it_from_the_first_frame():
    """``given_sigma``: exact poses stated as exact are kept as given (the map's frame too) and no ICP is run
    (status "exact"; such frames vote for removal as registered ones do); jittery poses stated as such still follow the fit: the
    frames fit each other within 1.5 mm and 0.05 degrees (median) where the given ones are 7 mm and 0.5
    degrees apart."""
    true = room_poses(8)
    depths = room_frames(true, noise="kinect")
    rng = np.random.default_rng(5)
    jittered = np.stack([perturbed(p, rng.normal(0, 0.005, 3), rng.normal(0, 0.3, 3)) for p in true])

    class ExactSource(FrameList):  # a source that says its poses are exact, as the simulator does without pose noise
        @property
        def pose_accuracy(self):
            return PoseNoise()

    def run(given, sigma, source=FrameList):
        frames = [DepthFrame(d, Intrinsics(), g, i, i / 30) for i, (d, g) in enumerate(zip(depths, given, strict=True))]
        loop = mabdi.MabdiLoop(source(frames), surface="quadtree", noise="kinect", registration=RegistrationParameters(given_sigma=sigma))
        records = [loop.step(i) for i in range(len(frames))]
        return records, loop.trajectory()

    for sigma, source in (([0.0, 0.0], FrameList), ("source", ExactSource)):
        records, trajectory = run(true, sigma, source)
        assert [r.registration for r in records] == ["exact"] * len(records) and not any(r.registered for r in records)
        assert all(np.isnan(r.residual_mm) and r.correction_mm < 1e-6 for r in records)  # no ICP, no correction
        np.testing.assert_allclose(trajectory, true, atol=1e-9)  # the given poses, as they are
    for sigma, source in (("source", FrameList), ("learnt", ExactSource)):  # not stated: learnt, and kept where the fit is no better
        records, learnt = run(true, sigma, source)
        assert all(r.registered for r in records[1:])
        assert max(transform_size(np.linalg.inv(t) @ p)[0] for t, p in zip(true, learnt, strict=True)) < 5e-4

    _, stated = run(jittered, [0.005, 0.3])
    relative = np.array(
        [transform_size(np.linalg.inv(np.linalg.inv(true[0]) @ true[i]) @ np.linalg.inv(stated[0]) @ stated[i]) for i in range(1, 8)]
    )
    assert np.median(relative[:, 0]) < 0.0015 and np.median(relative[:, 1]) < 0.05, relative


def test_given_sigma_is_checked():
    with pytest.raises(ConfigError, match="given_sigma"):
        RegistrationParameters(given_sigma=[0.001])
    with pytest.raises(ConfigError, match="given_sigma"):
        RegistrationParameters(given_sigma=[0.001, -1.0])
    with pytest.raises(ConfigError, match="given_sigma.*'source', 'learnt'.*'guess'"):
        RegistrationParameters(given_sigma="guess")
    rotation, translation = RegistrationParameters(given_sigma=[0.002, 0.5]).given_variance(PoseNoise(0.1, 1.0))
    assert rotation == pytest.approx((np.radians(0.5) ** 2, 0.0)) and translation == pytest.approx((0.002**2, 0.0))
    drifting = PoseNoise(jitter_translation=0.002, jitter_rotation=0.1, drift_translation=0.01, drift_rotation=0.5)
    rotation, translation = RegistrationParameters().given_variance(drifting)  # "source": the source's statement
    assert rotation == pytest.approx((np.radians(0.1) ** 2, np.radians(0.5) ** 2)) and translation == pytest.approx((0.002**2, 0.01**2))
    assert RegistrationParameters().given_variance(None) is None  # a source that states nothing: learnt
    assert RegistrationParameters(given_sigma="learnt").given_variance(drifting) is None


def anchored(offsets_rotation: np.ndarray, offsets_translation: np.ndarray, positions: np.ndarray, covariance=None) -> MapAnchor:
    """A MapAnchor fed frames whose registered poses differ from their given poses by the offsets (each
    registration with ``covariance``, None: exact)."""
    anchor = MapAnchor()
    travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))])
    for rotation, translation, position, s in zip(offsets_rotation, offsets_translation, positions, travelled, strict=True):
        given = np.eye(4)
        given[:3, 3] = position
        registered = np.eye(4)
        registered[:3, :3] = Rotation.from_rotvec(rotation).as_matrix()
        registered[:3, 3] = position + translation
        anchor.add(given, registered, s, covariance)
    return anchor


def test_the_anchor_averages_jitter_and_trusts_the_start_of_a_drift():
    """Map frame = world moved by (2 degrees about z, 5 cm in x). Given poses with white jitter: the anchor
    is the mean (within 3 sigma / sqrt(N)); given poses that drift from an exact start: the first frames."""
    n = 200
    rng = np.random.default_rng(0)
    angle = np.radians(2.0)
    positions = np.stack([3 * np.cos(np.linspace(0, 4 * np.pi, n)), 3 * np.sin(np.linspace(0, 4 * np.pi, n)), np.ones(n)], axis=1)
    true_rotation = np.array([0.0, 0.0, angle])
    rotation_matrix = Rotation.from_rotvec(true_rotation).as_matrix()
    lever = positions @ (rotation_matrix - np.eye(3)).T + [0.05, 0.0, 0.0]  # dt = (R_A - I) t_G + t_A
    sigma_r, sigma_t = np.radians(0.3), 0.005
    jitter = anchored(true_rotation + rng.normal(0, sigma_r, (n, 3)), lever + rng.normal(0, sigma_t, (n, 3)), positions)
    estimate = jitter.map_from_world
    error_rotation = np.degrees(Rotation.from_matrix(estimate[:3, :3].T @ rotation_matrix).magnitude())
    assert error_rotation < 3 * np.degrees(sigma_r) * np.sqrt(3) / np.sqrt(n)
    assert np.linalg.norm(estimate[:3, 3] - [0.05, 0.0, 0.0]) < 3 * sigma_t * np.sqrt(3) / np.sqrt(n) + 0.001

    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    walk_r = np.concatenate([np.zeros((1, 3)), np.cumsum(rng.normal(0, 1, (n - 1, 3)) * np.radians(0.5) * np.sqrt(steps)[:, None], axis=0)])
    walk_t = np.concatenate([np.zeros((1, 3)), np.cumsum(rng.normal(0, 1, (n - 1, 3)) * 0.01 * np.sqrt(steps)[:, None], axis=0)])
    drift = anchored(true_rotation + walk_r, lever + walk_t, positions)
    estimate = drift.map_from_world
    error_rotation = np.degrees(Rotation.from_matrix(estimate[:3, :3].T @ rotation_matrix).magnitude())
    assert error_rotation < 0.05, error_rotation  # the walk's spread over the run is degrees
    assert np.linalg.norm(estimate[:3, 3] - [0.05, 0.0, 0.0]) < 0.005


def test_the_anchor_turns_the_map_by_where_the_cameras_are_as_well_as_how_they_look():
    """Map frame = world turned by 0.2 degrees about a tilted axis; 60 given poses on a 3 m circle with
    white jitter of 0.3 degrees and 2 mm. The orientations alone place the map's rotation to about
    0.3 / sqrt(60) degrees per axis; the cameras' places, 3 m from the origin, to 2 mm / 3 m / sqrt(30)
    (0.007 degrees). The anchor uses both: within 0.015 degrees, learnt or stated, where the orientations'
    mean is further off."""
    n = 60
    rng = np.random.default_rng(3)
    circle = np.linspace(0, 2 * np.pi, n, endpoint=False)
    positions = np.stack([3 * np.cos(circle), 3 * np.sin(circle), 1.0 + 0.2 * np.sin(3 * circle)], axis=1)
    true_rotation = np.radians(0.2) * np.array([0.6, -0.48, 0.64])
    rotation_matrix = Rotation.from_rotvec(true_rotation).as_matrix()
    sigma_r, sigma_t = np.radians(0.3), 0.002
    rotations = true_rotation + rng.normal(0, sigma_r, (n, 3))
    translations = positions @ (rotation_matrix - np.eye(3)).T + [0.01, 0.0, -0.004] + rng.normal(0, sigma_t, (n, 3))
    orientations_alone = np.degrees(np.linalg.norm(rotations.mean(axis=0) - true_rotation))
    assert orientations_alone > 0.02, orientations_alone  # what the old anchor could do with these frames
    learnt = anchored(rotations, translations, positions).map_from_world
    stated = MapAnchor(stated=((sigma_r**2, 0.0), (sigma_t**2, 0.0)))
    for rotation, translation, position in zip(rotations, translations, positions, strict=True):
        given, registered = np.eye(4), np.eye(4)
        given[:3, 3] = position
        registered[:3, :3] = Rotation.from_rotvec(rotation).as_matrix()
        registered[:3, 3] = position + translation
        stated.add(given, registered, 0.0)
    for estimate in (learnt, stated.map_from_world):
        error = np.degrees(Rotation.from_matrix(estimate[:3, :3].T @ rotation_matrix).magnitude())
        assert error < 0.015, error
        assert np.linalg.norm(estimate[:3, 3] - [0.01, 0.0, -0.004]) < 0.001


def test_the_anchor_tells_the_given_poses_error_from_the_registrations_own():
    """Offsets of exact given poses spread by the registration's own noise (0.02 degrees, 1 mm): the given
    poses read as (nearly) exact: under half the registration's sigma. Given poses with jitter of 0.3 degrees / 5 mm on top: their variance is found
    within 25% (at the start: the white part). Drift: the variance grows with the distance travelled."""
    n = 200
    rng = np.random.default_rng(1)
    positions = np.stack([3 * np.cos(np.linspace(0, 4 * np.pi, n)), 3 * np.sin(np.linspace(0, 4 * np.pi, n)), np.ones(n)], axis=1)
    own_r, own_t = np.radians(0.02), 0.001
    covariance = np.diag([own_r**2] * 3 + [own_t**2] * 3)
    exact = anchored(rng.normal(0, own_r, (n, 3)), rng.normal(0, own_t, (n, 3)), positions, covariance)
    rotation, translation = exact.given_variance(0.0)
    assert np.sqrt(rotation) < 0.5 * own_r and np.sqrt(translation) < 0.5 * own_t
    sigma_r, sigma_t = np.radians(0.3), 0.005
    jitter = anchored(
        rng.normal(0, np.hypot(sigma_r, own_r), (n, 3)), rng.normal(0, np.hypot(sigma_t, own_t), (n, 3)), positions, covariance
    )
    rotation, translation = jitter.given_variance(0.0)
    assert abs(rotation / sigma_r**2 - 1) < 0.25 and abs(translation / sigma_t**2 - 1) < 0.25
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    walk = np.concatenate([np.zeros((1, 3)), np.cumsum(rng.normal(0, 1, (n - 1, 3)) * 0.01 * np.sqrt(steps)[:, None], axis=0)])
    drift = anchored(np.zeros((n, 3)), walk, positions, covariance)
    assert drift.given_variance(20.0)[1] > 1.5 * drift.given_variance(5.0)[1] > 0
    assert MapAnchor().given_variance(0.0) is None  # too few frames to tell


def test_offsets_bound_to_a_place_are_the_maps_error_not_drift():
    """Exact given poses registered to a map that is off by up to 1 cm / 0.1 degrees, differently at each place
    (a smooth function of where the frame is), each registration with 1 mm / 0.02 degrees of its own noise.
    Over two circles the offsets come back at each place: the given poses read as exact (under the
    registration's own sigma, 20 m on). The same map errors on a drive that never comes back cannot be told
    from drift and read as drift (the safe side)."""
    rng = np.random.default_rng(3)
    own_r, own_t = np.radians(0.02), 0.001
    covariance = np.diag([own_r**2] * 3 + [own_t**2] * 3)

    def map_error(phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        waves = np.stack([np.sin(phase), np.cos(2 * phase), np.sin(3 * phase)], axis=1)
        return np.radians(0.1) * waves + rng.normal(0, own_r, waves.shape), 0.01 * waves + rng.normal(0, own_t, waves.shape)

    n = 100
    angle = np.linspace(0, 4 * np.pi, n)
    circles = np.stack([3 * np.cos(angle), 3 * np.sin(angle), np.ones(n)], axis=1)
    rotation, translation = anchored(*map_error(angle), circles, covariance).given_variance(20.0)
    assert np.sqrt(rotation) < own_r and np.sqrt(translation) < own_t, (np.degrees(np.sqrt(rotation)), np.sqrt(translation))
    line = np.stack([np.linspace(0, 38, n), np.zeros(n), np.ones(n)], axis=1)
    rotation, translation = anchored(*map_error(line[:, 0] / 3), line, covariance).given_variance(20.0)
    assert np.sqrt(translation) > 0.005 and np.sqrt(rotation) > np.radians(0.05), (np.degrees(np.sqrt(rotation)), np.sqrt(translation))


def test_the_registered_pose_is_weighed_against_the_given_one():
    """fuse_with_given: an exact given pose is kept, a given pose far less certain than the registration
    gives way to it, equal uncertainties meet half way; the result's covariance is below both."""
    given = look_at([3.0, 1.0, 1.5], [0.0, 0.0, 0.5])
    registered = perturbed(given, [0.004, -0.002, 0.001], [0.1, -0.2, 0.05])
    covariance = np.diag([np.radians(0.01) ** 2] * 3 + [0.0005**2] * 3)
    kept, kept_covariance = fuse_with_given(given, registered, covariance, (0.0, 0.0))
    assert np.allclose(kept, given, atol=1e-12) and np.allclose(kept_covariance, 0.0)
    followed, _ = fuse_with_given(given, registered, covariance, (1.0, 1.0))
    assert transform_size(np.linalg.inv(registered) @ followed)[0] < 1e-6
    assert transform_size(np.linalg.inv(registered) @ followed)[1] < 1e-5
    half, half_covariance = fuse_with_given(given, registered, covariance, (np.radians(0.01) ** 2, 0.0005**2))
    assert np.allclose(half[:3, 3], (given[:3, 3] + registered[:3, 3]) / 2, atol=1e-9)
    assert transform_size(np.linalg.inv(given) @ half)[1] == pytest.approx(transform_size(np.linalg.inv(given) @ registered)[1] / 2, rel=1e-3)
    assert np.allclose(np.diag(half_covariance), np.diag(covariance) / 2)


def test_the_pose_covariance_counts_correlated_noise_once_per_tile(bunnies):
    """Structured-light depth (noise correlated over 2.5 pixels, quantised) against the true scene: the
    normal equations alone, which take every pixel as independent, put the pose 2-4 times too close
    (chi-square per frame far above 6); the tile-robust covariance says how far off the registered pose
    really is (median chi-square of the error within a factor 2.5 of 6 degrees of freedom)."""
    mesh, poses = bunnies
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("structured_light")
    chi2 = []
    for i, true in enumerate(poses):
        measured = depth_of(renderer, mesh, intrinsics, true, noise, frame=i)
        expected = depth_of(renderer, mesh, intrinsics, true)
        result = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        assert result.registered, result.status
        error = np.concatenate([Rotation.from_matrix(result.transform[:3, :3]).as_rotvec(), result.transform[:3, 3]])
        chi2.append(error @ np.linalg.pinv(result.covariance) @ error)
    assert np.median(chi2) < 2.5 * 6, chi2


def test_a_frame_that_does_not_register_casts_no_removal_votes():
    """Two frames whose given poses are 30 cm off: with registration they fail their checks and remove
    nothing; without registration their pixels see "through" the map and vote faces out."""
    true = room_poses(8)
    depths = room_frames(true)
    given = true.copy()
    given[5, :3, 3] += [0.0, 0.3, 0.0]
    given[6, :3, 3] += [0.3, 0.0, 0.0]
    frames = [DepthFrame(d, Intrinsics(), g, i, i / 30) for i, (d, g) in enumerate(zip(depths, given, strict=True))]
    loop = mabdi.MabdiLoop(FrameList(frames), surface="quadtree")
    records = [loop.step(i) for i in range(len(frames))]
    assert [r.registered for r in records[5:7]] == [False, False]
    assert all(r.registered for r in records[1:5])
    assert sum(r.cells_removed for r in records[:7]) == 0

    off = mabdi.MabdiLoop(FrameList(frames), surface="quadtree", registration=RegistrationParameters(enabled=False))
    assert sum(off.step(i).cells_removed for i in range(7)) > 0


def test_a_frame_whose_pose_is_stated_exact_votes_though_its_checks_fail():
    """A crate stands in the room for four frames and is gone for the next four. The ICP's checks are made
    to fail on every frame (``min_points`` beyond the image): where the source states its poses exact, each frame is
    meshed at its given pose anyway, so it votes and the crate leaves the map; where the source states
    nothing, the failed frames cast no votes and the crate stays."""
    true = room_poses(8)
    crate_points, crate_triangles = box([0.5, 0.5, 0.5])
    crate = (crate_points + [-0.2, 0.6, 0.25], crate_triangles)
    with_crate = room_frames(true, extra=crate)  # the crate is in frames 4-7
    without = room_frames(true)
    order = [4, 5, 6, 7, 0, 1, 2, 3]  # the crate seen first, then gone
    depths = [with_crate[i] if k < 4 else without[i] for k, i in enumerate(order)]
    frames = [DepthFrame(d, Intrinsics(), true[i], k, k / 30) for k, (d, i) in enumerate(zip(depths, order, strict=True))]

    class ExactSource(FrameList):  # as the simulator without pose noise
        @property
        def pose_accuracy(self):
            return PoseNoise()

    failing = RegistrationParameters(min_points=10_000_000)
    removed = {}
    for name, source in (("stated exact", ExactSource), ("not stated", FrameList)):
        loop = mabdi.MabdiLoop(source(frames), surface="quadtree", registration=failing)
        records = [loop.step(k) for k in range(len(frames))]
        assert not any(r.registered for r in records)
        removed[name] = sum(r.cells_removed for r in records[4:])
    assert removed["stated exact"] > 0 and removed["not stated"] == 0, removed


def test_registration_config_section_and_checks(tmp_path):
    config = load_run_config(REPO / "scenes" / "table.toml")
    assert config.registration.enabled
    set_value(config, "registration.max_rotation", 2.0)
    assert config.registration.max_rotation == 2.0
    path = tmp_path / "bad.toml"
    path.write_text("[registration]\nmin_inliers = 1.5\n")
    with pytest.raises(ConfigError, match="min_inliers"):
        load_run_config(path)
    path.write_text("[registration]\nlevel = 2\n")
    with pytest.raises(ConfigError, match="level"):
        load_run_config(path)


def test_the_compiled_steps_agree_with_their_array_formulations():
    """The ICP's compiled helpers against numpy and scipy: D's samples (each the mean point of the 2 x 2 pixels
    ending at its cell's centre that lie on the centre's surface; depths, tiles, counts) as the array
    expressions give them, Rodrigues' formula against scipy's rotation, a transform's size, the
    normal equations' step with no step along an unconstrained direction, and a cached normal equal
    to one computed afresh."""
    from mabdi.stages import registration_kernels as kernels
    from mabdi.stages.registration import COVARIANCE_TILE, SAMPLE_BLOCK, SAMPLE_MAX_JUMP, sample_points

    rng = np.random.default_rng(5)
    intrinsics = Intrinsics()
    k = intrinsics
    shape = (intrinsics.height, intrinsics.width)
    # half the pixels on one surface at 2 m (their neighbours are averaged in), half scattered over 0.5-4 m
    measured = np.where(rng.random(shape) < 0.5, rng.normal(2.0, 0.02, shape), rng.uniform(0.5, 4.0, shape)).astype(np.float32)
    measured[rng.random(shape) < 0.3] = np.nan
    for stride in (2, 3, 8):
        points, z, tiles, n_tiles, counts = sample_points(measured, intrinsics, stride)
        offset = stride // 2
        rows, cols = np.meshgrid(np.arange(offset, k.height, stride), np.arange(offset, k.width, stride), indexing="ij")
        centre = measured[rows, cols].astype(np.float64)
        valid = np.isfinite(centre)
        sums, taken = np.zeros((*rows.shape, 3)), np.zeros(rows.shape, dtype=int)
        for dr, dc in SAMPLE_BLOCK:
            r, c = rows + dr, cols + dc
            pixel = measured[np.maximum(r, 0), np.maximum(c, 0)].astype(np.float64)
            with np.errstate(invalid="ignore"):
                take = valid & (r >= 0) & (c >= 0) & (np.abs(pixel - centre) <= SAMPLE_MAX_JUMP * centre)
            point = np.stack([(c + 0.5 - k.cx) / k.fx * pixel, (r + 0.5 - k.cy) / k.fy * pixel, pixel], axis=-1)
            sums += np.where(take[..., None], point, 0.0)
            taken += take
        np.testing.assert_array_equal(counts, taken[valid])
        assert set(np.unique(counts)) == {1, 2, 3, 4}
        np.testing.assert_allclose(points, sums[valid] / taken[valid][:, None], rtol=1e-12)
        np.testing.assert_allclose(z, points[:, 2], rtol=1e-15)
        # noise-free D: each sample is its centre pixel
        single, single_z, _, _, single_counts = sample_points(measured, intrinsics, stride, average=False)
        assert (single_counts == 1).all()
        np.testing.assert_array_equal(single_z, centre[valid])
        np.testing.assert_array_equal(single[:, 0], (cols[valid] + 0.5 - k.cx) / k.fx * centre[valid])
        np.testing.assert_array_equal(single[:, 1], (rows[valid] + 0.5 - k.cy) / k.fy * centre[valid])
        across = -(-intrinsics.width // COVARIANCE_TILE)
        np.testing.assert_array_equal(tiles, (rows[valid] // COVARIANCE_TILE) * across + cols[valid] // COVARIANCE_TILE)
        assert n_tiles == across * -(-intrinsics.height // COVARIANCE_TILE)

    for vector in (rng.normal(0, 0.3, 3), np.zeros(3), np.array([1e-9, 0.0, 0.0])):
        transform = kernels.rigid_from_vector(vector, np.array([0.1, -0.2, 0.3]))
        np.testing.assert_allclose(transform[:3, :3], Rotation.from_rotvec(vector).as_matrix(), atol=1e-12)
        translation, angle = transform_size(transform)
        assert translation == pytest.approx(np.sqrt(0.14))
        assert angle == pytest.approx(np.degrees(np.linalg.norm(vector)), abs=1e-9)

    a = np.diag([4.0, 2.0, 1.0, 1e-12, 3.0, 5.0])  # the fourth direction unconstrained
    b = np.array([4.0, 2.0, 1.0, 7.0, 6.0, 5.0])
    step, inverse = kernels.solve_normal_equations(a, b, 1.0, kernels.NO_DIRECTION_HELD)
    np.testing.assert_allclose(step, [-1.0, -1.0, -1.0, 0.0, -2.0, -1.0])
    assert inverse[3, 3] == pytest.approx(1.0 / (kernels.UNCONSTRAINED * 5.0))  # not known: the floor's variance
    np.testing.assert_allclose(np.diag(inverse)[[0, 1, 2, 4, 5]], [0.25, 0.5, 1.0, 1 / 3, 0.2])
    # a weakly held direction (a translation along a wall, held by noise in the normals) takes no step either;
    # rotations count as lengths at ``length`` metres: 0.4 rad^-2 is 0.1 m^-2 at 2 m
    a = np.diag([0.4, 1.0, 1.0, 1.0, 1.0, 1e-5])
    step, inverse = kernels.solve_normal_equations(a, np.array([0.4, 1.0, 1.0, 1.0, 1.0, 1e-4]), 2.0, kernels.NO_DIRECTION_HELD)
    np.testing.assert_allclose(step, [-1.0, -1.0, -1.0, -1.0, -1.0, 0.0])
    np.testing.assert_allclose(inverse[0, 0], 2.5)
    assert inverse[5, 5] == pytest.approx(1.0 / (kernels.UNCONSTRAINED * 1.0))

    expected = measured.copy()
    normals, known = np.empty((*expected.shape, 3)), np.zeros(expected.shape, dtype=np.int8)
    k = intrinsics
    for row, col in rng.integers(0, [k.height, k.width], (300, 2)):
        fresh = kernels.point_and_normal(expected, row, col, k.fx, k.fy, k.cx, k.cy, 2, 0.5)
        first = kernels.cached_point_and_normal(expected, normals, known, row, col, k.fx, k.fy, k.cx, k.cy, 2, 0.5)
        again = kernels.cached_point_and_normal(expected, normals, known, row, col, k.fx, k.fy, k.cx, k.cy, 2, 0.5)
        assert fresh == first == again
        assert known[row, col] == (kernels.NORMAL_FOUND if fresh[0] else kernels.NORMAL_NONE)


def test_a_kept_workspace_registers_as_a_fresh_one(bunnies):
    """The normal cache a filter keeps from frame to frame starts each E afresh: registering frames one
    after the other with one workspace gives the poses each gets alone."""
    from mabdi.stages.registration import IcpWorkspace

    mesh, poses = bunnies
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("zbuffer")
    rng = np.random.default_rng(4)
    workspace = IcpWorkspace()
    for i, true in enumerate(poses[:3]):
        given = perturbed(true, rng.normal(0, 0.005, 3), rng.normal(0, 0.25, 3))
        measured = depth_of(renderer, mesh, intrinsics, true, noise, frame=i)
        expected = depth_of(renderer, mesh, intrinsics, given)
        kept = register_depth(measured, expected, intrinsics, noise, RegistrationParameters(), workspace=workspace)
        fresh = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        assert kept.status == fresh.status == "registered"
        np.testing.assert_array_equal(kept.transform, fresh.transform)
        np.testing.assert_array_equal(kept.covariance, fresh.covariance)


def _bunny_pair(bunnies, index: int = 0):
    """(D from the true pose with z-buffer noise, E of the true scene from a pose 5 mm / 0.3 degrees off)."""
    mesh, poses = bunnies
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("zbuffer")
    true = poses[index]
    given = perturbed(true, [0.005, -0.003, 0.002], [0.3, -0.2, 0.1])
    return depth_of(renderer, mesh, intrinsics, true, noise, frame=index), depth_of(renderer, mesh, intrinsics, given), intrinsics, noise


def test_a_level_ends_where_the_next_step_is_predicted_below_the_tolerance(bunnies, monkeypatch):
    """A level ends once the step that would follow, predicted from how steps shrank at a coarser level, is
    below the tolerance: the pose is where steps taken until they vanish lead (within that tolerance), and
    fewer steps get there."""
    import mabdi.stages.registration as registration

    for index in range(4):
        measured, expected, intrinsics, noise = _bunny_pair(bunnies, index)
        predicted = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        # tolerances no step reaches: each level runs until its steps vanish (or ten of them)
        monkeypatch.setattr(registration, "STEP_TRANSLATION", 1e-9)
        monkeypatch.setattr(registration, "STEP_ROTATION", 1e-8)
        converged = register_depth(measured, expected, intrinsics, noise, RegistrationParameters())
        monkeypatch.undo()
        assert predicted.status == converged.status == "registered"
        translation, angle = transform_size(np.linalg.inv(converged.transform) @ predicted.transform)
        assert translation < registration.STEP_TRANSLATION and angle < registration.STEP_ROTATION
        assert predicted.iterations < converged.iterations
        np.testing.assert_allclose(predicted.covariance, converged.covariance, rtol=0.05, atol=1e-12)


def test_a_step_that_undoes_the_one_before_is_halved():
    """Pairs flipping in and out of the gate make two poses swap for ever; a step back along the one before
    (about as long) is halved, one in another direction is taken whole."""
    from mabdi.stages.registration_kernels import NO_DIRECTION_HELD, gauss_newton_update

    a = np.eye(6)
    b = -np.array([0.001, 0.0, 0.0, 0.004, -0.002, 0.0])  # the step is -b: a rotation and a translation
    for previous, fraction in ((b.copy(), 0.5), (-b, 1.0), (np.zeros(6), 1.0), (np.array([0, 0, 0, 0, 0, 0.01]), 1.0), (4 * b, 1.0)):
        _, translation, _, step = gauss_newton_update(a, b, np.eye(4), previous, 2.0, NO_DIRECTION_HELD)
        np.testing.assert_allclose(step, -b * fraction)
        assert translation == pytest.approx(np.linalg.norm(b[3:]) * fraction, rel=1e-3)


def test_the_gate_does_not_cut_loose_the_few_pixels_that_hold_a_direction():
    """The table run seen from 2.5 m: the floor and the table top hold height, tilt and roll, and only the
    table's edges, legs and cups hold the camera along the floor. Once the floor fits, its residuals say the
    pose is near, and a gate shrunk by them would leave those few pixels out while they are still 2 cm off.
    With the drift of 1 cm / 0.5 degrees per metre, the loop's second and third frames start 2-4 cm and
    0.6-1.3 degrees off the map: they register to within a few millimetres, their pairs holding every
    direction."""
    from mabdi.loop import MappingRun

    config = load_run_config(REPO / "scenes" / "table.toml")
    config.surface.method = "quadtree"
    set_value(config, "sensor.pose_noise.drift_translation", 0.01)
    set_value(config, "sensor.pose_noise.drift_rotation", 0.5)
    simulation = MappingRun(config)
    records = [simulation.step(i) for i in range(3)]
    true, meshed = simulation.true_poses[:3], simulation.meshed_poses()[:3]
    for i in (1, 2):
        assert records[i].registered and records[i].constraint_support > 0.8
        assert records[i].correction_mm > 6.0
        # each frame against the first (where the map starts): the map's own placement drops out
        translation, angle = transform_size(np.linalg.inv(np.linalg.inv(true[0]) @ true[i]) @ np.linalg.inv(meshed[0]) @ meshed[i])
        assert translation < 0.003 and angle < 0.05


def test_a_large_step_is_summed_in_two_halves_that_add_up_to_the_whole(bunnies):
    """From SPLIT_MIN_POINTS samples on, a step's sums come from two halves (one on a helper thread); they
    are the sums over all the samples, up to rounding, with the residuals in the samples' order."""
    from mabdi.stages import registration
    from mabdi.stages.registration_kernels import point_to_plane_system

    measured, expected, intrinsics, noise = _bunny_pair(bunnies)
    points, z, tiles, n_tiles, _ = registration.sample_points(measured, intrinsics, 2)
    assert len(points) >= registration.SPLIT_MIN_POINTS  # the finest level is split
    scale = np.maximum(noise.sigma(z, intrinsics.near, intrinsics.far), 1e-4)
    gate = np.maximum(0.02, 3 * scale)
    transform = np.eye(4)
    transform[:3, 3] = [0.001, -0.002, 0.0015]
    image = registration._MapImage(expected, intrinsics, registration.IcpWorkspace())
    split = image.system(points, tiles, n_tiles, scale, gate, transform, 1.345, True)
    depth = np.ascontiguousarray(expected, dtype=np.float32)
    whole = point_to_plane_system(
        points, tiles, n_tiles, scale, gate, transform[:3, :3], np.ascontiguousarray(transform[:3, 3]), depth,
        np.empty((*depth.shape, 3)), np.zeros(depth.shape, dtype=np.int8), intrinsics.fx, intrinsics.fy,
        intrinsics.cx, intrinsics.cy, registration.NORMAL_STEP, registration.NORMAL_MAX_JUMP, 1.345, True,
    )  # fmt: skip
    for name, got, want in zip(("A", "b", "chi2"), split[:3], whole[:3], strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max(), err_msg=name)
    assert split[3] == whole[3] > 10_000 and split[4] == whole[4]  # pairs, candidates
    np.testing.assert_array_equal(split[5], whole[5])  # residuals, in order
    np.testing.assert_allclose(split[6], whole[6], rtol=1e-9, atol=1e-9 * np.abs(whole[6]).max())  # support
    np.testing.assert_allclose(split[7], whole[7], rtol=1e-9, atol=1e-9 * np.abs(whole[7]).max())  # tile sums


def test_the_residuals_alone_are_the_systems_residuals(bunnies):
    """How well a pose fits (the ICP's improvement over the given pose) reads the residuals without the normal
    equations: the same numbers in the same order as a step's, at several poses, split in halves or not."""
    from mabdi.stages import registration

    measured, expected, intrinsics, noise = _bunny_pair(bunnies)
    for stride in (2, 8):  # a fine sampling is split in halves; a coarse one is not
        points, z, tiles, n_tiles, _ = registration.sample_points(measured, intrinsics, stride)
        scale = np.maximum(noise.sigma(z, intrinsics.near, intrinsics.far), 1e-4)
        wide = np.full(len(points), 1.0)
        image = registration._MapImage(expected, intrinsics, registration.IcpWorkspace())
        fresh = registration._MapImage(expected, intrinsics, registration.IcpWorkspace())  # normals not yet cached
        for offset in ([0.0, 0.0, 0.0], [0.004, -0.002, 0.003], [-0.03, 0.01, 0.02]):
            transform = np.eye(4)
            transform[:3, 3] = offset
            want = image.system(points, tiles, n_tiles, scale, wide, transform, 1.345, False)[5]
            assert len(want) > 1000
            np.testing.assert_array_equal(fresh.residuals(points, transform), want)


#: Run in a fresh interpreter: register, then fork a child that registers again (the test process may hold other
#: libraries' threads, e.g. Ray's or Rerun's from other tests, and a fork beside them can hang on their locks).
_FORKED_CHILD = """
import multiprocessing, pickle, sys
import numpy as np
from mabdi.stages import registration
measured, expected, intrinsics, noise, parameters, transform = pickle.load(open(sys.argv[1], "rb"))
threaded = registration.register_depth(measured, expected, intrinsics, noise, parameters)
assert registration._cores() == 1 or registration._helper is not None  # the helper ran the second halves
with multiprocessing.get_context("fork").Pool(1) as pool:
    child = pool.apply_async(registration.register_depth, (measured, expected, intrinsics, noise, parameters)).get(timeout=120)
np.testing.assert_array_equal(threaded.transform, transform)
np.testing.assert_array_equal(child.transform, transform)
print("same")
"""


def test_the_registration_is_the_same_on_one_core_on_two_and_in_a_forked_child(bunnies, monkeypatch, tmp_path):
    """The halves are added in a fixed order, so the pose does not depend on whether a helper thread ran
    them; a child forked after the helper started gets its own and registers the same."""
    import pickle
    import subprocess
    import sys

    from mabdi.stages import registration

    measured, expected, intrinsics, noise = _bunny_pair(bunnies, 1)
    parameters = RegistrationParameters()
    threaded = register_depth(measured, expected, intrinsics, noise, parameters)
    assert threaded.status == "registered"
    if registration._cores() > 1:
        assert registration._helper is not None  # the helper ran the second halves
    case = tmp_path / "case.pkl"
    case.write_bytes(pickle.dumps((measured, expected, intrinsics, noise, parameters, threaded.transform)))
    child = subprocess.run([sys.executable, "-c", _FORKED_CHILD, str(case)], capture_output=True, text=True, timeout=300)
    assert child.returncode == 0 and child.stdout.strip() == "same", child.stderr[-2000:]
    monkeypatch.setattr(registration, "_cores", lambda: 1)
    monkeypatch.setattr(registration, "_helper", None)
    alone = register_depth(measured, expected, intrinsics, noise, parameters)
    assert registration._helper is None
    np.testing.assert_array_equal(alone.transform, threaded.transform)
    np.testing.assert_array_equal(alone.covariance, threaded.covariance)


def test_pose_jitter_tells_white_jitter_from_a_walk():
    """PoseJitter learns white jitter's variance from corrections one and two frames apart, and reads a walk
    (drift, or a map that moves with the poses that follow it) as no jitter."""
    from mabdi.stages.registration import PoseJitter

    rng = np.random.default_rng(3)
    icp = np.diag([1e-8] * 3 + [1e-8] * 3)  # the ICP's own variance: 0.1 mm, 0.006 degrees
    white, walk = PoseJitter(), PoseJitter()
    steps = np.cumsum(rng.normal(0.0, 0.004, (400, 6)), axis=0)  # a walk of 4 mm (4 mrad) a frame
    for i in range(400):
        jitter = rng.normal(0.0, 0.005, 6)  # 5 mm (5 mrad) per component
        white.add(jitter, jitter, icp)
        walk.add(steps[i], steps[i], icp)
    rotation, translation = white.variance()
    assert 0.8 * 0.005**2 < rotation < 1.2 * 0.005**2 and 0.8 * 0.005**2 < translation < 1.2 * 0.005**2, (rotation, translation)
    assert max(walk.variance()) < 0.1 * 0.004**2, walk.variance()
    assert PoseJitter().variance() is None


def test_the_icp_samples_sparsely_first_and_densely_where_few_pixels_hold_a_direction(bunnies):
    """The ICP first samples D every ``sparse_stride`` (3) pixels and keeps that pose where its pairs hold every
    direction well (the bunnies: the same pose as every 2nd pixel gives, to a fraction of a millimetre); where
    they hold one loosely (a wall whose 3 cm recess's edges alone hold the slide along it) or the sparse pass
    does not register the frame, the pose is the dense pass's, as if there were one pass only."""
    from dataclasses import replace

    from mabdi.stages.registration import DENSE_BELOW_SUPPORT

    parameters = RegistrationParameters()
    assert parameters.sparse_stride == 3 and parameters.stride == 2
    only_sparse, only_dense = replace(parameters, stride=3), replace(parameters, sparse_stride=2)  # one pass each
    measured, expected, intrinsics, noise = _bunny_pair(bunnies, 1)
    result = register_depth(measured, expected, intrinsics, noise, parameters)
    sparse = register_depth(measured, expected, intrinsics, noise, only_sparse)
    dense = register_depth(measured, expected, intrinsics, noise, only_dense)
    assert sparse.registered and sparse.support >= DENSE_BELOW_SUPPORT
    np.testing.assert_array_equal(result.transform, sparse.transform)
    assert not np.array_equal(sparse.transform, dense.transform)
    assert transform_size(np.linalg.inv(dense.transform) @ sparse.transform)[0] < 0.0005

    wall = merged(
        _moved(box((0.1, 9.5, 20.0)), [2.55, -5.25, 0.0]),
        _moved(box((0.1, 9.5, 20.0)), [2.55, 5.25, 0.0]),
        _moved(box((0.1, 1.0, 20.0)), [2.58, 0.0, 0.0]),
    )
    renderer = DepthRenderer()
    true = look_at([0.0, -0.3, 0.0], [2.5, 0.1, 0.05])
    given = perturbed(true, [0.004, 0.003, 0.006], [0.0, 0.0, 0.0])
    zbuffer = SensorNoise("zbuffer")
    measured = depth_of(renderer, wall, intrinsics, true, zbuffer)
    expected = depth_of(renderer, wall, intrinsics, given)
    result = register_depth(measured, expected, intrinsics, zbuffer, parameters)
    sparse = register_depth(measured, expected, intrinsics, zbuffer, only_sparse)
    dense = register_depth(measured, expected, intrinsics, zbuffer, only_dense)
    assert not (sparse.registered and sparse.support >= DENSE_BELOW_SUPPORT), (sparse.status, sparse.support)
    assert result.registered and result.status == dense.status
    np.testing.assert_array_equal(result.transform, dense.transform)
    # one pass where sparse_stride is not above stride
    single = register_depth(measured, expected, intrinsics, zbuffer, replace(parameters, sparse_stride=2))
    np.testing.assert_array_equal(single.transform, dense.transform)
    with pytest.raises(ConfigError, match="sparse_stride"):
        RegistrationParameters(sparse_stride=0)



def test_a_frame_no_pose_fits_keeps_the_pose_the_fit_started_from():
    """A frame 5 cm and two degrees off its true pose is fitted and followed; told that the run's frames fit ten times
    better than it does (:mod:`mabdi.stages.fit_check`: a smeared or bent image, whose ICP pose is no evidence against
    the given one), it keeps the pose the fit started from (the given pose), carries no correction on, and says so."""
    true = room_poses(9)
    given = true.copy()
    given[7] = perturbed(true[7], [0.05, 0.0, 0.0], [0.0, 2.0, 0.0])
    frames = [DepthFrame(d, Intrinsics(), g, i, i / 30) for i, (d, g) in enumerate(zip(room_frames(true, noise="kinect"), given, strict=True))]
    loop = mabdi.MabdiLoop(FrameList(frames), surface="quadtree", noise="kinect")
    for i in range(7):
        loop.step(i)
    measured = loop.depth_frames.measured(7)
    before = copy.deepcopy(loop.registration.state())
    carried = before["correction"]

    placed, placement = loop.registration.place(measured, loop.world.map)  # not judged: the ICP's pose is followed
    assert placement.status == "registered" and not placement.poor_fit and placement.correction_m > 0.04
    residual = placement.residual_m
    loop.registration.set_state(copy.deepcopy(before))  # as if that fit had not been made

    earlier = np.full(20, residual / 10.0)  # the run's frames fit ten times better
    kept, placement = loop.registration.place(measured, loop.world.map, earlier)
    assert placement.status == "registered" and placement.poor_fit
    assert placement.correction_m < 1e-6 and placement.correction_deg < 1e-6, placement  # at its given pose
    world_from_map = placement.world_from_map
    np.testing.assert_allclose(world_from_map @ kept.pose, given[7], atol=1e-9)
    np.testing.assert_array_equal(loop.registration.state()["correction"], carried)  # nothing carried on
    _, placement = loop.registration.place(loop.depth_frames.measured(8), loop.world.map, np.full(20, residual))
    assert not placement.poor_fit and placement.correction_m < 0.005
