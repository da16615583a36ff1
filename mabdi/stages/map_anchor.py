"""MapAnchor: where the map's frame lies in the world, from the given poses and the registered ones.

The map is built in a frame of its own, started at the first frame's given
pose; registration (:mod:`mabdi.stages.registration`) makes every frame
agree with it. The anchor ties that frame to the given poses as a whole.

Each frame that fits the map gives the offset between its registered pose
C (map frame) and its given pose G (world): dR = R_C R_G^T (a rotation
vector, radians) and dt = t_C - t_G (metres). The anchor A (map frame =
world moved by A) is their best linear unbiased estimate under a model of
the given poses' errors, learnt from the offsets: jitter (white, sigma^2)
plus drift (a random walk, q per metre travelled), fitted as a variogram
(:func:`_variogram_fit`; on a run that returns to places, :func:`_revisit_fit`
also separates the map's own error bound to a place). Pure jitter gives the
mean of all frames, pure drift the first frame.

``world_from_map`` is A's inverse: the loop builds the map in the map frame
and hands the map and the trajectory out in the world with it.
:meth:`MapAnchor.given_variance` says how good the given poses are (a
source's stated accuracy, else learnt from the offsets' spread less the
registration's noise and the map's placement error).

The reasoning behind the model: docs/architecture.md (``mabdi.stages.map_anchor``).
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
    (:meth:`mabdi.stages.registration.RegistrationParameters.given_variance`): ((sigma^2, q) of the rotation,
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
