"""ObjectRemoval: the loop's removal stage, one frame at a time (the rules are :mod:`mabdi.filters.removal`).

Inputs, all explicit (:meth:`ObjectRemoval.run`):

* D, the measured depth image (registered to the map), and E, the expected
  image rendered with face identity (its codes and their
  :class:`~mabdi.face_identity.FaceIdTable`), and the classifier's output
  (labels, the pose uncertainty per pixel);
* the map (:class:`~mabdi.filters.world_mesh.FilterWorldMesh`), whose faces
  gather the evidence;
* the sensor's noise model and the classifier's threshold tau(z);
* the surface filter and what it can do (its registry capabilities: a
  filter that keeps voxel statistics has them cleared with the faces);
* whether this frame votes (only frames registered to the map, or with
  registration off), and the faces refinement replaced this frame.

Output: a :class:`RemovalResult` (the removed faces, as a polydata for the
dashboard, and their number). The map is changed in place.

A frame where no pixel sees through the map is skipped whole: confirmations
only matter against contradictions, and it is the common case once the
world is known.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import unit_rays
from mabdi.depth import depth_array, image_intrinsics, image_pose, pixels_per_radian
from mabdi.face_identity import FaceIdTable
from mabdi.filters.classifier import CONTRADICTED, NO_RETURN, label_array, pose_sigma_array
from mabdi.filters.expected_image import face_id_array
from mabdi.filters.registry import SurfaceCapabilities
from mabdi.filters.removal import RemovalParameters, for_geometry, removal_votes
from mabdi.polydata import polydata_arrays


@dataclass
class RemovalResult:
    """What removal did in one frame: the faces it took out of the map (world metres) and their number."""

    removed: vtkPolyData = field(default_factory=vtkPolyData)

    @property
    def cells_removed(self) -> int:
        return int(self.removed.GetNumberOfCells())


class ObjectRemoval:
    """The removal stage (see the module docs): ``parameters`` are the rules, ``noise`` the sensor's model
    (its sigma(z) weighs the votes), ``threshold(depth, near, far)`` the classifier's tau."""

    def __init__(self, parameters: RemovalParameters, noise, threshold: Callable) -> None:
        self.parameters = parameters
        self.noise = noise
        self.threshold = threshold

    def run(
        self,
        measured_image,
        expected_image,
        classified_image,
        world,
        surface,
        capabilities: SurfaceCapabilities,
        votes: bool,
        replaced=(),
    ) -> RemovalResult:
        """Vote with this frame's contradicted and known pixels (when ``votes``), remove the faces the evidence
        condemns and the faces ``replaced`` (codes of E: refinement's, made from a much noisier look)."""
        gone = np.asarray(replaced, dtype=np.int64)
        labels = label_array(classified_image)
        voting = None
        if votes and self._anything_seen_through(labels, expected_image):
            voting, condemned = self._votes(labels, measured_image, expected_image, classified_image, world, surface, capabilities)
            gone = np.union1d(gone, condemned)
        if not len(gone):
            return RemovalResult()
        result = RemovalResult(world.remove_faces(gone, FaceIdTable.read(expected_image)))
        if capabilities.clears_space and result.cells_removed:
            # voxel planes: the statistics that made the removed faces go with them (else re-meshing brings
            # them back), and the voxels the voting rays crossed in free space
            points, triangles = polydata_arrays(result.removed)
            surface.clear_faces_at(points[triangles].mean(axis=1))
        if voting is not None and capabilities.clears_space:
            self._clear_free_space(voting, gone, measured_image, expected_image, surface)
        return result

    def _anything_seen_through(self, labels: np.ndarray, expected_image) -> bool:
        """Whether any pixel may see through the map: contradicted, or (``no_return_is_free``) no return where E has a face."""
        if np.any(labels == CONTRADICTED):
            return True
        if not self.parameters.no_return_is_free:
            return False
        no_return = labels == NO_RETURN
        return bool(no_return.any() and np.isfinite(depth_array(expected_image)[no_return]).any())

    def _votes(self, labels, measured_image, expected_image, classified_image, world, surface, capabilities):
        """(the voting contradicted pixels, the codes of the faces the evidence now condemns)."""
        geometry = image_intrinsics(measured_image)
        measured = depth_array(measured_image)
        codes = face_id_array(expected_image)
        table = FaceIdTable.read(expected_image)
        expected = depth_array(expected_image)
        rays, _ = unit_rays(geometry, np.float32)
        faces, contradicted, confirmed, voting = removal_votes(
            labels,
            measured,
            expected,
            codes,
            rays,
            image_pose(measured_image),
            lambda faces: world.face_normals_of(faces, table),
            self._parameters_for(expected, geometry, surface, capabilities),
            evidence_of=lambda faces: world.face_evidence_of(faces, table),
            sigma=lambda depth: self.noise.sigma(depth, geometry.near, geometry.far),
            far=geometry.far,
            pose_sigma=pose_sigma_array(classified_image),
        )
        if not len(faces):
            return voting, np.zeros(0, dtype=np.int64)
        return voting, world.update_evidence(faces, contradicted, confirmed, self.parameters, table)

    def _parameters_for(self, expected: np.ndarray, geometry, surface, capabilities: SurfaceCapabilities) -> RemovalParameters:
        """The removal rules for this frame: for the sensor's geometry, and the edge margin widened to the
        surface's ``face_overhang`` (metres, voxel planes) in pixels at the median depth of E (see
        :mod:`mabdi.filters.removal`)."""
        parameters = for_geometry(self.parameters, geometry)
        overhang = surface.face_overhang if capabilities.overhang else 0.0
        if overhang <= 0:
            return parameters
        shown = expected[::4, ::4]
        shown = shown[np.isfinite(shown)]
        if not len(shown):
            return parameters
        margin = int(np.ceil(overhang * pixels_per_radian(geometry) / float(np.median(shown))))
        margin = min(max(margin, parameters.edge_margin), parameters.max_edge_margin)
        return replace(parameters, edge_margin=margin)

    def _clear_free_space(self, voting: np.ndarray, gone: np.ndarray, measured_image, expected_image, surface) -> None:
        """Voxel planes: rays that saw through removed faces empty the voxels they crossed (up to tau before D)."""
        through = voting & np.isin(face_id_array(expected_image), gone)
        if not through.any():
            return
        geometry = image_intrinsics(measured_image)
        measured = depth_array(measured_image)
        pose = image_pose(measured_image)
        rays, length = unit_rays(geometry, np.float32)
        depth = np.where(np.isnan(measured[through]), geometry.far, measured[through]).astype(np.float64)
        tau = self.threshold(depth.astype(np.float32), geometry.near, geometry.far).astype(np.float64)
        directions = rays[through].astype(np.float64) @ pose[:3, :3].T
        ends = pose[:3, 3] + directions * (depth * length[through])[:, None]
        surface.clear_free_space(pose[:3, 3], ends, tau * length[through])
