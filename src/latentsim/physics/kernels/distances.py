r"""Compiled distances of contact pairs, without gradients: which pairs a broad phase found lie within reach.

``pair_distances`` gives the unsigned distance of each vertex-triangle and edge-edge pair, the formulas of
:func:`~latentsim.physics.primitives.point_triangle_distance` and
:func:`~latentsim.physics.primitives.segment_segment_distance` (their regions, their parallel test) pair by pair
instead of as array programs; ``near_pairs`` selects a self-contact broad phase's candidates by them and
``core_within`` a mesh collider's (a surface's primitive against the mesh's face, edge or vertex).  They select pairs,
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


@njit(**JIT)
def _select(x, faces, edges, f, v, a, b, reach, out):
    k = 0
    for i in range(f.shape[0]):
        p, t = v[i], faces[f[i]]
        if p != t[0] and p != t[1] and p != t[2] and _point_triangle(x[p], x[t[0]], x[t[1]], x[t[2]]) < reach:
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = p, t[0], t[1], t[2]
            k += 1
    n_fv = k
    for i in range(a.shape[0]):
        ea, eb = edges[a[i]], edges[b[i]]
        if ea[0] != eb[0] and ea[0] != eb[1] and ea[1] != eb[0] and ea[1] != eb[1]:
            if _segment_segment(x[ea[0]], x[ea[1]], x[eb[0]], x[eb[1]]) < reach:
                out[k, 0], out[k, 1], out[k, 2], out[k, 3] = ea[0], ea[1], eb[0], eb[1]
                k += 1
    return k, n_fv


def near_pairs(x: np.ndarray, faces: np.ndarray, edges: np.ndarray, fv: tuple, ee: tuple, reach: float) -> tuple[np.ndarray, int]:
    """Of a broad phase's candidates in x (n, 3), the vertex-triangle pairs fv = (triangles, vertices) and the edge pairs
    ee = (edges, edges), as rows of ``faces`` (T, 3) and ``edges`` (E, 2), those that share no vertex and lie nearer
    than ``reach`` (with :func:`within`'s slack): their vertices (P, 4), the vertex-triangle pairs first (vertex, three
    corners), then the edge pairs (two ends, two ends), and how many are vertex-triangle pairs."""
    f, v, a, b = (np.ascontiguousarray(i, dtype=np.int64) for i in (*fv, *ee))
    out = np.empty((len(f) + len(a), 4), np.int64)
    k, n_fv = _select(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3),
                      np.ascontiguousarray(edges, dtype=np.int64), f, v, a, b, reach * (1.0 + SLACK), out)  # fmt: skip
    return out[:k], int(n_fv)


@njit(**JIT)
def _core_within(ye, cores, i, j, reach, keep):
    k = ye.shape[1]
    for q in range(i.shape[0]):
        y, c = ye[i[q]], cores[j[q]]
        if k == 1:
            d = _point_triangle(y[0], c[0], c[1], c[2])
        elif k == 2:
            d = _segment_segment(c[0], c[1], y[0], y[1])
        else:
            d = _point_triangle(c[0], y[0], y[1], y[2])
        keep[q] = d < reach


def core_within(ye: np.ndarray, cores: np.ndarray, i: np.ndarray, j: np.ndarray, reach: float) -> np.ndarray:
    """Which pairs (i, j) of a surface's primitive ye[i] (N, k, 3) and a static mesh's core cores[j] (M, 4 - k, 3) lie
    nearer than ``reach`` (with :func:`within`'s slack): a vertex against a face (k = 1), an edge against an edge (2),
    a triangle against a vertex (3), the pairs of :func:`~latentsim.physics.primitives.core_distance`.  (P,) bool."""
    keep = np.empty(len(i), np.bool_)
    _core_within(np.ascontiguousarray(ye, dtype=np.float64), np.ascontiguousarray(cores, dtype=np.float64),
                 np.ascontiguousarray(i, dtype=np.int64), np.ascontiguousarray(j, dtype=np.int64), reach * (1.0 + SLACK), keep)  # fmt: skip
    return keep


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
