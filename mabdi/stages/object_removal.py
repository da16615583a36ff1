"""ObjectRemoval: the loop's removal stage, one frame at a time (the rules are :mod:`mabdi.stages.removal`).

Inputs, all explicit (:meth:`ObjectRemoval.find`):

* D, the measured depth image (registered to the map), and E, the expected
  image rendered with face identity (its codes and their
  :class:`~mabdi.face_identity.FaceIdTable`), and the classifier's output
  (labels, the pose uncertainty per pixel);
* the map (:class:`~mabdi.stages.world_mesh.FilterWorldMesh`), read only:
  its faces' normals and evidence;
* the sensor's noise model and the classifier's threshold tau(z);
* the surface filter and what it can do (its registry capabilities: the
  faces of a large surface overhang its silhouettes).

Output: the frame's :class:`RemovalVotes`; the loop, the map's one owner,
adds them to the faces' evidence and removes the faces it condemns
(:func:`mabdi.loop.loop.apply_removal`, a :class:`RemovalResult`).

A frame where no pixel sees through the map is skipped whole: confirmations
only matter against contradictions, and it is the common case once the
world is known.

**Blocks re-meshed after E was drawn.** The votes come after the frame's
append, where a keyed surface (voxel planes) replaces every block its new
points landed in, so E's codes of such a block name faces no longer there.
The pixels that showed it are cast against the block's new faces
(:func:`~mabdi.stages.ray_triangle_kernels.nearest_hits_in_boxes_kernel`) and
classified again against them with the same tau: a face still where it was
(its centre within :data:`~mabdi.world_map.UNCHANGED_FACE` of an old one's)
gets their votes; a face made or fitted again to this frame's points is not
judged by the same frame. Without this a block that keeps receiving points
(the jamb beside an opening door) never lets its old faces be voted out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from vtkmodules.util.numpy_support import vtk_to_numpy
from vtkmodules.vtkCommonDataModel import vtkPolyData

from mabdi.camera import project, unit_rays
from mabdi.face_identity import FaceIdTable, block_address, codes_in, rows_by_block
from mabdi.stages.classifier import CONTRADICTED, NO_RETURN, classify, dilate, neighbourhood_3x3
from mabdi.frame_values import Classified, Expected, Measured
from mabdi.stages.ray_triangle_kernels import nearest_hits_in_boxes_kernel
from mabdi.surfaces.registry import SurfaceCapabilities
from mabdi.stages.removal_kernels import points_in_boxes
from mabdi.stages.removal import RemovalParameters, for_geometry, free_space_filled, removal_votes, votes_between_pixels
from mabdi.polydata import triangle_frames
from mabdi.world_map import face_centres


#: Faces smaller than a pixel are looked for within a pixel's footprint on a plane seen this steeply (degrees).
MAX_INCIDENCE_DEG = 88.0
_COS_MAX_INCIDENCE = math.cos(math.radians(MAX_INCIDENCE_DEG))


@dataclass
class RemovalResult:
    """What removal did in one frame: the faces it took out of the map (world metres) and their number."""

    removed: vtkPolyData = field(default_factory=vtkPolyData)

    @property
    def cells_removed(self) -> int:
        return int(self.removed.GetNumberOfCells())


@dataclass
class RemovalVotes:
    """What one frame's pixels say about the map's faces (:meth:`ObjectRemoval.find`); the map's owner adds
    them to the faces' evidence (:meth:`~mabdi.world_map.WorldMap.update_evidence`) and removes what it condemns.

    ``faces``: codes of E (under ``table``) voted on; ``contradicted`` / ``confirmed``: their pixel votes;
    ``voting``: (H, W) bool, the contradicted pixels that voted; ``codes``: (H, W) the face each pixel's vote
    went to (E's codes, re-traced where a block was re-meshed after E was drawn)."""

    table: FaceIdTable
    faces: np.ndarray
    contradicted: np.ndarray
    confirmed: np.ndarray
    voting: np.ndarray
    codes: np.ndarray


class ObjectRemoval:
    """The removal stage (see the module docs): ``parameters`` are the rules, ``threshold(depth, noise, near,
    far, pose_sigma)`` the classifier's tau. The sensor's noise model (its sigma(z) weighs the votes) is the
    one D carries. It reads the map and returns what it found; :func:`mabdi.loop.loop.apply_removal` changes
    the map."""

    def __init__(self, parameters: RemovalParameters, threshold: Callable) -> None:
        self.parameters = parameters
        self.threshold = threshold

    def find(
        self, measured: Measured, expected: Expected, classified: Classified, world, surface, capabilities: SurfaceCapabilities
    ) -> RemovalVotes | None:
        """This frame's votes on the faces E shows (and on faces too small for a pixel beside them), from D
        (registered), E (with face identity) and the classifier's findings; None when no pixel sees through the
        map (confirmations only matter against contradictions). ``world`` is read only."""
        if not self._anything_seen_through(classified.labels, expected):
            return None
        return self._votes(classified.labels, measured, expected, classified, world, surface, capabilities)

    def free_space_rays(self, votes: RemovalVotes, gone: np.ndarray, frame: Measured) -> tuple | None:
        """Voxel planes: (origin, ends, margins) of the rays that saw through removed faces (``gone``: codes of
        E), world metres, ending tau short of D: the voxels they crossed are free; None when there are none."""
        through = votes.voting & codes_in(votes.codes, gone)
        if not through.any():
            return None
        geometry, measured, pose = frame.geometry, frame.depth, frame.pose
        rays, length = unit_rays(geometry, np.float32)
        depth = np.where(np.isnan(measured[through]), geometry.far, measured[through]).astype(np.float64)
        tau = self.threshold(depth.astype(np.float32), frame.noise, geometry.near, geometry.far).astype(np.float64)
        directions = rays[through].astype(np.float64) @ pose[:3, :3].T
        ends = pose[:3, 3] + directions * (depth * length[through])[:, None]
        return pose[:3, 3], ends, tau * length[through]

    def _anything_seen_through(self, labels: np.ndarray, expected: Expected) -> bool:
        """Whether any pixel may see through the map: contradicted, or (``no_return_is_free``) no return where E has a face."""
        if np.any(labels == CONTRADICTED):
            return True
        if not self.parameters.no_return_is_free:
            return False
        no_return = labels == NO_RETURN
        return bool(no_return.any() and np.isfinite(expected.depth[no_return]).any())

    def _votes(self, labels, frame: Measured, expected_image: Expected, classified: Classified, world, surface, capabilities) -> RemovalVotes:
        """The frame's votes (:class:`RemovalVotes`)."""
        geometry, noise, measured = frame.geometry, frame.noise, frame.depth
        codes, table, expected = expected_image.face_ids, expected_image.table, expected_image.depth
        pose_sigma = classified.pose_sigma
        labels, expected, codes, table = self._retraced(labels, measured, expected, codes, table, frame, pose_sigma, world)
        rays, _ = unit_rays(geometry, np.float32)
        parameters = self._parameters_for(expected, geometry, surface, capabilities)
        pose = frame.pose

        def sigma(depth):
            return noise.sigma(depth, geometry.near, geometry.far)

        faces, contradicted, confirmed, voting = removal_votes(
            labels,
            measured,
            expected,
            codes,
            rays,
            pose,
            lambda faces: world.face_normals_of(faces, table),
            parameters,
            evidence_of=lambda faces: world.face_evidence_of(faces, table),
            sigma=sigma,
            far=geometry.far,
            pose_sigma=pose_sigma,
        )
        if len(faces):
            between = self._between_pixels(
                faces, contradicted, confirmed, voting, measured, geometry, pose, table, world, parameters, sigma, pose_sigma
            )  # fmt: skip
            if len(between):
                faces = np.concatenate([faces, between])
                contradicted = np.concatenate([contradicted, np.ones(len(between), dtype=contradicted.dtype)])
                confirmed = np.concatenate([confirmed, np.zeros(len(between), dtype=confirmed.dtype)])
        return RemovalVotes(table, faces, contradicted, confirmed, voting, codes)

    def _between_pixels(self, faces, contradicted, confirmed, voting, measured, geometry, pose, table, world, parameters, sigma, pose_sigma):
        """Codes of the faces no pixel showed that this frame's contradictions see through
        (:func:`~mabdi.stages.removal.votes_between_pixels`), among the faces around those voted against, in
        any patch E drew: where something left, the faces too small for a pixel of this view go with it. (A
        patch whose faces are all smaller than a pixel here, a remnant of a departed object's surface meshed
        in one frame, gets no pixel and so no vote of its own.)

        Only voting pixels with a voting neighbour count here (where a surface was seen through, not a
        lone pixel of noise), and only faces whose first corner projects within a pixel of one are looked at, so
        a frame without such a cluster costs nothing and one with it costs a projection of the blocks' points.
        """
        clustered = voting & (neighbourhood_3x3(voting.astype(np.uint8), np.add, outside=0) >= 2)  # itself and one more
        against = faces[contradicted > confirmed]
        if not len(against) or not clustered.any():
            return np.zeros(0, dtype=np.int64)
        near_cluster = dilate(clustered, 1)
        height, width = clustered.shape
        block, local, keys = world.face_lookup(against, table)
        measured = free_space_filled(measured, parameters, geometry.far)
        rays, length = unit_rays(geometry, np.float32)
        rotation, origin = pose[:3, :3], pose[:3, 3]
        angle = geometry.pixel_angle()
        # where the map was seen through: around each block's contradicted faces, a pixel's footprint on a plane
        # seen at up to MAX_INCIDENCE_DEG, and their radius
        lows, highs = [], []
        for b, rows in rows_by_block(block):
            shown, shown_radii = face_centres(world.block(keys[b]), local[rows])
            reach = np.linalg.norm(shown - origin, axis=1) * angle / _COS_MAX_INCIDENCE + shown_radii
            lows.append((shown - reach[:, None]).min(axis=0))
            highs.append((shown + reach[:, None]).max(axis=0))
        if not lows:
            return np.zeros(0, dtype=np.int64)
        lows, highs = np.array(lows), np.array(highs)
        # every patch E drew that reaches into a region, voted on or not: their points in a region, projected
        # at once, and their faces whose first corner lands within a pixel of a cluster
        touching_blocks, around, around_points, first_corners = [], [], [], []
        point_count = 0
        for b in world.current_blocks(table):
            polydata = world.block(keys[b])
            bounds = np.asarray(polydata.GetBounds()).reshape(3, 2)
            touching = np.all((lows <= bounds[:, 1]) & (highs >= bounds[:, 0]), axis=1)
            if not touching.any():
                continue
            points = vtk_to_numpy(polydata.GetPoints().GetData())
            inside = np.flatnonzero(points_in_boxes(points, lows[touching], highs[touching]))
            if not len(inside):
                continue
            polys = polydata.GetPolys()
            touching_blocks.append(b)
            around.append(inside + point_count)
            around_points.append(points[inside])
            first_corners.append(vtk_to_numpy(polys.GetConnectivityArray())[vtk_to_numpy(polys.GetOffsetsArray())[:-1]] + point_count)
            point_count += len(points)
        if not touching_blocks:
            return np.zeros(0, dtype=np.int64)
        around = np.concatenate(around)
        uv, value = geometry.project_points(np.concatenate(around_points), pose)
        with np.errstate(invalid="ignore"):
            u, v = np.floor(uv[:, 0]), np.floor(uv[:, 1])
            inside = (u >= 0) & (u < width) & (v >= 0) & (v < height) & (value > 0)
        near = np.zeros(point_count, dtype=bool)
        near[around[inside]] = near_cluster[v[inside].astype(np.int64), u[inside].astype(np.int64)]
        face_counts = np.array([len(corners) for corners in first_corners])
        ends = np.cumsum(face_counts)
        rows = np.flatnonzero(near[np.concatenate(first_corners)])  # faces of the touching blocks, in order
        which = np.searchsorted(ends, rows, side="right")  # index into touching_blocks
        drawn = np.asarray(touching_blocks, dtype=np.int64)[which]
        codes = table.bases[drawn] + rows - (ends - face_counts)[which]
        unseen = ~codes_in(codes, faces)
        if not unseen.any():
            return np.zeros(0, dtype=np.int64)
        codes, drawn = codes[unseen], drawn[unseen]
        centres, radii = np.zeros((len(codes), 3)), np.zeros(len(codes))
        for b, rows in rows_by_block(drawn):
            centres[rows], radii[rows] = face_centres(world.block(keys[b]), codes[rows] - table.bases[b])
        uv, value = geometry.project_points(centres, pose)
        uv[value <= 0] = np.nan  # behind a camera
        hit = votes_between_pixels(
            centres, world.face_normals_of(codes, table), radii, measured, voting, rays, length, uv, origin, rotation,
            angle, parameters, sigma, pose_sigma,
        )
        return codes[hit]

    def _retraced(self, labels, measured, expected, codes, table: FaceIdTable, frame: Measured, pose_sigma, world):
        """(labels, E, codes, table) with the pixels that showed a block re-meshed since E was drawn (a keyed
        patch replaced at the append: its old faces are gone) cast against the block's new faces, and
        classified again against them: the votes of these pixels go to the faces now there, and only where D
        still sees through them (a new face fitted to this frame's points is not contradicted by them)."""
        stale = world.stale_blocks(table)
        if not stale:
            return labels, expected, codes, table
        geometry, pose = frame.geometry, frame.pose
        block_of, _ = table.lookup(codes)
        block_of = block_of.ravel()
        rays, length = unit_rays(geometry, np.float64)
        rays, length = rays.reshape(-1, 3), length.ravel()
        labels, expected, codes = labels.copy(), expected.copy(), codes.astype(np.int64)
        flat_expected, flat_codes = expected.reshape(-1), codes.reshape(-1)
        names, bases, counts, addresses = list(table.names), list(table.bases), list(table.counts), list(table.addresses)
        next_base = int((table.bases + table.counts).max()) + 1
        retraced = []
        for b in stale:
            pixels = np.flatnonzero(block_of == b)
            if not len(pixels):
                continue
            key = table.names[b]
            block = world.block(key)
            corner, edge1, edge2, cell_of = triangle_frames(block)
            slots = np.full(geometry.shape, -1, dtype=np.int64)
            slots.reshape(-1)[pixels] = np.arange(len(pixels))
            boxes = pixel_boxes(corner, edge1, edge2, geometry, pose)
            hit, distance = nearest_hits_in_boxes_kernel(
                pose[:3, 3].astype(np.float64), rays[pixels] @ pose[:3, :3].T, slots, boxes, corner, edge1, edge2, 0.0
            )
            found = hit >= 0
            if len(cell_of):
                cell = cell_of[np.maximum(hit, 0)]
                # a face fitted to this frame's points is not judged by the same frame: no vote on it
                voted = found & ~world.refitted_faces(key)[cell]
            else:  # no triangle to meet (degenerate polygons only)
                cell, voted = np.zeros(len(hit), dtype=np.int64), found
            flat_codes[pixels] = np.where(voted, next_base + cell, 0)
            flat_expected[pixels] = np.where(found, distance / length[pixels], np.nan).astype(np.float32)
            cells = block.GetNumberOfCells()
            names.append(key)
            bases.append(next_base)
            counts.append(cells)
            addresses.append(block_address(block))
            next_base += cells
            retraced.append(pixels)
        if not retraced:
            return labels, expected, codes, table
        pixels = np.concatenate(retraced)
        flat_labels = labels.reshape(-1)
        d = measured.reshape(-1)[pixels]
        sigma = None if pose_sigma is None else pose_sigma.reshape(-1)[pixels]
        tau = self.threshold(d, frame.noise, geometry.near, geometry.far, sigma)
        flat_labels[pixels] = classify(d, flat_expected[pixels], tau)
        return labels, expected, codes, FaceIdTable(names, np.array(bases), np.array(counts), np.array(addresses))

    def _parameters_for(self, expected: np.ndarray, geometry, surface, capabilities: SurfaceCapabilities) -> RemovalParameters:
        """The removal rules for this frame: for the sensor's geometry, and the edge margin widened to the
        surface's ``face_overhang`` (metres, voxel planes) in pixels at the median depth of E (see
        :mod:`mabdi.stages.removal`)."""
        parameters = for_geometry(self.parameters, geometry)
        overhang = surface.face_overhang if capabilities.overhang else 0.0
        if overhang <= 0:
            return parameters
        shown = expected[::4, ::4]
        shown = shown[np.isfinite(shown)]
        if not len(shown):
            return parameters
        margin = int(np.ceil(overhang * geometry.pixels_per_radian() / float(np.median(shown))))
        margin = min(max(margin, parameters.edge_margin), parameters.max_edge_margin)
        return replace(parameters, edge_margin=margin)


def pixel_boxes(corner: np.ndarray, edge1: np.ndarray, edge2: np.ndarray, geometry, world_from_sensor: np.ndarray) -> np.ndarray:
    """(M, 4) int64 the pixel columns u0..u1 and rows v0..v1 (inclusive, a pixel's margin around) that each
    triangle (``corner`` + a ``edge1`` + b ``edge2``, world frame) may cover in the image of ``geometry`` seen
    from ``world_from_sensor``. A camera's triangle wholly behind it covers none (u0 > u1); one crossing the
    camera's plane, or a range image's triangle across the azimuth seam, may cover any column."""
    height, width = geometry.shape
    vertices = np.stack([corner, corner + edge1, corner + edge2], axis=1).reshape(-1, 3)
    rotation, centre = world_from_sensor[:3, :3], world_from_sensor[:3, 3]
    if geometry.range_image:
        uv, _ = geometry.pixels((vertices - centre) @ rotation)
        in_front = np.ones(len(vertices), dtype=bool)
    else:
        uv, z = project(vertices, geometry, world_from_sensor)
        in_front = z > 1e-9
    uv = uv.reshape(-1, 3, 2)
    in_front = in_front.reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        low = np.floor(np.nan_to_num(uv.min(axis=1), nan=-1.0, posinf=width + height, neginf=-1.0)) - 1
        high = np.floor(np.nan_to_num(uv.max(axis=1), nan=width + height, posinf=width + height, neginf=-1.0)) + 1
    boxes = np.stack([low[:, 0], high[:, 0], low[:, 1], high[:, 1]], axis=1)
    every_column = ~in_front.all(axis=1)
    if geometry.wraps_around:
        every_column |= (high[:, 0] - low[:, 0]) > width / 2  # across the seam
    boxes[every_column] = [0, width - 1, 0, height - 1]
    boxes[~in_front.any(axis=1)] = [1, 0, 1, 0]  # wholly behind a camera
    boxes[:, 0:2] = np.clip(boxes[:, 0:2], 0, width - 1)
    boxes[:, 2:4] = np.clip(boxes[:, 2:4], 0, height - 1)
    outside = (high[:, 0] < 0) | (low[:, 0] > width - 1) | (high[:, 1] < 0) | (low[:, 1] > height - 1)
    boxes[outside & ~every_column] = [1, 0, 1, 0]
    return boxes.astype(np.int64)

