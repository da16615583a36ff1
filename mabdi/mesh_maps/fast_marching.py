"""The fast-marching method on a triangle mesh, one vertex at a time from a heap (compiled with numba).

Sethian's fast marching: vertices are *known* (their arrival time is final),
*trial* (a tentative time, in a binary heap) or *far*. The trial vertex with
the smallest time becomes known, and each triangle around it updates its
other corners from their known neighbours with the first-order triangle
update (:func:`_update`, the one copy: the numpy fast iterative solver the
tests compare against calls it too, through :func:`triangle_updates`; non-causal
updates, as in obtuse triangles, fall back to the edge updates). The heap allows stale entries (a vertex pushed
again with a smaller time; the old entry is skipped when popped).

The loop is sequential by nature, so it is compiled with numba (compiled on
the first call, cached on disk after; its cost on a million vertices:
docs/benchmarks.md, section "Mesh maps"). The vectorised fast iterative
solver in numpy, which gives the same times much more slowly, is kept with
the tests as the reference (tests/reference_kernels.py).
"""

from __future__ import annotations

import numpy as np

from numba import njit


def _update(c, a, b, ta, tb, s):
    """The first-order triangle update (the only copy; the rule is in :mod:`mabdi.mesh_maps.planning`'s docs): the time at
    corner ``c`` from corners ``a``, ``b`` (3-vectors) reached at ``ta``, ``tb`` (inf: not reached), slowness ``s``."""
    e1x, e1y, e1z = a[0] - c[0], a[1] - c[1], a[2] - c[2]
    e2x, e2y, e2z = b[0] - c[0], b[1] - c[1], b[2] - c[2]
    g11 = e1x * e1x + e1y * e1y + e1z * e1z
    g12 = e1x * e2x + e1y * e2y + e1z * e2z
    g22 = e2x * e2x + e2y * e2y + e2z * e2z
    edge = min(ta + s * np.sqrt(g11), tb + s * np.sqrt(g22))
    det = g11 * g22 - g12 * g12
    if not (np.isfinite(ta) and np.isfinite(tb)) or det <= 1e-20 * g11 * g22:
        return edge
    q11, q12, q22 = g22 / det, -g12 / det, g11 / det
    qa = q11 + 2.0 * q12 + q22
    qb = -2.0 * ((q11 + q12) * ta + (q12 + q22) * tb)
    qc = q11 * ta * ta + 2.0 * q12 * ta * tb + q22 * tb * tb - s * s
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        return edge
    t = (-qb + np.sqrt(disc)) / (2.0 * qa)
    da, db = ta - t, tb - t
    alpha = -(q11 * da + q12 * db)
    beta = -(q12 * da + q22 * db)
    if alpha >= 0.0 and beta >= 0.0 and t >= max(ta, tb):
        return min(t, edge)
    return edge


def _updates(c, a, b, ta, tb, s):
    """:func:`_update` for K triangles at once: (K, 3) corners, (K,) times and slowness; (K,) new times at ``c``."""
    out = np.empty(len(ta))
    for k in range(len(ta)):
        out[k] = _update(c[k], a[k], b[k], ta[k], tb[k], s[k])
    return out


def _march(vertices, faces, starts, incident, slowness, blocked, source):
    n = vertices.shape[0]
    times = np.full(n, np.inf)
    known = np.zeros(n, dtype=np.bool_)
    capacity = 8 * n + 16
    heap_t = np.empty(capacity)
    heap_v = np.empty(capacity, dtype=np.int64)
    size = 0
    times[source] = 0.0
    heap_t[0] = 0.0
    heap_v[0] = source
    size = 1
    while size > 0:
        t = heap_t[0]
        v = heap_v[0]
        size -= 1
        # move the last entry to the root and sift it down
        if size > 0:
            last_t, last_v = heap_t[size], heap_v[size]
            i = 0
            while True:
                child = 2 * i + 1
                if child >= size:
                    break
                if child + 1 < size and heap_t[child + 1] < heap_t[child]:
                    child += 1
                if heap_t[child] >= last_t:
                    break
                heap_t[i], heap_v[i] = heap_t[child], heap_v[child]
                i = child
            heap_t[i], heap_v[i] = last_t, last_v
        if known[v] or t > times[v]:
            continue  # a stale entry
        known[v] = True
        for k in range(starts[v], starts[v + 1]):
            f = incident[k]
            for corner in range(3):
                c = faces[f, corner]
                if known[c] or blocked[c]:
                    continue
                a = faces[f, (corner + 1) % 3]
                b = faces[f, (corner + 2) % 3]
                ta = times[a] if known[a] else np.inf
                tb = times[b] if known[b] else np.inf
                if not (np.isfinite(ta) or np.isfinite(tb)):
                    continue
                new = _update(vertices[c], vertices[a], vertices[b], ta, tb, slowness[c])
                if new < times[c]:
                    times[c] = new
                    if size == capacity:  # grow the heap
                        capacity *= 2
                        grown_t = np.empty(capacity)
                        grown_v = np.empty(capacity, dtype=np.int64)
                        grown_t[:size] = heap_t[:size]
                        grown_v[:size] = heap_v[:size]
                        heap_t, heap_v = grown_t, grown_v
                    i = size
                    size += 1
                    while i > 0:
                        parent = (i - 1) // 2
                        if heap_t[parent] <= new:
                            break
                        heap_t[i], heap_v[i] = heap_t[parent], heap_v[parent]
                        i = parent
                    heap_t[i], heap_v[i] = new, c
    return times


_update = njit(cache=True, fastmath=False)(_update)
_updates = njit(cache=True)(_updates)
_march = njit(cache=True)(_march)


def triangle_updates(c, a, b, t_a, t_b, s) -> np.ndarray:
    """First-order update of T at corners ``c`` from ``a``, ``b`` (all (K, 3) points, (K,) times and slowness):
    the update the heap uses, for the numpy fast iterative solver (the tests' reference)."""
    return _updates(
        np.ascontiguousarray(c, dtype=np.float64),
        np.ascontiguousarray(a, dtype=np.float64),
        np.ascontiguousarray(b, dtype=np.float64),
        np.ascontiguousarray(t_a, dtype=np.float64),
        np.ascontiguousarray(t_b, dtype=np.float64),
        np.ascontiguousarray(s, dtype=np.float64),
    )


def fast_marching(vertices, faces, starts, incident, slowness, blocked, source: int) -> np.ndarray:
    """Arrival times (N,) from vertex ``source``; ``starts``/``incident``: the faces around each vertex (CSR)."""
    return _march(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(starts, dtype=np.int64),
        np.ascontiguousarray(incident, dtype=np.int64),
        np.ascontiguousarray(slowness, dtype=np.float64),
        np.ascontiguousarray(blocked, dtype=np.bool_),
        int(source),
    )
