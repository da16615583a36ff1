"""Object removal by free-space contradiction (seed 001 §3 and §6): which map faces are gone.

Where the sensor measures *farther* than the map predicts (D > E + tau,
the classifier's "contradicted"), it sees through a surface of the map;
where D and E agree ("known"), the face is confirmed. E carries the face
each pixel shows (:class:`~mabdi.stages.expected_image.FilterExpectedImage`),
so every such pixel is a vote on one face. Only frames whose pose fits the
map vote (registered frames, :mod:`mabdi.stages.registration`). A LiDAR's
scan that keeps its pixels' own returns votes along those returns' own rays:
D and E there are the return and the map along the direction it was
measured (:meth:`~mabdi.stages.expected_image.FilterExpectedImage.along_returns`),
not a pixel centre's range carried from the returns around it, which errs at
slant and at edges (the loop passes that E and its classification here).

Which pixels vote (:func:`removal_votes`): not at depth discontinuities
(``edge_jump``, ``edge_margin`` pixels, widened by a surface's
``face_overhang``), not at grazing incidence (``grazing_deg``), not where a
misplaced edge explains D (:func:`misplaced_edge_explains`),
and a contradiction only when D lies beyond E by more than ``k_sigma``
times the noise of D - E and ``min_gap`` (:func:`contradiction_gap`).
Pixels with no return see through to the far limit (``no_return_is_free``)
unless the noise model loses returns.

The rule (:func:`mabdi.world_map.update_log_odds`): each face keeps the log-odds L that it
is gone, from 0; a frame with a majority of contradictions adds ``hit``,
otherwise confirmations subtract ``miss``; L stays in [``floor``,
``ceiling``]; a face goes when L >= ``threshold`` and at least
``min_frames`` frames contradicted it since a frame last confirmed it: 2
for the simulator's sensors, 4 for a real one ("auto"; a sensor that loses
returns), whose contradictions that are not departures (a mixed pixel, an
edge a beam off, multipath) come back for a frame or two while it passes.
Faces smaller than a pixel are voted on between pixels (:func:`votes_between_pixels`). A face removed takes
along its never-voted neighbours and the contradicted faces edge-connected to it that half the frames a face
needs (``follow_frames``: 1 for the simulator's sensors, 2 for a real one) contradicted since a frame last
confirmed them (:meth:`~mabdi.world_map.WorldMap.remove_faces`), so a real static surface's one-frame
contradictions do not chain a false removal across it; a face beside one removed earlier goes at its next
contradicting frame (:meth:`~mabdi.world_map.WorldMap.update_evidence`).

Units: metres (depths, gaps), degrees (angles), pixels (margins).
Why each rule is what it is: docs/architecture.md (``mabdi.stages.removal``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from mabdi.errors import ConfigError
from mabdi.face_identity import unique_codes
from mabdi.stages.image_kernels import depth_edges_kernel
from mabdi.stages.classifier import CONTRADICTED, KNOWN, NO_RETURN, dilate
from mabdi.stages.removal_kernels import window_extremes_at


#: ``min_frames = "auto"``: frames that must contradict a face for a real sensor (one that loses returns) and
#: for the simulator's, which return every surface where it lies (docs/benchmarks.md, "Four frames against a
#: face for a real sensor").
REAL_SENSOR_MIN_FRAMES = 4
SIMULATED_MIN_FRAMES = 2


@dataclass(frozen=True)
class RemovalParameters:
    """The evidence rule and the vote filters (see the module docs); angles in degrees. The ``[removal]``
    section of a run config; ``enabled = false`` keeps every face (removal runs only with the classifier on)."""

    enabled: bool = True
    hit: float = 1.1
    miss: float = 0.4
    floor: float = -0.7
    ceiling: float = 3.0
    threshold: float = 1.5
    #: Frames that must have contradicted a face before it goes: "auto" :data:`REAL_SENSOR_MIN_FRAMES` for a
    #: sensor that loses returns (a real one: a recording, a learnt noise model), else 2 (:meth:`min_frames_for`).
    min_frames: int | str = "auto"
    grazing_deg: float = 75.0
    edge_jump: float = 0.05
    edge_margin: int = 5
    max_edge_margin: int = 20
    min_gap: float = 0.05
    k_sigma: float = 3.0
    no_return_is_free: bool = True
    far_margin: float = 0.5
    #: Hold back a contradiction that a depth edge misplaced by a few pixels explains (module docs), within
    #: ``misplaced_reach`` pixels: "auto" twice the edge margin for a camera, one beam for a LiDAR.
    misplaced_edges: bool = True
    misplaced_reach: int | str = "auto"
    #: Columns the misplaced-edge window reaches per row of ``misplaced_reach``: 1 for a camera; a range
    #: image's widest beam spacing over its azimuth step (the same angle across as down), set by
    #: :func:`for_geometry`. Not a config key.
    misplaced_columns: float = field(default=1.0, metadata={"toml": False})
    #: The uncertainty (radians, one sigma) of a return's direction against the map (module docs, "within the
    #: noise"); "auto": a LiDAR's beam spacing over sqrt(12), none for a camera (:func:`for_geometry`).
    ray_sigma: float | str = "auto"

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ConfigError(f"removal: enabled must be true or false, got {self.enabled!r}")
        if not (self.hit > 0 and self.miss >= 0 and self.floor <= 0 < self.threshold <= self.ceiling):
            raise ConfigError("removal: need hit > 0, miss >= 0 and floor <= 0 < threshold <= ceiling")
        if self.far_margin < 0:
            raise ConfigError(f"removal: far_margin must be >= 0 metres, got {self.far_margin}")
        if self.k_sigma < 0:
            raise ConfigError(f"removal: k_sigma must be >= 0, got {self.k_sigma}")
        if self.min_gap < 0:
            raise ConfigError(f"removal: min_gap must be >= 0 metres, got {self.min_gap}")
        if self.misplaced_reach != "auto" and (isinstance(self.misplaced_reach, (bool, str)) or not isinstance(self.misplaced_reach, int) or self.misplaced_reach < 1):
            raise ConfigError(f"removal: misplaced_reach must be \"auto\" or a whole number of pixels >= 1, got {self.misplaced_reach!r}")
        if self.ray_sigma != "auto" and (isinstance(self.ray_sigma, (bool, str)) or not 0 <= self.ray_sigma < 0.5):
            raise ConfigError(f"removal: ray_sigma must be \"auto\" or 0 <= ray_sigma < 0.5 (radians), got {self.ray_sigma!r}")
        if self.min_frames != "auto" and (isinstance(self.min_frames, (bool, str)) or not isinstance(self.min_frames, int) or self.min_frames < 1):
            raise ConfigError(f"removal: min_frames must be \"auto\" or a whole number of frames >= 1, got {self.min_frames!r}")
        if self.edge_margin < 0 or self.max_edge_margin < self.edge_margin or not 0 < self.grazing_deg < 90 or self.edge_jump <= 0:
            raise ConfigError("removal: need 0 <= edge_margin <= max_edge_margin, 0 < grazing_deg < 90, edge_jump > 0")

    @property
    def frames_required(self) -> int:
        """The contradicting frames a face needs before it goes: ``min_frames``, or where "auto" was not resolved
        for a sensor (:func:`mabdi.loop.loop.resolve_settings` does) the simulator's 2."""
        return self.min_frames_for(False)

    @property
    def follow_frames(self) -> int:
        """The contradicting frames (since a frame last confirmed it) a face needs to go with a removed neighbour:
        half of :attr:`frames_required`, at least one (the module docs)."""
        return max(1, self.frames_required // 2)

    def min_frames_for(self, real_sensor: bool) -> int:
        """``min_frames`` as it applies to a sensor: "auto" is :data:`REAL_SENSOR_MIN_FRAMES` for a
        ``real_sensor`` (one that loses returns) and :data:`SIMULATED_MIN_FRAMES` otherwise (module docs)."""
        if self.min_frames != "auto":
            return int(self.min_frames)
        return REAL_SENSOR_MIN_FRAMES if real_sensor else SIMULATED_MIN_FRAMES


def for_geometry(parameters: RemovalParameters, geometry) -> RemovalParameters:
    """The rules as they apply to images of ``geometry``: a camera's as given; for a LiDAR's range images,
    whose beams lie further apart (the geometry's ``jump_scale()`` times a camera's pixel angle), ``edge_jump``
    scaled up by that factor (the same surface at the same incidence jumps that much more between beams) and
    the margins in pixels scaled down by it, to the same angle (at least one beam). A misplaced edge
    (``misplaced_reach`` "auto") reaches one beam down and the same angle across (``misplaced_columns``
    columns a row), with no silhouette of E asked for: a map edge made between beams is off by up to a beam
    spacing in any direction, and a small object's few beams all lie near its silhouette. ``ray_sigma``
    "auto": a LiDAR's widest beam spacing (the geometry's ``pixel_angle()``) over sqrt(12) (a return anywhere
    within its pixel), none for a camera."""
    scale = geometry.jump_scale()
    if parameters.ray_sigma == "auto":
        parameters = replace(parameters, ray_sigma=geometry.pixel_angle() / math.sqrt(12.0) if scale != 1.0 else 0.0)
    if scale == 1.0:
        return parameters
    margin = max(1, math.ceil(parameters.edge_margin / scale)) if parameters.edge_margin else 0
    return replace(
        parameters,
        misplaced_reach=1 if parameters.misplaced_reach == "auto" else parameters.misplaced_reach,
        misplaced_columns=geometry.pixel_angle() * geometry.width / (2.0 * math.pi),
        edge_jump=parameters.edge_jump * scale,
        edge_margin=margin,
        max_edge_margin=max(margin, math.ceil(parameters.max_edge_margin / scale)),
    )


def depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood holds a relative depth jump over ``jump`` (its largest depth over
    1 + ``jump`` times its smallest) or a pixel without a return (the image's own border is not an edge;
    NaN counts as no return). One compiled pass over the float32 image."""
    return depth_edges_kernel(np.ascontiguousarray(depth, dtype=np.float32), np.float32(1.0 + jump))


def removal_votes(
    labels: np.ndarray,
    measured: np.ndarray,
    expected: np.ndarray,
    face_ids: np.ndarray,
    unit_rays: np.ndarray,
    world_from_camera: np.ndarray,
    normals_of,
    parameters: RemovalParameters,
    evidence_of=None,
    sigma=None,
    far: float = np.inf,
    pose_sigma: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One frame's votes: (face ids, contradicting pixels, confirming pixels per face, the voting contradicted pixels' mask).

    ``labels`` (H, W) from the classifier; ``measured`` D and ``expected`` E (H, W) metres; ``face_ids`` (H, W) from E
    (0 = no face); ``unit_rays`` (H, W, 3) unit pixel rays in the camera frame; ``world_from_camera``
    the pose; ``normals_of(ids)`` -> (N, 3) world normals of faces (NaN for unknown ids);
    ``evidence_of(ids)`` -> their log-odds, to skip confirmations of faces already at the floor;
    ``sigma(depth)`` -> the sensor's noise (m) at depths (m), for the contradiction gate; ``far``: the
    sensor's range (m), the depth a pixel with no return stands for (``no_return_is_free``);
    ``pose_sigma`` (H, W): E's depth uncertainty from the registered pose's own uncertainty (m, NaN = 0),
    added to the noise of the difference.
    """
    measured = free_space_filled(measured, parameters, far)
    if parameters.no_return_is_free:
        # a pixel with no return sees through only where E is well inside the range: near the far limit noise alone loses returns
        inside = np.isfinite(expected) & (expected < np.float32(far - parameters.far_margin))
        seen_through = (labels == CONTRADICTED) | ((labels == NO_RETURN) & inside & np.isfinite(measured))
    else:
        seen_through = labels == CONTRADICTED
    contradicting_pixels = seen_through & (face_ids > 0)
    gap = np.full(labels.shape, np.float32(parameters.min_gap))
    if contradicting_pixels.any():
        gap[contradicting_pixels] = contradiction_gap(
            measured[contradicting_pixels],
            expected[contradicting_pixels],
            parameters,
            sigma,
            None if pose_sigma is None else pose_sigma[contradicting_pixels],
        )
        with np.errstate(invalid="ignore"):
            contradicting_pixels &= measured - expected > gap
    candidates = (face_ids > 0) & ((labels == KNOWN) | contradicting_pixels)
    if not candidates.any():
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, np.zeros(labels.shape, dtype=bool)
    # silhouettes of what the sensor sees (with no_return_is_free the edge of a no-return region is one);
    # a contradiction there is only doubtful near a silhouette of the map too: only there can a misplaced
    # map edge overhang what the sensor sees
    edges = depth_edges(measured, parameters.edge_jump)
    map_edges = depth_edges(expected, parameters.edge_jump)
    if parameters.edge_margin:
        margin = parameters.edge_margin
        silhouettes = map_edges
        edges = dilate(edges, margin)
        map_edges = dilate(map_edges, margin)
        if parameters.misplaced_edges and contradicting_pixels.any():
            # within twice the margin of a silhouette of E (the map's edge and the sensor's may each be off by the
            # margin), a misplaced edge explains a contradiction where E shows D's depth (or beyond) nearby and D
            # shows E's (or nearer): the surface the map shows is still there, a few pixels off
            reach = 2 * margin if parameters.misplaced_reach == "auto" else parameters.misplaced_reach
            explained = misplaced_edge_explains(
                contradicting_pixels, measured, expected, silhouettes, gap, reach, parameters.misplaced_reach == "auto",
                math.ceil(reach * parameters.misplaced_columns - 1e-9),
            )
            contradicting_pixels &= ~explained
            candidates &= ~explained
    candidates &= ~np.where(contradicting_pixels, edges & map_edges, edges)
    pixels = np.flatnonzero(candidates)
    ids = face_ids.ravel()[pixels].astype(np.int64)
    contradicting = contradicting_pixels.ravel()[pixels]
    faces, inverse = unique_codes(ids)
    if evidence_of is not None:
        # A confirmation cannot lower a face already at the floor: such pixels need no further work.
        useful = contradicting | (evidence_of(faces) > np.float32(parameters.floor))[inverse]
        pixels, inverse, contradicting = pixels[useful], inverse[useful], contradicting[useful]
    # normals into the camera frame (rows: n_world @ R = (R^T n_world)^T), one per face, then per pixel
    normals = (normals_of(faces) @ np.asarray(world_from_camera)[:3, :3]).astype(np.float32)[inverse]
    rays = unit_rays.reshape(-1, 3)[pixels]
    cosine = np.abs(normals[:, 0] * rays[:, 0] + normals[:, 1] * rays[:, 1] + normals[:, 2] * rays[:, 2])
    facing = cosine >= np.float32(np.cos(np.radians(parameters.grazing_deg)))  # NaN normals fail too
    # a confirmation counts up to grazing_deg; a contradiction where D is beyond E by the gap, stretched along the
    # ray beyond grazing_deg, and by k_sigma times the noise with the map's share across the face's plane
    facing &= ~contradicting
    if contradicting.any():
        at = pixels[contradicting]
        d, e, cos_at = measured.ravel()[at], expected.ravel()[at], cosine[contradicting]
        needed = gap_along_ray(gap.ravel()[at], cos_at, parameters)
        if sigma is not None:
            across = contradiction_gap(d, e, parameters, sigma, None if pose_sigma is None else pose_sigma.ravel()[at], cos_at)
            needed = np.maximum(needed, across)
        facing[contradicting] = d - e > needed
    pixels, inverse, contradicting = pixels[facing], inverse[facing], contradicting[facing]
    seen = np.bincount(inverse, minlength=len(faces))
    contradicted = np.bincount(inverse[contradicting], minlength=len(faces)).astype(np.int64)
    confirmed = seen.astype(np.int64) - contradicted
    voted = seen > 0
    faces, contradicted, confirmed = faces[voted], contradicted[voted], confirmed[voted]
    voting = np.zeros(labels.size, dtype=bool)
    voting[pixels[contradicting]] = True
    return faces, contradicted, confirmed, voting.reshape(labels.shape)


def free_space_filled(measured, parameters: RemovalParameters, far: float) -> np.ndarray:
    """D (float32) as removal reads it: with ``no_return_is_free`` a pixel with no return in a region of them
    (none in its 3x3 neighbourhood) met nothing up to the sensor's range ``far`` (m), so it reads ``far``; a
    lone hole between returns stays without one (a deskewed sweep's return that slid into the next pixel
    leaves one where a surface is). Without it, D as it is."""
    if not parameters.no_return_is_free:
        return measured
    region = np.isnan(measured) & ~dilate(np.isfinite(measured), 1)
    return np.where(region, np.float32(far), measured).astype(np.float32)


def misplaced_edge_explains(
    contradicting: np.ndarray, measured: np.ndarray, expected: np.ndarray, silhouettes: np.ndarray, gap: np.ndarray,
    reach: int, near_silhouette: bool, reach_columns: int | None = None,
) -> np.ndarray:
    """(H, W) bool: the ``contradicting`` pixels a misplaced edge explains: E shows D's depth (or beyond) within
    ``reach`` rows and ``reach_columns`` columns (None: ``reach``) and D shows E's (or nearer) within them (E's
    farthest and D's nearest depth in that window, edge-padded, differ by less than the ``gap``), and with
    ``near_silhouette`` a silhouette of E (``silhouettes``) lies within ``reach`` too. Windows are read at the contradicting pixels only (a known world has few: the cost follows
    what is new), with the same values as the full-image filters."""
    rows, cols = np.nonzero(contradicting)
    explained = np.zeros(contradicting.shape, dtype=bool)
    if not len(rows):
        return explained
    farthest, nearest, near = window_extremes_at(
        np.ascontiguousarray(expected, dtype=np.float32), np.ascontiguousarray(measured, dtype=np.float32),
        np.ascontiguousarray(silhouettes, dtype=bool), rows.astype(np.int64), cols.astype(np.int64), int(reach),
        int(reach) if near_silhouette else 0, int(reach if reach_columns is None else reach_columns),
    )  # fmt: skip
    d, e, g = measured[rows, cols], expected[rows, cols], gap[rows, cols]
    with np.errstate(invalid="ignore"):
        fits = ~(d - farthest > g) & ~(nearest - e > g)
    if near_silhouette:
        fits &= near
    explained[rows[fits], cols[fits]] = True
    return explained


def contradiction_gap(measured, expected, parameters: RemovalParameters, sigma=None, pose_sigma=None, cosine=None) -> np.ndarray:
    """(N,) float32 how far (m) D must lie beyond E for a contradiction (module docs, "within the noise"):
    ``k_sigma`` times the noise of the difference, sqrt(sigma(D)^2 + sigma(E)^2 + pose_sigma^2), and at least
    ``min_gap``. ``sigma(depth)`` -> the sensor's noise (None: ``min_gap`` alone); ``pose_sigma`` (N,) or None;
    ``cosine`` (N,) |cos(incidence)| on the face E shows, or None: the map's share sigma(E) lies across the
    face's plane, so along the ray it is sigma(E) / cosine (infinite edge-on), and a return's direction, off
    by ``ray_sigma`` (a number: :func:`for_geometry` resolves "auto"), moves where its ray meets the face by
    E ray_sigma tan(incidence) along it."""
    measured = np.asarray(measured, dtype=np.float32)
    gap = np.full(measured.shape, np.float32(parameters.min_gap))
    if sigma is None:
        return gap
    expected = np.asarray(expected, dtype=np.float32)
    map_sigma = sigma(expected)
    variance = sigma(measured) ** 2
    if cosine is not None:
        cosine = np.asarray(cosine, dtype=np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            map_sigma = np.where(cosine > 0, map_sigma / cosine, np.float32(np.inf))
            if parameters.ray_sigma not in ("auto", 0):
                tangent = np.where(cosine > 0, np.sqrt(np.maximum(1 - cosine * cosine, 0)) / cosine, np.float32(np.inf))
                variance = variance + (expected * np.float32(parameters.ray_sigma) * tangent) ** 2
    variance = variance + map_sigma**2
    if pose_sigma is not None:
        variance = variance + np.nan_to_num(pose_sigma, nan=0.0) ** 2
    return np.maximum(gap, np.float32(parameters.k_sigma) * np.sqrt(variance).astype(np.float32))


def gap_along_ray(gap, cosine, parameters: RemovalParameters) -> np.ndarray:
    """``gap`` (m) as it stands along a ray at ``cosine`` = |cos(incidence)| on a face: as it is up to
    ``grazing_deg``, beyond it stretched by cos(grazing_deg) / cosine (a face's error across its plane is
    1 / cosine times longer along the ray; continuous at ``grazing_deg``); infinite edge-on (or NaN normals)."""
    cos_grazing = np.float32(np.cos(np.radians(parameters.grazing_deg)))
    cosine = np.asarray(cosine, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        stretch = np.where(cosine > 0, np.maximum(np.float32(1.0), cos_grazing / cosine), np.float32(np.inf))
    return np.asarray(gap, dtype=np.float32) * stretch


def votes_between_pixels(
    centres: np.ndarray,
    normals: np.ndarray,
    radii: np.ndarray,
    measured: np.ndarray,
    voting: np.ndarray,
    unit_rays: np.ndarray,
    ray_length: np.ndarray,
    pixels_uv: np.ndarray,
    origin: np.ndarray,
    rotation: np.ndarray,
    pixel_angle: float,
    parameters: RemovalParameters,
    sigma=None,
    pose_sigma: np.ndarray | None = None,
) -> np.ndarray:
    """(M,) bool: which of M faces that no pixel centre showed this frame a voting contradiction sees through.

    A face smaller than the pixels' spacing where it is seen (a surface once seen closely, now from afar or
    at grazing incidence) gets no pixel of E, so no vote, and stays when the object it belonged to has gone.
    Such a face is contradicted where its centre projects into a pixel that voted a contradiction this frame
    (``voting``, from :func:`removal_votes`: that ray saw through the face E showed, past every gate), the
    ray crosses the face's plane near the face (within its radius and the pixel's footprint on the plane,
    ``pixel_angle`` times the distance over cos(incidence)) and D lies beyond the crossing by the gap of
    :func:`contradiction_gap`, stretched along the ray as :func:`gap_along_ray` says. The crossing, not
    the centre's own depth, is what D is compared with, so a face of the surface D hits (a road beside a
    departed car, seen at grazing incidence) is not seen through.

    ``centres``, ``normals`` (M, 3) world frame, ``radii`` (M,) m; ``measured`` D (H, W) (a pixel with no return
    standing for the far limit); ``unit_rays`` (H, W, 3) sensor frame and ``ray_length`` (H, W) the distance
    along it per unit of D; ``pixels_uv`` (M, 2) the centres' continuous pixel coordinates (NaN: not in
    the image); ``origin``, ``rotation``: the sensor's position and world_from_sensor rotation.
    """
    height, width = measured.shape
    hit = np.zeros(len(centres), dtype=bool)
    with np.errstate(invalid="ignore"):
        u, v = np.floor(pixels_uv[:, 0]), np.floor(pixels_uv[:, 1])
        inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    faces = np.flatnonzero(inside)
    u, v = u[faces].astype(np.int64), v[faces].astype(np.int64)
    on = voting[v, u]
    faces, u, v = faces[on], u[on], v[on]
    if not len(faces):
        return hit
    rays = unit_rays[v, u].astype(np.float64) @ np.asarray(rotation, dtype=np.float64).T
    normal = normals[faces].astype(np.float64)
    along = np.einsum("ij,ij->i", normal, rays)
    cosine = np.abs(along)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("ij,ij->i", normal, centres[faces] - origin) / along  # distance along the ray to the plane
        off = np.linalg.norm(origin + t[:, None] * rays - centres[faces], axis=1)
        near_face = (t > 0) & (off <= radii[faces] + pixel_angle * t / np.maximum(cosine, 1e-6))
    length = ray_length[v, u]
    d = measured[v, u].astype(np.float64)
    crossing = (t / length).astype(np.float32)  # the crossing in D's own units (z-depth or range)
    crossing_sigma = None if pose_sigma is None else pose_sigma[v, u]
    needed = gap_along_ray(contradiction_gap(d, crossing, parameters, sigma, crossing_sigma), cosine, parameters)
    if sigma is not None and parameters.ray_sigma not in ("auto", 0):  # a LiDAR's: the return's direction too
        needed = np.maximum(needed, contradiction_gap(d, crossing, parameters, sigma, crossing_sigma, cosine))
    with np.errstate(invalid="ignore"):
        beyond = (d * length - t) > needed * length
    hit[faces] = near_face & beyond
    return hit
