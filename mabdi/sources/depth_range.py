"""A depth camera's near and far, learnt from a recording's own frames where nothing states them.

A recording's camera file rarely gives the depth range, and the defaults
(0.5-4 m, a Kinect v1's) drop what a close-range camera (0.2-0.8 m) or a
far-reaching one (to 8 m and more) measures. Where neither the recording's
``mabdi.toml`` ``[camera]`` table nor ``--camera ...,near,far`` states
them, :func:`learn_depth_range` reads up to :data:`SAMPLE_FRAMES` frames
spread over those run and moves a limit that would drop more than
:data:`DROPPED_SHARE` of their depth values:

* near to :data:`MARGIN` below the 0.1st percentile of the values (not
  below :data:`MIN_NEAR`); far to :data:`MARGIN` beyond the 99.9th
  percentile. A limit that drops no more than that share stays.
* **Every value on one side** of near..far (all nearer than near, or all
  beyond far) moves nothing: a depth unit other than the reader's
  (``--depth-scale``) is the likelier cause, and a range moved to fit it
  would make a map of the wrong size. The run then says what was dropped
  and why (:mod:`mabdi.loop.run_outputs`).

The depth values are counted before the near/far cut (:meth:`FrameSource.read_frame`). Units: metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mabdi.sources.frames import FrameSource

#: A share of a recording's depth values dropped as nearer than near or beyond far above which the range is
#: learnt (and above which a run whose range is stated says what it dropped).
DROPPED_SHARE = 0.02
#: The frames read to learn the range, spread evenly over those run.
SAMPLE_FRAMES = 10
#: The percentiles of the depth values the learnt limits are put beyond (a stray value does not move them).
LOW_PERCENTILE = 0.1
HIGH_PERCENTILE = 99.9
#: How far beyond those percentiles the limits go (a share of the value).
MARGIN = 0.05
#: The nearest near learnt (m): nearer depth values are a camera's junk, not surface.
MIN_NEAR = 0.05


@dataclass(frozen=True)
class DepthRange:
    """A learnt near and far (m), with the defaults' ``near_before``, ``far_before`` and the share of the sampled
    frames' depth values those dropped (``dropped_before``), from ``frames`` frames."""

    near: float
    far: float
    near_before: float
    far_before: float
    dropped_before: float
    frames: int

    def note(self) -> str:
        """The learnt range in words, for the run's source line."""
        return (
            f"depth range {self.near:g}-{self.far:g} m learnt from {self.frames} of its frames "
            f"({self.near_before:g}-{self.far_before:g} m dropped {100.0 * self.dropped_before:.1f}% of their depth values)"
        )


def sampled_depth_values(recording: FrameSource, count: int) -> tuple[np.ndarray, int]:
    """The depth values (m, finite and > 0, before the near/far cut) of up to :data:`SAMPLE_FRAMES` frames
    spread over the first ``count`` of ``recording``, and how many frames were read."""
    indices = np.unique(np.linspace(0, count - 1, min(SAMPLE_FRAMES, count)).round().astype(np.int64))
    values = []
    for index in indices:
        depth = np.asarray(recording.read_frame(int(index)).depth, dtype=np.float32)
        with np.errstate(invalid="ignore"):
            values.append(depth[np.isfinite(depth) & (depth > 0)])
    return np.concatenate(values), len(indices)


def learn_depth_range(recording: FrameSource, count: int) -> DepthRange | None:
    """The near and far for the first ``count`` frames of a depth camera's ``recording`` (see the module docs);
    None where the range it has keeps all but :data:`DROPPED_SHARE` of the sampled depth values on each side,
    or where every value lies on one side of it."""
    intrinsics = recording.intrinsics
    near, far = float(intrinsics.near), float(intrinsics.far)
    values, frames = sampled_depth_values(recording, count)
    if values.size == 0:
        return None
    nearer, beyond = np.count_nonzero(values <= near), np.count_nonzero(values >= far)
    if nearer == values.size or beyond == values.size:
        return None  # a unit other than the reader's is likelier than a camera that sees nothing within its range
    new_near, new_far = near, far
    if nearer > DROPPED_SHARE * values.size:
        low = float(np.percentile(values, LOW_PERCENTILE))
        new_near = max(MIN_NEAR, math.floor(100.0 * low * (1.0 - MARGIN)) / 100.0)  # whole cm, below the values
    if beyond > DROPPED_SHARE * values.size:
        high = float(np.percentile(values, HIGH_PERCENTILE))
        new_far = math.ceil(10.0 * high * (1.0 + MARGIN)) / 10.0  # whole decimetres, beyond the values
    if (new_near, new_far) == (near, far):
        return None
    return DepthRange(new_near, new_far, near, far, (nearer + beyond) / values.size, frames)
