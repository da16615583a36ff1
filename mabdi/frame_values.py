"""The values a frame's stages hand each other: D as measured, where registration placed it, E, the labels.

Plain numpy with units and frames, made once a frame and not changed after.
The loop passes them from stage to stage as they are; the VTK filters of the
pipeline API read and write them as depth images with field data, at their
edge only (:meth:`Measured.to_image`, :meth:`Measured.from_image`; E's and the
labels' arrays: :mod:`mabdi.stages.expected_image`,
:mod:`mabdi.stages.classifier`). The frame path: docs/architecture.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData

from mabdi.depth import (
    SensorGeometry,
    depth_array,
    fill_depth_image,
    image_colour,
    image_return_points,
    image_frame,
    image_intrinsics,
    image_noise,
    image_pose,
    image_timestamp,
)
from mabdi.face_identity import FaceIdTable
from mabdi.sensor_noise import SensorNoise


@dataclass(frozen=True, eq=False)
class Measured:
    """D: one frame's depth as the stages read it.

    ``depth``: (H, W) float32, metres along the camera's z (a LiDAR's: range), NaN where there is no return
    within (near, far); ``geometry``: the sensor's; ``pose``: 4x4 camera-to-frame, the source's
    world_from_camera as read, the map's frame once registered (:meth:`placed`); ``noise``: the sensor's
    noise model as it stood when D was made; ``index``: the frame's index in the run; ``timestamp``: s (NaN:
    none); ``colour``: (H, W, 3) uint8 RGB registered to the depth, or None; ``return_points``: a LiDAR's
    (H, W, 3) float32 sensor-frame return each pixel took its range from (NaN: none), or None
    (:func:`mabdi.depth.check_return_points`): where the surfaces put a pixel's vertex.
    """

    depth: np.ndarray
    geometry: SensorGeometry
    pose: np.ndarray
    noise: SensorNoise
    index: int
    timestamp: float = float("nan")
    colour: np.ndarray | None = None
    return_points: np.ndarray | None = None

    def placed(self, pose: np.ndarray) -> Measured:
        """The same D at ``pose`` (4x4)."""
        return replace(self, pose=pose)

    def showing(self, depth: np.ndarray) -> Measured:
        """The same frame with another (H, W) float32 ``depth`` (the pixels a surface is to mesh)."""
        return replace(self, depth=depth)

    def to_image(self) -> vtkImageData:
        """D as a depth-image vtkImageData (field data: geometry, pose, frame, timestamp, noise; point data
        ``colour`` when it has one). The image holds copies."""
        image = vtkImageData()
        self.fill(image)
        return image

    def fill(self, image: vtkImageData) -> None:
        """Write D into an existing vtkImageData (a filter's output), as :meth:`to_image`."""
        colour = None if self.colour is None else self.colour.copy()
        points = None if self.return_points is None else self.return_points.copy()
        fill_depth_image(
            image, self.depth.copy(), self.geometry, self.pose, self.index, self.timestamp, colour, noise=self.noise,
            return_points=points,
        )  # fmt: skip

    @classmethod
    def from_image(cls, image) -> Measured:
        """D of a depth-image vtkImageData (its depth cleaned of values that are not returns; no noise model:
        noise-free)."""
        return cls(
            depth_array(image), image_intrinsics(image), image_pose(image), image_noise(image), image_frame(image),
            image_timestamp(image), image_colour(image), image_return_points(image),
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class Placement:
    """Where registration placed a frame (:mod:`mabdi.stages.registration`).

    ``status``: an entry of :data:`mabdi.stages.registration.STATUSES` ("off" without registration);
    ``correction_m`` / ``correction_deg``: how far the meshed pose lies from the given one (the camera centre
    moved, metres; and turned, degrees); ``residual_m``: RMS residual of the ICP's pairs; ``inlier_share``;
    ``support``: the least share of a constrained direction's constraint its pairs carry; ``iterations``;
    ``given_exact``: the source states its poses exact (the frame kept its given pose); ``given_pose``: 4x4
    world_from_camera as the source gave it; ``world_from_map``: where the map's frame lies in the world;
    ``covariance``: 6x6 of the meshed pose (rotation vector in rad, translation in m), None when not registered;
    ``fitted_pose``: 4x4 camera-to-map, the pose the ICP fitted D to the map at (the meshed pose may keep the given
    one instead), None when not registered; ``poor_fit``: the fit ran (registered, or stopped unconverged or beyond its
    bound), but no rigid pose fits D to the map as the run's frames fit (:mod:`mabdi.stages.fit_check`): the frame
    keeps the pose the fit started from and casts no removal votes.
    """

    status: str
    given_pose: np.ndarray
    world_from_map: np.ndarray
    correction_m: float = 0.0
    correction_deg: float = 0.0
    residual_m: float = float("nan")
    inlier_share: float = float("nan")
    support: float = float("nan")
    iterations: int = 0
    given_exact: bool = False
    covariance: np.ndarray | None = None
    fitted_pose: np.ndarray | None = None
    poor_fit: bool = False

    @classmethod
    def unregistered(cls, given_pose: np.ndarray) -> Placement:
        """A frame used at its given pose, no registration run."""
        return cls("off", given_pose, np.eye(4))


@dataclass(frozen=True, eq=False)
class Expected:
    """E: the map seen from D's pose (:mod:`mabdi.stages.expected_image`).

    ``depth``: (H, W) float32 as D's (NaN where the map has no surface within (near, far)); ``geometry`` and
    ``pose`` (4x4 camera-to-map): D's; ``face_ids``: (H, W) int32 the code of the map face each pixel shows
    (0: none) and ``table`` what the codes are, both None when rendered without identity; ``covered``: (H, W)
    bool, a range image's map within each beam's footprint, None for a camera.
    """

    depth: np.ndarray
    geometry: SensorGeometry
    pose: np.ndarray
    index: int
    timestamp: float = float("nan")
    face_ids: np.ndarray | None = None
    table: FaceIdTable | None = None
    covered: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Classified:
    """The classifier's findings on D against E (:mod:`mabdi.stages.classifier`).

    ``labels``: (H, W) uint8 (0 no return, 1 known, 2 novel, 3 contradicted); ``depth``: (H, W) float32 what
    the surface meshes (the novel pixels and their rim, metres; NaN elsewhere); ``pose_sigma``: (H, W) float32
    E's depth uncertainty from D's pose covariance (m), None without one; ``counts``: pixels ``valid``,
    ``novel``, ``specks``, ``contradicted``; ``novel_pixels``: (H, W) bool, the pixels of ``depth`` meshed for
    their own sake (the rest is the rim), where the surface's patch keeps only their faces
    (:mod:`mabdi.surfaces.seam_trim`), None where the patch is kept whole.
    """

    labels: np.ndarray
    depth: np.ndarray
    counts: dict[str, int]
    pose_sigma: np.ndarray | None = None
    novel_pixels: np.ndarray | None = None
