"""FilterExpectedImage: the expected depth image E, the map seen from the measured image's pose.

Port 0 is the map (a vtkPolyData, or the world mesh's composite dataset of
blocks, drawn block by block); port 1 is the measured depth image D. E is
rendered without noise with D's intrinsics and pose and carries D's frame
index and timestamp (:meth:`FilterExpectedImage.render`: a
:class:`~mabdi.frame_values.Measured` D in, an
:class:`~mabdi.frame_values.Expected` E out; the loop calls it so). Pixels
where the map has no surface within (near, far) are NaN.

The rendering is :class:`~mabdi.render.depth_image.DepthRenderer`'s: one
off-screen window reused across frames, multisampling off, one mapper per
map block so a frame uploads only the blocks that changed. Registration
shares it and draws the map at the given pose first; E at a registered pose
within :data:`REUSE_WITHIN_PX` of it is that drawing, not a second one.

Only the map's chunks in the view frustum are drawn (the renderer skips a
block whose bounding box lies outside it), so E's cost follows what is in
view, not the size of the map.

**Face identity** (``identity=True``, the loop's default): the same render
draws every face in the colour of a 24-bit code, and the output gains the
int32 point array ``face_id`` (per pixel, the code of the map face seen
there; 0 = none) and the field data that says which block and cell each code
is (:class:`mabdi.face_identity.FaceIdTable`). Object removal
(:mod:`mabdi.stages.removal`) and refinement vote on faces through it.

**Along a LiDAR's own returns** (:meth:`FilterExpectedImage.along_returns`; range images whose pixels keep
their own returns, :func:`mabdi.depth.check_return_points`): a pixel's range is carried from its return's ray
to its centre's, which across a slanted surface or an edge moves it by centimetres or more. E of the same
drawing can be cast along each return's own ray instead and carried to the centre by the same amount
(:func:`along_returns`): D - E is then the return against the map along the ray it was measured on, and the
face code the face that ray meets. Removal votes on it (:mod:`mabdi.loop.loop`); the classifier's novelty,
which chooses the range image's pixels to mesh, reads E along the centre rays, as the surfaces' own tests do.

**The map within each beam's footprint** (range images only): the uint8
point array ``map_in_footprint`` is 1 where a map triangle lies within the
beam's footprint, hit by the beam or not
(:meth:`mabdi.render.range_rendering.RangeRenderer.footprint_covered`).
The classifier keeps thin novel strips where it is 0 (see its docs).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet, vtkDataObject, vtkImageData, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from mabdi.algorithm import MabdiAlgorithm
from mabdi.depth import depth_array, fill_depth_image, only_returns, image_frame, image_intrinsics, image_pose, image_timestamp
from mabdi.face_identity import FaceIdTable
from mabdi.frame_values import Expected, Measured
from mabdi.render.depth_image import DepthRenderer
from mabdi.sensor_noise import SensorNoise
from mabdi.render.range_rendering import TRIANGLE_RGB_ARRAY, RangeRenderer
from mabdi.spherical import SphericalGeometry

MAP_PORT, MEASURED_PORT = 0, 1
#: Point data of E with identity: the map face seen at each pixel (int32, 0 = none).
FACE_ID_ARRAY = "face_id"
#: Point data of a range image's E: 1 where the map reaches into the beam's footprint (uint8).
MAP_IN_FOOTPRINT_ARRAY = "map_in_footprint"


#: E drawn at a pose within this many pixels of the last drawing's (the same map) is that drawing
#: (:meth:`mabdi.render.depth_image.DepthRenderer.render_zbuffer`): a tenth of a pixel changes E by far less than D's noise.
REUSE_WITHIN_PX = 0.1

class MapAndImageAlgorithm(MabdiAlgorithm):
    """A filter of the map (port 0, any data object) and a depth image (port 1) whose output is an image
    of the depth image's extent (E, or D registered to the map)."""

    def FillInputPortInformation(self, port, info):  # noqa: N802 (VTK API)
        kind = "vtkImageData" if port == MEASURED_PORT else "vtkDataObject"
        info.Set(vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE(), kind)
        return 1

    def RequestInformation(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        measured = inInfo[MEASURED_PORT].GetInformationObject(0)
        extent = measured.Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
        if extent is not None:
            outInfo.GetInformationObject(0).Set(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT(), extent, 6)
        return 1


class FilterExpectedImage(MapAndImageAlgorithm):
    """Render the map (port 0) from the pose of the depth image on port 1 (map + D -> E)."""

    def __init__(self, backend: str = "egl", identity: bool = False) -> None:
        super().__init__(nInputPorts=2, nOutputPorts=1, outputType="vtkImageData")
        self.identity = identity
        self.renderer = DepthRenderer(backend, face_identity=identity)
        # registration draws E at the given pose first; a registered pose within a tenth of a pixel of it is that E
        self.renderer.reuse_within_px = REUSE_WITHIN_PX
        #: E of a LiDAR's range images (made at the first one).
        self.range_renderer: RangeRenderer | None = None

    def render(self, world, measured: Measured) -> Expected:
        """E: the map ``world`` (a vtkPolyData or the world mesh's blocks) drawn with ``measured``'s geometry
        from its pose (see the module docs)."""
        intrinsics, pose = measured.geometry, measured.pose
        covered = ids = table = None
        if intrinsics.range_image:  # a LiDAR's range image
            depth, ids, table = self._range_image(world, intrinsics, pose)
            covered = self.range_renderer.footprint_covered()
        else:
            depth = render_expected(self.renderer, world, intrinsics, pose)
            if self.identity:
                ids, table = self.renderer.render_identity().astype(np.int32), self.renderer.identities
        if ids is not None:
            ids[np.isnan(depth)] = 0  # beyond the range: no face
        depth = only_returns(depth, intrinsics.near, intrinsics.far)
        covered = None if covered is None else np.asarray(covered, dtype=bool)
        return Expected(depth, intrinsics, pose, measured.index, measured.timestamp, ids, table, covered)

    def RequestData(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        world = map_input(inInfo, "FilterExpectedImage")
        expected = self.render(world, Measured.from_image(vtkImageData.GetData(inInfo[MEASURED_PORT], 0)))
        write_expected(vtkImageData.GetData(outInfo), expected)
        return 1

    def along_returns(self, measured: Measured, expected: Expected) -> Expected:
        """E of ``measured`` (a LiDAR's range image) along each pixel's own return's ray, from the drawing of the
        map that :meth:`render` just made for it (``expected``, the same frame): the map's range along the
        return's direction carried to the pixel's centre as the return was (:func:`along_returns`), the face
        that ray meets and the map within its footprint; a pixel without a return of its own keeps ``expected``'s
        values. ``expected`` itself when D keeps no returns (a camera, an instant sweep). See the module docs."""
        if measured.return_points is None or not measured.geometry.range_image:
            return expected
        renderer = self.range_renderer
        drawn = None if renderer is None else renderer.drawn_pose
        if drawn is None or expected.index != measured.index or not np.array_equal(drawn, measured.pose):
            raise ValueError("FilterExpectedImage.along_returns: render E of this frame first")
        own = np.linalg.norm(measured.return_points, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            directions = measured.return_points / own[..., None]
        depth = along_returns(renderer.cast(directions), measured.depth, own)
        cast = renderer.along_directions()
        depth = only_returns(np.where(cast, depth, expected.depth), measured.geometry.near, measured.geometry.far)
        ids = None
        if expected.face_ids is not None:
            ids = np.where(cast, renderer.face_ids()[0], expected.face_ids).astype(np.int32)
            ids[np.isnan(depth)] = 0
        covered = np.where(cast, renderer.footprint_covered(), expected.covered)
        return replace(expected, depth=depth, face_ids=ids, covered=covered)

    def _range_image(self, world, geometry: SphericalGeometry, pose):
        """E of a LiDAR: the map's range image, the face code each beam hits and their table
        (:mod:`mabdi.render.range_rendering`); no codes without identity."""
        if self.range_renderer is None:
            self.range_renderer = RangeRenderer(DepthRenderer(self.renderer.backend, identity_array=TRIANGLE_RGB_ARRAY))
        depth = self.range_renderer.render(world, geometry, pose)
        if not self.identity:
            return depth, None, None
        codes, table = self.range_renderer.face_ids()
        return depth, codes.astype(np.int32), table


def along_returns(expected: np.ndarray, measured: np.ndarray, own: np.ndarray) -> np.ndarray:
    """(H, W) float32 E of a LiDAR whose pixels keep their own returns: the map's range ``expected`` along each
    return's own ray, carried to the pixel's centre ray by the return's own carry (``measured``, D's range
    there, less ``own``, the return's range; none where either is NaN). So D - E is the return's range less
    the map's along the same ray: a return carried half a pixel across a slanted surface is compared where it
    was measured, not where its pixel's centre looks."""
    carry = np.nan_to_num(np.asarray(measured, dtype=np.float64) - own)
    return (expected + carry).astype(np.float32)


def write_expected(image, expected: Expected) -> None:
    """E as a depth image (the filter's edge): its depth, D's geometry, pose, frame and timestamp; the point
    arrays ``face_id`` (with the table in the field data) and ``map_in_footprint`` when it has them."""
    fill_depth_image(image, expected.depth.copy(), expected.geometry, expected.pose, expected.index, expected.timestamp)
    if expected.covered is not None:
        array = numpy_to_vtk(expected.covered.astype(np.uint8).ravel(), deep=True)
        array.SetName(MAP_IN_FOOTPRINT_ARRAY)
        image.GetPointData().AddArray(array)
    if expected.face_ids is not None:
        array = numpy_to_vtk(expected.face_ids.ravel(), deep=True)
        array.SetName(FACE_ID_ARRAY)
        image.GetPointData().AddArray(array)
        expected.table.write(image.GetFieldData())


def expected_of_image(image) -> Expected:
    """E of an expected depth image (the filter's output or a file's)."""
    geometry = image_intrinsics(image)
    ids = image.GetPointData().GetArray(FACE_ID_ARRAY)
    covered = image.GetPointData().GetArray(MAP_IN_FOOTPRINT_ARRAY)
    return Expected(
        depth_array(image), geometry, image_pose(image), image_frame(image), image_timestamp(image),
        None if ids is None else vtk_to_numpy(ids).reshape(geometry.shape),
        None if ids is None else FaceIdTable.read(image),
        None if covered is None else vtk_to_numpy(covered).reshape(geometry.shape).astype(bool),
    )  # fmt: skip


def map_input(inInfo, name: str):
    """The map on port :data:`MAP_PORT` of a filter that renders it (a vtkPolyData or a composite dataset
    of polydata), or a TypeError naming the filter ``name``."""
    world = vtkDataObject.GetData(inInfo[MAP_PORT], 0)
    if not isinstance(world, (vtkPolyData, vtkCompositeDataSet)):
        raise TypeError(
            f"{name}: port 0 (the map) must be a vtkPolyData or a composite dataset of polydata, "
            f"got {world.GetClassName() if world is not None else None}"
        )
    return world


def render_expected(renderer: DepthRenderer, world, intrinsics, world_from_camera) -> np.ndarray:
    """(H, W) float32 metric depth of the map seen from ``world_from_camera``, without noise (NaN: no surface)."""
    zbuffer = renderer.render_zbuffer(world, intrinsics, world_from_camera)
    return SensorNoise("none").depth_from_zbuffer(zbuffer, intrinsics.near, intrinsics.far, None)


def map_in_footprint(image) -> np.ndarray | None:
    """(H, W) bool: the map reaches into each pixel's footprint (E of a range image), or None when E does not
    say (a camera's E)."""
    array = image.GetPointData().GetArray(MAP_IN_FOOTPRINT_ARRAY)
    if array is None:
        return None
    return vtk_to_numpy(array).reshape(image_intrinsics(image).shape).astype(bool)


def face_id_array(image) -> np.ndarray:
    """(H, W) int32 face codes of an expected image rendered with identity (0 = no face); what they mean is
    :meth:`mabdi.face_identity.FaceIdTable.read` of the same image."""
    array = image.GetPointData().GetArray(FACE_ID_ARRAY)
    if array is None:
        raise ValueError(f"expected image has no point array '{FACE_ID_ARRAY}' (rendered without identity?)")
    return vtk_to_numpy(array).reshape(image_intrinsics(image).shape)
