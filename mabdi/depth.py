"""The depth image: a vtkImageData every mabdi filter reads and writes.

Layout (every filter reads and writes it so):

* extent (0, W-1, 0, H-1, 0, 0), origin 0, spacing 1;
* point array ``depth`` (float32): metric z-depth along the optical axis,
  NaN where there is no return, row-major with index v*W + u and v = 0 the
  **top** row of the image;
* field data ``intrinsics`` (float64[8]: fx, fy, cx, cy, width, height, near,
  far) for a camera, or ``spherical`` (float64[6], and optionally
  ``beam_elevations``) for a LiDAR's range image (:mod:`mabdi.spherical`:
  then the point array holds range along the beam, not z-depth),
  ``world_from_camera`` (float64[16], row-major), ``frame``
  (int64[1], the frame index, -1 when unknown) and ``timestamp`` (float64[1],
  seconds, NaN when unknown);
* field data ``noise_model`` (a string: the sensor's noise model,
  :mod:`mabdi.sensor_noise`) and ``noise_parameters`` (float64: its
  parameters, :meth:`~mabdi.sensor_noise.SensorNoise.to_array`), where the
  source states them; an image without them is read as noise-free
  (:func:`image_noise`). Every filter that needs the sensor's sigma(z) reads
  it here, so the noise model travels with the frame as the intrinsics do;
* optionally the point array ``colour`` (uint8, 3 components, sRGB): the
  colour image registered to the depth, pixel for pixel (the same index
  v*W + u), when the source has one.

**What counts as a return** is decided here, once, for every source and
filter (:func:`returns`): a depth that is finite and inside the sensor's
range, near < z < far. Anything else (NaN, 0, negative, +-inf, beyond far)
is "no return". :func:`depth_array` applies the rule, so a filter that reads
its input through it never meshes a depth behind the camera or at infinity.

:class:`DepthFrame` is the numpy side of the same thing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
from vtkmodules.vtkCommonCore import vtkStringArray
from vtkmodules.vtkCommonDataModel import vtkImageData

from mabdi.camera import Intrinsics, check_pose
from mabdi.depth_kernels import continues_kernel
from mabdi.sensor_noise import SensorNoise
from mabdi.spherical import BEAM_ELEVATIONS_ARRAY, SPHERICAL_ARRAY, SphericalGeometry

#: What a depth image's pixels are: a pinhole camera's (z-depth) or a spinning LiDAR's (range).
SensorGeometry = Intrinsics | SphericalGeometry

DEPTH_ARRAY = "depth"
INTRINSICS_ARRAY = "intrinsics"
POSE_ARRAY = "world_from_camera"
FRAME_ARRAY = "frame"
TIMESTAMP_ARRAY = "timestamp"
COLOUR_ARRAY = "colour"
NOISE_MODEL_ARRAY = "noise_model"
NOISE_PARAMETERS_ARRAY = "noise_parameters"
#: Optional point data of a depth image that holds only some pixels (the classifier's output): the whole
#: measured image, for the surfaces' tests that look at the samples beyond the pixels they mesh.
MEASURED_ARRAY = "measured_depth"
#: Optional point data of a LiDAR's range image: each pixel's own return (:func:`check_return_points`).
RETURN_POINTS_ARRAY = "return_points"


def returns(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Boolean mask of the pixels that hold a return: finite and near < depth < far (metres)."""
    depth = np.asarray(depth)
    kind = depth.dtype.type if depth.dtype.kind == "f" else float
    with np.errstate(invalid="ignore"):
        return (depth > kind(near)) & (depth < kind(far))  # NaN and +-inf fail one of the two


def only_returns(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """``depth`` as float32 with every pixel that is not a return (:func:`returns`) set to NaN.

    Returns the input itself (no copy) when it is float32 and every pixel is
    a return or NaN already.
    """
    depth = np.asarray(depth)
    if depth.dtype != np.float32:
        depth = depth.astype(np.float32)
    keep = returns(depth, near, far)
    odd = ~keep & ~np.isnan(depth)
    if not odd.any():
        return depth
    return np.where(keep, depth, np.float32(np.nan))


def check_colour(colour, shape: tuple[int, int]) -> np.ndarray | None:
    """``colour`` as a (H, W, 3) uint8 array for a depth image of ``shape`` (H, W), or None; ValueError otherwise."""
    if colour is None:
        return None
    colour = np.asarray(colour)
    if colour.shape != (*shape, 3) or colour.dtype != np.uint8:
        raise ValueError(f"colour image must be uint8 of shape {(*shape, 3)} (registered to the depth), got {colour.dtype} {colour.shape}")
    return colour


def check_return_points(points, shape: tuple[int, int]) -> np.ndarray | None:
    """``points`` as a (H, W, 3) float32 array for a range image of ``shape`` (H, W), or None; ValueError otherwise.

    A LiDAR scan's range image holds, at each pixel, the range along the pixel centre's ray; the return the
    pixel took it from was measured along its own direction, up to half a pixel off. ``return_points`` holds
    that return (sensor frame, m; NaN: the pixel has none of its own), so that the surfaces mesh where the
    sensor measured and not a pixel centre's estimate (:func:`mabdi.sources.range_images.range_image_and_returns`).
    """
    if points is None:
        return None
    points = np.asarray(points)
    if points.shape != (*shape, 3) or points.dtype.kind != "f":
        raise ValueError(f"return points must be floats of shape {(*shape, 3)} (one a pixel), got {points.dtype} {points.shape}")
    return np.asarray(points, dtype=np.float32)


@dataclass
class DepthFrame:
    """A depth image as numpy: (H, W) float32 metres, its intrinsics, pose and frame index, and optionally
    ``colour``: (H, W, 3) uint8 RGB registered to the depth pixel for pixel (None when the source has none)
    and a LiDAR's ``return_points`` (:func:`check_return_points`; None: every pixel's point is on its centre's ray)."""

    depth: np.ndarray
    intrinsics: SensorGeometry
    world_from_camera: np.ndarray
    frame: int = -1
    timestamp: float = float("nan")
    colour: np.ndarray | None = None
    return_points: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.depth = np.asarray(self.depth, dtype=np.float32)
        if self.depth.shape != self.intrinsics.shape:
            raise ValueError(
                f"depth image has shape {self.depth.shape}, but intrinsics say (height, width) = {self.intrinsics.shape}"
            )
        self.world_from_camera = check_pose(self.world_from_camera, "world_from_camera")
        self.colour = check_colour(self.colour, self.intrinsics.shape)
        self.return_points = check_return_points(self.return_points, self.intrinsics.shape)

    def to_image(self) -> vtkImageData:
        """This frame as a depth-image vtkImageData."""
        return depth_image(
            self.depth, self.intrinsics, self.world_from_camera, self.frame, self.timestamp, self.colour,
            return_points=self.return_points,
        )  # fmt: skip

    @classmethod
    def from_image(cls, image) -> DepthFrame:
        """Read a depth-image vtkImageData (copies the depth array; non-returns become NaN)."""
        intrinsics = image_intrinsics(image)
        colour = image_colour(image)
        points = image_return_points(image)
        return cls(
            np.array(depth_array(image), copy=True), intrinsics, image_pose(image), image_frame(image), image_timestamp(image),
            None if colour is None else colour.copy(), None if points is None else points.copy(),
        )


def depth_image(
    depth,
    intrinsics: SensorGeometry,
    world_from_camera,
    frame: int = -1,
    timestamp: float = float("nan"),
    colour=None,
    noise: SensorNoise | str | None = None,
    return_points=None,
) -> vtkImageData:
    """Build a depth-image vtkImageData from a (H, W) array of metres (v = 0 the top row); copies ``depth``,
    ``colour`` and ``return_points``. ``noise``: the sensor's noise model the image carries (a
    :class:`SensorNoise` or its name; None: none stated, read as noise-free)."""
    depth = np.array(depth, dtype=np.float32, order="C", copy=True)
    if depth.shape != intrinsics.shape:
        raise ValueError(
            f"depth image has shape {depth.shape}, but intrinsics say (height, width) = {intrinsics.shape}"
        )
    colour = check_colour(colour, intrinsics.shape)
    return_points = check_return_points(return_points, intrinsics.shape)
    image = vtkImageData()
    fill_depth_image(
        image, depth, intrinsics, check_pose(world_from_camera, "world_from_camera"), frame, timestamp,
        None if colour is None else colour.copy(), None if noise is None else SensorNoise.of(noise),
        None if return_points is None else return_points.copy(),
    )
    return image


def fill_depth_image(
    image: vtkImageData,
    depth: np.ndarray,
    intrinsics: SensorGeometry,
    pose: np.ndarray,
    frame: int,
    timestamp: float = float("nan"),
    colour: np.ndarray | None = None,
    noise: SensorNoise | None = None,
    return_points: np.ndarray | None = None,
) -> None:
    """Fill an existing vtkImageData (a filter's output) with a depth image (and its (H, W, 3) uint8
    ``colour``, the sensor's ``noise`` model and a LiDAR's (H, W, 3) float32 ``return_points``, when given).
    Inputs are trusted.

    The image shares ``depth``'s (and ``colour``'s) memory: hand over arrays nobody else writes to.
    """
    height, width = depth.shape
    image.SetExtent(0, width - 1, 0, height - 1, 0, 0)
    image.SetOrigin(0.0, 0.0, 0.0)
    image.SetSpacing(1.0, 1.0, 1.0)
    # Shallow: the VTK array keeps a reference to the numpy buffer (callers hand over a fresh array).
    array = numpy_to_vtk(np.ascontiguousarray(depth, dtype=np.float32).ravel(), deep=False)
    array.SetName(DEPTH_ARRAY)
    point_data = image.GetPointData()
    point_data.Initialize()
    point_data.SetScalars(array)
    if colour is not None:
        set_colour(image, colour)
    if return_points is not None:
        _add_pixel_array(image, RETURN_POINTS_ARRAY, np.ascontiguousarray(return_points, dtype=np.float32))
    field = image.GetFieldData()
    field.Initialize()
    geometry = [(INTRINSICS_ARRAY, intrinsics.to_array())]
    if intrinsics.range_image:
        geometry = [(SPHERICAL_ARRAY, intrinsics.to_array())]
        if intrinsics.beam_elevations:
            geometry.append((BEAM_ELEVATIONS_ARRAY, np.asarray(intrinsics.beam_elevations, dtype=np.float64)))
    for name, values in (
        *geometry,
        (POSE_ARRAY, np.asarray(pose, dtype=np.float64).ravel()),
        (FRAME_ARRAY, np.array([frame], dtype=np.int64)),
        (TIMESTAMP_ARRAY, np.array([timestamp], dtype=np.float64)),
    ):
        vtk_array = numpy_to_vtk(values, deep=True)
        vtk_array.SetName(name)
        field.AddArray(vtk_array)
    if noise is not None:
        set_noise(image, noise)


def set_noise(image, noise: SensorNoise) -> None:
    """Write the sensor's noise model into a depth image's field data (replacing any it held)."""
    field = image.GetFieldData()
    model = vtkStringArray()
    model.SetName(NOISE_MODEL_ARRAY)
    model.InsertNextValue(noise.model)
    parameters = numpy_to_vtk(noise.to_array(), deep=True)
    parameters.SetName(NOISE_PARAMETERS_ARRAY)
    field.AddArray(model)  # AddArray replaces an array of the same name
    field.AddArray(parameters)


def image_noise(image) -> SensorNoise:
    """The sensor's noise model a depth image carries (``none`` when it carries none: a noise-free
    sensor, as a hand-made image is read); ValueError when its arrays are malformed."""
    field = image.GetFieldData()
    model = field.GetAbstractArray(NOISE_MODEL_ARRAY)
    if model is None:
        return NO_NOISE
    parameters = field.GetArray(NOISE_PARAMETERS_ARRAY)
    if not isinstance(model, vtkStringArray) or model.GetNumberOfValues() != 1 or parameters is None:
        raise ValueError(f"depth image field data: '{NOISE_MODEL_ARRAY}' must be one string with '{NOISE_PARAMETERS_ARRAY}' beside it")
    return SensorNoise.from_array(model.GetValue(0), vtk_to_numpy(parameters))


#: What an image without a noise model is read as.
NO_NOISE = SensorNoise("none")


def _field_array(image, name: str) -> np.ndarray:
    if image is None or not hasattr(image, "GetFieldData"):
        raise TypeError(f"expected a depth-image vtkImageData, got {type(image).__name__}")
    array = image.GetFieldData().GetArray(name)
    if array is None:
        raise ValueError(f"depth image has no field-data array '{name}' (is it a mabdi depth image?)")
    return vtk_to_numpy(array)


def image_intrinsics(image) -> SensorGeometry:
    """The sensor geometry stored in a depth image's field data: a camera's :class:`~mabdi.camera.Intrinsics`, or a
    LiDAR range image's :class:`~mabdi.spherical.SphericalGeometry` (both give shape, near, far and rays)."""
    if image is not None and hasattr(image, "GetFieldData") and image.GetFieldData().GetArray(SPHERICAL_ARRAY) is not None:
        table = image.GetFieldData().GetArray(BEAM_ELEVATIONS_ARRAY)
        return SphericalGeometry.from_array(_field_array(image, SPHERICAL_ARRAY), None if table is None else vtk_to_numpy(table))
    return Intrinsics.from_array(_field_array(image, INTRINSICS_ARRAY))


#: Neighbouring samples continue one flat surface when the next lies within this many standard deviations
#: of the straight line through the two before it (:func:`straight_continuations`).
LINE_SIGMAS = 3.0
#: A floor on that tolerance, as a share of the range: the renderer's and float32's precision (a noise-free sensor).
LINE_FLOOR = 1e-4
#: Samples along a line may space out by at most this factor from one step to the next (a plane seen towards
#: its horizon spaces out without bound, and there noise is all there is).
LINE_SPACING = 4.0


def _continues(before: np.ndarray, last: np.ndarray, after: np.ndarray, sigma_after: np.ndarray) -> np.ndarray:
    """Whether ``after`` lies on the straight line through ``before`` and ``last`` (..., 3 points), within
    :data:`LINE_SIGMAS` of the extrapolation's error (sigma sqrt(1 + (1 + k)^2 + k^2), k the step ratio) plus
    the floor, stepping forwards by a ratio within :data:`LINE_SPACING`. The definition: the compiled
    :func:`mabdi.depth_kernels.continues_kernel` computes it over an image (the tests compare the two)."""
    step = last - before
    ahead = after - last
    length = np.linalg.norm(step, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.linalg.norm(ahead, axis=-1) / length
        along = np.einsum("...i,...i->...", ahead, step) / length
        off_line = np.linalg.norm(np.cross(ahead, step), axis=-1) / length
        spread = sigma_after * np.sqrt(1.0 + (1.0 + ratio) ** 2 + ratio**2)
        tolerance = LINE_SIGMAS * spread + LINE_FLOOR * np.linalg.norm(after, axis=-1)
        return (along > 0) & (ratio <= LINE_SPACING) & (ratio >= 1.0 / LINE_SPACING) & (off_line <= tolerance)


def straight_continuations(points: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which neighbouring samples of a (H, W, 3) sensor-frame point image (NaN: no return) lie on one flat
    surface however steeply it is seen (a ground plane at grazing incidence, whose neighbouring beams are
    metres apart; a silhouette's two sides are not on one line). ``sigma``: (H, W) the samples' standard
    deviation (m). Returns the masks of the edges between (v, u) and (v + 1, u) (H - 1, W), (v, u) and
    (v, u + 1) (H, W - 1), and (v, u + 1) and (v + 1, u) (H - 1, W - 1).

    Along an image line of samples ..., p0, a, b, p3, ..., the edge (a, b) is straight where

    * each of a and b lies on the straight line through the two samples before it (``forward``: b on the
      line p0 a; ``backward``: a on the line p3 b), or
    * one way only, where the sample that continues the line is not also the start of the next surface:
      ``forward`` and b not on the line p4 p3 beyond it (``backward`` of the next edge), or the mirror.
      The last two rings of a road before its end, or before the foot of a wall, have no sample beyond them
      on the same line (no return, or a wall), and the line from the near side alone decides. A sample
      beyond a silhouette that happens to lie on the foreground's extrapolated line does not count: it
      continues its own surface's line (the far facade behind a car's roof).

    An edge whose sample beyond is missing (no return, or the image's border) is decided the one way."""
    height, width = points.shape[:2]
    p = np.ascontiguousarray(points, dtype=np.float64)
    s = np.ascontiguousarray(sigma, dtype=np.float64)

    def continues(out, start, step) -> None:
        """``out[v, u]``: the sample at ``start`` + (v, u) + 2 ``step`` on the line through the two before it."""
        continues_kernel(p, s, start[0], start[1], step[0], step[1], LINE_SIGMAS, LINE_FLOOR, LINE_SPACING, out)

    vertical = np.zeros((height - 1, width), dtype=bool)
    horizontal = np.zeros((height, width - 1), dtype=bool)
    diagonal = np.zeros((height - 1, width - 1), dtype=bool)
    if height >= 3:  # edges (v, v + 1): forward from rows v - 1, v (v >= 1); backward from rows v + 2, v + 1
        forward, backward = np.zeros_like(vertical), np.zeros_like(vertical)
        continues(forward[1:], (0, 0), (1, 0))  # rows v, v + 1, v + 2
        continues(backward[:-1], (2, 0), (-1, 0))  # rows v + 2, v + 1, v
        vertical = _straight_edges(forward, backward, _shifted(backward, 1, 0), _shifted(forward, -1, 0))
    if width >= 3:
        forward, backward = np.zeros_like(horizontal), np.zeros_like(horizontal)
        continues(forward[:, 1:], (0, 0), (0, 1))
        continues(backward[:, :-1], (0, 2), (0, -1))
        horizontal = _straight_edges(forward, backward, _shifted(backward, 0, 1), _shifted(forward, 0, -1))
    if height >= 3 and width >= 3:
        # the edge (v, u) joins (v, u + 1) and (v + 1, u), on the line ..., (v - 1, u + 2), (v, u + 1), (v + 1, u),
        # (v + 2, u - 1), ...; the next edge along it is (v + 1, u - 1)
        forward, backward = np.zeros_like(diagonal), np.zeros_like(diagonal)
        continues(forward[1:, :-1], (0, 2), (1, -1))  # (v, u + 2), (v + 1, u + 1), (v + 2, u)
        continues(backward[:-1, 1:], (2, 0), (-1, 1))  # (v + 2, u), (v + 1, u + 1), (v, u + 2)
        diagonal = _straight_edges(forward, backward, _shifted(backward, 1, -1), _shifted(forward, -1, 1))
    return vertical, horizontal, diagonal


def _straight_edges(forward, backward, next_backward, previous_forward) -> np.ndarray:
    """The rule of :func:`straight_continuations` from its four tests on every edge."""
    return (forward & backward) | (forward & ~next_backward) | (backward & ~previous_forward)


def _shifted(edges: np.ndarray, dv: int, du: int) -> np.ndarray:
    """``edges`` read at (v + dv, u + du) for every (v, u); False beyond the array."""
    out = np.zeros_like(edges)
    height, width = edges.shape
    out[max(0, -dv) : height - max(0, dv), max(0, -du) : width - max(0, du)] = edges[
        max(0, dv) : height - max(0, -dv), max(0, du) : width - max(0, -du)
    ]
    return out


def is_range_image(image) -> bool:
    """True when a depth image is a LiDAR's range image (spherical geometry), False for a camera's."""
    return image_intrinsics(image).range_image


def image_pose(image) -> np.ndarray:
    """``world_from_camera`` (4x4) stored in a depth image's field data."""
    values = _field_array(image, POSE_ARRAY)
    if values.size != 16:
        raise ValueError(f"depth image field '{POSE_ARRAY}' must hold 16 values, got {values.size}")
    return check_pose(values.reshape(4, 4), "depth image world_from_camera")


def image_frame(image) -> int:
    """Frame index stored in a depth image's field data (-1 when absent)."""
    array = image.GetFieldData().GetArray(FRAME_ARRAY)
    return int(vtk_to_numpy(array)[0]) if array is not None and array.GetNumberOfTuples() else -1


def image_timestamp(image) -> float:
    """Timestamp (seconds) stored in a depth image's field data (NaN when absent)."""
    array = image.GetFieldData().GetArray(TIMESTAMP_ARRAY)
    return float(vtk_to_numpy(array)[0]) if array is not None and array.GetNumberOfTuples() else float("nan")


def _add_pixel_array(image, name: str, values: np.ndarray) -> None:
    """Put contiguous (H, W, 3) ``values`` into ``image`` as its point array ``name`` (shared memory)."""
    array = numpy_to_vtk(values.reshape(-1, 3), deep=False)
    array.SetName(name)
    image.GetPointData().AddArray(array)


def _pixel_array(image, name: str) -> np.ndarray | None:
    """The (H, W, 3) point array ``name`` of a depth image (a view), or None when it has none."""
    array = image.GetPointData().GetArray(name) if image is not None else None
    if array is None:
        return None
    intrinsics = image_intrinsics(image)
    return vtk_to_numpy(array).reshape(intrinsics.height, intrinsics.width, 3)


def set_colour(image, colour: np.ndarray) -> None:
    """Put (H, W, 3) uint8 ``colour`` into ``image`` as its point array ``colour`` (shared memory)."""
    _add_pixel_array(image, COLOUR_ARRAY, np.ascontiguousarray(colour, dtype=np.uint8))


def image_colour(image) -> np.ndarray | None:
    """(H, W, 3) uint8 colour of a depth image (a view), or None when it has none."""
    return _pixel_array(image, COLOUR_ARRAY)


def image_return_points(image) -> np.ndarray | None:
    """(H, W, 3) float32 return points of a LiDAR's depth image (a view; :func:`check_return_points`), or None."""
    return _pixel_array(image, RETURN_POINTS_ARRAY)


def copy_colour(source, target) -> None:
    """Hand ``source``'s colour array (if any) to ``target``, a depth image of the same size (shared, not copied):
    filters that rebuild a depth image from D (registration, the classifier) keep D's colour so."""
    array = source.GetPointData().GetArray(COLOUR_ARRAY)
    if array is not None:
        target.GetPointData().AddArray(array)


def colours_at(colour: np.ndarray, intrinsics: Intrinsics, camera_points: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: the colour of the pixel each camera-frame point (N, 3, metres) projects into, (u, v) =
    floor(f x / z + c), clipped to the image; points at z <= 0 take the nearest edge pixel."""
    points = np.asarray(camera_points, dtype=np.float64).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(intrinsics.fx * points[:, 0] / points[:, 2] + intrinsics.cx)
        v = np.floor(intrinsics.fy * points[:, 1] / points[:, 2] + intrinsics.cy)
    u = np.clip(np.nan_to_num(u, nan=0.0), 0, intrinsics.width - 1).astype(np.int64)
    v = np.clip(np.nan_to_num(v, nan=0.0), 0, intrinsics.height - 1).astype(np.int64)
    return colour[v, u]


def depth_array(image, raw: bool = False) -> np.ndarray:
    """(H, W) float32 depth of a depth image (row 0 is the top), non-returns as NaN (:func:`returns`).

    A view of the image's array when every pixel is a return or NaN, else a
    cleaned copy; ``raw=True`` always gives the view, as stored.
    """
    intrinsics = image_intrinsics(image)
    array = image.GetPointData().GetArray(DEPTH_ARRAY)
    if array is None:
        raise ValueError(f"depth image has no point array '{DEPTH_ARRAY}'")
    values = vtk_to_numpy(array)
    if values.size != intrinsics.width * intrinsics.height:
        raise ValueError(
            f"depth array has {values.size} values, intrinsics say {intrinsics.width}x{intrinsics.height}"
        )
    values = values.reshape(intrinsics.shape)
    if raw:
        return values
    return only_returns(values, intrinsics.near, intrinsics.far)


def measured_depth(image) -> np.ndarray | None:
    """(H, W) float32 the whole measured image behind a depth image that holds only some of its pixels (the
    classifier's output carries it as :data:`MEASURED_ARRAY`), non-returns as NaN; None when it carries none."""
    array = image.GetPointData().GetArray(MEASURED_ARRAY)
    if array is None:
        return None
    intrinsics = image_intrinsics(image)
    return only_returns(vtk_to_numpy(array).reshape(intrinsics.shape), intrinsics.near, intrinsics.far)
