"""Surface seen in front of the map, meshed once it has been seen there in a few frames.

A real camera sees a known surface a little in front of where the map holds it now and then: the
recording's poses drift between two visits, an object's rim spreads over a silhouette in one look and not
the next. Meshed at once, such a look is a second copy of the surface in front of the map, which hides the
map's own from every later look and which later frames then contradict (docs/benchmarks.md, "Surface in
front of the map waits for a second and third look"). A new object stays in front frame after frame.

:class:`FrontConfirmation` keeps the memory. Its cells are voxels (:data:`VOXEL`, metres, map frame) of the
map's surface that E shows behind pixels of D in front of it. Each frame:

* a voxel with more of its pixels in front of it than on it this frame (those within
  :data:`MAJORITY_REACH_PX` of the ones in front) counts one more frame;
* a voxel the frame sees as known is forgotten: the map's surface was confirmed there (as many of its pixels
  known as in front, or none in front and the pixel its centre projects to known, E's point there in it);
* a pixel in front is meshed once its voxel has counted ``frames`` frames (its voxel is then forgotten: the
  map holds the surface in front); before that it waits, labelled novel but not meshed.

Voxels out of view keep their count. ``frames = 1`` meshes every pixel in front at once (the memory is not
used). The classifier applies it to a pinhole camera's frames
(:meth:`mabdi.stages.classifier.FilterClassifier.classify`); the loop owns the memory and resets and
checkpoints it with the map.
"""

from __future__ import annotations

import numpy as np

from mabdi.camera import Intrinsics, pixel_rays, project
from mabdi.stages.image_kernels import dilate_kernel
from mabdi.voxels.voxel_map import pack_keys, unpack_keys

#: Edge of the memory's voxels (metres): a few pixels of a camera's surface at 1-3 m, below the 5 cm at
#: which the held-out scores count a surface as misplaced.
VOXEL = 0.02
#: A voxel's pixels on the map's surface are counted within this many pixels of its pixels in front (the
#: voxel's few pixels at 1-3 m).
MAJORITY_REACH_PX = 8
#: Voxel indices are packed into one int64 key (:func:`mabdi.voxels.voxel_map.pack_keys`): +-2**20 voxels
#: (+-21 km at 2 cm) around the map's origin.
_REACH = 1 << 20


def voxel_keys(points: np.ndarray, voxel: float = VOXEL) -> np.ndarray:
    """(N,) int64 keys of the voxels that hold ``points`` ((N, 3) metres)."""
    index = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)
    if len(index) and ((index < -_REACH).any() or (index >= _REACH).any()):
        raise ValueError(f"a point lies more than {_REACH * voxel:.0f} m from the map's origin")
    return pack_keys(index)


def voxel_centres(keys: np.ndarray, voxel: float = VOXEL) -> np.ndarray:
    """(N, 3) centres (metres) of the voxels of ``keys``."""
    return (unpack_keys(keys) + 0.5) * voxel


class FrontConfirmation:
    """The frames each voxel of the map's surface was seen covered by something in front of it (module docs)."""

    def __init__(self, frames: int, voxel: float = VOXEL) -> None:
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        self.frames = int(frames)
        self.voxel = float(voxel)
        self.reset()

    def reset(self) -> None:
        """Forget every voxel."""
        #: sorted int64 voxel keys and, per key, the frames counted
        self._keys = np.zeros(0, dtype=np.int64)
        self._counts = np.zeros(0, dtype=np.int32)

    @property
    def voxels(self) -> int:
        """Voxels remembered (seen covered, not confirmed since)."""
        return len(self._keys)

    def waiting(
        self, front: np.ndarray, known: np.ndarray, expected: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray
    ) -> np.ndarray:
        """Count one frame and return (H, W) bool: the pixels of ``front`` that wait.

        ``front``: (H, W) bool, pixels of D in front of the map (novel where E has a surface); ``known``: (H, W)
        bool, pixels on the map's surface; ``expected``: E (H, W, metres, NaN where no surface); ``pose``: 4x4
        map from camera of D and E.
        """
        waiting = np.zeros(front.shape, dtype=bool)
        if self.frames <= 1:
            return waiting
        finite = np.isfinite(expected)
        front, known = front & finite, known & finite  # E's surface behind the pixel is what is counted
        rows, cols = np.nonzero(front)
        front_keys = self._keys_of(rows, cols, expected, intrinsics, pose)
        covered, pixel_voxel, front_pixels = np.unique(front_keys, return_inverse=True, return_counts=True)
        self._forget(self._confirmed(known, expected, intrinsics, pose, covered))
        # a voxel covered this frame with as many of its pixels on the map's surface as in front of it is confirmed
        rows_k, cols_k = np.nonzero(known & dilate_kernel(np.ascontiguousarray(front), MAJORITY_REACH_PX))
        known_keys = self._keys_of(rows_k, cols_k, expected, intrinsics, pose)
        at = np.minimum(np.searchsorted(covered, known_keys), max(len(covered) - 1, 0))
        on_covered = covered[at] == known_keys if len(covered) else np.zeros(len(known_keys), dtype=bool)
        confirmed = np.bincount(at[on_covered], minlength=len(covered)) >= front_pixels
        self._forget(covered[confirmed])
        frames = np.zeros(len(covered), dtype=np.int32)  # 0 for the confirmed: their pixels wait
        frames[~confirmed] = self._count_one_more(covered[~confirmed])
        waiting[rows, cols] = frames[pixel_voxel] < self.frames
        self._forget(covered[frames >= self.frames])  # meshed: the map holds the surface in front now
        return waiting

    def _keys_of(self, rows, cols, expected, intrinsics: Intrinsics, pose) -> np.ndarray:
        """Voxel keys of E's points (map frame) at the pixels (``rows``, ``cols``)."""
        points = pixel_rays(intrinsics)[rows, cols] * expected[rows, cols, None]
        return voxel_keys(points @ pose[:3, :3].T + pose[:3, 3], self.voxel)

    def _count_one_more(self, keys: np.ndarray) -> np.ndarray:
        """Count one more frame for the voxels ``keys`` (sorted, unique; new ones start at 1); their counts."""
        at = np.minimum(np.searchsorted(self._keys, keys), max(len(self._keys) - 1, 0))
        found = self._keys[at] == keys if len(self._keys) else np.zeros(len(keys), dtype=bool)
        self._counts[at[found]] += 1
        self._keys = np.concatenate([self._keys, keys[~found]])
        self._counts = np.concatenate([self._counts, np.ones(np.count_nonzero(~found), dtype=np.int32)])
        order = np.argsort(self._keys, kind="stable")
        self._keys, self._counts = self._keys[order], self._counts[order]
        return self._counts[np.searchsorted(self._keys, keys)]

    def _confirmed(self, known, expected, intrinsics: Intrinsics, pose, covered) -> np.ndarray:
        """Keys of remembered voxels not in ``covered`` whose centre falls on a ``known`` pixel whose E lies in it."""
        if not len(self._keys):
            return self._keys
        keys = self._keys[~np.isin(self._keys, covered, assume_unique=True)]
        uv, z = project(voxel_centres(keys, self.voxel), intrinsics, pose)
        ahead = z > 0
        keys, pixels = keys[ahead], np.floor(uv[ahead]).astype(np.int64)
        u, v = pixels[:, 0], pixels[:, 1]
        inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
        keys, u, v = keys[inside], u[inside], v[inside]
        on_map = known[v, u]
        keys, u, v = keys[on_map], u[on_map], v[on_map]
        return keys[self._keys_of(v, u, expected, intrinsics, pose) == keys]

    def _forget(self, keys: np.ndarray) -> None:
        if len(keys) and len(self._keys):
            keep = ~np.isin(self._keys, keys)
            self._keys, self._counts = self._keys[keep], self._counts[keep]

    def state(self) -> dict:
        """The memory, for checkpoints (plain arrays)."""
        return {"keys": self._keys.copy(), "counts": self._counts.copy()}

    def set_state(self, state: dict) -> None:
        """Go on from a :meth:`state`."""
        self._keys = np.array(state["keys"], dtype=np.int64)
        self._counts = np.array(state["counts"], dtype=np.int32)
