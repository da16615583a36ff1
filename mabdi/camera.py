"""Pinhole intrinsics, poses and the conversions between them and VTK.

Conventions (every module follows them):

* World frame: metres, z up.
* Camera frame: OpenCV (x right, y down, z forward along the optical axis).
* A pose is a 4x4 float64 ``world_from_camera`` matrix: it maps camera-frame
  points to world-frame points.
* Pixel (u, v) covers [u, u+1) x [v, v+1) with v = 0 the top row; its centre
  is (u + 0.5, v + 0.5) and its ray is ((u + 0.5 - cx)/fx, (v + 0.5 - cy)/fy, 1).
  Continuous pixel coordinates returned by :func:`project` follow the same
  convention, so ``floor(u), floor(v)`` is the pixel a point falls in.
  (Libraries with integer pixel centres, Open3D among them, need cx - 0.5,
  cy - 0.5.)
* Depth is z-depth along the optical axis in metres, not range along the ray.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.spatial.transform import Rotation

from mabdi.errors import ConfigError, PoseError

#: Tolerance for rigidity checks of a pose's rotation block.
RIGID_TOLERANCE = 1e-6

#: How far from orthonormal (max |R^T R - I|) a pose file's rotation block may be and still be read as a
#: rotation: files written to 6-7 significant digits, or from float32 trackers, carry 1e-7 to 1e-4; four
#: decimals about 3e-4. Beyond 5e-3 (a 0.25% scale or shear) the matrix is not a rigid motion written
#: coarsely, and reading it is an error.
POSE_FILE_TOLERANCE = 5e-3


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics and depth range.

    Focal lengths and principal point are in pixels, ``near`` and ``far`` in
    metres. The defaults are Kinect-v1-like: 640x480, f = 525 px, principal
    point at the image centre, range 0.5-4.0 m.
    """

    #: A camera's image holds z-depth along the optical axis, not range along each ray (a LiDAR's does).
    range_image: ClassVar[bool] = False
    #: The image's last column does not meet its first (a LiDAR's 360 degrees do).
    wraps_around: ClassVar[bool] = False

    fx: float = 525.0
    fy: float = 525.0
    cx: float = 320.0
    cy: float = 240.0
    width: int = 640
    height: int = 480
    near: float = 0.5
    far: float = 4.0

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"intrinsics: focal length {name} must be positive and finite, got {value!r}")
        for name in ("cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise ConfigError(f"intrinsics: principal point {name} must be finite, got {getattr(self, name)!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, float) and value.is_integer():
                object.__setattr__(self, name, int(value))
                value = int(value)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise ConfigError(f"intrinsics: {name} must be a positive integer (pixels), got {value!r}")
        for name, size in (("cx", "width"), ("cy", "height")):
            if not 0.0 <= getattr(self, name) <= getattr(self, size):
                raise ConfigError(
                    f"intrinsics: principal point {name} = {getattr(self, name)!r} lies outside the image "
                    f"(0 .. {size} = {getattr(self, size)} pixels)"
                )
        if not (math.isfinite(self.near) and math.isfinite(self.far) and 0 < self.near < self.far):
            raise ConfigError(f"intrinsics: need 0 < near < far (metres), got near={self.near!r}, far={self.far!r}")

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape as numpy sees it: (height, width)."""
        return (self.height, self.width)

    def to_array(self) -> np.ndarray:
        """float64[8]: fx, fy, cx, cy, width, height, near, far (the field-data layout)."""
        return np.array(
            [self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.near, self.far], dtype=np.float64
        )

    @classmethod
    def from_array(cls, values) -> Intrinsics:
        """Inverse of :meth:`to_array`."""
        a = np.asarray(values, dtype=np.float64).ravel()
        if a.shape != (8,):
            raise ConfigError(f"intrinsics array must have 8 values (fx, fy, cx, cy, width, height, near, far), got shape {a.shape}")
        return cls(float(a[0]), float(a[1]), float(a[2]), float(a[3]), int(round(a[4])), int(round(a[5])), float(a[6]), float(a[7]))

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K (pixel centres at +0.5, see the module docs)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def rays(self) -> np.ndarray:
        """(H, W, 3) camera-frame rays through pixel centres, with z = 1."""
        u = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        rays = np.empty((self.height, self.width, 3))
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        rays[..., 2] = 1.0
        return rays

    def rays_at(self, u, v) -> np.ndarray:
        """(..., 3) camera-frame rays with z = 1 at continuous pixel coordinates (u column, v row; pixel corners at
        integers, centres at + 0.5): depth times ray is the point."""
        u = np.asarray(u, dtype=np.float64)
        v = np.asarray(v, dtype=np.float64)
        return np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones(np.broadcast(u, v).shape)], axis=-1)

    # -- the questions every sensor geometry answers (the LiDAR's: mabdi.spherical.SphericalGeometry) --
    def pixels_per_radian(self) -> float:
        """How many pixels one radian of view spans at the image centre: ``fx``."""
        return self.fx

    def pixel_angle(self) -> float:
        """The largest angle (radians) between neighbouring pixels' rays at the image centre: 1 / min(fx, fy)."""
        return 1.0 / min(self.fx, self.fy)

    def jump_scale(self) -> float:
        """What a relative depth jump between neighbouring pixels scales by: 1 (the surfaces' thresholds were
        chosen for a camera)."""
        return 1.0

    def sensor_values(self, sensor_points) -> np.ndarray:
        """(...) the image's value for camera-frame points (..., 3): their z-depth (metres)."""
        return np.asarray(sensor_points)[..., 2]

    def project_points(self, points, world_from_sensor) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) to continuous pixel coordinates (N, 2: u column, v row; the pixel is ``floor``)
        and (N,) their z-depth (metres; <= 0 behind the camera) (:func:`project`)."""
        return project(points, self, world_from_sensor)

    @property
    def vertical_view_angle(self) -> float:
        """Full vertical field of view in degrees (what ``vtkCamera.SetViewAngle`` takes)."""
        return math.degrees(2.0 * math.atan(0.5 * self.height / self.fy))


# ---------------------------------------------------------------------------
# Poses


def _checked_pose(pose, name: str, tolerance: float, reason: str = "") -> tuple[np.ndarray, float]:
    """(``pose`` as a float64 4x4 array, max |R^T R - I| of its rotation block), or :class:`PoseError`: 4x4,
    finite, last row (0, 0, 0, 1) and a right-handed rotation block orthonormal within ``tolerance``
    (``reason`` follows the figure in the message)."""
    try:
        m = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PoseError(f"{name} must be a 4x4 numeric matrix: {exc}") from None
    if m.shape != (4, 4):
        raise PoseError(f"{name} must be a 4x4 world_from_camera matrix, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise PoseError(f"{name} has non-finite entries")
    if np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max() > tolerance:
        raise PoseError(f"{name} last row must be (0, 0, 0, 1), got {m[3].tolist()}")
    r = m[:3, :3]
    error = float(np.abs(r.T @ r - np.eye(3)).max())
    if error > tolerance:
        raise PoseError(f"{name} is not rigid: rotation block is not orthonormal (max |R^T R - I| = {error:.3g}{reason})")
    if np.linalg.det(r) < 0:
        raise PoseError(f"{name} is not rigid: rotation block is a reflection (det < 0)")
    return m, error


def check_pose(pose, name: str = "pose") -> np.ndarray:
    """Return ``pose`` as a float64 4x4 array, or raise :class:`PoseError`.

    A pose must be 4x4, finite, with last row (0, 0, 0, 1) and an orthonormal,
    right-handed rotation block (tolerance :data:`RIGID_TOLERANCE`).
    """
    return _checked_pose(pose, name, RIGID_TOLERANCE)[0]


def nearest_rotation(rotation) -> np.ndarray:
    """The rotation matrix nearest (Frobenius) to a 3x3 ``rotation``: U V^T of its SVD, det +1."""
    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=np.float64))
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] = -u[:, -1]
    return u @ vt


def pose_from_file(pose, name: str = "pose", tolerance: float = POSE_FILE_TOLERANCE) -> tuple[np.ndarray, float]:
    """A pose as a file wrote it, made rigid: (the 4x4 pose with its rotation block replaced by the nearest
    rotation, max |R^T R - I| of the block as read), or :class:`PoseError`.

    A block within ``tolerance`` of orthonormal is a rotation written to a few digits (see
    :data:`POSE_FILE_TOLERANCE`); beyond it, a reflection, a last row other than (0, 0, 0, 1), or a
    non-finite entry, the matrix is no rigid motion and ``name`` (file and line) is named.
    """
    reason = f", more than the {tolerance:g} a rotation written to a few digits carries"
    m, error = _checked_pose(pose, name, tolerance, reason)
    m[:3, :3] = nearest_rotation(m[:3, :3])
    m[3] = (0.0, 0.0, 0.0, 1.0)
    return m, error


@dataclass
class PoseRepairs:
    """What reading a pose file made rigid: how many rotation blocks were not orthonormal to
    :data:`RIGID_TOLERANCE`, the largest max |R^T R - I| among them, and how far the largest replacement moved a
    point 1 m from the sensor (metres)."""

    poses: int = 0
    repaired: int = 0
    worst_error: float = 0.0
    worst_shift: float = 0.0

    def read(self, pose, name: str = "pose") -> np.ndarray:
        """:func:`pose_from_file` of ``pose``, counted."""
        rigid, error = pose_from_file(pose, name)
        self.poses += 1
        if error > RIGID_TOLERANCE:
            self.repaired += 1
            self.worst_error = max(self.worst_error, error)
            shift = float(np.linalg.norm(np.asarray(pose, dtype=np.float64)[:3, :3] - rigid[:3, :3], ord=2))
            self.worst_shift = max(self.worst_shift, shift)
        return rigid

    def note(self, where: str) -> str | None:
        """One line on the repairs for a user (None when none was needed)."""
        if not self.repaired:
            return None
        return (
            f"{where}: {self.repaired} of {self.poses} poses have rotation blocks up to {self.worst_error:.2g} "
            f"from orthonormal (max |R^T R - I|, as poses written to a few digits do); each was replaced by its "
            f"nearest rotation, moving a point 1 m from the sensor by at most {self.worst_shift * 1000:.2g} mm"
        )


@functools.lru_cache(maxsize=8)
def _cached_rays(intrinsics: Intrinsics, unit: bool, dtype: str) -> tuple[np.ndarray, np.ndarray]:
    rays = intrinsics.rays()  # ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, 1)
    length = np.linalg.norm(rays, axis=-1)
    out = (rays / length[..., None] if unit else rays).astype(dtype, copy=False)
    out.setflags(write=False)
    length.setflags(write=False)
    return out, length


def pixel_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) float64 camera-frame rays through pixel centres with z = 1 (:meth:`Intrinsics.rays`), computed
    once per intrinsics and shared: read-only."""
    return _cached_rays(intrinsics, False, "float64")[0]


def at_returns(points: np.ndarray, return_points: np.ndarray | None, shift: np.ndarray | None = None) -> np.ndarray:
    """Sensor-frame ``points`` (..., 3, m) of a LiDAR's pixels (its unit rays times the range) moved to each
    pixel's own return where ``return_points`` (..., 3; NaN: none; None: no pixel has one) holds it, pushed
    along that return's direction by ``shift`` (..., m: how far smoothing moved the pixel's range; None: 0).
    The range image holds the range along each pixel centre's ray, for comparisons with the map's image;
    a surface's vertex belongs where the sensor measured (:func:`mabdi.depth.check_return_points`)."""
    if return_points is None:
        return points
    own = np.asarray(return_points, dtype=np.float64)
    has = np.isfinite(own[..., 0])
    if not has.any():
        return points
    if shift is not None:
        length = np.linalg.norm(own, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            own = own * ((length + np.nan_to_num(np.asarray(shift, dtype=np.float64))) / length)[..., None]
    return np.where(has[..., None], own, points)


def unit_rays(intrinsics: Intrinsics, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) unit camera-frame rays through pixel centres (as ``dtype``), and (H, W) float64 their length per
    metre of z-depth (a point at depth z lies ``z * length`` along its unit ray). Computed once per intrinsics and
    dtype and shared (the pipeline's one ray cache): read-only."""
    return _cached_rays(intrinsics, True, np.dtype(dtype).name)


def quaternions_from_rotations(rotations) -> np.ndarray:
    """(N, 4) unit quaternions (x, y, z, w) of (N, 3, 3) rotation matrices (w >= 0; the nearest rotation if not exact).

    The one conversion mabdi uses (scipy's :class:`~scipy.spatial.transform.Rotation`): TUM trajectories, ROS 2
    transforms, goal poses on a map.
    """
    q = Rotation.from_matrix(np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)).as_quat()
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``world_from_camera`` of a camera at ``eye`` whose optical axis points at ``target``.

    The image's up direction (-y of the camera) is as close to ``up`` (world)
    as possible. Raises :class:`PoseError` when eye == target or the view
    direction is parallel to ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    norm = np.linalg.norm(z)
    if norm < 1e-12:
        raise PoseError(f"look_at: eye and target coincide at {eye.tolist()}")
    z /= norm
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise PoseError(f"look_at: view direction {z.tolist()} is parallel to up {up.tolist()}")
    x /= nx
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


# ---------------------------------------------------------------------------
# Z-buffer <-> metric depth (OpenGL perspective projection, depth range [0, 1])


def zbuffer_to_depth(zbuffer, near: float, far: float) -> np.ndarray:
    """Metric z-depth (m) from normalised z-buffer values d in [0, 1].

    z = f n / (f - d (f - n)). Values d >= 1 (the cleared background, or
    anything at or beyond the far plane) become NaN: no return. Computed in
    the input's floating type (float32 for a read-back z-buffer, whose 24-bit
    resolution it exceeds) or float64 otherwise.
    """
    d = np.asarray(zbuffer)
    if d.dtype != np.float32:
        d = d.astype(np.float64)
    z = d * d.dtype.type(-(far - near))
    z += d.dtype.type(far)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(d.dtype.type(far * near), z, out=z)
    np.copyto(z, np.nan, where=~(d < 1.0))
    return z


def depth_to_zbuffer(depth, near: float, far: float) -> np.ndarray:
    """Inverse of :func:`zbuffer_to_depth`: d = f (z - n) / (z (f - n)); NaN stays NaN."""
    z = np.asarray(depth, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return far * (z - near) / (z * (far - near))


def zbuffer_depth_derivative(depth, near: float, far: float) -> np.ndarray:
    """|dz/dd| at metric depth z: (f - n) z^2 / (f n), metres per unit of d (float32 stays float32)."""
    z = np.asarray(depth)
    if z.dtype != np.float32:
        z = z.astype(np.float64)
    return (far - near) * z * z / (far * near)


# ---------------------------------------------------------------------------
# Back-projection and projection


def backproject(depth, intrinsics: Intrinsics, world_from_camera, keep_invalid: bool = False) -> np.ndarray:
    """World points (m) of a (H, W) metric depth image.

    Returns (N, 3) points of the valid (finite) pixels in row-major order, or
    with ``keep_invalid=True`` an (H, W, 3) array with NaN at invalid pixels.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != intrinsics.shape:
        raise ValueError(f"depth image shape {depth.shape} does not match intrinsics (height, width) {intrinsics.shape}")
    pose = check_pose(world_from_camera, "world_from_camera")
    camera_points = intrinsics.rays() * depth[..., None]
    world = camera_points @ pose[:3, :3].T + pose[:3, 3]
    if keep_invalid:
        return world
    return world[np.isfinite(depth)]


def project(points, intrinsics: Intrinsics, world_from_camera) -> tuple[np.ndarray, np.ndarray]:
    """Project world points to continuous pixel coordinates.

    Returns ``(uv, z)``: (N, 2) pixel coordinates (u right, v down; the pixel
    is ``floor(uv)``) and (N,) z-depth in the camera frame (m). Points behind
    the camera get z <= 0 and meaningless uv; callers filter on z.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pose = check_pose(world_from_camera, "world_from_camera")
    r, t = pose[:3, :3], pose[:3, 3]
    cam = (pts - t) @ r
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * cam[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * cam[:, 1] / z + intrinsics.cy
    return np.stack([u, v], axis=1), z


def in_view(points, intrinsics: Intrinsics, world_from_camera) -> np.ndarray:
    """Boolean mask: which world points lie inside the image and the depth range."""
    uv, z = project(points, intrinsics, world_from_camera)
    return (
        (z >= intrinsics.near)
        & (z <= intrinsics.far)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= intrinsics.width)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= intrinsics.height)
    )


def frustum_planes(intrinsics: Intrinsics, world_from_camera) -> np.ndarray:
    """(6, 4) world-frame planes (a, b, c, d) of the view frustum, inside where a x + b y + c z + d >= 0: the four
    image edges (u = 0, u = width, v = 0, v = height) and near <= z <= far."""
    i = intrinsics
    camera = np.array([
        [i.fx, 0.0, i.cx, 0.0],
        [-i.fx, 0.0, i.width - i.cx, 0.0],
        [0.0, i.fy, i.cy, 0.0],
        [0.0, -i.fy, i.height - i.cy, 0.0],
        [0.0, 0.0, 1.0, -i.near],
        [0.0, 0.0, -1.0, i.far],
    ])
    pose = check_pose(world_from_camera, "world_from_camera")
    normals = camera[:, :3] @ pose[:3, :3].T
    return np.column_stack([normals, camera[:, 3] - normals @ pose[:3, 3]])


def boxes_outside(bounds, planes) -> np.ndarray:
    """(N,) bool: which axis-aligned boxes (N, 6: xmin, xmax, ymin, ymax, zmin, zmax) lie wholly outside one of
    ``planes`` (from :func:`frustum_planes`). Conservative: a box reported inside may still miss the frustum."""
    bounds = np.asarray(bounds, dtype=np.float64).reshape(-1, 6)
    lower, upper = bounds[:, 0::2], bounds[:, 1::2]
    planes = np.asarray(planes, dtype=np.float64)
    # per box and plane, the corner farthest along the plane's normal
    corner = np.where(planes[None, :, :3] > 0, upper[:, None, :], lower[:, None, :])
    return ((corner * planes[None, :, :3]).sum(axis=2) + planes[None, :, 3] < 0).any(axis=1)


# ---------------------------------------------------------------------------
# VTK camera


def configure_vtk_camera(camera, intrinsics: Intrinsics, world_from_camera) -> None:
    """Set a ``vtkCamera`` so a render of size (width, height) matches the pinhole model exactly.

    * position / focal point / view up from the pose (VTK looks along -z with
      +y up; the OpenCV camera looks along +z with +y down);
    * vertical view angle 2 atan(H / (2 fy));
    * explicit aspect (W fy) / (H fx), so fx != fy works;
    * window centre (1 - 2 cx / W, 2 cy / H - 1) for an off-centre principal point;
    * clipping range (near, far).
    """
    pose = check_pose(world_from_camera, "world_from_camera")
    position = pose[:3, 3]
    forward = pose[:3, 2]
    down = pose[:3, 1]
    camera.SetPosition(*position)
    camera.SetFocalPoint(*(position + forward))
    camera.SetViewUp(*(-down))
    camera.SetViewAngle(intrinsics.vertical_view_angle)
    camera.SetUseHorizontalViewAngle(False)
    camera.SetExplicitAspectRatio((intrinsics.width * intrinsics.fy) / (intrinsics.height * intrinsics.fx))
    camera.SetUseExplicitAspectRatio(True)
    camera.SetWindowCenter(1.0 - 2.0 * intrinsics.cx / intrinsics.width, 2.0 * intrinsics.cy / intrinsics.height - 1.0)
    camera.SetClippingRange(intrinsics.near, intrinsics.far)


def intrinsics_from_vtk_camera(camera, width: int, height: int) -> Intrinsics:
    """Inverse of :func:`configure_vtk_camera` for a window of ``width`` x ``height`` pixels.

    Without an explicit aspect ratio VTK assumes square pixels (fx = fy).
    """
    if camera.GetUseHorizontalViewAngle():
        fx = 0.5 * width / math.tan(math.radians(camera.GetViewAngle()) / 2.0)
        aspect = camera.GetExplicitAspectRatio() if camera.GetUseExplicitAspectRatio() else width / height
        fy = fx * aspect * height / width
    else:
        fy = 0.5 * height / math.tan(math.radians(camera.GetViewAngle()) / 2.0)
        aspect = camera.GetExplicitAspectRatio() if camera.GetUseExplicitAspectRatio() else width / height
        fx = fy * width / (height * aspect)
    wcx, wcy = camera.GetWindowCenter()
    near, far = camera.GetClippingRange()
    return Intrinsics(
        fx=fx,
        fy=fy,
        cx=(1.0 - wcx) * width / 2.0,
        cy=(1.0 + wcy) * height / 2.0,
        width=int(width),
        height=int(height),
        near=near,
        far=far,
    )


def pose_from_vtk_camera(camera) -> np.ndarray:
    """``world_from_camera`` (OpenCV camera frame) of a ``vtkCamera``."""
    position = np.array(camera.GetPosition())
    forward = np.array(camera.GetDirectionOfProjection())
    up = np.array(camera.GetViewUp())
    z = forward / np.linalg.norm(forward)
    y = -(up - np.dot(up, z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, position
    return pose
