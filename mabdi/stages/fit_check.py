"""Whether a frame's depth fits the map as well as the run's frames do.

Registration (:mod:`mabdi.stages.registration`, and for a LiDAR's scans
:mod:`mabdi.stages.scan_registration`) fits each frame's depth to the map;
the residual it leaves (the RMS of a camera frame's ICP pairs, the median
|residual| of a scan's) is the sensor's noise plus the map's own error, a
few millimetres to centimetres, and steady over a run. A frame that no
rigid pose fits as well leaves several times that: a camera turning fast
enough for its rolling read-out to bend the image, a blurred frame, a pose
further off than registration follows. What such a frame sees through the map is doubtful: the
same misfit that leaves its residual puts its depth behind the map's faces.

The rule (:func:`fits_poorly`): a frame the fit ran to its end on
(:data:`JUDGED`: registered, or stopped unconverged or beyond its bound, as a
bent image's fit can) fits poorly where its residual exceeds :data:`POOR_FIT` times the median residual of the run's
last :data:`WINDOW` registered frames, once :data:`MIN_FRAMES` of them are
known. Every registered frame that moved enters the median, poorly fitting or
not, so a run whose residual rises for good (a far room, a growing LiDAR map)
takes it as its new level within half a window. A frame whose pose lies within
:data:`STILL_METRES` and :data:`STILL_DEGREES` of the frame before it does not
(:func:`moved`): a sensor standing still sees the map from where it was made and
fits it at its noise alone, a level the first frames that move exceed several
times (a handheld LiDAR standing still for nine scans fitted at 3 mm, its first
moving scans at 9-11 mm). Registration judges each frame by
it (``earlier_residuals`` of :meth:`mabdi.stages.registration.FilterRegistration.place`
and :meth:`mabdi.stages.scan_registration.ScanRegistration.place`): a camera's
frame keeps the pose the fit started from (the given pose, or the carried
correction where that fitted better), since the ICP's pose of an image no rigid
motion explains is no evidence against it, and carries nothing on to the next
frame; a LiDAR's scan keeps the fit's pose (the module docs there say why). It is still meshed; it casts no removal votes and does not teach the
noise model (:mod:`mabdi.loop.loop`), and the run counts it
(``registration.poor_fit`` in summary.json). The reasoning: docs/architecture.md
(``mabdi.stages.removal``, "Frames that fit the map poorly"); measured: docs/benchmarks.md.
"""

from __future__ import annotations

import numpy as np

#: The registration statuses of frames whose residual is judged: the fit ran over enough pairs to leave one.
JUDGED = ("registered", "not_converged", "beyond_bound")
#: A frame fits poorly where its residual exceeds this many times the run's median.
POOR_FIT = 3.0
#: The median is over the last this many registered frames' residuals ...
WINDOW = 100
#: ... once at least this many are known (before that no frame is judged).
MIN_FRAMES = 5
#: A frame within both of these of the frame before it (m, degrees) stood still: its residual is not counted.
STILL_METRES = 0.001
STILL_DEGREES = 0.1


def moved(poses: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each of the (N, 4, 4) ``poses`` lies :data:`STILL_METRES` or :data:`STILL_DEGREES` or more
    from the pose before it (the first, and a pose or its predecessor NaN: False)."""
    poses = np.asarray(poses, dtype=np.float64)
    out = np.zeros(len(poses), dtype=bool)
    if len(poses) < 2:
        return out
    before, after = poses[:-1], poses[1:]
    with np.errstate(invalid="ignore"):
        shift = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1)
        relative = np.einsum("nji,njk->nik", before[:, :3, :3], after[:, :3, :3])
        cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        turn = np.degrees(np.arccos(cosine))
        out[1:] = (shift >= STILL_METRES) | (turn >= STILL_DEGREES)
    return out


def fits_poorly(residual: float, earlier: np.ndarray) -> bool:
    """Whether a registered frame's ``residual`` (m) is more than :data:`POOR_FIT` times the median of
    ``earlier``: the residuals (m) of the run's registered frames before it, oldest first (NaN entries are
    skipped). False where fewer than :data:`MIN_FRAMES` are known or the residual is not a number."""
    earlier = np.asarray(earlier, dtype=np.float64)
    recent = earlier[np.isfinite(earlier)][-WINDOW:]
    if len(recent) < MIN_FRAMES or not np.isfinite(residual):
        return False
    return bool(residual > POOR_FIT * float(np.median(recent)))
