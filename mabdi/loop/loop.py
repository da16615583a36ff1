"""MabdiLoop: the MABDI loop of seed 001 Fig. 3-4, fed by any source of depth frames.

Frame i, each stage called with the frame's values (:mod:`mabdi.frame_values`)::

    SourceDepthFrames.measured(i) -> D --> FilterRegistration.place(D, map) -> D at its map pose, Placement
    FilterExpectedImage.render(map, D) -> E --> FilterClassifier.classify(D, E) -> labels, novel depth
    surface.mesh_frame(novel depth, D) -> triangles, less those wholly on the rim or on the map (E's faces)
        --> FilterWorldMesh.append
    then MapRefinement.step and ObjectRemoval.find: what they find, the loop applies to the map

A LiDAR's scan that keeps each pixel's own return votes for removal along
those returns' own rays (:meth:`FilterExpectedImage.along_returns`, cast from
the same drawing as E and classified as D is); the classifier's novelty reads
E along the pixels' centre rays, as the surfaces' tests do.

E is the map as it stood after frame i - 1; refinement and removal change
the map after this frame's E was used. The loop alone changes the map. With
``noise = "auto"`` D - E feeds the noise calibration. With the classifier
off (the "black box") the surface meshes every valid pixel of D. A LiDAR's
range images run through the same loop, registered by
:class:`~mabdi.stages.scan_registration.ScanRegistration` (which hands the loop
the E it drew where the scan keeps its start pose); refinement is
camera-only for now (:func:`lidar_rules`).

``loop.step(i)`` runs frame i and returns its :class:`FrameRecord`;
:attr:`MabdiLoop.last_frame` holds its values, :meth:`measured_image`,
:meth:`expected_image`, :meth:`classified_image` show them as depth images.
The frame path as a whole: docs/architecture.md.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData

from mabdi.camera import Intrinsics
from mabdi.loop.blas_threads import one_blas_thread
from mabdi.interrupts import interrupts_unwrapped
from mabdi.stages.classifier import ClassifierParameters, FilterClassifier, dilate, write_classified
from mabdi.render.depth_image import BACKENDS
from mabdi.sensor_noise import SensorNoise
from mabdi.stages.expected_image import FilterExpectedImage, write_expected
from mabdi.stages.fit_check import moved
from mabdi.stages.front_confirmation import FrontConfirmation
from mabdi.stages.refinement import MapRefinement, RefinementParameters, RefinementResult
from mabdi.surfaces.quadtree import QuadTreeParameters, resolved as resolved_quadtree
from mabdi.stages.registration import STATUSES, FilterRegistration, RegistrationParameters, write_placement
from mabdi.stages.scan_registration import ScanRegistration
from mabdi.stages.registration_check import (
    CAUSES, LIDAR_CAUSES, PosesDisagreeWarning, PoseJumpWarning, jumps_that_removed, pose_excursion, poses_disagree,
)
from mabdi.surfaces.registry import make_surface_filter, mesh_frame, seam_pixels, surface_filter
from mabdi.surfaces.seam_trim import trimmed_patch, without_faces_on_map
from mabdi.stages.object_removal import ObjectRemoval, RemovalResult, RemovalVotes
from mabdi.stages.removal import RemovalParameters, depth_edges
from mabdi.frame_values import Classified, Expected, Measured, Placement
from mabdi.stages.world_mesh import FilterWorldMesh
from mabdi.world_map import CHUNK_SIZE, LIDAR_CHUNK_SIZE, LIDAR_POOL_SIZE, POOL_SIZE
from mabdi.polydata import polydata_area, polydata_arrays, transformed_polydata
from mabdi.sources.frames import FrameSource, SourceDepthFrames


@dataclass(slots=True)  # one per frame, kept for the whole run: small
class FrameRecord:
    """What one frame did. Counts of cells are triangles; ``cells_added`` is the map's net change. Times in ms."""

    frame: int
    novel_fraction: float
    cells_added: int
    cells_total: int
    t_depth_ms: float
    t_expected_ms: float
    t_classify_ms: float
    t_surface_ms: float
    t_append_ms: float
    t_total_ms: float
    points_total: int = 0
    valid_pixels: int = 0
    novel_pixels: int = 0
    speck_pixels: int = 0
    contradicted_pixels: int = 0
    #: Faces removed this frame (object removal, :mod:`mabdi.stages.removal`), and the stage's time.
    cells_removed: int = 0
    area_removed: float = 0.0  # m^2
    t_remove_ms: float = 0.0
    #: Vertices moved by refinement this frame (:mod:`mabdi.stages.refinement`), and the stage's time.
    vertices_refined: int = 0
    t_refine_ms: float = 0.0
    #: Registration to the map (:mod:`mabdi.stages.registration`): its status ("off" when not run), the
    #: correction of the given pose (mm, degrees), the RMS residual of its pairs (mm), the inlier share, and
    #: the least share of a constrained direction's constraint that its pairs carry.
    registration: str = "off"
    correction_mm: float = 0.0
    correction_deg: float = 0.0
    residual_mm: float = float("nan")
    inlier_share: float = float("nan")
    constraint_support: float = float("nan")
    t_register_ms: float = 0.0
    #: One-pixel holes of D filled before the frame was used (:mod:`mabdi.depth_holes`).
    filled_pixels: int = 0
    #: 1 where the frame registered but its depth fits the map several times worse than the run's frames do
    #: (:mod:`mabdi.stages.fit_check`): meshed, no removal votes; else 0.
    poor_fit: int = 0

    @property
    def registered(self) -> bool:
        """Whether the frame's pose was registered to the map (only such frames vote for removal)."""
        return self.registration == "registered"


def lidar_rules(geometry, refining: bool, registration: RegistrationParameters) -> tuple[bool, RegistrationParameters]:
    """(refining, registration) for a sensor of ``geometry``: unchanged for a camera; for a LiDAR's range
    images (:class:`~mabdi.spherical.SphericalGeometry`) refinement off (its kernels are the pinhole camera's);
    their registration is :class:`~mabdi.stages.scan_registration.ScanRegistration`."""
    if geometry.range_image:
        return False, registration
    return refining, registration


def apply_removal(
    world: FilterWorldMesh,
    surface,
    capabilities,
    stage: ObjectRemoval,
    votes: RemovalVotes | None,
    replaced: np.ndarray,
    expected: Expected,
    measured: Measured,
) -> RemovalResult:
    """Change the map as one frame's removal found: its ``votes`` (:meth:`ObjectRemoval.find`; None: no vote)
    added to the faces' evidence, then the faces the evidence condemns and those refinement ``replaced`` (codes
    of E) removed; a surface that keeps statistics (voxel planes) forgets the removed faces' and empties the
    voxels the voting rays saw through. The loop's one place where removal changes the map."""
    gone = np.asarray(replaced, dtype=np.int64)
    table = expected.table if votes is None else votes.table
    if votes is not None and len(votes.faces):
        condemned = world.update_evidence(votes.faces, votes.contradicted, votes.confirmed, stage.parameters, table)
        gone = np.union1d(gone, condemned)
    if not len(gone):
        return RemovalResult()
    result = RemovalResult(world.remove_faces(gone, table, stage.parameters.follow_frames))
    if capabilities.clears_space and result.cells_removed:
        # voxel planes: the statistics that made the removed faces go with them (else re-meshing brings them back)
        points, triangles = polydata_arrays(result.removed)
        surface.clear_faces_at(points[triangles].mean(axis=1))
    if votes is not None and capabilities.clears_space:
        rays = stage.free_space_rays(votes, gone, measured)
        if rays is not None:
            surface.clear_free_space(*rays)
    return result


#: Columns of the loop's per-frame registration record (see ``MabdiLoop._registrations``).
REGISTRATION_COLUMNS = 6


@dataclass(frozen=True)
class LoopSettings:
    """What a loop runs with, every "auto" resolved for its sensor and noise model (:func:`resolve_settings`)."""

    #: The classifier's thresholds, its ``rim`` (the surface's seam) and ``rim_on_map`` resolved.
    classifier: ClassifierParameters
    #: Removal's rules; ``no_return_is_free`` off where the sensor or the source loses returns.
    removal: RemovalParameters
    refinement: RefinementParameters
    #: Registration's settings (a LiDAR's rules applied: :func:`lidar_rules`).
    registration: RegistrationParameters
    #: Whether object removal runs (classifier and removal on).
    removing: bool
    #: Whether refinement runs (classifier on, refinement on or "auto" with correlated noise, a noisy sensor).
    refining: bool


def resolve_settings(
    geometry,
    noise: SensorNoise,
    loses_returns: bool,
    classifier: ClassifierParameters,
    surface: str,
    surface_parameters,
    removal: RemovalParameters | None,
    refinement: RefinementParameters | None,
    registration: RegistrationParameters | None,
) -> LoopSettings:
    """The one place where a loop's "auto" settings are decided, from the sensor ``geometry``, its ``noise``
    model and whether its source ``loses_returns`` (None parameters: the defaults)."""
    if classifier.rim == "auto":  # the rim the surface needs to close its seams with the map
        chosen = surface_parameters if surface_parameters is not None else surface_filter(surface).parameters()
        if isinstance(chosen, QuadTreeParameters):
            chosen = resolved_quadtree(chosen, geometry)  # its reduction, "auto", by the sensor
        classifier = replace(classifier, rim=seam_pixels(surface, chosen, noise.noisy))
    removal = removal if removal is not None else RemovalParameters()
    removing = classifier.enabled and removal.enabled
    real_sensor = noise.loses_returns or loses_returns  # a camera's noise model says so, a recording's source does
    if removal.no_return_is_free and real_sensor:
        # a sensor that loses returns on real surfaces: a pixel without one is not free space
        removal = replace(removal, no_return_is_free=False)
    if removal.min_frames == "auto":  # a real sensor's false contradictions come back for a few frames
        removal = replace(removal, min_frames=removal.min_frames_for(real_sensor))
    refinement = refinement if refinement is not None else RefinementParameters()
    if refinement.gate_k == "auto":  # a real camera's looks at a surface differ by more than its pixels' noise
        refinement = replace(refinement, gate_k=refinement.gate_k_for(noise))
    refinement_on = refinement.enabled
    if refinement_on == "auto":
        refinement_on = noise.correlated  # errors one look's smoothing cannot remove: average later looks in
    # only with a noisy sensor: a noise-free measurement is exact the first time
    refining = classifier.enabled and refinement_on and noise.noisy
    registration = registration if registration is not None else RegistrationParameters()
    refining, registration = lidar_rules(geometry, refining, registration)
    if classifier.outer_radius == "auto":  # a real camera's new surface waits for a more central look
        classifier = replace(classifier, outer_radius=classifier.outer_radius_for(noise))
    if classifier.front_frames == "auto":  # a real camera's surface in front of the map waits for more looks
        classifier = replace(classifier, front_frames=classifier.front_frames_for(noise))
    if classifier.rim_on_map == "auto":  # the seam on the map's surface where the map is refined
        classifier = replace(classifier, rim_on_map=bool(refining))
    if classifier.front_k == "auto":  # a look in front of the map within refinement's gate refines the map
        front = max(classifier.k_sigma, float(refinement.gate_k)) if refining else classifier.k_sigma
        classifier = replace(classifier, front_k=float(front))
    return LoopSettings(classifier, removal, refinement, registration, removing, refining)


def chunk_size_for(geometry) -> float:
    """The world map's chunk edge (metres) for a sensor of ``geometry``: :data:`~mabdi.world_map.CHUNK_SIZE` for
    a camera, :data:`~mabdi.world_map.LIDAR_CHUNK_SIZE` for a LiDAR's range images, which show tens of metres
    all around at once (2 m chunks would put hundreds of blocks in every view, each drawn, culled and voted
    on apart)."""
    return LIDAR_CHUNK_SIZE if geometry.range_image else CHUNK_SIZE


def pool_size_for(geometry) -> float:
    """The edge (metres) of the cubes in which one frame's faces pool their removal evidence
    (:meth:`mabdi.world_map.WorldMap.update_evidence`): :data:`~mabdi.world_map.POOL_SIZE` for a camera,
    :data:`~mabdi.world_map.LIDAR_POOL_SIZE` for a LiDAR."""
    return LIDAR_POOL_SIZE if geometry.range_image else POOL_SIZE


@dataclass(eq=False)
class FrameValues:
    """One frame's values as the loop passed them from stage to stage (:mod:`mabdi.frame_values`; None: the
    stage did not run), and the depth images the pipeline API shows of them, made when first asked."""

    measured: Measured | None = None
    placement: Placement | None = None
    expected: Expected | None = None
    classified: Classified | None = None
    #: What the surface meshed (map frame), what refinement did and what removal took.
    added: vtkPolyData = field(default_factory=vtkPolyData)
    refined: RefinementResult | None = None
    removed: vtkPolyData = field(default_factory=vtkPolyData)
    _images: dict = field(default_factory=dict)

    def measured_image(self, registered: bool) -> vtkImageData:
        if "measured" not in self._images:
            image = vtkImageData() if self.measured is None else self.measured.to_image()
            if registered and self.placement is not None:
                write_placement(image, self.placement)
            self._images["measured"] = image
        return self._images["measured"]

    def expected_image(self) -> vtkImageData | None:
        if self.expected is not None and "expected" not in self._images:
            self._images["expected"] = vtkImageData()
            write_expected(self._images["expected"], self.expected)
        return self._images.get("expected")

    def classified_image(self) -> vtkImageData | None:
        if self.classified is not None and "classified" not in self._images:
            self._images["classified"] = vtkImageData()
            write_classified(self._images["classified"], self.measured, self.classified)
        return self._images.get("classified")


class MabdiLoop:
    """Expected image, classifier, surface and world mesh over a :class:`FrameSource` (see the module docs).

    ``classifier``: :class:`ClassifierParameters` (its ``enabled`` chooses the
    black box); ``surface``: a registered surface name and its parameters
    (None: the filter's defaults); ``noise``: the sensor's noise model (None: the source's own
    statement, :attr:`FrameSource.noise`, else noise-free), which D carries to the
    classifier's threshold tau(z), registration, removal and the noise-aware surfaces; ``removal`` and
    ``refinement``: their rules (None: defaults), used when ``classifier`` turns them on;
    ``registration``: frame-to-map registration (None: defaults, on), used when the classifier is on.
    """

    def __init__(
        self,
        source: FrameSource,
        classifier: ClassifierParameters | None = None,
        surface: str = "quadtree",
        surface_parameters=None,
        noise: SensorNoise | str | None = None,
        backend: str = BACKENDS[0],
        removal: RemovalParameters | None = None,
        refinement: RefinementParameters | None = None,
        registration: RegistrationParameters | None = None,
        pixel_holes: bool | str = "auto",
    ) -> None:
        self.source = source
        self.classifier_parameters = classifier if classifier is not None else ClassifierParameters()
        #: The sensor's noise model: D carries it (and, for ``auto``, the curve :attr:`SensorNoise.calibration`
        #: learns from each frame); the loop's own rules below are chosen by it.
        self.noise = SensorNoise.of(noise if noise is not None else (source.noise or "none"))
        self.surface_name = surface
        #: Every "auto" of the stages' settings resolved for this sensor and noise model (:func:`resolve_settings`).
        self.settings = resolve_settings(
            source.intrinsics, self.noise, source.loses_returns, self.classifier_parameters, surface, surface_parameters,
            removal, refinement, registration,
        )  # fmt: skip
        self.classifier_parameters = self.settings.classifier
        removal_parameters, refinement_parameters = self.settings.removal, self.settings.refinement
        self.registration_parameters = self.settings.registration
        self.removal, self.refining = self.settings.removing, self.settings.refining
        self.refinement = MapRefinement(refinement_parameters)
        #: D of each frame, from the source (hole filling, the noise model as it stands)
        self.depth_frames = SourceDepthFrames(source, noise=self.noise, pixel_holes=pixel_holes)
        # compacted at the end of each frame (step)
        self.world = FilterWorldMesh(
            chunk_size=chunk_size_for(source.intrinsics), compact_on_append=False, pool_size=pool_size_for(source.intrinsics)
        )
        self.expected = FilterExpectedImage(backend=backend, identity=self.removal or self.refining)
        #: D registered to the map (the renderer of E is shared: one upload of the map); None: poses as given
        self.registration: FilterRegistration | ScanRegistration | None = None
        if self.classifier_parameters.enabled and self.registration_parameters.enabled:
            if source.intrinsics.range_image:  # a LiDAR's scans: fitted along their returns, E drawn once
                self.registration = ScanRegistration(self.registration_parameters, self.expected, source.pose_accuracy)
            else:
                self.registration = FilterRegistration(
                    self.registration_parameters, renderer=self.expected.renderer, pose_accuracy=source.pose_accuracy
                )
        self.classifier = FilterClassifier(self.classifier_parameters)
        #: The frames each part of the map was seen covered by a surface in front of it (None: such a surface is
        #: meshed at once)
        frames = int(self.classifier_parameters.front_frames)
        self.front_memory = FrontConfirmation(frames) if frames > 1 else None
        #: The removal stage (its rules: :attr:`removal_parameters`).
        self.object_removal = ObjectRemoval(removal_parameters, self.classifier.threshold)
        self.surface = make_surface_filter(surface, surface_parameters)
        #: What the surface filter can do beyond meshing a frame (declared in its registry entry).
        self.surface_capabilities = surface_filter(surface).capabilities
        #: The last frame's values (:mod:`mabdi.frame_values`) and what its surface meshed
        self._frame = FrameValues()
        #: The frames the per-frame arrays cover: the source's length when known, else the frames run so far
        #: (a stream's: the arrays grow as frames come)
        self._known = source.frames_known or 0
        self._frames = self._known
        #: (N, 4, 4) the pose each frame was meshed with (registered, or as given); NaN for frames not run
        self._poses = np.full((self._frames, 4, 4), np.nan)
        #: (N, REGISTRATION_COLUMNS) per frame, for the checks of the run's poses: its registration status (its
        #: index in STATUSES; "off" where the source states its poses exact), correction (m, degrees), the share
        #: of its valid pixels that saw through the map (contradicted), the faces it removed, and its
        #: registration's residual (m; NaN where not registered); NaN for frames not run
        self._registrations = np.full((self._frames, REGISTRATION_COLUMNS), np.nan)
        self._poses_checked = False
        self._jumps_checked = False
        self._given_exact = False  # the last frame's pose stated exact by the source

    @property
    def removal_parameters(self) -> RemovalParameters:
        """The rules of object removal (the removal stage's)."""
        return self.object_removal.parameters

    @removal_parameters.setter
    def removal_parameters(self, parameters: RemovalParameters) -> None:
        self.object_removal.parameters = parameters

    @classmethod
    def from_config(cls, config, source: FrameSource) -> MabdiLoop:
        """The loop of a run config (:class:`mabdi.config.RunConfig`) over ``source``."""
        return cls(
            source,
            classifier=config.classifier,
            surface=config.surface.method,
            surface_parameters=config.surface.parameters_of(),
            noise=config.sensor.sensor_noise(),
            backend=config.sensor.backend,
            removal=config.removal,
            refinement=config.refinement,
            registration=config.registration,
            pixel_holes=config.sensor.fill_pixel_holes,
        )

    # -- running -----------------------------------------------------------
    @property
    def classifier_enabled(self) -> bool:
        return self.classifier_parameters.enabled

    @property
    def intrinsics(self) -> Intrinsics:
        return self.source.intrinsics

    def reset(self) -> None:
        """Empty the map, and a surface filter's own memory (voxel statistics); render windows stay."""
        self.world.reset()
        self.refinement.reset()
        if self.front_memory is not None:
            self.front_memory.reset()
        if self.registration is not None:
            self.registration.reset()
        if self.noise.calibration is not None:
            self.noise.calibration.reset()
        self._frames = self._known
        self._poses[:] = np.nan
        self._registrations[:] = np.nan
        self._poses_checked = False
        self._jumps_checked = False
        self._frame = FrameValues()
        if self.surface_capabilities.keeps_state:
            self.surface.reset()

    def state(self) -> dict:
        """The loop's state between frames, for checkpoints: the map, refinement's and a stateful surface
        filter's memory. Plain data only (dicts, lists, numbers, strings, numpy arrays: :mod:`mabdi.io.checkpoint`)."""
        state = {
            "world": self.world.state(), "refinement": self.refinement.state(self.world),
            "poses": self._poses[: self._frames].copy(), "registrations": self._registrations[: self._frames].copy(),
        }  # fmt: skip
        if self.surface_capabilities.keeps_state:
            state["surface"] = self.surface.state()
        if self.registration is not None:
            state["registration"] = self.registration.state()
        if self.noise.calibration is not None:
            state["noise_calibration"] = self.noise.calibration.state()
        if self.front_memory is not None:
            state["front_memory"] = self.front_memory.state()
        return state

    def set_state(self, state: dict) -> None:
        """Go on from a :meth:`state` (the next :meth:`step` continues the saved run)."""
        self.world.set_state(state["world"])
        self.refinement.set_state(state["refinement"], self.world)
        if "surface" in state:
            self.surface.set_state(state["surface"])
        poses = np.array(state["poses"], dtype=np.float64).reshape(-1, 4, 4)
        self._frames = max(self._known, len(poses))
        self._poses = np.full((self._frames, 4, 4), np.nan)
        self._poses[: len(poses)] = poses
        self._registrations = np.full((self._frames, REGISTRATION_COLUMNS), np.nan)
        if "registrations" in state:  # (checkpoints before it: the check sees the frames run since)
            registrations = np.array(state["registrations"], dtype=np.float64)
            self._registrations[: len(registrations), : registrations.shape[1]] = registrations
        if self.registration is not None:
            self.registration.set_state(state["registration"])
        if self.noise.calibration is not None:
            self.noise.calibration.set_state(state["noise_calibration"])
        if self.front_memory is not None and "front_memory" in state:  # (checkpoints before it: an empty memory)
            self.front_memory.set_state(state["front_memory"])

    def step(self, index: int) -> FrameRecord:
        """Run frame ``index``: read D, render E, classify, mesh, append. Times each stage. An error that Ctrl-C
        caused (numba's SystemError around it: :func:`mabdi.interrupts.caused_by_interrupt`) is raised as
        KeyboardInterrupt. Frames come in order from any source, one of known length or a stream; the run's
        poses are checked when it ends (:meth:`finish`)."""
        self._cover(index)
        with interrupts_unwrapped(), one_blas_thread():
            record = self._step(index)
        judged = "off" if self._given_exact else record.registration
        seen_through = record.contradicted_pixels / record.valid_pixels if record.valid_pixels else np.nan
        residual = record.residual_mm / 1000.0 if record.registered else np.nan
        self._registrations[index] = (
            STATUSES.index(judged), record.correction_mm / 1000.0, record.correction_deg, seen_through, record.cells_removed,
            residual,
        )  # fmt: skip
        return record

    def finish(self) -> None:
        """End the run: a :class:`PosesDisagreeWarning` when the run's poses disagree with its depth
        (:mod:`mabdi.stages.registration_check`), once a run. The runner calls it after the last frame; a
        script stepping the loop itself calls it when its frames end."""
        self._check_poses()
        self._check_pose_jumps()

    def _check_pose_jumps(self) -> None:
        """Warn (once a run) where the given poses jump and the frames after the jump removed much of what the
        run removed (:func:`~mabdi.stages.registration_check.jumps_that_removed`). Not for a source that
        states how far its poses are off (the simulator), nor without removal."""
        if self._jumps_checked or self.source.pose_accuracy is not None or not self.removal:
            return
        self._jumps_checked = True
        try:
            given = np.asarray(self.source.poses, dtype=np.float64)[: self._frames]
        except Exception:  # a source that cannot list its poses
            return
        # removal takes what the frames after a jump see through once it has seen through it long enough
        window = self.removal_parameters.frames_required + 1
        message = jumps_that_removed(given, self._registrations[: len(given), 4], window)
        if message is not None:
            warnings.warn(message, PoseJumpWarning, stacklevel=3)

    def _cover(self, index: int) -> None:
        """Make the per-frame arrays reach frame ``index`` (a stream's grow as its frames come; doubling)."""
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            return  # the source's check_index says what is wrong with it
        if self._known and index >= self._known:
            return  # past the end of a source of known length: its check_index says so
        if index >= len(self._poses):
            capacity = max(index + 1, 2 * len(self._poses), 16)
            poses, registrations = np.full((capacity, 4, 4), np.nan), np.full((capacity, REGISTRATION_COLUMNS), np.nan)
            poses[: len(self._poses)] = self._poses
            registrations[: len(self._registrations)] = self._registrations
            self._poses, self._registrations = poses, registrations
        self._frames = max(self._frames, int(index) + 1)

    def meshed_pose(self, frame: int) -> np.ndarray | None:
        """(4, 4) the pose frame ``frame`` was meshed with (map frame); a frame not run here (a run resumed from
        an older checkpoint): the source's given pose; None when neither is known."""
        if frame < 0:
            return None
        if frame < len(self._poses) and np.isfinite(self._poses[frame]).all():
            return self._poses[frame]
        try:
            given = self.source.poses  # a stream's: the frames read so far
        except Exception:  # a source that cannot list its poses
            return None
        return np.asarray(given[frame], dtype=np.float64) if frame < len(given) else None

    def _check_poses(self) -> None:
        """Warn (once a run) when the frames' registrations say the poses disagree with the depth. Not for a
        source that states how far its poses are off (the simulator): no pose file, no depth scale to blame."""
        if self._poses_checked or self.source.pose_accuracy is not None:
            return
        self._poses_checked = True
        registrations = self._registrations[: self._frames]
        done = registrations[np.isfinite(registrations[:, 0])]
        statuses = [STATUSES[int(code)] for code in done[:, 0]]
        causes = LIDAR_CAUSES if self.intrinsics.range_image else CAUSES
        message = poses_disagree(statuses, done[:, 1], done[:, 2], done[:, 3], causes)
        if message is None:  # a stretch of frames moved far, which the medians hide
            message = pose_excursion(np.flatnonzero(np.isfinite(registrations[:, 0])), statuses, done[:, 1], done[:, 2])
        if message is not None:
            warnings.warn(message, PosesDisagreeWarning, stacklevel=3)

    def _step(self, index: int) -> FrameRecord:
        start = time.perf_counter()
        measured = self.depth_frames.measured(index)
        t_depth = time.perf_counter()
        t_register = t_expected = t_classify = t_depth
        cells_removed = 0
        placement = Placement.unregistered(measured.pose)
        drawn = None  # E, where registration drew it at the pose the scan is meshed with
        if isinstance(self.registration, ScanRegistration):
            measured, placement, drawn = self.registration.place(measured, self.world.map, self._earlier_residuals(index))
            t_register = t_expected = t_classify = time.perf_counter()
        elif self.registration is not None:
            measured, placement = self.registration.place(measured, self.world.map, self._earlier_residuals(index))
            t_register = t_expected = t_classify = time.perf_counter()
        expected = classified = voted_on = None
        surface_input, whole = measured, None  # the black box meshes all of D
        if self.classifier_enabled:
            expected = drawn if drawn is not None else self.expected.render(self.world.map, measured)
            # removal votes along a LiDAR's own returns' rays: cast now, while the drawing is of this map
            voted_on = self.expected.along_returns(measured, expected) if self.removal else expected
            t_expected = time.perf_counter()
            last = self._poses[index - 1] if index > 0 else None  # the last frame's pose (map frame), NaN if not run
            motion = np.linalg.inv(last) @ measured.pose if last is not None and np.isfinite(last).all() else None
            classified = self.classifier.classify(
                measured, expected, placement.covariance, placement.fitted_pose, motion, self.front_memory
            )
            t_classify = time.perf_counter()
            surface_input, whole = measured.showing(classified.depth), measured.depth
        added = mesh_frame(self.surface, surface_input, whole)
        if classified is not None and classified.novel_pixels is not None and not self.surface_capabilities.keeps_state:
            # the rim's own faces are the map's (a surface that keeps state hands out its own patches whole)
            added = trimmed_patch(added, classified.novel_pixels, measured.geometry, measured.pose)
            # and so are the faces the map already holds where they stand
            added = without_faces_on_map(added, expected, self.world.face_corners_of)
        t_surface = time.perf_counter()
        self.world.append(added, index)
        t_append = time.perf_counter()
        frame = self._frame = FrameValues(measured, placement, expected, classified, added)
        self._poses[index] = measured.pose
        # Removal votes only from frames whose pose is known to fit the map: registered, or given without
        # registration, or stated exact by the source (the ICP's checks fail where what held the pose has
        # left the scene: that is when the votes matter); and not from a registered frame that no pose fits
        # as well as the run's frames fit (:mod:`mabdi.stages.fit_check`; registration judged it).
        poor_fit = placement.poor_fit
        votes = (placement.status in ("registered", "off") or placement.given_exact) and not poor_fit
        self._given_exact = placement.given_exact
        if self.noise.calibration is not None and self.classifier_enabled and votes:
            self._calibrate_noise(measured, expected)
        # Refinement and removal last: the map changes after this frame's E was used, so E is not drawn
        # twice; the surface behind a removed or replaced face is novel (and meshed) in the next frame.
        replaced = np.zeros(0, dtype=np.int64)
        moved = 0
        if self.refining:
            frame.refined = self.refinement.step(measured, expected, classified.labels, self.world, self.meshed_pose)
            self.world.move_points_of(frame.refined.moves)  # the map changes here, by its owner
            replaced, moved = frame.refined.replaced, frame.refined.moved_vertices
        t_refine = time.perf_counter()
        if (self.removal and votes) or len(replaced):
            found = None
            if self.removal and votes:
                seen = classified
                if voted_on is not expected:  # the returns against the map along their own rays, classified as D is
                    seen = self.classifier.classify(measured, voted_on, placement.covariance, placement.fitted_pose)
                found = self.object_removal.find(
                    measured, voted_on, seen, self.world, self.surface, self.surface_capabilities
                )
            removal = apply_removal(
                self.world, self.surface, self.surface_capabilities, self.object_removal, found, replaced, expected, measured
            )  # fmt: skip
            frame.removed = removal.removed
            cells_removed = removal.cells_removed
        t_remove = time.perf_counter()
        self.world.compact()  # now that this frame's E and its face codes have been used
        compact_s = time.perf_counter() - t_remove  # counted with the append: both keep the map's blocks

        if classified is not None:
            counts = classified.counts
        else:
            valid = int(np.count_nonzero(np.isfinite(measured.depth)))
            counts = {"valid": valid, "novel": valid, "specks": 0, "contradicted": 0}
        ms = 1000.0
        return FrameRecord(
            frame=index,
            novel_fraction=counts["novel"] / counts["valid"] if counts["valid"] else 0.0,
            cells_added=self.world.cells_added,
            cells_total=self.world.number_of_cells,
            t_depth_ms=ms * (t_depth - start),
            t_expected_ms=ms * (t_expected - t_register),
            t_classify_ms=ms * (t_classify - t_expected),
            t_surface_ms=ms * (t_surface - t_classify),
            t_append_ms=ms * (t_append - t_surface + compact_s),
            t_total_ms=ms * (t_remove + compact_s - start),
            points_total=self.world.number_of_points,
            valid_pixels=counts["valid"],
            novel_pixels=counts["novel"],
            speck_pixels=counts["specks"],
            contradicted_pixels=counts["contradicted"],
            cells_removed=cells_removed,
            vertices_refined=moved,
            t_refine_ms=ms * (t_refine - t_append),
            area_removed=polydata_area(frame.removed) if cells_removed else 0.0,
            t_remove_ms=ms * (t_remove - t_refine),
            registration=placement.status,
            correction_mm=1000.0 * placement.correction_m,
            correction_deg=placement.correction_deg,
            residual_mm=1000.0 * placement.residual_m,
            inlier_share=placement.inlier_share,
            constraint_support=placement.support,
            t_register_ms=ms * (t_register - t_depth),
            filled_pixels=self.depth_frames.filled_pixels,
            poor_fit=int(poor_fit),
        )

    def _earlier_residuals(self, index: int) -> np.ndarray:
        """The registration residuals (m) of the registered frames before ``index`` that moved from the frame before
        them (:func:`mabdi.stages.fit_check.moved`), in order."""
        earlier = self._registrations[:index]
        counted = (earlier[:, 0] == STATUSES.index("registered")) & moved(self._poses[:index])
        return earlier[counted, 5]

    def _calibrate_noise(self, measured: Measured, expected: Expected) -> None:
        """``noise = "auto"``: this frame's D - E where the map explains D, away from E's silhouettes
        (:mod:`mabdi.noise_calibration`)."""
        silhouettes = dilate(depth_edges(expected.depth, self.removal_parameters.edge_jump), 2)
        self.noise.calibration.observe(measured.depth, expected.depth, silhouettes)

    # -- what the last frame produced --------------------------------------
    @property
    def last_frame(self) -> FrameValues:
        """The last frame's values as the stages passed them: D at the pose it was meshed with (map frame), its
        placement, E, the classifier's findings, what was meshed, refined and removed (None before the first)."""
        return self._frame

    def measured_image(self) -> vtkImageData:
        """D of the last frame as a depth image (field data: intrinsics, pose, frame, timestamp, noise), with its
        pose registered to the map when registration is on (the given pose and the registration's figures
        beside it, :func:`mabdi.stages.registration.write_placement`). Made when asked (the loop itself
        passes :meth:`measured`); empty before the first frame."""
        return self._frame.measured_image(self.registration is not None)

    def world_from_map(self) -> np.ndarray:
        """Where the map's frame lies in the world (4x4): the loop builds the map in its own frame, started at
        the first frame's given pose and tied to the given poses as a whole (:mod:`mabdi.stages.map_anchor`);
        identity without registration, and for a LiDAR's scans (mapped in the world's frame)."""
        if not isinstance(self.registration, FilterRegistration):
            return np.eye(4)
        return self.registration.anchor.world_from_map

    def trajectory(self) -> np.ndarray:
        """(N, 4, 4) world_from_camera each frame was meshed with (registered, else as given), in the world
        frame; NaN for frames not run."""
        return np.einsum("ij,njk->nik", self.world_from_map(), self._poses[: self._frames])

    def expected_image(self) -> vtkImageData | None:
        """E of the last frame as a depth image (with ``face_id`` when drawn with identity), or None when the
        classifier is off. Made when asked."""
        return self._frame.expected_image()

    def classified_image(self) -> vtkImageData | None:
        """The classifier's output of the last frame as a depth image (the meshed depth, ``label``), or None
        when it is off. Made when asked."""
        return self._frame.classified_image()

    def labels(self) -> np.ndarray | None:
        """(H, W) uint8 labels of the last frame (0 no return, 1 known, 2 novel, 3 contradicted), or None."""
        return None if self._frame.classified is None else self._frame.classified.labels

    def refinement_result(self):
        """What refinement did in the last frame (:class:`~mabdi.stages.refinement.RefinementResult`), or None."""
        return self._frame.refined

    def removed_surface(self) -> vtkPolyData:
        """The faces object removal took out of the map in the last frame (the map frame: :meth:`world_from_map` places them)."""
        return self._frame.removed

    def novel_surface(self) -> vtkPolyData:
        """What the surface meshed in the last frame, in the map's frame."""
        return self._frame.added

    def mesh(self) -> vtkPolyData:
        """The whole map as one vtkPolyData (cell data ``frame``), in the world frame (:meth:`world_from_map`)."""
        world_from_map = self.world_from_map()
        if np.array_equal(world_from_map, np.eye(4)):
            return self.world.mesh()
        return transformed_polydata(self.world.mesh(), world_from_map)

    def memory_bytes(self) -> int:
        """Memory held by the map's blocks."""
        return self.world.memory_bytes()

    def close(self) -> None:
        """Release the render windows (of E, and of the source)."""
        self.expected.renderer.close()
        self.source.close()
