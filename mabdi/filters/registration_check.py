"""Whether a run's poses agree with its depth: the rule behind :class:`PosesDisagreeWarning`.

Registration (:mod:`mabdi.filters.registration`) fits each frame's depth to
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

Large corrections of frames that do register have a third cause the run
cannot tell from these: registration itself drifting away from good given
poses (a real camera's depth against a map of single looks), so that
warning names it too.

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
once a run's last frame is done and warns once.
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
#: The statuses of frames not judged (:data:`mabdi.filters.registration.STATUSES`).
NOT_JUDGED = ("off", "no_map", "exact")
#: The likely causes, named in the warning.
CAUSES = (
    "likely causes: poses given as camera_from_world (mabdi reads world_from_camera: invert them), "
    "or a wrong depth scale (--depth-scale, depth units per metre)"
)


class PosesDisagreeWarning(UserWarning):
    """A run's poses disagree with its depth (:func:`poses_disagree`)."""


def poses_disagree(
    statuses: Sequence[str],
    corrections_m: Sequence[float],
    corrections_deg: Sequence[float],
    seen_through_shares: Sequence[float] | None = None,
) -> str | None:
    """Why the frames' poses disagree with their depth, in one line, or None when they agree (the rule: the
    module docs). One entry per frame: its registration status, correction (m) and correction (degrees), and
    the share of its valid pixels that saw through the map (contradicted; None: not known, not asked);
    frames not to be judged carry
    ``"off"`` or ``"no_map"``."""
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
            f"near their given poses; {CAUSES}"
        )
    if len(registered) >= MIN_REGISTERED:
        metres = float(np.median([corrections_m[i] for i in registered]))
        degrees = float(np.median([corrections_deg[i] for i in registered]))
        if metres > MAX_CORRECTION_M or degrees > MAX_CORRECTION_DEG:
            return (
                f"the poses disagree with the depth: registration moved the frames {1000 * metres:.0f} mm and "
                f"{degrees:.1f} deg from their given poses (median of {len(registered)} registered frames; poses "
                f"that fit are off by millimetres); {CAUSES}; or, where the given poses are known to be good "
                f"(a dataset's own), registration drifting away from them (--no-registration keeps them)"
            )
    return None
