"""numpy reference versions of mabdi's numba kernels, for the tests that compare the two.

The package runs only the compiled kernels (numba is a required dependency).
These are the whole-array numpy versions they were written from, kept here so
that a test can hand both the same inputs and check that they agree:

* quad-tree stages 1-5 and the small-leaf plane test
  (:mod:`mabdi.surfaces.quadtree_kernels`): :func:`reduce_points`,
  :func:`point_normals`, :func:`build_leaves`, :func:`plane_residual`, and
  :func:`quadtree_leaves_of_image` (:func:`mabdi.surfaces.quadtree.leaves_of_image`
  with these stages); tests/test_quadtree.py.
* refinement's per-block work (:mod:`mabdi.stages.refinement_kernels`):
  :func:`observe_block`; tests/test_refinement.py.
* voxel traversal (:mod:`mabdi.voxels.traversal`): :func:`reference_voxels`
  and :func:`reference_pairs`; tests/test_voxel_traversal.py.
* fast marching on a mesh map (:mod:`mabdi.mesh_maps.fast_marching`):
  :func:`iterative_arrival_times`; tests/test_maps.py.
* the cost layers' neighbourhood statistics (:func:`mabdi.mesh_maps.neighbourhood.radius_statistics`):
  :func:`neighbourhoods` (a KD-tree), :func:`roughness` and :func:`height_difference`; tests/test_maps.py.
* the noise calibration's binning of a frame's residuals (:mod:`mabdi.noise_calibration_kernels`):
  :func:`add_residuals`; tests/test_noise_calibration.py.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mabdi.camera import Intrinsics
from mabdi.surfaces.depth_smoothing import smooth_depth_by_noise
from mabdi.surfaces.quadtree import Leaves, fitting_leaves
from mabdi.voxels.traversal import prepare_rays
from mabdi.mesh_maps.fast_marching import triangle_updates
from mabdi.mesh_maps.planning import _vertex_faces

# ---------------------------------------------------------------------------
# quad-tree (mabdi.surfaces.quadtree_kernels)


def reduce_points(depth: np.ndarray, intrinsics: Intrinsics, reduction: int) -> tuple[np.ndarray, Intrinsics]:
    """Camera-frame points of the ``reduction``-square blocks (NaN-aware median), and the reduced intrinsics.

    Each block's point is the pixel holding the block's (lower) median depth
    (among equal depths, in pixel order), back-projected through that pixel's own centre: noise-free surfaces stay
    exactly on the surface, even in blocks that straddle an edge (a block
    centre ray at a median depth would float between the two surfaces). A
    block needs a valid majority.
    """
    depth = np.asarray(depth, dtype=np.float64)
    r = reduction
    k = intrinsics
    if r == 1:
        return k.rays() * depth[..., None], k
    h, w = depth.shape[0] // r, depth.shape[1] // r
    values = depth[: h * r, : w * r].reshape(h, r, w, r).swapaxes(1, 2).reshape(h, w, r * r)
    finite = np.isfinite(values)
    count = finite.sum(axis=-1)
    keyed = np.where(finite, values, np.inf)  # NaN sorts last
    full = count == r * r
    partial = ~full & (count * 2 > r * r)
    # a stable sort: among equal depths the median is taken in pixel order (as the compiled kernel does)
    order = np.argsort(keyed, axis=-1, kind="stable")
    slot = np.take_along_axis(order, np.maximum((count - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    slot[~full & ~partial] = 0
    median_depth = np.take_along_axis(values, slot[..., None], axis=-1)[..., 0]
    rows, cols = np.mgrid[0:h, 0:w]
    u = cols * r + slot % r + 0.5
    v = rows * r + slot // r + 0.5
    points = np.stack([(u - k.cx) / k.fx * median_depth, (v - k.cy) / k.fy * median_depth, median_depth], axis=-1)
    points[~(full | partial)] = np.nan
    return points, Intrinsics(k.fx / r, k.fy / r, k.cx / r, k.cy / r, w, h, k.near, k.far)


def point_normals(points: np.ndarray, max_jump: float = 0.05) -> np.ndarray:
    """(H, W, 3) unit normals of a camera-frame point map (NaN where invalid), facing the camera.

    A neighbour across a depth jump (more than ``max_jump`` of the depth) counts as missing, so
    pixels beside a discontinuity take the one-sided difference on their own surface.
    """
    valid = np.isfinite(points[..., 2])
    z = points[..., 2]

    def difference(axis: int) -> np.ndarray:
        forward = np.full_like(points, np.nan)
        backward = np.full_like(points, np.nan)
        if axis == 1:
            forward[:, :-1] = points[:, 1:]
            backward[:, 1:] = points[:, :-1]
        else:
            forward[:-1] = points[1:]
            backward[1:] = points[:-1]
        with np.errstate(invalid="ignore"):
            has_forward = np.abs(forward[..., 2] - z) <= max_jump * z
            has_backward = np.abs(backward[..., 2] - z) <= max_jump * z
        central = forward - backward
        one_sided = np.where(has_forward[..., None], forward - points, points - backward)
        return np.where((has_forward & has_backward)[..., None], central, one_sided)

    du, dv = difference(1), difference(0)
    normals = -np.cross(du, dv)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = normals / length
    facing = np.einsum("...i,...i->...", normals, points) > 0
    normals[facing] *= -1.0
    normals[~valid | ~np.isfinite(length[..., 0]) | (length[..., 0] == 0)] = np.nan
    return normals


def _pad_even(array: np.ndarray, fill) -> np.ndarray:
    """``array`` padded with ``fill`` at the bottom and right to even height and width."""
    h, w = array.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return array
    padded = np.full((h + h % 2, w + w % 2, *array.shape[2:]), fill, dtype=array.dtype)
    padded[:h, :w] = array
    return padded


def build_leaves(
    points: np.ndarray, normals: np.ndarray, n_t: float, d_t: float, allowances=None, min_distance: float = 0.0
) -> tuple[Leaves, int]:
    """Merge bottom-up (seed invariant 1, eq. 14 and the plane-distance test); return leaves and the root's region count.

    ``allowances``: None for the seed's fixed thresholds, or the (normal, distance) (H, W) images of the
    noise-aware test (averaged up the pyramid, halved per level above the first).

    Each level is padded with invalid pixels to even sides before its parents are
    formed (the same as padding the image to a power of two, without the work).
    """
    valid = np.isfinite(normals[..., 0]) & np.isfinite(points[..., 2])
    single = [valid]
    count = [valid.astype(np.int64)]
    ns = [np.where(valid[..., None], normals, 0.0).astype(np.float32)]
    ps = [np.where(valid[..., None], points, 0.0).astype(np.float32)]
    aware = allowances is not None
    zeros = np.zeros(valid.shape, np.float32)
    ss = [np.where(valid[..., None], np.stack(allowances if aware else (zeros, zeros), axis=-1), 0.0).astype(np.float32)]
    shrink = np.float32(1.0)
    while single[-1].size > 1:
        s, c = _pad_even(single[-1], False), _pad_even(count[-1], 0)
        nn, pp, sn = _pad_even(ns[-1], 0.0), _pad_even(ps[-1], 0.0), _pad_even(ss[-1], 0.0)
        children = ((slice(0, None, 2), slice(0, None, 2)), (slice(0, None, 2), slice(1, None, 2)),
                    (slice(1, None, 2), slice(0, None, 2)), (slice(1, None, 2), slice(1, None, 2)))
        all_single = s[children[0]] & s[children[1]] & s[children[2]] & s[children[3]]
        n_avg = (nn[children[0]] + nn[children[1]] + nn[children[2]] + nn[children[3]]) * np.float32(0.25)
        p_avg = (pp[children[0]] + pp[children[1]] + pp[children[2]] + pp[children[3]]) * np.float32(0.25)
        length = np.linalg.norm(n_avg, axis=-1, keepdims=True)
        unit = np.divide(n_avg, length, out=np.zeros_like(n_avg), where=length > 0)
        s_avg = (sn[children[0]] + sn[children[1]] + sn[children[2]] + sn[children[3]]) * np.float32(0.25)
        normal_limit, distance_limit = np.float32(n_t), np.float32(d_t)
        if aware:
            normal_limit = np.maximum(np.float32(n_t), s_avg[..., 0] * shrink)
            distance_limit = np.minimum(np.float32(d_t), np.maximum(np.float32(min_distance), s_avg[..., 1] * shrink))
        merged = all_single.copy()
        for k in children:
            merged &= np.abs(n_avg - nn[k]).max(axis=-1) < normal_limit
            merged &= np.abs(np.einsum("...i,...i->...", unit, pp[k] - p_avg)) < distance_limit
        single.append(merged)
        shrink = shrink * np.float32(0.5)
        if not merged.any():
            # nothing merges here, so nothing can above: the regions are the children's
            total = np.zeros(merged.shape, dtype=np.int64)
            total.flat[0] = int(c.sum())
            count.append(total)
            ns.append(n_avg)
            ps.append(p_avg)
            ss.append(s_avg)
            break
        count.append(np.where(merged, 1, c[children[0]] + c[children[1]] + c[children[2]] + c[children[3]]))
        ns.append(np.where(merged[..., None], n_avg, np.float32(0.0)))
        ps.append(np.where(merged[..., None], p_avg, np.float32(0.0)))
        ss.append(np.where(merged[..., None], s_avg, np.float32(0.0)))
    levels, rows, cols, normal_list, point_list = [], [], [], [], []
    for level, s in enumerate(single):
        if level + 1 < len(single):
            parent = np.repeat(np.repeat(single[level + 1], 2, axis=0), 2, axis=1)[: s.shape[0], : s.shape[1]]
            leaf = s & ~parent
        else:
            leaf = s
        r, c = np.nonzero(leaf)
        if len(r) == 0:
            continue
        nv = ns[level][r, c].astype(np.float64)
        normal_list.append(nv / np.linalg.norm(nv, axis=1, keepdims=True))
        point_list.append(ps[level][r, c].astype(np.float64))
        levels.append(np.full(len(r), level))
        rows.append(r)
        cols.append(c)
    if not levels:
        empty = np.zeros(0, dtype=np.int64)
        return Leaves(empty, empty, empty, np.zeros((0, 3)), np.zeros((0, 3))), 0
    leaves = Leaves(
        np.concatenate(levels),
        np.concatenate(rows),
        np.concatenate(cols),
        np.concatenate(normal_list),
        np.concatenate(point_list),
    )
    return leaves, int(count[-1].sum())


def plane_residual(points: np.ndarray, leaves: Leaves, max_jump: float, largest: int = 2) -> np.ndarray:
    """For leaves of up to ``largest`` pixels a side: the largest distance (m) of a same-surface pixel
    of the leaf or its one-pixel ring from the leaf's plane (0 for bigger leaves, whose planes rest on
    enough pixels)."""
    residual = np.zeros(len(leaves.level))
    h, w = points.shape[:2]
    for side in (s for s in (1, 2, 4, 8) if s <= largest):
        small = np.flatnonzero(leaves.size == side)
        if len(small) == 0:
            continue
        top, left = leaves.row[small] * side, leaves.col[small] * side
        own = leaves.point[small]
        for dr in range(-1, side + 1):
            for dc in range(-1, side + 1):
                r, c = top + dr, left + dc
                inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
                neighbour = points[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)]
                with np.errstate(invalid="ignore"):
                    same = inside & (np.abs(neighbour[:, 2] - own[:, 2]) <= max_jump * own[:, 2])
                    distance = np.abs(np.einsum("ij,ij->i", neighbour - own, leaves.normal[small]))
                residual[small] = np.maximum(residual[small], np.where(same, distance, 0.0))
    return residual


def quadtree_leaves_of_image(depth: np.ndarray, intrinsics: Intrinsics, p, noise) -> tuple[np.ndarray, Intrinsics, Leaves]:
    """:func:`mabdi.surfaces.quadtree.leaves_of_image` with the numpy stages above instead of the numba kernels."""
    from mabdi.surfaces.quadtree import resolved

    p = resolved(p, intrinsics)
    if p.smooth_depth:
        depth = smooth_depth_by_noise(depth, noise, intrinsics)
    points, reduced = reduce_points(depth, intrinsics, p.reduction)
    normals = point_normals(points, p.max_jump)
    from mabdi.surfaces.quadtree import MERGE_MIN_DISTANCE, merge_allowances, noise_merge_on

    allowances = merge_allowances(points, reduced, noise, p.smooth_depth) if noise_merge_on(p, noise) else None
    leaves, regions = build_leaves(points, normals, p.n_t, p.d_t, allowances, MERGE_MIN_DISTANCE)
    residual = plane_residual(points, leaves, p.max_jump)
    leaves = fitting_leaves(leaves, residual, reduced, noise)
    leaves.regions = regions
    return points, reduced, leaves


# ---------------------------------------------------------------------------
# refinement (mabdi.stages.refinement_kernels)


def observe_block(
    triangles, points, original, normal, prior, weight, total,
    cells, rays, measured, expected, length, sd, centre,
    focal, cos_grazing, gate_k, replace, replace_ratio, replace_share, radius_px,
):  # fmt: skip
    """One block's pixels (``cells``: the face each shows; ``rays`` unit world rays, ``measured`` and
    ``expected`` z-depths D and E, ``length`` ray metres per metre of z-depth, ``sd`` sigma(D), ``centre`` the
    camera's position, ``focal`` in pixels): adds the observations to the block's ``weight`` and ``total`` in
    place (see the module docs); returns (per pixel: its face is replaced, pixels that observed, vertices whose
    weight grew). The numpy reference of :func:`mabdi.stages.refinement_kernels.observe_block_kernel`
    (formerly ``mabdi.stages.refinement.observe_block``)."""
    tri = triangles[cells]
    corners = points[tri].astype(np.float64)  # (n, 3, 3) current positions
    a = corners[:, 0]
    e1, e2 = corners[:, 1] - a, corners[:, 2] - a
    face_normal = np.cross(e1, e2)
    norm = np.linalg.norm(face_normal, axis=1)
    cosine = np.abs(np.einsum("ij,ij->i", rays, face_normal)) / np.where(norm > 0, norm, 1.0)
    facing = (norm > 0) & (cosine >= cos_grazing)

    # same surface: D within the gate around E that both uncertainties allow (the face's and the pixel's)
    face_var = (1.0 / (prior[tri] + weight[tri])).mean(axis=1)
    same = facing & (np.abs(measured - expected) <= gate_k * np.sqrt(sd**2 + face_var))

    # replacement: faces made from a much noisier look than this one
    better = same & (face_var >= (replace_ratio * sd) ** 2)
    gone = np.zeros(len(cells), dtype=bool)
    if replace and better.any():
        _, face_of_pixel = np.unique(cells, return_inverse=True)  # the block's faces in view, compacted
        votes = np.bincount(face_of_pixel, weights=better)
        counts = np.bincount(face_of_pixel, weights=facing)
        gone = ((votes >= replace_share * counts) & (votes > 0))[face_of_pixel]

    # refinement: pixels on the same surface as faces that stay
    use = same & ~gone
    if not use.any():
        return gone, 0, np.zeros(0, dtype=np.int64)
    tri, w, sd = tri[use], rays[use], sd[use]
    e_ray = expected[use] * length[use]
    d_ray = measured[use] * length[use]
    hit = centre + w * e_ray[:, None]
    beta = _barycentric(hit - a[use], e1[use], e2[use])
    # the measured point, on the pixel's ray at D: the hit point moved by the residual along the ray
    measured_point = hit + w * (d_ray - e_ray)[:, None]
    # each corner's observation: the measured point's offset from the corner's original position along the
    # corner's normal, from pixels within radius_px footprints of the corner across that normal only
    toward = measured_point[:, None, :] - original[tri]  # (n, 3 corners, 3)
    corner_normal = normal[tri]
    offset = np.einsum("ikj,ikj->ik", corner_normal, toward)
    across = np.linalg.norm(toward - offset[..., None] * corner_normal, axis=2)
    radius = radius_px * measured[use] / focal
    contribution = np.where(across <= radius[:, None], beta * (cosine[use] / sd**2)[:, None], 0.0)
    # sums per corner vertex, over the block's vertices in view only (compacted; a block may hold a whole
    # frame's 300k vertices)
    vertices, corner_of = np.unique(tri.ravel(), return_inverse=True)
    gained = np.bincount(corner_of, weights=contribution.ravel())
    weight[vertices] += gained
    total[vertices] += np.bincount(corner_of, weights=(contribution * offset).ravel())
    return gone, int(use.sum()), vertices[gained > 0]


def _barycentric(v: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric weights of points a + v on triangles (a, a + e1, a + e2), clipped to the triangle
    (a hit a rounding error outside its face counts on the nearest side) and normalised."""
    d00 = np.einsum("ij,ij->i", e1, e1)
    d01 = np.einsum("ij,ij->i", e1, e2)
    d11 = np.einsum("ij,ij->i", e2, e2)
    d20 = np.einsum("ij,ij->i", v, e1)
    d21 = np.einsum("ij,ij->i", v, e2)
    denominator = d00 * d11 - d01 * d01
    denominator = np.where(denominator > 0, denominator, 1.0)
    b1 = (d11 * d20 - d01 * d21) / denominator
    b2 = (d00 * d21 - d01 * d20) / denominator
    beta = np.clip(np.stack([1.0 - b1 - b2, b1, b2], axis=1), 0.0, 1.0)
    return beta / np.maximum(beta.sum(axis=1, keepdims=True), 1e-12)


# ---------------------------------------------------------------------------
# voxel traversal (mabdi.voxels.traversal)


def reference_voxels(origins, ends, voxel_size: float, margins=0.0, *, include_end: bool = True) -> np.ndarray:
    """:func:`mabdi.voxels.traversal.traverse_voxels` in numpy, exactly (the tests' reference).

    Candidates: the voxels of samples every s/4 along each segment (its end included) and their 26
    neighbours (between two samples each coordinate moves less than a voxel, so every crossed voxel is
    among them); each candidate is kept when the slab intersection of the voxel with [0, T) has
    positive length (and, without ``include_end``, the ray leaves the voxel at t <= T).
    """
    _, voxels = reference_pairs(origins, ends, voxel_size, margins, include_end=include_end)
    return np.unique(voxels, axis=0) if len(voxels) else voxels


def reference_pairs(origins, ends, voxel_size: float, margins=0.0, *, include_end: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mabdi.voxels.traversal.ray_voxels` in numpy (see :func:`reference_voxels`): ray indices (K,) and voxels (K, 3),
    by ray and along it."""
    origins, ends, margins = prepare_rays(origins, ends, margins)
    s = float(voxel_size)
    delta = ends - origins
    length = np.linalg.norm(delta, axis=1)
    limit = length - margins
    rays = np.flatnonzero(limit > 0)
    found_rays, found_voxels = [np.zeros(0, dtype=np.int64)], [np.zeros((0, 3), dtype=np.int64)]
    neighbours = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    step = s / 4
    chunks = max(1, int(np.ceil((limit[rays] / step + 2).sum() / 100_000))) if len(rays) else 1
    for chunk in np.array_split(rays, chunks):
        if len(chunk) == 0:
            continue
        u = delta[chunk] / length[chunk, None]
        samples = np.ceil(limit[chunk] / step).astype(np.int64) + 1
        ray = np.repeat(np.arange(len(chunk)), samples)
        k = np.arange(samples.sum()) - np.repeat(np.cumsum(samples) - samples, samples)
        t = np.minimum(k * step, limit[chunk][ray])
        points = origins[chunk][ray] + t[:, None] * u[ray]
        voxels = np.floor(points / s).astype(np.int64)
        candidates = (voxels[:, None, :] + neighbours[None]).reshape(-1, 3)
        owner = np.repeat(ray, len(neighbours))
        pairs = np.unique(np.column_stack([owner, candidates]), axis=0)
        owner, candidates = pairs[:, 0], pairs[:, 1:]
        o, d = origins[chunk][owner], u[owner]
        lower, upper = candidates * s, (candidates + 1) * s
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lower - o) / d, (upper - o) / d
        moving = d != 0
        inside = (lower <= o) & (o < upper)
        enter = np.where(moving, np.minimum(t1, t2), np.where(inside, -np.inf, np.inf)).max(axis=1)
        leave = np.where(moving, np.maximum(t1, t2), np.where(inside, np.inf, -np.inf)).min(axis=1)
        end = limit[chunk][owner]
        crossed = np.maximum(enter, 0.0) < np.minimum(leave, end)
        if not include_end:
            crossed &= leave <= end
        order = np.lexsort((enter[crossed], owner[crossed]))
        found_rays.append(chunk[owner[crossed][order]])
        found_voxels.append(candidates[crossed][order])
    return np.concatenate(found_rays), np.concatenate(found_voxels)


# ---------------------------------------------------------------------------
# fast marching (mabdi.mesh_maps.fast_marching)


def iterative_arrival_times(mesh_map, source: int, slowness: np.ndarray, blocked: np.ndarray) -> np.ndarray:
    """:func:`mabdi.mesh_maps.planning.arrival_times` by the fast iterative method (formerly its ``method="iterative"``):
    a band of active vertices updated all at once with numpy until no time improves by more than 1e-9 of the
    domain size; the same triangle update and solution as the compiled heap, much slower on big maps."""
    vertices = mesh_map.vertices.astype(np.float64)
    faces = mesh_map.faces
    n = len(vertices)
    starts, incident = _vertex_faces(faces, n)
    times = np.full(n, np.inf)
    times[source] = 0.0
    active = np.array([source])
    low, high = mesh_map.bounds()
    tolerance = 1e-9 * max(float(np.linalg.norm(high - low)), 1e-9)
    while len(active):
        counts = starts[active + 1] - starts[active]
        index = np.repeat(starts[active] - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) + np.arange(counts.sum())
        band = np.unique(incident[index])
        tri = faces[band]
        targets, new_times = [], []
        for k in range(3):
            c, a, b = tri[:, k], tri[:, (k + 1) % 3], tri[:, (k + 2) % 3]
            update = ~blocked[c] & (c != source)
            c, a, b = c[update], a[update], b[update]
            targets.append(c)
            new_times.append(triangle_updates(vertices[c], vertices[a], vertices[b], times[a], times[b], slowness[c]))
        targets = np.concatenate(targets)
        new_times = np.concatenate(new_times)
        before = times.copy()
        np.minimum.at(times, targets, new_times)
        active = np.flatnonzero(times < before - tolerance)
    return times


CHUNK = 1 << 17


def neighbourhoods(vertices: np.ndarray, radius: float, max_neighbours: int) -> np.ndarray:
    """(N, K) indices of the vertices within ``radius`` (nearest first, the vertex itself first), N where none.

    """
    points = np.asarray(vertices, dtype=np.float64)
    tree = cKDTree(points)
    k = min(max_neighbours, len(points))
    out = np.empty((len(points), k), dtype=np.int64)
    for start in range(0, len(points), CHUNK):
        _, index = tree.query(points[start : start + CHUNK], k=k, distance_upper_bound=radius, workers=-1)
        out[start : start + CHUNK] = index.reshape(-1, k)
    return out


def _padded(values: np.ndarray, fill: float) -> np.ndarray:
    """``values`` with one more row of ``fill``: the KD-tree's "no neighbour" index N points there."""
    return np.concatenate([values, np.full((1,) + values.shape[1:], fill, dtype=values.dtype)])


def roughness(normals: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Mean of 1 - |n_v . n_u| over each vertex's neighbourhood (``index`` from :func:`neighbourhoods`)."""
    normals = np.asarray(normals, dtype=np.float32)
    padded = _padded(normals, 0.0)
    out = np.empty(len(normals))
    for start in range(0, len(normals), CHUNK):
        block = slice(start, start + CHUNK)
        valid = index[block] < len(normals)
        dots = np.abs(np.einsum("nkc,nc->nk", padded[index[block]], normals[block]))
        out[block] = np.where(valid, 1.0 - dots, 0.0).sum(axis=1) / valid.sum(axis=1)
    return out


def height_difference(vertices: np.ndarray, index: np.ndarray) -> np.ndarray:
    """max z - min z over each vertex's neighbourhood (m)."""
    z = np.asarray(vertices, dtype=np.float64)[:, 2]
    return _padded(z, -np.inf)[index].max(axis=1) - _padded(z, np.inf)[index].min(axis=1)


def add_residuals(calibration, measured: np.ndarray, expected: np.ndarray, silhouettes: np.ndarray | None) -> int:
    """:func:`mabdi.noise_calibration_kernels.add_residuals_kernel` on ``calibration``'s rings
    (:class:`mabdi.noise_calibration.NoiseCalibration`), by a stable sort of the counted residuals by depth bin."""
    s = calibration.stride
    d = measured[::s, ::s]
    e = expected[::s, ::s]
    use = np.isfinite(d) & np.isfinite(e)
    if silhouettes is not None:
        use &= ~silhouettes[::s, ::s]
    d, e = d[use].astype(np.float64), e[use].astype(np.float64)
    residual = np.abs(d - e)
    keep = residual <= np.maximum(calibration.gate_k * calibration.sigma(e), calibration.min_gate)
    z, residual = e[keep], residual[keep]
    which = np.searchsorted(calibration.edges, z, side="right") - 1
    inside = (which >= 0) & (which < len(calibration._added))
    which, residual = which[inside], residual[inside]
    order = np.argsort(which, kind="stable")
    which, residual = which[order], residual[order]
    bins, starts, counts = np.unique(which, return_index=True, return_counts=True)
    for b, start, count in zip(bins, starts, counts, strict=True):
        values = residual[start : start + count][-calibration.samples_per_bin :]
        slots = (calibration._added[b] + np.arange(len(values))) % calibration.samples_per_bin
        calibration._residuals[b, slots] = values
        calibration._added[b] += len(values)
    return int(len(residual))
