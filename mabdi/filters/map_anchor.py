"""MapAnchor: where the map's frame lies in the world, from the given poses and the registered ones.

Frame-to-map registration (:mod:`mabdi.filters.registration`) makes every
frame agree with the map, but the map itself was started from a given pose:
the first frame is meshed where its pose says, error included, and every
later frame is registered into that frame. A map whose first pose was
0.2 degrees off is 0.2 degrees off as a whole (1.4 cm at 4 m), however well
the frames fit it. The given poses are the only link to the world, so the
map's frame is tied to them as a whole, not to the first one alone.

Each frame that fits the map gives the *apparent offset* between its
registered pose C (map frame) and its given pose G (world): the rotation
dR = R_C R_G^T (a rotation vector) and the translation dt = t_C - t_G. If
the map frame is the world moved by A = (R_A, t_A), then dR = R_A and
dt = (R_A - I) t_G + t_A, up to the errors of the given pose. How those
errors behave decides which frames to believe:

* **jitter** (a motion-capture system, a SLAM with loop closures): errors
  independent from frame to frame, so the mean over all frames is best;
* **drift** (odometry): errors that start at zero and grow as a random walk
  with the distance travelled s, so the first frames are best.

The anchor learns which it is from the offsets themselves: half the mean
squared difference of two frames' offsets, per component, is modelled as
sigma^2 + q |s_i - s_j| / 2 (the variogram of white noise plus a random
walk in s) and fitted by the method of moments (:func:`_variogram_fit`),
and A is the best linear unbiased estimate under the covariance
sigma^2 I + q min(s_i, s_j) across frames: the mean for pure jitter, the
first frame for pure drift, in between for both. A's rotation is estimated
from both halves of each offset together (:func:`_anchor_fit`, generalised
least squares over rotation and translation): the orientations say R_A
directly, and the places say it through (R_A - I) t_G, a lever as long as
the cameras are far from the origin. With a camera circling 3 m out, 2 mm
of positional jitter pins the rotation to 2 mm / 3 m / sqrt(N/2), three
times better than 0.15 degrees of orientation jitter does
(0.15 / sqrt(N)); each half is weighted by its own noise. Until
:data:`MIN_FRAMES_FOR_DRIFT` frames say how the two noises compare (learnt),
the rotation is the orientations' mean and the translation the mean of what
is left. At most :data:`MAX_FRAMES` frames take part, spread evenly over
the run (the first always).

``world_from_map`` is A's inverse: the loop builds the map in the map frame
(E, the classifier and the surfaces all work there) and turns the map and
the trajectory into the world with it when they are handed out.

**How good the given poses are** (:meth:`MapAnchor.given_variance`): a
source that states it is taken at its word (sigma^2 + q s per component,
rotation in rad^2, translation in m^2). Otherwise it is learnt from the
offsets (registered minus given): their spread about their mean, per
component, less the two errors the registration brings of its own. One is
its noise (each frame's pose covariance, the mean of the diagonal per
block). The other is the map's own placement error, which no number of
pixels averages away: the map was meshed from earlier frames of the same
sensor, whose error is partly correlated across the image (depth
calibration and distortion, a structured-light camera's correlated noise,
the surfaces' chords), so a frame registered to it is off by about the
sensor's depth noise at the depth it sees: sigma(z) in translation and
sigma(z) over the half-width of the view at z in rotation (each frame
brings it: :func:`mabdi.filters.registration.map_placement_variance`).
Given poses whose offsets stay within what the map itself resolves are
kept as they are (a good tracker's); jitter or a drift beyond it spreads
the offsets further and the registration takes over. The spread, not the
variogram's extrapolation q s: a fit that reads the map's slowly changing
error as a drift (one pass, no returns) has the registration follow it;
the map it then builds walks with it, which the next offsets read as more
drift, and the poses walk away from good ones (docs/benchmarks.md, "Real
frames: 7-Scenes redkitchen, held out"). Where the run has come back to
places, the returns' fit below says it instead, with both errors taken off
its white part.

**Offsets bound to a place, not to the distance travelled.** A map is not
exact: a voxel-plane map cuts chords through a curved surface, a terrace of
correlated noise meshed from a first look stays in the map. Frames that see
such a part of the map register a few millimetres off however exact their
given poses, and frames that see the same part again, a circle later, are
off by the same amount. Over one pass these offsets change slowly from frame
to frame, which is what a drift looks like; only a return to a place tells
them apart: under drift the offsets on a return differ by the walk since the
first visit, offsets of the map's own error agree. So when the run has come
back (at least :data:`MIN_REVISITS` pairs of frames within
:data:`PLACE_RADIUS` of each other that travelled :data:`REVISIT_DISTANCE`
or more between them), the variogram is fitted on pairs of nearby frames
only, with a third term growing with their place distance (the map's error
changing from place to place): sigma^2 + q |s_i - s_j| / 2 + c d_ij, by
non-negative least squares (:func:`_revisit_fit`). A frame's place is its
given camera centre and the point it looks at (along the optical axis at
the median depth of its image); d_ij is the mean of the two distances.
Without returns (a straight drive) the two cannot be told apart and the
offsets are read as drift, the safe side: a map that is off is then followed
rather than a pose source trusted that may be drifting.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation

#: Frames that take part in the estimate, at most (spread evenly over the run, the first always).
MAX_FRAMES = 128
#: Below this many frames the given poses' errors are taken as white (too few to see a drift).
MIN_FRAMES_FOR_DRIFT = 8
#: Frames whose places (camera centre and looked-at point, mean distance) are closer than this (m) see
#: much the same part of the map.
PLACE_RADIUS = 1.0
#: A return to a place: two frames within :data:`PLACE_RADIUS` that travelled at least this far (m) between them.
REVISIT_DISTANCE = 3.0 * PLACE_RADIUS
#: Returns needed before place-bound offsets are told from drift (:func:`_revisit_fit`).
MIN_REVISITS = 8
#: A floor on the white-noise variance (relative), so the covariance stays invertible for pure drift.
REGULARISER = 1e-6
#: A floor on it (rad^2 or m^2): offsets never agree to better than a micrometre or microradian.
VARIANCE_FLOOR = 1e-12


def _variogram_fit(values: np.ndarray, travelled: np.ndarray) -> tuple[float, float]:
    """(sigma^2, q) of white noise plus a random walk in s, per component, by the method of moments:
    consecutive frames differ by 2 sigma^2 + q ds in mean square, and the frames spread about their mean
    by about sigma^2 + q L / 6 (L: the distance covered; a Brownian path's mean spread). Both >= 0.
    With fewer than :data:`MIN_FRAMES_FOR_DRIFT` frames the offsets are taken as white noise."""
    n = len(values)
    if n < MIN_FRAMES_FOR_DRIFT:
        return 1.0, 0.0
    components = values.shape[1]
    steps = np.diff(travelled)
    consecutive = 0.5 * float(np.sum(np.diff(values, axis=0) ** 2)) / ((n - 1) * components)  # sigma^2 + q ds / 2
    spread = float(np.sum((values - values.mean(axis=0)) ** 2)) / ((n - 1) * components)  # sigma^2 + q L / 6
    half_step = 0.5 * float(steps.mean())
    sixth = (float(travelled[-1] - travelled[0])) / 6.0
    if sixth <= half_step:  # no distance to tell a walk from noise by
        return spread, 0.0
    q = max((spread - consecutive) / (sixth - half_step), 0.0)
    sigma2 = max(consecutive - q * half_step, 0.0)
    return sigma2, q


def _nearby_pairs(travelled: np.ndarray, places: np.ndarray) -> tuple[np.ndarray, ...] | None:
    """The pairs of frames within :data:`PLACE_RADIUS` of each other: (first, second, place distance, distance
    travelled between them), or None when the run has not come back to a place often enough to tell the
    map's own error from drift (see the module docs). ``places``: (n, 2, 3) camera centres and looked-at points (m)."""
    first, second = np.triu_indices(len(travelled), 1)
    distance = 0.5 * np.linalg.norm(places[first] - places[second], axis=2).sum(axis=1)
    apart = np.abs(travelled[first] - travelled[second])
    near = distance < PLACE_RADIUS
    if np.count_nonzero(near & (apart >= REVISIT_DISTANCE)) < MIN_REVISITS:
        return None
    return first[near], second[near], distance[near], apart[near]


def _revisit_fit(values: np.ndarray, pairs: tuple[np.ndarray, ...]) -> tuple[float, float]:
    """(sigma^2, q) from the pairs of frames at nearby places (:func:`_nearby_pairs`), with the map's own error
    as a third term that grows with their place distance (see the module docs)."""
    first, second, distance, apart = pairs
    half_squares = 0.5 * np.mean((values[first] - values[second]) ** 2, axis=1)
    design = np.stack([np.ones_like(apart), 0.5 * apart, distance], axis=1)
    (sigma2, q, _), _ = nnls(design, half_squares)
    return float(sigma2), float(q)


def _offsets_fit(values: np.ndarray, travelled: np.ndarray, pairs: tuple[np.ndarray, ...] | None) -> tuple[float, float]:
    """(sigma^2, q) of the given poses' error: from returns to a place where the run has them
    (:func:`_revisit_fit`), else from the distance travelled alone (:func:`_variogram_fit`)."""
    if pairs is not None and len(values) >= MIN_FRAMES_FOR_DRIFT:
        return _revisit_fit(values, pairs)
    return _variogram_fit(values, travelled)


def _offsets_covariance(sigma2: float, q: float, travelled: np.ndarray, own: np.ndarray | None = None) -> np.ndarray:
    """The covariance across frames of one component of the offsets: sigma^2 I + q min(s_i, s_j), plus
    ``own`` (each frame's registration variance) on the diagonal where given."""
    n = len(travelled)
    scale = max(sigma2 + q * float(travelled.max(initial=0.0)), 1e-300)
    white = max(sigma2 + REGULARISER * scale, VARIANCE_FLOOR)
    covariance = q * np.minimum(travelled[:, None], travelled[None, :]) + white * np.eye(n)
    if own is not None:
        covariance[np.diag_indices(n)] += own
    return covariance


def _skews(vectors: np.ndarray) -> np.ndarray:
    """(n, 3, 3) matrices [v]x of (n, 3) vectors."""
    x, y, z = vectors.T
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], 1), np.stack([z, zero, -x], 1), np.stack([-y, x, zero], 1)], 1)


def _anchor_fit(
    rotations: np.ndarray,
    translations: np.ndarray,
    positions: np.ndarray,
    rotation_covariance: np.ndarray,
    translation_covariance: np.ndarray,
    prior: tuple[float, float] | None,
    start: np.ndarray,
) -> np.ndarray:
    """A (4x4, map from world) from the offsets by generalised least squares, rotation and translation together.

    ``rotations``, ``translations``: the offsets dR (rotation vectors) and dt, (n, 3); ``positions``: the given
    camera centres t_G (n, 3); the two covariances across frames (n, n) hold for each component; ``start``:
    a rotation (3x3) near A's, about which the model is linearised (R_A = exp(delta) R0):
    dR_i = rotvec(R0) + delta and dt_i - (R0 - I) t_Gi = delta x (R0 t_Gi) + t_A. The cameras' places
    say as much of A's rotation as their orientations do (a map turned by 0.02 degrees moves cameras 3 m
    from the origin by a millimetre). ``prior``: the variances (rad^2, m^2 per component) of A about the
    identity (the first given pose's, which placed the map), None for none; a part whose variance is 0 is
    the identity's (``start`` must then be the identity if it is the rotation).
    """
    base = Rotation.from_matrix(start).as_rotvec()
    ones = np.ones(len(rotations))
    rotation_information = np.linalg.solve(rotation_covariance, ones)
    translation_information = np.linalg.inv(translation_covariance)
    hessian = np.zeros((6, 6))
    gradient = np.zeros(6)
    hessian[:3, :3] += float(ones @ rotation_information) * np.eye(3)
    gradient[:3] += (rotations - base).T @ rotation_information
    design = -_skews(positions @ start.T)  # (n, 3 components, 3 of delta): dt's part that delta explains
    residual = translations - positions @ (start - np.eye(3)).T
    column = translation_information @ ones
    for k in range(3):
        rows = design[:, k, :]
        hessian[:3, :3] += rows.T @ translation_information @ rows
        hessian[:3, 3 + k] += rows.T @ column
        hessian[3 + k, :3] += rows.T @ column
        hessian[3 + k, 3 + k] += float(ones @ column)
        gradient[:3] += rows.T @ translation_information @ residual[:, k]
        gradient[3 + k] += float(column @ residual[:, k])
    free = np.ones(6, dtype=bool)
    if prior is not None:
        for part, variance in enumerate(prior):
            block = slice(3 * part, 3 * part + 3)
            if variance <= 0:
                free[block] = False  # held at the identity: delta = 0 (start = I) or t_A = 0
                continue
            hessian[block, block] += np.eye(3) / variance
            gradient[block] -= (base if part == 0 else 0.0) / variance
    delta = np.zeros(6)
    delta[free] = np.linalg.solve(hessian[np.ix_(free, free)], gradient[free])
    anchor = np.eye(4)
    anchor[:3, :3] = Rotation.from_rotvec(delta[:3]).as_matrix() @ start
    anchor[:3, 3] = delta[3:]
    return anchor


class MapAnchor:
    """The map frame's place in the world, estimated from (given, registered) pose pairs (see the module docs).

    ``stated``: the given poses' error when the pose source states it
    (:meth:`mabdi.filters.registration.RegistrationParameters.given_variance`): ((sigma^2, q) of the rotation,
    (sigma^2, q) of the translation), rad^2 and m^2 per component, q per metre travelled. The fit is not
    learnt then (each frame's registration variance adds to the stated one), and A is drawn towards the
    identity as far as the first given pose (where the map started) is known to be good (a prior of that
    variance about it): with exact poses stated, A is the identity whatever the registrations say.
    """

    def __init__(self, stated: tuple[tuple[float, float], tuple[float, float]] | None = None) -> None:
        self.stated = stated
        self.reset()

    def reset(self) -> None:
        self._rotations = np.zeros((0, 3))  # dR as rotation vectors (rad)
        self._translations = np.zeros((0, 3))  # dt (m)
        self._positions = np.zeros((0, 3))  # t_G (m)
        self._looks = np.zeros((0, 3))  # the points the given poses look at (m)
        self._travelled = np.zeros(0)  # s (m)
        self._registration_variances = np.zeros((0, 2))  # the registration's variance per frame (rad^2, m^2)
        self._map_errors = np.zeros((0, 2))  # the map's own placement variance per frame (rad^2, m^2)
        self._spreads = (0.0, 0.0)  # the offsets' mean squared spread about their mean (rad^2, m^2 per component)
        self._fits = ((1.0, 0.0), (1.0, 0.0))  # (sigma^2, q) of the rotations and the translations
        self._returned = False  # whether the fits come from returns to a place (_revisit_fit)
        self._map_from_world = np.eye(4)

    def __len__(self) -> int:
        return len(self._travelled)

    @property
    def map_from_world(self) -> np.ndarray:
        """A: world coordinates to map coordinates (4x4)."""
        return self._map_from_world.copy()

    @property
    def world_from_map(self) -> np.ndarray:
        """A's inverse: map coordinates to world coordinates (4x4)."""
        return np.linalg.inv(self._map_from_world)

    def add(
        self,
        given: np.ndarray,
        registered: np.ndarray,
        travelled: float,
        covariance: np.ndarray | None = None,
        depth: float = 0.0,
        map_error: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """One frame that fits the map: its given pose (world), its registered pose (map frame), the
        distance (m) the given poses travelled from the first frame to it, the registration's 6x6
        pose covariance (rotation vector in rad, then translation in m; None: exact), the median depth (m)
        the frame sees along its optical axis (its place is where it is and what it looks at) and the
        map's own placement variance there (rad^2, m^2 per component; see the module docs). Updates the
        estimate."""
        variances = np.zeros(2) if covariance is None else np.array([np.trace(covariance[:3, :3]), np.trace(covariance[3:, 3:])]) / 3.0
        self._registration_variances = np.vstack([self._registration_variances, variances])
        self._map_errors = np.vstack([self._map_errors, np.asarray(map_error, dtype=np.float64).reshape(1, 2)])
        rotation = Rotation.from_matrix(registered[:3, :3] @ given[:3, :3].T).as_rotvec()
        self._rotations = np.vstack([self._rotations, rotation])
        self._translations = np.vstack([self._translations, registered[:3, 3] - given[:3, 3]])
        self._positions = np.vstack([self._positions, given[:3, 3]])
        self._looks = np.vstack([self._looks, given[:3, 3] + float(depth) * given[:3, 2]])
        self._travelled = np.append(self._travelled, float(travelled))
        self._estimate()

    def _estimate(self) -> None:
        n = len(self._travelled)
        use = np.unique(np.round(np.linspace(0, n - 1, min(n, MAX_FRAMES))).astype(int))
        s = self._travelled[use]
        rotations = self._rotations[use]
        own = self._registration_variances[use]
        pairs = None if self.stated is not None else _nearby_pairs(s, np.stack([self._positions[use], self._looks[use]], axis=1))
        fit_rotation = _offsets_fit(rotations, s, pairs) if self.stated is None else self.stated[0]
        # a first rotation from the orientations alone, to fit the translations' noise and linearise about
        weights = np.linalg.solve(_offsets_covariance(*fit_rotation, s), np.ones(len(s)))
        start = Rotation.from_rotvec(weights @ rotations / weights.sum()).as_matrix()
        residual = self._translations[use] - (self._positions[use] @ (start - np.eye(3)).T)
        fit_translation = _offsets_fit(residual, s, pairs) if self.stated is None else self.stated[1]
        self._fits = (fit_rotation, fit_translation)
        self._returned = pairs is not None and len(s) >= MIN_FRAMES_FOR_DRIFT
        self._spreads = tuple(float(np.mean((v - v.mean(axis=0)) ** 2)) for v in (rotations, residual))
        if self.stated is None and len(s) < MIN_FRAMES_FOR_DRIFT:
            # too few frames to say how the orientations' noise compares with the places': orientations alone
            self._map_from_world = np.eye(4)
            self._map_from_world[:3, :3] = start
            self._map_from_world[:3, 3] = residual.mean(axis=0)
            return
        if self.stated is not None and self.stated[0][0] <= 0:
            start = np.eye(3)  # the first given pose's orientation, which placed the map, is exact
        # learnt: the offsets' fitted spread holds the registration's own error; stated: it comes on top
        extra = (own[:, 0], own[:, 1]) if self.stated is not None else (None, None)
        prior = None if self.stated is None else (self.stated[0][0], self.stated[1][0])
        self._map_from_world = _anchor_fit(
            rotations, self._translations[use], self._positions[use],
            _offsets_covariance(*fit_rotation, s, extra[0]), _offsets_covariance(*fit_translation, s, extra[1]), prior, start,
        )  # fmt: skip

    def given_variance(self, travelled: float) -> tuple[float, float] | None:
        """The variance (rad^2, m^2 per component) of a given pose's error in the map frame at ``travelled``
        metres: as stated, or learnt as the offsets' spread less what the registration's noise and the
        map's own placement error explain (see the module docs); None while fewer than
        :data:`MIN_FRAMES_FOR_DRIFT` frames say how the given poses behave."""
        if self.stated is not None:
            return tuple(sigma2 + q * max(float(travelled), 0.0) for sigma2, q in self.stated)
        if len(self._travelled) < MIN_FRAMES_FOR_DRIFT:
            return None
        own = self._registration_variances.mean(axis=0)
        placement = self._map_errors.mean(axis=0)
        if self._returned:  # returns to places tell drift from the map's error bound to a place
            return tuple(
                max(sigma2 - o - m, 0.0) + q * max(float(travelled), 0.0)
                for (sigma2, q), o, m in zip(self._fits, own, placement, strict=True)
            )
        return tuple(max(spread - o - m, 0.0) for spread, o, m in zip(self._spreads, own, placement, strict=True))

    def state(self) -> dict:
        """Plain arrays (for checkpoints)."""
        return {
            "registration_variances": self._registration_variances.copy(),
            "map_errors": self._map_errors.copy(),
            "rotations": self._rotations.copy(),
            "translations": self._translations.copy(),
            "positions": self._positions.copy(),
            "looks": self._looks.copy(),
            "travelled": self._travelled.copy(),
        }

    def set_state(self, state: dict) -> None:
        self._rotations = np.array(state["rotations"], dtype=np.float64).reshape(-1, 3)
        self._translations = np.array(state["translations"], dtype=np.float64).reshape(-1, 3)
        self._positions = np.array(state["positions"], dtype=np.float64).reshape(-1, 3)
        self._travelled = np.array(state["travelled"], dtype=np.float64).ravel()
        self._looks = np.array(state.get("looks", self._positions), dtype=np.float64).reshape(-1, 3)
        variances = state.get("registration_variances", np.zeros((len(self._travelled), 2)))
        self._registration_variances = np.array(variances, dtype=np.float64).reshape(-1, 2)
        map_errors = state.get("map_errors", np.zeros((len(self._travelled), 2)))
        self._map_errors = np.array(map_errors, dtype=np.float64).reshape(-1, 2)
        self._map_from_world = np.eye(4)
        self._spreads = (0.0, 0.0)
        self._fits = ((1.0, 0.0), (1.0, 0.0))
        self._returned = False
        if len(self._travelled):
            self._estimate()
