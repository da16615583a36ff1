"""A real camera sees a known surface with a bias that depends on the view (its depth distortion, a pose slightly
off): D departs from E gradually there, and such a region is neither new surface nor a departed one. A new or
departed object's border is a step. And where registration fitted D to the map at another pose than the one it
is meshed at, what the difference between the two poses makes is explained."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

import mabdi
from mabdi.camera import Intrinsics
from mabdi.depth import DepthFrame
from mabdi.sources.frames import FrameList
from mabdi.spherical import SphericalGeometry
from mabdi.stages.classifier import (
    CONTRADICTED,
    KNOWN,
    NOVEL,
    ClassifierParameters,
    FilterClassifier,
    classify,
    explained_at,
    explained_by_fit,
    gradual_regions,
    pose_trusted,
)
from mabdi.depth import depth_image
from mabdi.frame_values import Measured
from mabdi.stages.expected_image import expected_of_image
from mabdi.stages.image_kernels import border_steps_kernel
from mabdi.stages.registration_kernels import rigid_from_vector
from test_classifier import POSE, SMALL, run_classifier
from test_registration_distorted_depth import there_and_back_frames

WALL = 2.0  # metres


def bump(amplitude: float, width_px: float = 6.0) -> np.ndarray:
    """(H, W) a Gaussian bump of ``amplitude`` metres in the middle of SMALL's image."""
    v, u = np.mgrid[0 : SMALL.height, 0 : SMALL.width]
    return amplitude * np.exp(-((u - 32) ** 2 + (v - 24) ** 2) / (2 * width_px**2))


def wall() -> np.ndarray:
    return np.full(SMALL.shape, WALL, np.float32)


PARAMETERS = ClassifierParameters(min_width=1, min_region=0, rim=0)


@pytest.mark.parametrize("amplitude", [-0.04, 0.04])
def test_a_region_that_departs_gradually_is_known(amplitude):
    """A wall seen 4 cm nearer (or farther) in the middle, the departure growing smoothly from nothing: beyond tau
    (1 cm) on 160 pixels, and yet no step anywhere along the region's border. It is the map seen with a bias:
    known, nothing meshed. With ``gradual = false`` the same pixels are novel (in front) or contradicted."""
    measured = wall() + bump(amplitude).astype(np.float32)
    beyond = np.abs(measured - WALL) > 0.01
    assert beyond.sum() > 100
    frame, labels, _ = run_classifier(measured, wall(), PARAMETERS)
    assert (labels == KNOWN).all()
    assert not np.isfinite(frame.depth).any()
    off = ClassifierParameters(min_width=1, min_region=0, rim=0, gradual=False)
    _, labels, _ = run_classifier(measured, wall(), off)
    assert (labels[beyond] == (NOVEL if amplitude < 0 else CONTRADICTED)).all()


def test_a_gradual_contradiction_votes_where_the_pose_is_uncertain():
    """Where poor poses are being corrected (E's depth uncertain from the pose by about the sensor's sigma), the
    map's patches may lie where poor poses put them, and a gradual contradiction is as likely such a patch:
    it stays contradicted (removal mends it). A gradual region in front of the map is still known."""
    measured = wall() + bump(0.04).astype(np.float32)
    in_front = wall() - bump(0.04).astype(np.float32)
    classifier = FilterClassifier(PARAMETERS)
    uncertain = np.diag([1e-6, 1e-6, 1e-6, 4e-5, 4e-5, 4e-5])  # 6 mm a translation axis: E uncertain by ~6 mm
    for depth, label in ((measured, CONTRADICTED), (in_front, KNOWN)):
        d = Measured.from_image(depth_image(depth, SMALL, POSE, frame=4, noise="kinect"))
        e = expected_of_image(depth_image(wall(), SMALL, POSE, frame=4))
        beyond = np.abs(depth - WALL) > 0.03  # beyond tau with the pose's uncertainty too (2.5 cm)
        assert beyond.sum() > 30
        assert (classifier.classify(d, e, uncertain).labels[beyond] == label).all()
        assert (classifier.classify(d, e, np.zeros((6, 6))).labels[beyond] == KNOWN).all()
    assert not pose_trusted(np.full(SMALL.shape, 0.006), np.full(SMALL.shape, 0.01))
    assert pose_trusted(np.full(SMALL.shape, 0.004), np.full(SMALL.shape, 0.01)) and pose_trusted(None, np.ones(1))


def test_an_object_with_a_step_at_its_border_stays_new_and_a_departed_one_stays_seen_through():
    """A box 3 cm in front of the wall (its border a 3 cm step) is novel and meshed; where the map holds a box that
    has gone (E 3 cm nearer on a block, D the wall), the block is contradicted: each the size of the gradual bump."""
    measured, expected = wall(), wall()
    measured[14:26, 8:20] = WALL - 0.03  # a new box
    expected[14:26, 40:52] = WALL - 0.03  # a box that left
    frame, labels, _ = run_classifier(measured, expected, PARAMETERS)
    assert (labels[14:26, 8:20] == NOVEL).all()
    assert np.isfinite(frame.depth[14:26, 8:20]).all()
    assert (labels[14:26, 40:52] == CONTRADICTED).all()
    assert (labels[:10] == KNOWN).all()


def test_a_region_half_stepped_half_gradual_stays():
    """An object whose border is a step on more than a quarter of it stays novel: a ramp leaning on the wall, 5 cm
    proud at its free end and rising from the wall at the other."""
    measured = wall()
    ramp = np.linspace(0.0, 0.05, 16, dtype=np.float32)
    measured[14:26, 20:36] = WALL - ramp[None, :]
    _, labels, _ = run_classifier(measured, wall(), PARAMETERS)
    proud = (WALL - measured) > 0.01
    assert (labels[proud] == NOVEL).all()


def test_a_region_bordered_mostly_by_pixels_without_a_return_stays():
    """The foot of a departed box, where its side met the floor: D - E grows from nothing at the floor, and above
    the box the sensor saw nothing (beyond its range). A gradual region with more than half of its border
    without a return is not judged by the rest: it stays contradicted; with its border known all round it is
    the map seen with a bias."""
    measured = wall() + bump(0.04).astype(np.float32)
    expected = wall()
    above = np.zeros(SMALL.shape, dtype=bool)
    above[:28] = True
    walled = measured.copy()
    walled[above & (np.abs(measured - WALL) <= 0.01)] = np.nan  # no return above the dent's middle row
    _, labels, _ = run_classifier(walled, expected, PARAMETERS)
    assert (labels[np.isfinite(walled) & (walled - WALL > 0.01)] == CONTRADICTED).all()
    _, labels, _ = run_classifier(measured, expected, PARAMETERS)
    assert (labels[measured - WALL > 0.01] == KNOWN).all()


def test_a_door_turned_about_its_hinge_stays_seen_through():
    """A door the map holds, turned open about its hinge: D departs from E gradually at the hinge and by a metre at
    the free edge, and the region's only border with known pixels is the hinge's (the rest is the image's edge).
    Most of its pixels lie more than GRADUAL_MAX_TAU tau from E's surface: an object's size, not a bias. It stays
    contradicted."""
    measured, expected = wall(), wall()
    # the room behind the doorway, seen further the further from the hinge: millimetres beside it, a metre at the edge
    opening = (np.linspace(0.0, 1.0, SMALL.width - 32) ** 2).astype(np.float32)
    measured[:, 32:] = WALL + opening[None, :]
    _, labels, _ = run_classifier(measured, expected, PARAMETERS)
    assert (labels[measured - WALL > 0.01] == CONTRADICTED).all()


def test_gradual_regions_needs_a_border_to_judge_by():
    """A region with fewer than eight pairs on its border with known pixels is left as it is (a region the size of
    the image, or one walled in by pixels without a return)."""
    measured = wall() - 0.05
    expected = wall()
    tau = np.full(SMALL.shape, 0.01, np.float32)
    labels = classify(measured, expected, tau)
    assert not gradual_regions(labels == NOVEL, labels, measured, expected, tau).any()


def reference_border_steps(regions, count, known, measured, expected, tau, cosine, far_k):
    """border_steps_kernel's counts by array indexing, direction by direction."""
    rows, cols = np.nonzero(regions)
    region = regions[rows, cols]
    here = measured[rows, cols].astype(np.float64) - expected[rows, cols]
    pairs, steps, outline = (np.zeros(count + 1, dtype=np.int64) for _ in range(3))
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < regions.shape[0]) & (c >= 0) & (c < regions.shape[1])
        r, c = np.where(inside, r, 0), np.where(inside, c, 0)
        outside = inside & (regions[r, c] != region)
        border = outside & known[r, c]
        step = np.abs(here - (measured[r, c].astype(np.float64) - expected[r, c])) > tau[rows, cols]
        outline += np.bincount(region[outside], minlength=count + 1)
        pairs += np.bincount(region[border], minlength=count + 1)
        steps += np.bincount(region[border & step], minlength=count + 1)
    size = np.bincount(region, minlength=count + 1)
    slant = np.nan_to_num(cosine[rows, cols], nan=1.0)
    far = np.bincount(region[np.abs(here) * slant > far_k * tau[rows, cols]], minlength=count + 1)
    return pairs, steps, outline, size, far


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_border_kernel_counts_what_array_indexing_counts(seed):
    rng = np.random.default_rng(seed)
    measured = (2.0 + rng.normal(0, 0.02, (40, 50))).astype(np.float32)
    expected = np.full(measured.shape, 2.0, np.float32)
    measured[rng.random(measured.shape) < 0.05] = np.nan
    tau = np.full(measured.shape, 0.015, np.float32)
    labels = classify(measured, expected, tau)
    for mask in (labels == NOVEL, labels == CONTRADICTED):
        regions, count = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        regions = regions.astype(np.int32)
        cosine = rng.uniform(0.2, 1.0, measured.shape).astype(np.float32)
        cosine[rng.random(measured.shape) < 0.05] = np.nan
        got = border_steps_kernel(regions, count, labels == KNOWN, measured, expected, tau, cosine, 1.5)
        want = reference_border_steps(regions, count, labels == KNOWN, measured, expected, tau, cosine, 1.5)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
        assert want[0].sum() > 100 and want[4].sum() > 10


def plane_values(geometry, normal, offset) -> np.ndarray:
    """(H, W) the image's values (a camera's z-depth, a LiDAR's range) of the plane normal . X = offset (sensor
    frame), NaN where a ray does not meet it in front."""
    rays = geometry.rays()
    along = rays @ np.asarray(normal, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        values = offset / along
    return np.where(values > 0, values, np.nan).astype(np.float32)


@pytest.mark.parametrize(
    "geometry",
    [Intrinsics(), SphericalGeometry(beams=32, columns=360, fov_up=-5.0, fov_down=-45.0, range_min=0.3, range_max=40.0)],
    ids=["camera", "lidar"],
)
def test_what_the_difference_between_the_meshed_and_the_fitted_pose_makes_is_explained(geometry):
    """The map a slanted floor seen from the meshed pose (E); D the same floor seen from where the ICP fitted it,
    5 cm and 1.3 degrees away: most of D lies beyond tau (1 cm) of E. Placed at the fitted pose, all of it agrees
    with E (but where it leaves the image) except an object 20 cm proud of the floor, which stays novel. Placed at the meshed pose, nothing is
    explained."""
    normal = np.array([0.0, 0.6, 0.8]) if isinstance(geometry, Intrinsics) else np.array([0.05, 0.0, -1.0])
    normal /= np.linalg.norm(normal)
    offset = 1.5
    meshed_from_fitted = rigid_from_vector(np.radians([0.8, -1.0, 0.2]), np.array([0.03, -0.02, 0.03]))
    expected = plane_values(geometry, normal, offset)
    # the plane in the fitted frame: n' = R^T n, d' = d - n . t
    rotation, shift = meshed_from_fitted[:3, :3], meshed_from_fitted[:3, 3]
    measured = plane_values(geometry, rotation.T @ normal, offset - normal @ shift)
    object_pixels = np.zeros(measured.shape, dtype=bool)
    rows, cols = np.nonzero(np.isfinite(measured))
    pick = np.argsort(rows * measured.shape[1] + cols)[len(rows) // 2 : len(rows) // 2 + 20]
    object_pixels[rows[pick], cols[pick]] = True
    measured[object_pixels] -= 0.2
    tau = np.full(measured.shape, 0.01, np.float32)
    labels = classify(measured, expected, tau)
    departing = (labels == NOVEL) & np.isfinite(expected) | (labels == CONTRADICTED)
    assert departing.sum() > 0.5 * np.isfinite(measured).sum()
    explained = explained_by_fit(labels, measured, expected, tau, geometry, meshed_from_fitted)
    inside_both = departing & ~object_pixels
    # all but the far rows at the image's edge, where the moved return leaves the image or E changes by near tau
    # from one pixel to the next (E is read at the pixel the return falls in; measured: 96.3% camera)
    assert explained[inside_both].mean() > 0.95, explained[inside_both].mean()
    assert not explained[object_pixels].any()
    assert not explained_by_fit(labels, measured, expected, tau, geometry, np.eye(4))[departing].any()


def test_a_cameras_compiled_pass_explains_the_pixels_the_array_passes_do():
    """The camera's one compiled pass (:func:`explained_by_fit_kernel`) against the array passes any geometry
    takes, on a rough E with holes and a D that departs from it by up to 3 cm, at a fitted pose 2 cm and a degree
    off: the same pixels, and a share of them both explained and not."""
    geometry = Intrinsics()
    rng = np.random.default_rng(7)
    shape = geometry.shape
    expected = (2.0 + 0.3 * np.sin(np.arange(shape[1]) / 40.0)[None, :] + 0.002 * rng.standard_normal(shape)).astype(np.float32)
    expected[rng.random(shape) < 0.05] = np.nan
    expected[100:140, 200:260] = np.nan  # a hole wider than the bilinear read
    measured = (expected + rng.uniform(-0.03, 0.03, shape)).astype(np.float32)
    measured[np.isnan(measured)] = 2.2
    tau = np.full(shape, 0.01, np.float32)
    labels = classify(measured, expected, tau)
    suspect = ((labels == NOVEL) & np.isfinite(expected)) | (labels == CONTRADICTED)
    meshed_from_fitted = rigid_from_vector(np.radians([0.5, -0.7, 0.3]), np.array([0.02, -0.01, 0.015]))
    compiled = explained_by_fit(labels, measured, expected, tau, geometry, meshed_from_fitted)
    arrays = explained_at(suspect, measured, expected, tau, geometry, meshed_from_fitted)
    assert np.array_equal(compiled, arrays)
    assert 0.05 < compiled[suspect].mean() < 0.95, compiled[suspect].mean()
    assert not compiled[~suspect].any()


# --- the loop on a camera with a depth distortion ---------------------------------------------------------

@pytest.fixture(scope="module")
def distorted_there_and_back():
    """60 frames 1.6 m sideways past a small room and back, Kinect noise, the depth 3% too far at the image corners
    (exact poses; :func:`test_registration_distorted_depth.there_and_back_frames`)."""
    true, depths = there_and_back_frames()
    return [DepthFrame(d, Intrinsics(), p, i, i / 30) for i, (d, p) in enumerate(zip(depths, true, strict=True))]


@pytest.mark.slow
def test_a_static_room_seen_through_a_distorting_camera_keeps_its_faces_and_stops_growing(distorted_there_and_back):
    """The room seen again on the way back shows each surface at another place in the image, so with another bias
    (up to 7 cm): the map neither loses faces to it nor grows by it. Measured: 5 faces removed of 102,255 made, and
    2,302 novel pixels meshed over the 30 frames back. Before (each such region novel or contradicted): 961 faces
    removed (0.8%) and 10,549 pixels meshed on the way back, layers of the walls in front of the first."""
    loop = mabdi.MabdiLoop(FrameList(distorted_there_and_back), surface="quadtree", noise="kinect")
    records = [loop.step(i) for i in range(len(distorted_there_and_back))]
    removed = sum(r.cells_removed for r in records)
    made = loop.mesh().GetNumberOfCells() + removed
    assert removed < 0.001 * made, (removed, made)
    back = sum(r.novel_pixels for r in records[30:])
    assert back < 5000, back
