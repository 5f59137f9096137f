r"""Compiled distances of contact pairs, without gradients: which pairs a broad phase found lie within reach.

``pair_distances`` gives the unsigned distance of each vertex-triangle and edge-edge pair, the formulas of
:func:`~latentsim.physics.primitives.point_triangle_distance` and
:func:`~latentsim.physics.primitives.segment_segment_distance` (their regions, their parallel test) pair by pair
instead of as array programs; ``self_pairs`` finds a surface's pairs with itself by them (a uniform grid, then
the boxes, then the distances) and ``grid_within`` a mesh collider's pairs (a surface's primitive against the mesh's
face, edge or vertex) by a grid over the static mesh (``MeshGrid``).  They select pairs,
they do not measure them: self-contact and the mesh barrier keep the pairs nearer than their reach by these, with a
slack (``SLACK``) far above the two implementations' rounding, and measure those again in PyTorch; a pair kept by the
slack alone lies beyond the reach there and its barrier, and that barrier's gradient, are exactly zero.  Within a
learned loss, the same test as arrays over every candidate of every state was a quarter of a self-contact scene's
epoch (``physics.self_contact``) and most of a mesh collider's (``physics.mesh_contact``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT
from latentsim.physics.primitives import PARALLEL

# a pair this much (relative to the reach) beyond the reach here may lie within it in PyTorch's arithmetic
SLACK = 1e-6


@njit(**INLINE)
def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


@njit(**INLINE)
def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@njit(**INLINE)
def _cross(u, v):
    return u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]


@njit(**INLINE)
def _point_segment(p, a, b):
    """|p - q|, q the point of [a, b] closest to p (a for a zero-length segment)."""
    e = _sub(b, a)
    ee = _dot(e, e)
    s = _dot(_sub(p, a), e) / ee if ee > 0 else 0.0
    s = min(max(s, 0.0), 1.0)
    d = (p[0] - a[0] - s * e[0], p[1] - a[1] - s * e[1], p[2] - a[2] - s * e[2])
    return math.sqrt(_dot(d, d))


@njit(**INLINE)
def _point_triangle(p, t0, t1, t2):
    e1, e2 = _sub(t1, t0), _sub(t2, t0)
    n = _cross(e1, e2)
    nn = _dot(n, n)
    if nn > PARALLEL * _dot(e1, e1) * _dot(e2, e2):
        inside = (_dot(_cross(_sub(t1, t0), _sub(p, t0)), n) >= 0 and _dot(_cross(_sub(t2, t1), _sub(p, t1)), n) >= 0
                  and _dot(_cross(_sub(t0, t2), _sub(p, t2)), n) >= 0)  # fmt: skip
        if inside:
            return abs(_dot(_sub(p, t0), n)) / math.sqrt(nn)
    return min(_point_segment(p, t0, t1), _point_segment(p, t1, t2), _point_segment(p, t2, t0))


@njit(**INLINE)
def _segment_segment(a0, a1, b0, b1):
    ea, eb, r = _sub(a1, a0), _sub(b1, b0), _sub(a0, b0)
    aa, bb, ab, ar, br = _dot(ea, ea), _dot(eb, eb), _dot(ea, eb), _dot(ea, r), _dot(eb, r)
    den = aa * bb - ab * ab
    s_num, t_num = ab * br - ar * bb, aa * br - ab * ar
    if den > PARALLEL * aa * bb and s_num >= 0 and s_num <= den and t_num >= 0 and t_num <= den:
        s, t = s_num / den, t_num / den
        d = (a0[0] + s * ea[0] - b0[0] - t * eb[0], a0[1] + s * ea[1] - b0[1] - t * eb[1], a0[2] + s * ea[2] - b0[2] - t * eb[2])
        return math.sqrt(_dot(d, d))
    return min(_point_segment(a0, b0, b1), _point_segment(a1, b0, b1), _point_segment(b0, a0, a1), _point_segment(b1, a0, a1))


@njit(**JIT)
def _pair_distances(x, state, ids, n_fv, out):
    for k in range(ids.shape[0]):
        y = x[state[k]]
        p0, p1, p2, p3 = y[ids[k, 0]], y[ids[k, 1]], y[ids[k, 2]], y[ids[k, 3]]
        out[k] = _point_triangle(p0, p1, p2, p3) if k < n_fv else _segment_segment(p0, p1, p2, p3)


#: the most cells of the grid an axis (a state far larger than its primitives, as a diverged prediction, shares the
#: outermost cells: clamping keeps neighbouring cells neighbours, so no pair is missed)
CELLS = 2**20


@njit(**INLINE)
def _cell(p, a, h, origin):
    f = (p - origin[a]) / h
    return 1 if not f >= 1 else (CELLS if f >= CELLS else int(f))


@njit(**JIT)
def _cells(lo, h, origin):
    """Each box's cell (P, 3) in a grid of spacing h from origin, by its lower corner (1 ... CELLS an axis)."""
    c = np.empty((lo.shape[0], 3), np.int64)
    for i in range(lo.shape[0]):
        for a in range(3):
            c[i, a] = _cell(lo[i, a], a, h, origin)
    return c


@njit(**JIT)
def _grid(cells, dims):
    """The boxes sorted by their cell's key (x-major), the sorted keys, for a range search of each cell."""
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="mergesort")
    return order, key[order]


@njit(**JIT)
def _self_pairs(x, faces, edges, reach, out):
    """The self-contact pairs of x within reach (module function :func:`self_pairs`); (how many, of them vertex-triangle),
    or (-1, 0) where ``out`` is too short."""
    n, F, E = x.shape[0], faces.shape[0], edges.shape[0]
    flo, fhi = np.empty((F, 3)), np.empty((F, 3))
    elo, ehi = np.empty((E, 3)), np.empty((E, 3))
    h = 0.0
    for i in range(F):
        for a in range(3):
            lo, hi = min(x[faces[i, 0], a], x[faces[i, 1], a], x[faces[i, 2], a]), max(x[faces[i, 0], a], x[faces[i, 1], a], x[faces[i, 2], a])
            flo[i, a], fhi[i, a] = lo, hi
            h = max(h, hi - lo)
    for i in range(E):
        for a in range(3):
            lo, hi = min(x[edges[i, 0], a], x[edges[i, 1], a]), max(x[edges[i, 0], a], x[edges[i, 1], a])
            elo[i, a], ehi[i, a] = lo, hi
            h = max(h, hi - lo)
    h = h + reach  # a box's extent plus the reach spans at most two cells an axis: its partners lie in the 27 about it
    if not h > 0:
        h = 1.0
    origin = np.empty(3)
    dims = np.full(3, CELLS + 2, np.int64)  # cells 1 ... CELLS, their neighbours 0 ... CELLS + 1
    for a in range(3):
        lo = x[0, a]
        for v in range(n):
            lo = min(lo, x[v, a])
        origin[a] = lo - h
    k = 0
    # every vertex against the triangles whose box comes within reach of it
    fc = _cells(flo, h, origin)
    order, keys = _grid(fc, dims)
    for v in range(n):
        cx, cy, cz = _cell(x[v, 0], 0, h, origin), _cell(x[v, 1], 1, h, origin), _cell(x[v, 2], 2, h, origin)
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                key0 = ((cx + dx) * dims[1] + cy + dy) * dims[2] + cz - 1
                q = np.searchsorted(keys, key0)
                while q < F and keys[q] <= key0 + 2:
                    t = order[q]
                    q += 1
                    if faces[t, 0] == v or faces[t, 1] == v or faces[t, 2] == v:
                        continue
                    if (x[v, 0] < flo[t, 0] - reach or x[v, 0] > fhi[t, 0] + reach or x[v, 1] < flo[t, 1] - reach
                            or x[v, 1] > fhi[t, 1] + reach or x[v, 2] < flo[t, 2] - reach or x[v, 2] > fhi[t, 2] + reach):  # fmt: skip
                        continue
                    if _point_triangle(x[v], x[faces[t, 0]], x[faces[t, 1]], x[faces[t, 2]]) < reach:
                        if k == out.shape[0]:
                            return -1, 0
                        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = v, faces[t, 0], faces[t, 1], faces[t, 2]
                        k += 1
    n_fv = k
    # every two edges that share no vertex and whose boxes come within reach of each other, each pair once
    ec = _cells(elo, h, origin)
    order, keys = _grid(ec, dims)
    for i in range(E):
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                key0 = ((ec[i, 0] + dx) * dims[1] + ec[i, 1] + dy) * dims[2] + ec[i, 2] - 1
                q = np.searchsorted(keys, key0)
                while q < E and keys[q] <= key0 + 2:
                    j = order[q]
                    q += 1
                    if j <= i:
                        continue
                    a0, a1, b0, b1 = edges[i, 0], edges[i, 1], edges[j, 0], edges[j, 1]
                    if a0 == b0 or a0 == b1 or a1 == b0 or a1 == b1:
                        continue
                    if (elo[i, 0] > ehi[j, 0] + reach or elo[j, 0] > ehi[i, 0] + reach or elo[i, 1] > ehi[j, 1] + reach
                            or elo[j, 1] > ehi[i, 1] + reach or elo[i, 2] > ehi[j, 2] + reach or elo[j, 2] > ehi[i, 2] + reach):  # fmt: skip
                        continue
                    if _segment_segment(x[a0], x[a1], x[b0], x[b1]) < reach:
                        if k == out.shape[0]:
                            return -1, 0
                        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = a0, a1, b0, b1
                        k += 1
    return k, n_fv


def self_pairs(x: np.ndarray, faces: np.ndarray, edges: np.ndarray, reach: float) -> tuple[np.ndarray, int]:
    """The pairs of a surface's own primitives in x (n, 3) that share no vertex and lie nearer than ``reach`` (with
    :func:`within`'s slack): every vertex and every triangle (F, 3) of ``faces``, every two ``edges`` (E, 2).  A
    uniform grid of the largest primitive's extent plus the reach, each primitive in the cell of its box's lower corner,
    its partners among the 27 cells about it; their boxes, then their distances, compiled.  Their vertices (P, 4), the
    vertex-triangle pairs first (vertex, three corners), then the edge pairs (two ends, two ends), and how many are
    vertex-triangle pairs."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    edges = np.ascontiguousarray(edges, dtype=np.int64).reshape(-1, 2)
    size = 8 * (len(x) + len(edges))
    while True:
        out = np.empty((size, 4), np.int64)
        k, n_fv = _self_pairs(x, faces, edges, reach * (1.0 + SLACK), out)
        if k >= 0:
            return out[:k].copy(), int(n_fv)
        size *= 4


#: the most cells of a static mesh's grid (its spacing grows until the mesh's box holds no more)
MESH_CELLS = 2**21


class MeshGrid:
    """A static mesh's primitives cores (M, q, 3) in a uniform grid over the mesh's box: each primitive listed in every
    cell its box overlaps (compressed rows: cell ``c``'s primitives ``ids[start[c]:start[c + 1]]``, ascending), the
    spacing ``h`` [m] a face's mean extent (the mesh's own scale, for its vertices and edges too) or larger.  For
    :func:`grid_within`."""

    def __init__(self, cores: np.ndarray, h: float):
        cores = np.ascontiguousarray(cores, dtype=np.float64)
        self.cores = cores
        self.lo, self.hi = cores.min(1), cores.max(1)
        self.origin = self.lo.min(0)
        span = self.hi.max(0) - self.origin
        h = float(h) if h > 0 else float(max(span.max(), 1.0)) / 64.0
        while np.prod(np.floor(span / h) + 1) > MESH_CELLS:
            h *= 1.25
        self.h = h
        self.dims = (np.floor(span / h) + 1).astype(np.int64)
        self.start, self.ids = _mesh_grid(self.lo, self.hi, self.origin, h, self.dims)


@njit(**INLINE)
def _mesh_cell(p, a, h, origin, dims):
    f = (p - origin[a]) / h
    return 0 if not f >= 0 else (dims[a] - 1 if f >= dims[a] - 1 else int(f))


@njit(**JIT)
def _mesh_grid(lo, hi, origin, h, dims):
    M = lo.shape[0]
    count = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for rep in range(2):  # count each cell's primitives, then fill them in, in ascending order
        if rep == 1:
            for c in range(1, count.shape[0]):
                count[c] += count[c - 1]
            ids = np.empty(count[-1], np.int64)
            fill = count[:-1].copy()
        for j in range(M):
            c0 = np.empty(3, np.int64)
            c1 = np.empty(3, np.int64)
            for a in range(3):
                c0[a], c1[a] = _mesh_cell(lo[j, a], a, h, origin, dims), _mesh_cell(hi[j, a], a, h, origin, dims)
            for cx in range(c0[0], c1[0] + 1):
                for cy in range(c0[1], c1[1] + 1):
                    for cz in range(c0[2], c1[2] + 1):
                        c = (cx * dims[1] + cy) * dims[2] + cz
                        if rep == 0:
                            count[c + 1] += 1
                        else:
                            ids[fill[c]] = j
                            fill[c] += 1
    return count, ids


@njit(**INLINE)
def _core_within(y, k, core, lo, hi, qlo, qhi, reach):
    """Whether a surface primitive y (k, 3), its box grown by the reach (qlo, qhi), lies within reach of a mesh core
    (4 - k, 3) whose box is (lo, hi): the boxes, then the distance of :func:`~latentsim.physics.primitives.core_distance`."""
    if hi[0] < qlo[0] or lo[0] > qhi[0] or hi[1] < qlo[1] or lo[1] > qhi[1] or hi[2] < qlo[2] or lo[2] > qhi[2]:
        return False
    if k == 1:
        return _point_triangle(y[0], core[0], core[1], core[2]) < reach
    if k == 2:
        return _segment_segment(core[0], core[1], y[0], y[1]) < reach
    return _point_triangle(core[0], y[0], y[1], y[2]) < reach


@njit(**JIT)
def _grid_within(ye, cores, lo, hi, origin, h, dims, start, ids, reach, out):
    """The pairs (i, j) within reach, i ascending and each i's j ascending (module function :func:`grid_within`);
    how many, or -1 where ``out`` is too short."""
    N, k, M = ye.shape[0], ye.shape[1], cores.shape[0]
    seen = np.full(M, -1, np.int64)
    found = np.empty(M, np.int64)
    qlo, qhi = np.empty(3), np.empty(3)
    c0, c1 = np.empty(3, np.int64), np.empty(3, np.int64)
    n = 0
    for i in range(N):
        y = ye[i]
        finite = True
        for a in range(3):
            qlo[a], qhi[a] = y[0, a], y[0, a]
            for v in range(k):
                qlo[a], qhi[a] = min(qlo[a], y[v, a]), max(qhi[a], y[v, a])
                finite = finite and np.isfinite(y[v, a])
            qlo[a] -= reach
            qhi[a] += reach
        if not finite:
            continue
        outside = False
        for a in range(3):
            if qhi[a] < origin[a] or qlo[a] > origin[a] + dims[a] * h:
                outside = True
            c0[a], c1[a] = _mesh_cell(qlo[a], a, h, origin, dims), _mesh_cell(qhi[a], a, h, origin, dims)
        if outside:
            continue
        m = 0
        if (c1[0] - c0[0] + 1) * (c1[1] - c0[1] + 1) * (c1[2] - c0[2] + 1) > M:  # a far-flung state: every primitive
            for j in range(M):
                if _core_within(y, k, cores[j], lo[j], hi[j], qlo, qhi, reach):
                    found[m] = j
                    m += 1
        else:  # the primitives of the cells the grown box overlaps, each once
            for cx in range(c0[0], c1[0] + 1):
                for cy in range(c0[1], c1[1] + 1):
                    for cz in range(c0[2], c1[2] + 1):
                        c = (cx * dims[1] + cy) * dims[2] + cz
                        for q in range(start[c], start[c + 1]):
                            j = ids[q]
                            if seen[j] != i:
                                seen[j] = i
                                if _core_within(y, k, cores[j], lo[j], hi[j], qlo, qhi, reach):
                                    found[m] = j
                                    m += 1
        if n + m > out.shape[0]:
            return -1
        found[:m].sort()
        for q in range(m):
            out[n, 0], out[n, 1] = i, found[q]
            n += 1
    return n


def grid_within(ye: np.ndarray, grid: MeshGrid, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (i, j) of a surface's primitive ye[i] (N, k, 3) and a static mesh's core ``grid.cores[j]`` that lie
    nearer than ``reach`` (with :func:`within`'s slack), the pairs of
    :func:`~latentsim.physics.primitives.core_distance` (a vertex against a face, k = 1; an edge against an edge, 2; a
    triangle against a vertex, 3): each primitive's box grown by the reach, the grid's cells it overlaps (every
    primitive where those outnumber them), their primitives' boxes, then the distances, compiled.  i ascending and each i's j
    ascending; a primitive with a coordinate not finite has none."""
    ye = np.ascontiguousarray(ye, dtype=np.float64)
    size = 4 * len(ye) + 64
    while True:
        out = np.empty((size, 2), np.int64)
        n = _grid_within(ye, grid.cores, grid.lo, grid.hi, grid.origin, grid.h, grid.dims, grid.start, grid.ids,
                         reach * (1.0 + SLACK), out)  # fmt: skip
        if n >= 0:
            return out[:n, 0].copy(), out[:n, 1].copy()
        size *= 4


def pair_distances(x: np.ndarray, state: np.ndarray, ids: np.ndarray, n_fv: int) -> np.ndarray:
    """The unsigned distance of each pair ids (P, 4) in the states x (S, n, 3), pair k's in x[state[k]]: the first
    ``n_fv`` vertex-triangle pairs (vertex, three corners), the rest edge pairs (two ends, two ends).  (P,) float64."""
    out = np.empty(len(ids))
    x = np.ascontiguousarray(x, dtype=np.float64)
    _pair_distances(x, np.ascontiguousarray(state, dtype=np.int64), np.ascontiguousarray(ids, dtype=np.int64), int(n_fv), out)
    return out


def within(x: np.ndarray, state: np.ndarray, ids: np.ndarray, n_fv: int, reach: float) -> np.ndarray:
    """Which pairs (:func:`pair_distances`) lie nearer than ``reach`` (P,) bool, with the slack ``SLACK`` reach: a
    pair nearer than the reach by any other float64 implementation of these distances is among them."""
    return pair_distances(x, state, ids, n_fv) < reach * (1.0 + SLACK)
