"""FilterClassifier: labels against known answers, metric thresholds, speck removal, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from mabdi.camera import Intrinsics, look_at
from mabdi.depth import DepthFrame, depth_image
from mabdi.sensor_noise import SensorNoise
from mabdi.stages.classifier import (
    CONTRADICTED,
    KNOWN,
    NO_RETURN,
    NOVEL,
    ClassifierParameters,
    FilterClassifier,
    classify,
    hole_fills,
    pixel_counts,
    remove_specks,
)

SMALL = Intrinsics(fx=52.5, fy=52.5, cx=32.0, cy=24.0, width=64, height=48)
POSE = look_at([0, -3, 1], [0, 0, 1])


def run_classifier(measured, expected, parameters=None, noise="none", pose_e=POSE, intrinsics_e=SMALL):
    classifier = FilterClassifier(parameters or ClassifierParameters(min_width=1, min_region=0, rim=0))
    classifier.SetInputDataObject(0, depth_image(measured, SMALL, POSE, frame=4, noise=noise))
    classifier.SetInputDataObject(1, depth_image(expected, intrinsics_e, pose_e, frame=4))
    classifier.Update()
    output = classifier.GetOutput()
    labels = vtk_to_numpy(output.GetPointData().GetArray("label")).reshape(intrinsics_e.shape)
    return DepthFrame.from_image(output), labels, classifier


def test_labels_on_known_cases():
    measured = np.full(SMALL.shape, 2.0, np.float32)
    expected = np.full(SMALL.shape, 2.0, np.float32)
    measured[:10] = np.nan  # no return
    expected[10:20] = np.nan  # map has nothing there: novel
    measured[20:30] = 1.9  # nearer than the map by 10 cm: novel
    measured[30:40] = 2.1  # farther than the map by 10 cm: contradicted
    measured[40:] = 2.005  # within tau = 1 cm: known
    frame, labels, classifier = run_classifier(measured, expected)
    assert (labels[:10] == NO_RETURN).all()
    assert (labels[10:20] == NOVEL).all()
    assert (labels[20:30] == NOVEL).all()
    assert (labels[30:40] == CONTRADICTED).all()
    assert (labels[40:] == KNOWN).all()
    novel = (labels == NOVEL)
    np.testing.assert_array_equal(np.isfinite(frame.depth), novel)
    np.testing.assert_array_equal(frame.depth[novel], measured[novel])
    assert frame.frame == 4
    assert pixel_counts(classifier.GetOutput())["novel"] == novel.sum()
    assert pixel_counts(classifier.GetOutput())["valid"] == (labels != NO_RETURN).sum()


def test_threshold_grows_with_range_for_the_kinect_model():
    classifier = FilterClassifier(ClassifierParameters(tau_min=0.01, k_sigma=3.0))
    kinect = SensorNoise("kinect")
    tau = classifier.threshold(np.array([0.5, 2.0, 3.0]), kinect, 0.5, 4.0)
    np.testing.assert_allclose(tau, [0.01, 3 * 1.425e-3 * 4, 3 * 1.425e-3 * 9])
    # 2 cm nearer is novel at 1 m but within the noise at 3 m
    labels = classify(np.array([0.98, 2.98]), np.array([1.0, 3.0]), classifier.threshold(np.array([0.98, 2.98]), kinect, 0.5, 4.0))
    assert labels.tolist() == [NOVEL, KNOWN]


def test_specks_thin_lines_and_small_blobs_are_not_novel():
    novel = np.zeros((60, 80), bool)
    novel[5, 5:70] = True  # a 1-px sliver
    novel[10:12, 5:70] = True  # a 2-px sliver
    novel[20:24, 20:24] = True  # 16 px blob
    novel[30:50, 30:60] = True  # a real region
    kept = remove_specks(novel, min_width=3, min_region=32)
    assert not kept[:25].any()
    assert kept[30:50, 30:60].all()
    assert remove_specks(novel, 1, 0).sum() == novel.sum()


def test_specks_that_fill_a_hole_of_the_map_stay_novel():
    """A wall at 2 m seen by a noisy camera (tau 1.7 cm): small regions where E sees through the map, ringed
    by the map at D's depth, are holes and stay novel; a crack of E one pixel wide, a sliver beside the map's
    silhouette and a speck of D just in front of the map are specks. Noise-free D fills no hole."""
    measured = np.full(SMALL.shape, 2.0, np.float32)
    expected = np.full(SMALL.shape, 2.0, np.float32)
    expected[5:8, 5:8] = np.nan  # a hole of the map, 3 x 3 pixels: nothing behind it
    expected[5:7, 20:23] = 3.5  # a hole of the map, 2 x 3 pixels, the far wall behind it
    expected[15, 5:25] = np.nan  # a crack one pixel wide between the map's triangles
    expected[20:24, 5:9] = 2.03  # D 3 cm in front of the map: beyond tau (1 cm), not seeing through
    measured[:, 50:] = 3.5  # the far wall beside the near one's edge at column 50 ...
    expected[:, 48:] = 3.5  # ... which the map has two pixels short
    parameters = ClassifierParameters(min_width=3, min_region=32, rim=0)
    frame, labels, classifier = run_classifier(measured, expected, parameters, noise="kinect")
    holes = np.zeros(SMALL.shape, bool)
    holes[5:8, 5:8] = holes[5:7, 20:23] = True
    np.testing.assert_array_equal(labels == NOVEL, holes)
    np.testing.assert_array_equal(np.isfinite(frame.depth), holes)
    assert pixel_counts(classifier.GetOutput())["specks"] == 20 + 16 + 2 * 48
    _, labels, _ = run_classifier(measured, expected, dataclasses.replace(parameters, fill_holes=False), noise="kinect")
    assert not (labels == NOVEL).any()
    _, labels, _ = run_classifier(measured, expected, parameters)  # noise-free
    assert not (labels == NOVEL).any()
    # a hole at the image's border: its ring is short (two sides), still within the map; a hole beside pixels
    # D lost where the map goes on, and one beside a narrow band lost by both; a strip along the map's edge
    # where nothing lies beyond (no return, no map, wide)
    measured = np.full(SMALL.shape, 2.0, np.float32)
    expected = np.full(SMALL.shape, 2.0, np.float32)
    expected[:3, 30:34] = np.nan
    expected[30:33, 20:23] = np.nan
    measured[29:34, 23] = np.nan
    measured[:, 40:] = np.nan
    expected[:, 38:] = np.nan
    expected[40:43, 10:13] = np.nan  # a hole beside a band two pixels wide that neither D nor the map has
    measured[38:46, 13:15] = expected[38:46, 13:15] = np.nan
    _, labels, _ = run_classifier(measured, expected, parameters, noise="kinect")
    holes = np.zeros(SMALL.shape, bool)
    holes[:3, 30:34] = holes[30:33, 20:23] = holes[40:43, 10:13] = True
    np.testing.assert_array_equal(labels == NOVEL, holes)
    # where E says the map reaches into a pixel's footprint (a range image), its beam missed the map: no hole
    labels = classify(measured, expected, np.full(SMALL.shape, 0.01, np.float32))
    specks = labels == NOVEL
    np.testing.assert_array_equal(hole_fills(specks, measured, expected, labels, np.full(SMALL.shape, 0.01)), holes)
    covered = np.zeros(SMALL.shape, bool)
    covered[29:34, 19:24] = covered[39:44, 9:14] = True
    np.testing.assert_array_equal(hole_fills(specks, measured, expected, labels, np.full(SMALL.shape, 0.01), covered), holes & ~covered)


def reference_hole_fills(specks, measured, expected, labels, tau, covered=None):
    """:func:`hole_fills` written region by region and pixel by pixel, as the module docs say it."""
    from scipy import ndimage

    from mabdi.stages.classifier import HOLE_BAND_PX, HOLE_JUMP, HOLE_RING_MIN, HOLE_RING_SHARE

    valid = np.isfinite(measured)

    def lost_run(r, c, along_rows):
        run, line, at = 1, (valid[r] if along_rows else valid[:, c]), (c if along_rows else r)
        for sign in (-1, 1):
            k = at + sign
            while 0 <= k < len(line) and not line[k]:
                run, k = run + 1, k + sign
        return run

    fills = np.zeros_like(specks)
    regions, count = ndimage.label(specks, structure=np.ones((3, 3), bool))
    for label in range(1, count + 1):
        region = regions == label
        depth = np.median(measured[region])
        jump = np.maximum(HOLE_JUMP * measured, 2.0 * tau)
        through = region & (~np.isfinite(expected) | (expected - measured > jump))
        if covered is not None:
            through &= ~covered
        wide = ndimage.binary_opening(through, structure=np.ones((2, 2), bool)).any()
        ring = ndimage.binary_dilation(region, structure=np.ones((3, 3), bool)) & ~specks
        counted = level = 0
        for r, c in zip(*np.nonzero(ring), strict=True):
            d, e = measured[r, c], expected[r, c]
            if np.isnan(d) and np.isnan(e) and min(lost_run(r, c, True), lost_run(r, c, False)) < HOLE_BAND_PX:
                continue
            counted += 1
            surface = d if np.isfinite(d) else e
            mapped = labels[r, c] == KNOWN or (np.isnan(d) and np.isfinite(e))
            allowed = max(HOLE_JUMP * depth, 2.0 * tau[r, c]) if np.isfinite(tau[r, c]) else HOLE_JUMP * depth
            level += bool(mapped and abs(surface - depth) <= allowed)
        if through.sum() >= 0.5 * region.sum() and wide and level >= HOLE_RING_MIN and level >= HOLE_RING_SHARE * counted:
            fills |= region
    return fills


@pytest.mark.parametrize("seed", range(4))
def test_hole_fills_match_their_region_by_region_formulation(seed):
    """Random walls with holes in the map, bands D lost, specks of noise, far walls seen through holes and
    regions that touch each other: the vectorised rule and the plain one keep the same specks."""
    rng = np.random.default_rng(seed)
    shape = (60, 90)
    measured = (2.0 + 0.3 * rng.random() + 0.002 * np.arange(shape[1])[None, :] + np.zeros(shape)).astype(np.float32)
    expected = measured.copy()
    for _ in range(25):  # holes of the map, some with the far wall behind them
        r, c, h, w = rng.integers(0, 58), rng.integers(0, 88), rng.integers(1, 5), rng.integers(1, 5)
        expected[r : r + h, c : c + w] = np.nan if rng.random() < 0.6 else 3.5
    for _ in range(6):  # bands D lost, some lost by the map too
        c, w = rng.integers(0, 88), rng.integers(1, 12)
        rows = slice(rng.integers(0, 30), rng.integers(30, 60))
        measured[rows, c : c + w] = np.nan
        if rng.random() < 0.5:
            expected[rows, c : c + w] = np.nan
    for _ in range(10):  # specks of D in front of the map
        r, c = rng.integers(0, 58), rng.integers(0, 88)
        measured[r : r + 2, c : c + 3] -= 0.05
    tau = np.where(np.isfinite(measured), 0.02, np.nan).astype(np.float32)
    labels = classify(measured, expected, tau)
    novel = labels == NOVEL
    specks = novel & ~remove_specks(novel, 3, 32)
    covered = rng.random(shape) < 0.1
    for cover in (None, covered):
        fast = hole_fills(specks, measured, expected, labels, tau, cover)
        np.testing.assert_array_equal(fast, reference_hole_fills(specks, measured, expected, labels, tau, cover))
    assert hole_fills(specks, measured, expected, labels, tau).any()  # the case is not empty


def test_rim_grows_the_meshed_pixels_by_one():
    measured = np.full(SMALL.shape, 2.0, np.float32)
    expected = np.full(SMALL.shape, 2.0, np.float32)
    expected[10:30, 10:40] = np.nan
    frame, labels, _ = run_classifier(measured, expected, ClassifierParameters(min_width=3, min_region=32, rim=1))
    assert (labels[10:30, 10:40] == NOVEL).all()
    meshed = np.isfinite(frame.depth)
    assert meshed[9:31, 9:41].all() and meshed.sum() == 22 * 32


def test_the_rim_on_the_map_carries_e_where_d_agrees_with_it_and_d_elsewhere():
    """``rim_on_map``: the rim's known pixels take E's depth (the seam's strip on the map's surface); novel
    pixels keep D's, and so do rim pixels that disagree with the map (contradicted, or a speck in front of
    it); off, the rim is D throughout."""
    measured = np.full(SMALL.shape, 2.004, np.float32)  # within tau (1 cm) of the map: known
    expected = np.full(SMALL.shape, 2.0, np.float32)
    expected[10:30, 10:40] = np.nan  # a hole of the map: novel
    measured[10:30, 40:42] = 2.1  # beside it, D beyond the map: contradicted
    measured[30, 20] = 1.9  # a one-pixel speck in front of the map, in the rim
    on = ClassifierParameters(min_width=3, min_region=32, rim=2, rim_on_map=True)
    frame, labels, _ = run_classifier(measured, expected, on)
    novel = labels == NOVEL
    assert novel[10:30, 10:40].all() and novel.sum() == 20 * 30
    rim = np.isfinite(frame.depth) & ~novel
    assert rim.sum() == 24 * 34 - 20 * 30  # two pixels all round
    np.testing.assert_array_equal(frame.depth[novel], measured[novel])
    agrees = rim & (labels == KNOWN)
    agrees[30, 20] = False  # the speck is relabelled known, but D lies 10 cm in front of the map there
    assert agrees.sum() == rim.sum() - 2 * 20 - 1
    np.testing.assert_array_equal(frame.depth[agrees], expected[agrees])
    assert np.allclose(frame.depth[10:30, 40:42], 2.1) and np.isclose(frame.depth[30, 20], 1.9)
    off = ClassifierParameters(min_width=3, min_region=32, rim=2, rim_on_map=False)
    frame_off, _, _ = run_classifier(measured, expected, off)
    np.testing.assert_array_equal(frame_off.depth[rim], measured[rim])
    # "auto" on a classifier of its own is D's (the loop decides it by whether it refines the map)
    frame_auto, _, _ = run_classifier(measured, expected, ClassifierParameters(min_width=3, min_region=32, rim=2))
    np.testing.assert_array_equal(frame_auto.depth[rim], measured[rim])


def test_all_nan_measurement_gives_nothing_and_does_not_fail():
    measured = np.full(SMALL.shape, np.nan, np.float32)
    expected = np.full(SMALL.shape, 2.0, np.float32)
    frame, labels, classifier = run_classifier(measured, expected, ClassifierParameters())
    assert (labels == NO_RETURN).all()
    assert np.isnan(frame.depth).all()
    assert pixel_counts(classifier.GetOutput())["valid"] == 0


def test_mismatched_sizes_are_a_clear_error():
    other = Intrinsics(fx=52.5, fy=52.5, cx=40.0, cy=24.0, width=80, height=48)
    with pytest.raises(ValueError, match="share size and intrinsics"):
        run_classifier(np.ones(SMALL.shape), np.ones(other.shape), intrinsics_e=other)


def test_mismatched_poses_are_a_clear_error():
    with pytest.raises(ValueError, match="same pose"):
        run_classifier(np.ones(SMALL.shape), np.ones(SMALL.shape), pose_e=look_at([0, -3, 1.1], [0, 0, 1]))


def test_bad_parameters():
    from mabdi.errors import ConfigError

    with pytest.raises(ConfigError, match="tau_min"):
        ClassifierParameters(tau_min=0.0)
    with pytest.raises(ConfigError, match='rim_on_map must be true, false or "auto", got 1'):
        ClassifierParameters(rim_on_map=1)


@pytest.mark.parametrize("radius", [1, 2])
def test_slice_morphology_matches_scipy(radius):
    from scipy import ndimage

    from mabdi.stages.classifier import dilate, erode

    mask = np.random.default_rng(radius).random((50, 70)) > 0.3
    square = np.ones((2 * radius + 1, 2 * radius + 1), bool)
    np.testing.assert_array_equal(erode(mask, radius), ndimage.binary_erosion(mask, structure=square))
    np.testing.assert_array_equal(dilate(mask, radius), ndimage.binary_dilation(mask, structure=square))


def test_the_rim_closes_the_seam_between_a_new_quad_tree_patch_and_the_map():
    """A wall 3 m away under z-buffer noise, its left part in the map (meshed from one look): the rest of it,
    seen in the next look, is novel. The quad-tree's 3 x 3 blocks need a valid majority and a patch's edge
    corners move up to half a block in: without a rim a crack runs along the seam, and with noise both edges
    are ragged, so a one-pixel rim leaves gaps along it. The rim the quad-tree asks for with noisy depth
    (``reduction`` = 3, what the loop sets for ``rim = "auto"``) closes the seam wherever it falls among the
    blocks, but for notches where two blocks' corners meet it; noise-free depth needs one pixel."""
    from conftest import merged
    from mabdi.render.depth_image import DepthRenderer
    from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters
    from mabdi.surfaces.registry import seam_pixels

    parameters = QuadTreeParameters(triangles=True)
    from mabdi.surfaces.pixel_grid import PixelGridParameters

    assert seam_pixels("quadtree", parameters, True) == 3 and seam_pixels("quadtree", parameters, False) == 1
    assert seam_pixels("quadtree", QuadTreeParameters(reduction=1), True) == 1
    assert seam_pixels("pixel_grid", PixelGridParameters(), True) == 1
    intrinsics, pose, noise = Intrinsics(), look_at([0, -3, 1], [0, 0, 1]), SensorNoise("zbuffer")
    renderer = DepthRenderer()
    rng = np.random.default_rng(7)

    def quadtree(image):
        surface = FilterQuadTree(parameters)
        surface.SetInputDataObject(0, image)
        surface.Update()
        return surface.GetOutput()

    def rendered(mesh, k=intrinsics):
        zbuffer = renderer.render_zbuffer(mesh, k, pose)
        return SensorNoise().depth_from_zbuffer(zbuffer, k.near, k.far, None)

    # coverage is looked at on a grid twice as fine: a crack one pixel wide between two pixel centres (a
    # patch ending at one pixel's centre, the next starting at its neighbour's) holds no centre of the
    # sensor's grid
    twice = Intrinsics(fx=2 * intrinsics.fx, fy=2 * intrinsics.fy, cx=2 * intrinsics.cx, cy=2 * intrinsics.cy,
                       width=2 * intrinsics.width, height=2 * intrinsics.height, near=intrinsics.near, far=intrinsics.far)

    def covered(mesh):
        return np.isfinite(rendered(mesh, twice))

    def look():
        sigma = float(noise.sigma(np.array([3.0]), intrinsics.near, intrinsics.far)[0])
        return (3.0 + rng.normal(0.0, sigma, intrinsics.shape)).astype(np.float32)

    # what one mesh of the whole wall covers (the quad-tree leaves the image's outermost pixels bare)
    whole = covered(quadtree(depth_image(np.full(intrinsics.shape, 3.0, np.float32), intrinsics, pose)))
    cracks = {}
    for seam in (300, 301, 302):  # the seam at each place within a 3-pixel block
        first = look()
        first[:, seam:] = np.nan
        known = quadtree(depth_image(first, intrinsics, pose, noise=noise))
        expected = rendered(known)
        second = look()
        for rim in (0, 1, seam_pixels("quadtree", parameters, True)):
            classifier = FilterClassifier(ClassifierParameters(rim=rim))
            classifier.SetInputDataObject(0, depth_image(second, intrinsics, pose, frame=1, noise=noise))
            classifier.SetInputDataObject(1, depth_image(expected, intrinsics, pose, frame=1))
            classifier.Update()
            uncovered = whole & ~covered(merged(known, quadtree(classifier.GetOutput())))
            cracks[seam, rim] = int(np.count_nonzero(uncovered[:, 2 * (seam - 6) : 2 * (seam + 7)]))
    cracks = sorted(cracks.items())
    by_rim = {rim: [count for (_, r), count in cracks if r == rim] for rim in (0, 1, 3)}
    assert max(by_rim[3]) <= 12, cracks  # a notch or two, against two fine pixels on every row without a rim
    assert sum(by_rim[1]) > 4 * max(sum(by_rim[3]), 10), cracks
    # without a rim the crack runs along the whole seam (where the seam falls inside a block, the map's last
    # block, a minority of pixels short of it, ends where the novel pixels begin)
    assert min(by_rim[0][:2]) >= 2 * intrinsics.height, cracks  # a crack along a good part of the wall


def test_a_look_in_front_of_the_map_within_front_k_sigma_is_known_not_novel():
    """A wall 2 m away (Kinect sigma(2 m) = 5.7 mm) seen 4 sigma nearer on one half and 4 sigma further on the other:
    with k_sigma (front_k "auto" and no loop) the near half is new surface and the far half contradicts; with
    front_k 5 (a real camera's map refined within 5 sigma) the near half is the map's surface seen again, and the
    far half still contradicts: only the side in front of the map changes."""
    from mabdi.errors import ConfigError
    from mabdi.frame_values import Expected, Measured

    camera = Intrinsics(fx=80.0, fy=80.0, cx=40.0, cy=30.0, width=80, height=60)
    noise = SensorNoise("kinect")
    step = 4.0 * float(noise.sigma(np.array([2.0]), camera.near, camera.far)[0])
    depth = np.full(camera.shape, 2.0, np.float32)
    depth[:, :40] -= step
    depth[:, 40:] += step
    measured = Measured(depth, camera, np.eye(4), noise, 1)
    expected = Expected(np.full(camera.shape, 2.0, np.float32), camera, np.eye(4), 1)
    for front_k, near_label in (("auto", NOVEL), (3.0, NOVEL), (5.0, KNOWN)):
        classifier = FilterClassifier(ClassifierParameters(front_k=front_k, rim=0, gradual=False))
        labels = classifier.classify(measured, expected).labels
        assert (labels[:, :40] == near_label).all(), front_k
        assert (labels[:, 40:] == CONTRADICTED).all(), front_k
    with pytest.raises(ConfigError, match="front_k"):
        ClassifierParameters(front_k=-1.0)
