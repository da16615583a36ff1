"""Which ground-truth samples a run actually saw.

A sample counts as observed when some pose of the run had it inside the
image and the depth range, on the surface that pose saw: the noise-free
render of the ground truth from that pose (the scene as it stood at that
frame) reaches it and no further. Concretely, with (u, v) the sample's
continuous pixel position, z its depth and s = max(5 mm, 0.5% z) the slack,
the sample is seen when

    min(depth at the 2x2 pixel centres around (u, v)) - s <= z <= max(the same four) + s

Taking the largest and smallest of the four neighbouring depths lets samples
on steep surfaces between two pixel centres pass; anything hidden behind an
occluder lies centimetres or more behind all four. A sample in front of all
four lay in free space at that pose: its surface was not there yet (a door
that closes later, an object that arrives), so that pose did not see it,
however clear the line of sight was then.
"""

from __future__ import annotations

import numpy as np

from mabdi.depth import SensorGeometry
from mabdi.render.depth_image import SensorRenderer

#: Depth slack of the visibility test: metres, and a fraction of the depth.
VISIBILITY_SLACK_M = 0.005
VISIBILITY_SLACK_RELATIVE = 0.005


def visible_in_depth(samples: np.ndarray, depth: np.ndarray, intrinsics: SensorGeometry, pose: np.ndarray) -> np.ndarray:
    """Boolean mask of ``samples`` (N, 3) seen in a noise-free ``depth`` image (H, W) taken from ``pose``
    (a camera's z-depth or a LiDAR's range: z is then the range): on the surface the image shows, neither
    behind it nor in front of it (see the module docs)."""
    uv, z = intrinsics.project_points(samples, pose)
    w, h = intrinsics.width, intrinsics.height
    inside = (z >= intrinsics.near) & (z <= intrinsics.far) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    seen = np.zeros(len(samples), dtype=bool)
    if not inside.any():
        return seen
    index = np.flatnonzero(inside)
    # the 2x2 pixel centres around (u, v): centres sit at integer + 0.5
    u0 = np.clip(np.floor(uv[index, 0] - 0.5).astype(np.int64), 0, w - 1)
    v0 = np.clip(np.floor(uv[index, 1] - 0.5).astype(np.int64), 0, h - 1)
    u1 = np.minimum(u0 + 1, w - 1)
    v1 = np.minimum(v0 + 1, h - 1)
    neighbours = np.stack([depth[v0, u0], depth[v0, u1], depth[v1, u0], depth[v1, u1]], axis=1)
    finite = np.isfinite(neighbours)
    farthest = np.max(np.where(finite, neighbours, -np.inf), axis=1)
    nearest = np.min(np.where(finite, neighbours, np.inf), axis=1)
    zi = z[index]
    slack = np.maximum(VISIBILITY_SLACK_M, VISIBILITY_SLACK_RELATIVE * zi)
    seen[index] = np.isfinite(farthest) & (zi <= farthest + slack) & (zi >= nearest - slack)
    return seen


def observed_mask(samples: np.ndarray, scenes, poses: np.ndarray, intrinsics: SensorGeometry, backend: str = "egl") -> np.ndarray:
    """Which ``samples`` some pose saw. ``scenes`` is one mesh (a static world) or one mesh per pose."""
    poses = np.asarray(poses)
    samples = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    per_pose = isinstance(scenes, (list, tuple))
    renderer = SensorRenderer(backend)
    seen = np.zeros(len(samples), dtype=bool)
    try:
        for i, pose in enumerate(poses):
            scene = scenes[i] if per_pose else scenes
            depth = renderer.render(scene, intrinsics, pose)
            todo = ~seen
            if not todo.any():
                break
            seen[todo] = visible_in_depth(samples[todo], depth, intrinsics, pose)
    finally:
        renderer.close()
    return seen
