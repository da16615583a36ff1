"""Whether a run's poses agree with its depth: the rule behind :class:`PosesDisagreeWarning`.

Registration (:mod:`mabdi.stages.registration`) fits each frame's depth to
the map near its given pose. With poses that are right to millimetres
(motion capture, a SLAM system, a simulation) nearly every frame registers,
corrected by millimetres and tenths of a degree; odometry that drifts by
centimetres over a run stays within a few centimetres. Two mistakes in the
inputs show instead, and nothing else in the run says so (the map is made,
exit 0):

* poses given as camera_from_world (mabdi reads world_from_camera): each
  frame's depth lands metres from the map, and no frame registers;
* a wrong depth scale (``--depth-scale``): the depth is a few per cent to
  several times too long or short, no frame fits the map where its pose
  puts it, and the frames that register are moved by decimetres.

Large corrections of frames that register may also be registration itself
drifting away from good given poses; that warning names it too.

The rule, over the frames judged against the map (registered or not; not
the first, which has no map to fit, nor frames whose poses are stated
exact, nor runs with registration off; and only for a source that does not
state how far its poses are off, a recording: the simulator knows its pose
noise, and has no pose file or depth scale to get wrong): with at least
:data:`MIN_JUDGED` of them, the poses disagree when fewer than
:data:`MIN_REGISTERED_SHARE` of them registered while more than a few of their pixels
saw through the map at the given poses (:data:`MIN_SEEN_THROUGH_SHARE`;
frames that fit the map but give the registration too few samples, a
small image, see through almost none of it), or fewer than
:data:`MIN_REGISTERED_SHARE_SEEN_THROUGH` while a tenth of them did
(:data:`MANY_SEEN_THROUGH_SHARE`), or when at least
:data:`MIN_REGISTERED` registered and their median correction is beyond
:data:`MAX_CORRECTION_M` or :data:`MAX_CORRECTION_DEG`. The loop checks it
once a run's last frame is done and warns once; also for :data:`MIN_STRETCH`
registered frames in a row corrected beyond them (:func:`pose_excursion`).

Given poses that jump (:func:`pose_jumps`; a tracking reset, a loop closure)
make the frames after the jump see the map displaced; the run warns
(:class:`PoseJumpWarning`) where removal then took much (:func:`jumps_that_removed`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Frames judged against the map that the rule needs.
MIN_JUDGED = 4
#: Fewer than this share of the judged frames registered: the depth does not fit the map near the given poses ...
MIN_REGISTERED_SHARE = 1.0 / 3.0
#: ... when, at the given poses, more than this share of their pixels (median over the judged frames) saw through
#: the map (contradicted): in a static scene, poses that fit leave almost none however few samples the
#: registration gets (a small image); camera_from_world poses and a wrong depth scale leave a tenth or more
MIN_SEEN_THROUGH_SHARE = 0.05
#: Fewer than this share registered is enough ... when more than this share of their pixels (median) saw through the
#: map: a tenth of a static scene's pixels behind its map is what wrong poses or a wrong scale leave, and a map made
#: of faces merged over many pixels still lets some of such frames register near their given poses
MIN_REGISTERED_SHARE_SEEN_THROUGH = 0.5
MANY_SEEN_THROUGH_SHARE = 0.10
#: The registered frames' median correction beyond these (metres, degrees), taken over at least
#: :data:`MIN_REGISTERED` frames: more than any ordinary pose source is off by.
MAX_CORRECTION_M = 0.05
MAX_CORRECTION_DEG = 2.0
MIN_REGISTERED = 3
#: Registered frames in a row, each corrected beyond MAX_CORRECTION_M or MAX_CORRECTION_DEG, that make an excursion.
MIN_STRETCH = 10
#: The statuses of frames not judged (:data:`mabdi.stages.registration.STATUSES`).
NOT_JUDGED = ("off", "no_map", "exact")
#: The likely causes, named in the warning.
CAUSES = (
    "likely causes: poses given as camera_from_world (mabdi reads world_from_camera: invert them), "
    "or a wrong depth scale (--depth-scale, depth units per metre)"
)
#: ... and for a LiDAR's scans, which have no depth scale to get wrong and whose poses often come from odometry.
LIDAR_CAUSES = (
    "likely causes: poses given as sensor_from_world (mabdi reads world_from_sensor: invert them), "
    "or odometry whose heading lags or drifts (registration corrected it: the meshed poses fit the map, the given "
    "ones do not)"
)


#: A given pose jumps when its step from the frame before is over this many times the larger of the steps
#: beside it (the frame before's, the frame after's) ...
JUMP_RATIO = 4.0
#: ... and over this far (metres) or this much (degrees).
JUMP_MIN_M = 0.02
JUMP_MIN_DEG = 1.0
#: A jump is named when the frames from it to this many after removed (removal that asks two frames to see
#: through a face; :func:`jumps_that_removed` takes the window as removal asks it) ...
JUMP_FRAMES = 3
#: ... at least this share of the faces the run removed, and at least :data:`JUMP_MIN_REMOVED` faces.
JUMP_REMOVED_SHARE = 0.2
JUMP_MIN_REMOVED = 100


def pose_excursion(frames, statuses, corrections_m, corrections_deg) -> str | None:
    """The longest stretch of at least :data:`MIN_STRETCH` frames in a row that registered with a correction
    beyond :data:`MAX_CORRECTION_M` or :data:`MAX_CORRECTION_DEG`, in one line, or None. One entry per frame
    judged, in order: its index in the run, status, correction (m) and correction (degrees)."""
    best, start = None, None
    rows = list(zip(frames, statuses, corrections_m, corrections_deg))
    for i, (_, status, metres, degrees) in enumerate([*rows, (None, "", 0.0, 0.0)]):
        beyond = status == "registered" and (metres > MAX_CORRECTION_M or degrees > MAX_CORRECTION_DEG)
        if beyond and start is None:
            start = i
        elif not beyond and start is not None:
            if i - start >= MIN_STRETCH and (best is None or i - start > best[1] - best[0]):
                best = (start, i)
            start = None
    if best is None:
        return None
    stretch = rows[best[0] : best[1]]
    metres = max(row[2] for row in stretch)
    degrees = max(row[3] for row in stretch)
    return (
        f"the poses disagree with the depth over frames {int(stretch[0][0])}-{int(stretch[-1][0])}: registration "
        f"moved {len(stretch)} frames in a row beyond {1000 * MAX_CORRECTION_M:.0f} mm or {MAX_CORRECTION_DEG:g} deg "
        f"from their given poses (at most {1000 * metres:.0f} mm, {degrees:.1f} deg): the given poses drift or jump "
        f"there, or, where they are known to be good (a dataset's own), registration drifted away from them "
        f"(--no-registration keeps them)"
    )


class PoseJumpWarning(UserWarning):
    """A run's given poses jump and the frames after the jump removed much of what the run removed
    (:func:`jumps_that_removed`)."""


def _steps(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) metres and (N,) degrees each pose moved from the one before (NaN for the first and beside poses
    not known): ``poses`` (N, 4, 4) world_from_camera."""
    metres = np.full(len(poses), np.nan)
    degrees = np.full(len(poses), np.nan)
    if len(poses) < 2:
        return metres, degrees
    relative = np.linalg.inv(poses[:-1]) @ poses[1:]
    metres[1:] = np.linalg.norm(relative[:, :3, 3], axis=1)
    cosine = np.clip((np.trace(relative[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    degrees[1:] = np.degrees(np.arccos(cosine))
    return metres, degrees


def pose_jumps(poses) -> list[tuple[int, float, float, float, float]]:
    """The frames whose given pose jumped from the frame before (the rule: the module docs), as (frame, metres,
    degrees, the larger of the steps beside it in metres, in degrees). ``poses`` (N, 4, 4) world_from_camera,
    NaN for frames not known; the first and last frames are not judged (a step beside them is missing)."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or len(poses) < 3:
        return []
    with np.errstate(invalid="ignore"):
        metres, degrees = _steps(np.where(np.isfinite(poses), poses, np.nan))
    found = []
    for i in range(2, len(poses) - 1):
        beside_m = max(metres[i - 1], metres[i + 1])
        beside_deg = max(degrees[i - 1], degrees[i + 1])
        if not (np.isfinite(metres[i]) and np.isfinite(beside_m) and np.isfinite(beside_deg)):
            continue
        moved = metres[i] > JUMP_RATIO * beside_m and metres[i] > JUMP_MIN_M
        turned = degrees[i] > JUMP_RATIO * beside_deg and degrees[i] > JUMP_MIN_DEG
        if moved or turned:
            found.append((i, float(metres[i]), float(degrees[i]), float(beside_m), float(beside_deg)))
    return found


def jumps_that_removed(poses, removed, window: int = JUMP_FRAMES) -> str | None:
    """Where the given ``poses`` (N, 4, 4; :func:`pose_jumps`) jump and the ``window`` frames from a jump on
    (removal's frames required plus one) removed at least :data:`JUMP_REMOVED_SHARE` of the faces the run
    removed (``removed`` (N,): faces each frame removed, NaN where not known), why the run is doubtful there, in
    one line; None otherwise."""
    removed = np.nan_to_num(np.asarray(removed, dtype=np.float64), nan=0.0)
    total = float(removed.sum())
    named = []
    for frame, metres, degrees, beside_m, beside_deg in pose_jumps(poses):
        after = float(removed[frame : frame + window].sum())
        if after >= JUMP_MIN_REMOVED and after >= JUMP_REMOVED_SHARE * total:
            named.append(
                f"at frame {frame} ({1000 * metres:.0f} mm and {degrees:.1f} deg from frame {frame - 1}, against at most "
                f"{1000 * beside_m:.0f} mm and {beside_deg:.1f} deg for the steps beside it), after which {after:,.0f} faces "
                f"were removed in {window} frames ({after / total:.0%} of the {total:,.0f} the run removed)"
            )
    if not named:
        return None
    return (
        "the given poses jump " + "; ".join(named) + ": a pose source that jumps (a tracking reset, a loop closure) or "
        "frames missing there; the frames after a jump see the map displaced and removal takes what they see "
        "through. If nothing moved there, correct the poses or map the frames before and after the jump apart "
        "(--no-removal keeps every face)"
    )


class PosesDisagreeWarning(UserWarning):
    """A run's poses disagree with its depth (:func:`poses_disagree`)."""


def poses_disagree(
    statuses: Sequence[str],
    corrections_m: Sequence[float],
    corrections_deg: Sequence[float],
    seen_through_shares: Sequence[float] | None = None,
    causes: str = CAUSES,
) -> str | None:
    """Why the frames' poses disagree with their depth, in one line, or None when they agree (the rule: the
    module docs). One entry per frame: its registration status, correction (m) and correction (degrees), and
    the share of its valid pixels that saw through the map (contradicted; None: not known, not asked);
    frames not to be judged carry
    ``"off"`` or ``"no_map"``. ``causes``: what the warning names as likely (:data:`CAUSES`, a LiDAR's:
    :data:`LIDAR_CAUSES`)."""
    judged = [i for i, status in enumerate(statuses) if status not in NOT_JUDGED]
    if len(judged) < MIN_JUDGED:
        return None
    registered = [i for i in judged if statuses[i] == "registered"]
    shares = [] if seen_through_shares is None else [seen_through_shares[i] for i in judged]
    seen_through = float(np.nanmedian(shares)) if np.isfinite(shares).any() else 1.0
    few = len(registered) < MIN_REGISTERED_SHARE * len(judged) and seen_through > MIN_SEEN_THROUGH_SHARE
    if few or (len(registered) < MIN_REGISTERED_SHARE_SEEN_THROUGH * len(judged) and seen_through > MANY_SEEN_THROUGH_SHARE):
        return (
            f"the poses disagree with the depth: only {len(registered)} of {len(judged)} frames registered to the map "
            f"near their given poses; {causes}"
        )
    if len(registered) >= MIN_REGISTERED:
        metres = float(np.median([corrections_m[i] for i in registered]))
        degrees = float(np.median([corrections_deg[i] for i in registered]))
        if metres > MAX_CORRECTION_M or degrees > MAX_CORRECTION_DEG:
            return (
                f"the poses disagree with the depth: registration moved the frames {1000 * metres:.0f} mm and "
                f"{degrees:.1f} deg from their given poses (median of {len(registered)} registered frames; poses "
                f"that fit are off by millimetres); {causes}; or, where the given poses are known to be good "
                f"(a dataset's own), registration drifting away from them (--no-registration keeps them)"
            )
    return None
