"""Held-out frames: how well a map predicts depth images that were never fused into it.

Real recordings have no ground-truth mesh, but every frame is a measurement.
Hold some frames out (every K-th, :func:`held_out_split`), build each map from
the others, then look at the map from each held-out frame's pose with its
camera and compare the map's depth with the frame's measured depth D:

* ``within`` (one share per threshold, 2 cm and 5 cm by default): of the
  valid measured pixels (a return: finite depth; the reader has already
  dropped the rest), the share where the map has a surface whose z-depth is
  within the threshold of D. A pixel where the map has nothing counts as a miss;
* ``median_abs_error_mm``: the median |map - D| over the pixels where both exist;
* ``coverage``: the share of valid measured pixels where the map has a surface at all.

The map's depth comes from exact ray casting of its triangles
(:class:`MapRaycaster`: Moller-Trumbore on the triangles whose projection
may cover a pixel: :func:`~mabdi.stages.ray_triangle_kernels.nearest_hits_in_boxes_kernel`,
with a tolerance of :data:`EDGE_TOLERANCE` on the barycentric
coordinates so that a ray through the edge two triangles share meets one of
them: a closed surface has no cracks),
through mabdi's pixel centres (pixel (u, v) centred on (u + 0.5, v + 0.5),
:func:`mabdi.camera.unit_rays`), the first surface along each ray, met from
either side. Triangles wholly nearer than the camera's near plane are not
cast (the sensor does not see there, and no return lies there). No
renderer and no Open3D are needed, so any map (mabdi's, a TSDF's) is scored
by the same code.

Scores over many frames are pooled pixel by pixel (:class:`HeldOutTally`):
shares over all valid pixels of all held-out frames, the median from a
histogram of 0.1 mm bins (:data:`ERROR_BIN_M`).

:func:`pose_differences` compares two sets of poses (the poses a run meshed
its frames with against the given ones): translation in mm, rotation angle
in degrees. The frames a map is built from are a
:class:`~mabdi.sources.frames.FrameSubset` of the recording.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import Intrinsics, project, unit_rays
from mabdi.stages.ray_triangle_kernels import nearest_hits_in_boxes_kernel
from mabdi.polydata import triangle_frames

#: The thresholds (metres) of the ``within`` shares.
THRESHOLDS = (0.02, 0.05)
#: The bin width (metres) of the pooled |error| histogram the median is read from.
ERROR_BIN_M = 1e-4
#: Errors beyond this (metres) share one last bin (a median there reads as this value).
ERROR_RANGE_M = 5.0
#: How far outside a triangle (in barycentric coordinates) a ray may pass and still meet it.
EDGE_TOLERANCE = 1e-9


def held_out_split(frames: int, every: int) -> tuple[np.ndarray, np.ndarray]:
    """(integrated, held_out) frame indices of ``range(frames)``: every ``every``-th frame (indices
    ``every - 1``, ``2 every - 1``, ...) is held out, the others are integrated; so the first frame, which
    starts a map, is always integrated. ``every`` >= 2."""
    if frames < 1:
        raise ValueError(f"held_out_split: need at least one frame, got {frames}")
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 2:
        raise ValueError(f"held_out_split: every must be an integer >= 2, got {every!r}")
    index = np.arange(frames)
    held = (index + 1) % every == 0
    return index[~held], index[held]


# ---------------------------------------------------------------------------
# The map's depth at a pose


class MapRaycaster:
    """A triangle mesh (vtkPolyData; polygons fanned into triangles) ready to be cast from any pose.

    :meth:`depth` gives the (H, W) z-depth (metres) of the first surface along each pixel's ray, NaN where
    the ray meets none.
    """

    def __init__(self, mesh: vtkPolyData) -> None:
        corner, edge1, edge2, _ = triangle_frames(mesh)
        self.corner = np.ascontiguousarray(corner, dtype=np.float64)
        self.edge1 = np.ascontiguousarray(edge1, dtype=np.float64)
        self.edge2 = np.ascontiguousarray(edge2, dtype=np.float64)

    @property
    def triangles(self) -> int:
        return len(self.corner)

    def boxes(self, intrinsics: Intrinsics, world_from_camera: np.ndarray) -> np.ndarray:
        """(T, 4) int64 pixel columns u0..u1 and rows v0..v1 (inclusive, one pixel's margin) each triangle may
        cover; u0 > u1: none (behind the camera, outside the image, or wholly nearer than ``near``). A triangle
        across the camera's plane that reaches beyond ``near`` may cover any pixel."""
        height, width = intrinsics.height, intrinsics.width
        vertices = np.stack([self.corner, self.corner + self.edge1, self.corner + self.edge2], axis=1).reshape(-1, 3)
        uv, z = project(vertices, intrinsics, world_from_camera)
        uv, z = uv.reshape(-1, 3, 2), z.reshape(-1, 3)
        in_front = z > 1e-9
        with np.errstate(invalid="ignore"):
            low = np.floor(np.nan_to_num(uv.min(axis=1), nan=-1.0, posinf=width + height, neginf=-1.0)) - 1
            high = np.floor(np.nan_to_num(uv.max(axis=1), nan=width + height, posinf=width + height, neginf=-1.0)) + 1
        boxes = np.stack([low[:, 0], high[:, 0], low[:, 1], high[:, 1]], axis=1)
        outside = (high[:, 0] < 0) | (low[:, 0] > width - 1) | (high[:, 1] < 0) | (low[:, 1] > height - 1)
        across = ~in_front.all(axis=1)
        boxes[across] = [0, width - 1, 0, height - 1]
        boxes[:, 0:2] = np.clip(boxes[:, 0:2], 0, width - 1)
        boxes[:, 2:4] = np.clip(boxes[:, 2:4], 0, height - 1)
        none = (outside & ~across) | (z.max(axis=1) <= intrinsics.near)
        boxes[none] = [1, 0, 1, 0]
        return boxes.astype(np.int64)

    def depth(self, intrinsics: Intrinsics, world_from_camera: np.ndarray) -> np.ndarray:
        """(H, W) float64 z-depth of the map seen from ``world_from_camera`` with ``intrinsics``; NaN: no surface."""
        height, width = intrinsics.height, intrinsics.width
        out = np.full((height, width), np.nan)
        if not self.triangles:
            return out
        pose = np.asarray(world_from_camera, dtype=np.float64)
        boxes = self.boxes(intrinsics, pose)
        keep = boxes[:, 0] <= boxes[:, 1]
        if not keep.any():
            return out
        rays, length = unit_rays(intrinsics, np.float64)
        directions = np.ascontiguousarray(rays.reshape(-1, 3) @ pose[:3, :3].T)
        slots = np.arange(height * width, dtype=np.int64).reshape(height, width)  # every pixel cast, row-major
        _, distances = nearest_hits_in_boxes_kernel(
            np.ascontiguousarray(pose[:3, 3]), directions, slots, np.ascontiguousarray(boxes[keep]),
            np.ascontiguousarray(self.corner[keep]), np.ascontiguousarray(self.edge1[keep]), np.ascontiguousarray(self.edge2[keep]),
            EDGE_TOLERANCE,
        )
        found = np.isfinite(distances)
        flat = out.reshape(-1)
        flat[found] = distances[found] / length.reshape(-1)[found]
        return out


def map_depth(mesh: vtkPolyData, intrinsics: Intrinsics, world_from_camera: np.ndarray) -> np.ndarray:
    """(H, W) z-depth of ``mesh`` seen from ``world_from_camera`` (NaN: no surface); see :class:`MapRaycaster`."""
    return MapRaycaster(mesh).depth(intrinsics, world_from_camera)


# ---------------------------------------------------------------------------
# Scores


@dataclass
class HeldOutScore:
    """How well a map predicts measured depth (see the module docs). Shares are of ``valid_pixels``."""

    valid_pixels: int
    within: dict[float, float]
    coverage: float
    median_abs_error_mm: float
    frames: int = 1

    def as_dict(self) -> dict:
        out = asdict(self)
        out["within"] = {f"{1000.0 * t:g}mm": v for t, v in self.within.items()}
        for t, v in self.within.items():
            out[f"within_{100.0 * t:g}cm"] = v
        return out


def _pixel_errors(measured: np.ndarray, predicted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(valid, |error| over the valid pixels, NaN where the map has nothing), shapes checked."""
    measured = np.asarray(measured, dtype=np.float64)
    predicted = np.asarray(predicted, dtype=np.float64)
    if measured.shape != predicted.shape:
        raise ValueError(f"measured depth has shape {measured.shape}, the map's depth {predicted.shape}")
    valid = np.isfinite(measured) & (measured > 0)
    errors = np.abs(predicted[valid] - measured[valid])
    return valid, errors


def score_depth(measured: np.ndarray, predicted: np.ndarray, thresholds=THRESHOLDS) -> HeldOutScore:
    """The scores of one frame: ``measured`` D and the map's ``predicted`` depth (both (H, W) z-depth in metres,
    NaN (or 0 in D) where none). Exact median."""
    tally = HeldOutTally(thresholds)
    tally.add(measured, predicted)
    score = tally.score()
    _, errors = _pixel_errors(measured, predicted)
    both = errors[np.isfinite(errors)]
    score.median_abs_error_mm = float(1000.0 * np.median(both)) if len(both) else float("nan")
    return score


@dataclass
class HeldOutTally:
    """Scores pooled over frames, pixel by pixel: :meth:`add` each frame, :meth:`score` the pool (the median
    from a histogram of :data:`ERROR_BIN_M` bins: within half a bin of the exact one)."""

    thresholds: tuple = THRESHOLDS
    valid: int = 0
    covered: int = 0
    hits: dict = field(default_factory=dict)
    frames: int = 0
    histogram: np.ndarray = field(default_factory=lambda: np.zeros(int(round(ERROR_RANGE_M / ERROR_BIN_M)) + 1, dtype=np.int64))

    def __post_init__(self) -> None:
        self.thresholds = tuple(float(t) for t in self.thresholds)
        if not self.thresholds or min(self.thresholds) <= 0:
            raise ValueError(f"HeldOutTally: thresholds must be positive metres, got {self.thresholds!r}")
        self.hits = {t: 0 for t in self.thresholds}

    def add(self, measured: np.ndarray, predicted: np.ndarray) -> HeldOutScore:
        """Pool one frame; returns that frame's own score."""
        valid, errors = _pixel_errors(measured, predicted)
        both = errors[np.isfinite(errors)]
        n = int(valid.sum())
        frame_hits = {t: int(np.count_nonzero(both <= t)) for t in self.thresholds}
        self.valid += n
        self.covered += len(both)
        for t in self.thresholds:
            self.hits[t] += frame_hits[t]
        self.frames += 1
        bins = np.minimum((both / ERROR_BIN_M).astype(np.int64), len(self.histogram) - 1)
        self.histogram += np.bincount(bins, minlength=len(self.histogram))
        return HeldOutScore(
            valid_pixels=n,
            within={t: (frame_hits[t] / n if n else float("nan")) for t in self.thresholds},
            coverage=len(both) / n if n else float("nan"),
            median_abs_error_mm=float(1000.0 * np.median(both)) if len(both) else float("nan"),
        )

    def score(self) -> HeldOutScore:
        n = self.valid
        median = float("nan")
        if self.covered:
            cumulative = np.cumsum(self.histogram)
            k = int(np.searchsorted(cumulative, 0.5 * self.covered))  # the bin holding the middle error
            median = 1000.0 * (k + 0.5) * ERROR_BIN_M
        return HeldOutScore(
            valid_pixels=n,
            within={t: (self.hits[t] / n if n else float("nan")) for t in self.thresholds},
            coverage=self.covered / n if n else float("nan"),
            median_abs_error_mm=median,
            frames=self.frames,
        )


def score_map(mesh: vtkPolyData, frames, thresholds=THRESHOLDS) -> tuple[HeldOutScore, list[HeldOutScore]]:
    """(pooled score, per-frame scores) of ``mesh`` against ``frames`` (an iterable of
    :class:`~mabdi.depth.DepthFrame`: each cast from its pose with its intrinsics)."""
    caster = MapRaycaster(mesh)
    tally = HeldOutTally(thresholds)
    per_frame = [tally.add(frame.depth, caster.depth(frame.intrinsics, frame.world_from_camera)) for frame in frames]
    return tally.score(), per_frame


# ---------------------------------------------------------------------------
# Poses


def pose_differences(reference: np.ndarray, poses: np.ndarray) -> dict:
    """How far ``poses`` (N, 4, 4) are from ``reference`` (N, 4, 4): translation (mm, of the camera centres)
    and rotation (degrees, the angle of R_ref^T R), median and max over the frames where both are finite."""
    reference = np.asarray(reference, dtype=np.float64).reshape(-1, 4, 4)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if reference.shape != poses.shape:
        raise ValueError(f"pose_differences: {reference.shape} reference poses against {poses.shape} poses")
    ok = np.isfinite(reference).all(axis=(1, 2)) & np.isfinite(poses).all(axis=(1, 2))
    reference, poses = reference[ok], poses[ok]
    if not len(poses):
        nan = float("nan")
        return {"frames": 0, "translation_mm_median": nan, "translation_mm_max": nan, "rotation_deg_median": nan, "rotation_deg_max": nan}
    translation = 1000.0 * np.linalg.norm(poses[:, :3, 3] - reference[:, :3, 3], axis=1)
    relative = np.einsum("nji,njk->nik", reference[:, :3, :3], poses[:, :3, :3])
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rotation = np.degrees(np.arccos(cosine))
    return {
        "frames": int(len(poses)),
        "translation_mm_median": float(np.median(translation)),
        "translation_mm_max": float(translation.max()),
        "rotation_deg_median": float(np.median(rotation)),
        "rotation_deg_max": float(rotation.max()),
    }


def corrected_poses(given: np.ndarray, meshed_at, meshed: np.ndarray, at) -> np.ndarray:
    """(len(at), 4, 4) the poses of frames ``at`` corrected as the run corrected the frames around them.

    ``given``: (N, 4, 4) every frame's given pose; ``meshed``: the poses the run meshed frames ``meshed_at``
    (increasing indices into ``given``) with. Each meshed frame's correction in its camera's frame,
    ``inv(given) @ meshed``, is interpolated at each frame of ``at`` between the meshed frames before and
    after it (rotation by slerp, translation linearly, by frame index; held at the ends) and applied to its
    given pose. For a map built with registration this is the pose the map would have given a frame it
    skipped (where the map's frame is not the given poses' one, the given pose looks at the map from
    slightly elsewhere)."""
    from scipy.spatial.transform import Rotation, Slerp

    given = np.asarray(given, dtype=np.float64)
    meshed_at = np.asarray(meshed_at, dtype=np.int64)
    at = np.asarray(at, dtype=np.int64)
    meshed = np.asarray(meshed, dtype=np.float64)
    if len(meshed_at) != len(meshed) or not len(meshed_at):
        raise ValueError(f"corrected_poses: {len(meshed)} meshed poses for {len(meshed_at)} frames")
    if np.any(np.diff(meshed_at) <= 0):
        raise ValueError("corrected_poses: meshed_at must be increasing")
    corrections = np.linalg.inv(given[meshed_at]) @ meshed
    t = np.clip(at, meshed_at[0], meshed_at[-1]).astype(np.float64)
    if len(meshed_at) == 1:
        correction = np.broadcast_to(corrections[0], (len(at), 4, 4)).copy()
    else:
        rotation = Slerp(meshed_at.astype(np.float64), Rotation.from_matrix(corrections[:, :3, :3]))(t).as_matrix()
        translation = np.stack([np.interp(t, meshed_at, corrections[:, k, 3]) for k in range(3)], axis=1)
        correction = np.tile(np.eye(4), (len(at), 1, 1))
        correction[:, :3, :3] = rotation
        correction[:, :3, 3] = translation
    return given[at] @ correction
