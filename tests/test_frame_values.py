"""The frame's values and the pipeline API's edge: the VTK filters give what the methods the loop calls give.

Each stage has a method the loop calls with plain values (mabdi.frame_values) and a RequestData that reads
its input image into those values, calls the method and writes the result: the two must agree, and a value
written as an image and read back must be the same value.
"""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkImageData

from conftest import plane_mesh
from mabdi.camera import Intrinsics
from mabdi.depth import depth_array, depth_image, image_noise, image_pose
from mabdi.stages.classifier import ClassifierParameters, FilterClassifier, label_array, pixel_counts, pose_sigma_array
from mabdi.stages.expected_image import MAP_PORT, MEASURED_PORT, FilterExpectedImage, expected_of_image, face_id_array, write_expected
from mabdi.surfaces.quadtree import FilterQuadTree, QuadTreeParameters
from mabdi.stages.registration import write_placement
from mabdi.surfaces.registry import mesh_frame
from mabdi.frame_values import Measured, Placement
from mabdi.mesh_maps.mesh_map import COLOUR_LAYER
from mabdi.noise_calibration import NoiseCalibration
from mabdi.polydata import polydata_arrays
from mabdi.sensor_noise import SensorNoise

SMALL = Intrinsics(fx=80.0, fy=80.0, cx=40.0, cy=30.0, width=80, height=60)


def _pose() -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [0.02, -0.01, 0.0]
    return pose


def _measured(noise: SensorNoise) -> Measured:
    """D of a wall at 2 m with a box face at 1.5 m before its left half and a hole."""
    depth = np.full(SMALL.shape, 2.0, np.float32)
    depth[10:40, 5:30] = 1.5
    depth[50:55, 60:70] = np.nan
    colour = np.zeros((*SMALL.shape, 3), np.uint8)
    colour[..., 0] = 200
    return Measured(depth, SMALL, _pose(), noise, 7, 12.5, colour)


def test_d_written_as_an_image_and_read_back_is_the_same_value():
    calibration = NoiseCalibration()
    noise = SensorNoise("auto", calibration=calibration)
    measured = _measured(noise.snapshot())
    back = Measured.from_image(measured.to_image())
    np.testing.assert_array_equal(back.depth, measured.depth)
    np.testing.assert_array_equal(back.pose, measured.pose)
    np.testing.assert_array_equal(back.colour, measured.colour)
    assert (back.geometry, back.noise, back.index, back.timestamp) == (SMALL, measured.noise, 7, 12.5)
    # a snapshot is what an image carries of the model as it stands: equal to reading it back
    assert image_noise(depth_image(measured.depth, SMALL, _pose(), noise=noise)) == noise.snapshot()


def test_a_lidar_s_return_points_go_through_the_image_and_back():
    from mabdi.depth import DepthFrame, NO_NOISE
    from mabdi.spherical import SphericalGeometry

    geometry = SphericalGeometry(4, 8, 10.0, -10.0, 0.5, 50.0)
    depth = np.full(geometry.shape, 5.0, dtype=np.float32)
    points = np.random.default_rng(1).normal(size=(*geometry.shape, 3)).astype(np.float32)
    points[1, 2] = np.nan  # a pixel with no return of its own
    measured = Measured(depth, geometry, np.eye(4), NO_NOISE, 3, return_points=points)
    back = Measured.from_image(measured.to_image())
    np.testing.assert_array_equal(back.return_points, points)
    frame = DepthFrame.from_image(DepthFrame(depth, geometry, np.eye(4), 3, return_points=points).to_image())
    np.testing.assert_array_equal(frame.return_points, points)
    assert Measured.from_image(Measured(depth, geometry, np.eye(4), NO_NOISE, 3).to_image()).return_points is None
    with pytest.raises(ValueError, match="return points must be floats of shape"):
        DepthFrame(depth, geometry, np.eye(4), return_points=points[:, :4])


def test_a_value_image_holds_copies():
    measured = _measured(SensorNoise("kinect"))
    image = measured.to_image()
    depth_array(image, raw=True)[0, 0] = 9.0
    assert measured.depth[0, 0] == 2.0


def test_e_and_the_labels_from_the_pipeline_are_the_values_the_loop_gets():
    noise = SensorNoise("kinect")
    measured = _measured(noise)
    world = plane_mesh([0, 0, 2.0], [0, 0, -1], size=4.0, subdivisions=8)  # the wall: the box face is novel
    covariance = np.diag([1e-6, 1e-6, 1e-6, 1e-5, 1e-5, 1e-5])

    stage = FilterExpectedImage(identity=True)
    expected = stage.render(world, measured)
    pipeline = FilterExpectedImage(identity=True)
    pipeline.SetInputDataObject(MAP_PORT, world)
    pipeline.SetInputDataObject(MEASURED_PORT, measured.to_image())
    pipeline.Update()
    image = pipeline.GetOutput()
    np.testing.assert_array_equal(depth_array(image), expected.depth)
    np.testing.assert_array_equal(face_id_array(image), expected.face_ids)
    np.testing.assert_array_equal(image_pose(image), measured.pose)
    assert np.isfinite(expected.depth).mean() > 0.9 and (expected.face_ids > 0).mean() > 0.9

    again = vtkImageData()
    write_expected(again, expected)
    read = expected_of_image(again)
    np.testing.assert_array_equal(read.depth, expected.depth)
    np.testing.assert_array_equal(read.face_ids, expected.face_ids)
    assert read.table.names == expected.table.names and read.covered is None

    classifier = FilterClassifier(ClassifierParameters())
    classified = classifier.classify(measured, expected, covariance)
    registered = measured.to_image()
    write_placement(registered, Placement("registered", measured.pose, np.eye(4), covariance=covariance))
    pipeline_classifier = FilterClassifier(ClassifierParameters())
    pipeline_classifier.SetInputDataObject(0, registered)
    pipeline_classifier.SetInputConnection(1, pipeline.GetOutputPort())
    pipeline_classifier.Update()
    output = pipeline_classifier.GetOutput()
    np.testing.assert_array_equal(label_array(output), classified.labels)
    np.testing.assert_array_equal(depth_array(output), classified.depth)
    np.testing.assert_array_equal(pose_sigma_array(output), classified.pose_sigma)
    assert pixel_counts(output) == classified.counts
    assert classified.counts["novel"] >= 25 * 30  # the box face, and its rim
    assert classified.counts["valid"] == np.isfinite(measured.depth).sum()

    # the surface: the filter fed the classifier's image meshes what mesh_frame meshes of the values
    surface = FilterQuadTree(QuadTreeParameters(triangles=True))
    direct = mesh_frame(surface, measured.showing(classified.depth), measured.depth)
    through = FilterQuadTree(QuadTreeParameters(triangles=True))
    through.SetInputConnection(pipeline_classifier.GetOutputPort())
    through.Update()
    points, triangles = polydata_arrays(direct)
    points_vtk, triangles_vtk = polydata_arrays(through.GetOutput())
    assert len(triangles) > 0
    np.testing.assert_array_equal(points, points_vtk)
    np.testing.assert_array_equal(triangles, triangles_vtk)
    colours = vtk_to_numpy(direct.GetPointData().GetArray(COLOUR_LAYER))
    assert (colours[:, 0] == 200).all()
    stage.renderer.close()
    pipeline.renderer.close()
