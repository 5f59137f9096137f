"""Isotropic remeshing of a closed triangle surface to a target edge length.

:func:`remesh_isotropic` follows Botsch & Kobbelt 2004 ("A remeshing approach
to multiresolution modeling"): each iteration splits the edges longer than
``4/3 L``, collapses those shorter than ``4/5 L``, flips edges where that
brings the four vertices' valences closer to 6, moves every vertex
tangentially towards the centroid of its neighbours and projects it back onto
the input surface.  The result has near-equilateral triangles, which TetGen
can keep (``Y``) without being forced into slivers.

The topological operations are applied in batches: each round picks, greedily
from the most urgent edge, a set of edges whose neighbourhoods do not overlap,
so every operation is checked against the mesh it changes.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from latentsim.mesh.geometry import (
    cells_around_vertices,
    enclosed_volume,
    remove_unreferenced,
    triangle_areas,
)
from latentsim.mesh.surface import check_closed_surface
from latentsim.mesh.validation import MeshError, as_cells, as_vertices, require_finite

logger = logging.getLogger(__name__)

#: Botsch & Kobbelt's bounds on the edge length, as fractions of the target
SPLIT_ABOVE, COLLAPSE_BELOW = 4.0 / 3.0, 4.0 / 5.0


def _edge_table(F: np.ndarray, n: int):
    """Edges of a closed manifold surface and their two sides.

    Returns
    -------
    half : (k, 2, 2) int64, for each undirected edge its two half-edges
        ``(from, to)`` as the two triangles traverse it.
    faces : (k, 2) int64, the triangle of each half-edge.
    opposite : (k, 2) int64, the vertex opposite the edge in that triangle.
    """
    he = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    owner = np.repeat(np.arange(len(F)), 3)
    opp = F[:, [2, 0, 1]].ravel()
    key = np.minimum(he[:, 0], he[:, 1]) * n + np.maximum(he[:, 0], he[:, 1])
    order = np.argsort(key, kind="stable")
    ks = key[order]
    if len(ks) % 2 or (ks[0::2] != ks[1::2]).any():
        raise MeshError("remesh: the surface is no longer a closed manifold")
    pair = order.reshape(-1, 2)
    return he[pair], owner[pair], opp[pair]


def _normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted normals (t, 3) (twice the area long) of triangles (t, 3)."""
    x = V[F]
    return np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])


def _split_long(V: np.ndarray, F: np.ndarray, high: float):
    """One round of midpoint splits of edges longer than ``high``, no two in one triangle."""
    half, faces, opp = _edge_table(F, len(V))
    a, b = half[:, 0, 0], half[:, 0, 1]
    length = np.linalg.norm(V[a] - V[b], axis=1)
    cand = np.flatnonzero(length > high)
    if cand.size == 0:
        return V, F, 0
    used = np.zeros(len(F), dtype=bool)
    chosen = []
    for e in cand[np.argsort(-length[cand])]:
        f0, f1 = faces[e]
        if not (used[f0] or used[f1]):
            used[f0] = used[f1] = True
            chosen.append(e)
    chosen = np.asarray(chosen)
    m = len(V) + np.arange(len(chosen))
    V = np.vstack([V, 0.5 * (V[a[chosen]] + V[b[chosen]])])
    F = F.copy()
    new = []
    for side in (0, 1):
        s, t = half[chosen, side, 0], half[chosen, side, 1]
        o = opp[chosen, side]
        F[faces[chosen, side]] = np.stack([s, m, o], axis=1)
        new.append(np.stack([m, t, o], axis=1))
    return V, np.vstack([F] + new), len(chosen)


def _collapse_short(V: np.ndarray, F: np.ndarray, low: float, high: float):
    """One round of edge collapses (to the midpoint) of edges shorter than ``low``.

    A collapse is made only when the two ends share exactly the two opposite
    vertices (the link condition, which keeps the surface manifold), both ends
    have valence above 3, no edge of the result is longer than ``high`` and no
    triangle around it turns by more than 60 degrees or becomes degenerate.
    """
    n = len(V)
    half, faces, opp = _edge_table(F, n)
    a, b = half[:, 0, 0], half[:, 0, 1]
    length = np.linalg.norm(V[a] - V[b], axis=1)
    cand = np.flatnonzero(length < low)
    if cand.size == 0:
        return V, F, 0
    start, vf = cells_around_vertices(F, n)
    normals = _normals(V, F)
    locked = np.zeros(n, dtype=bool)
    remap = np.arange(n)
    V = V.copy()
    count = 0
    for e in cand[np.argsort(length[cand])]:
        i, j = int(a[e]), int(b[e])
        if locked[i] or locked[j]:
            continue
        around = np.concatenate([vf[start[i]:start[i + 1]], vf[start[j]:start[j + 1]]])
        ring = np.unique(F[around])
        if locked[ring].any():
            continue
        ni = np.setdiff1d(F[vf[start[i]:start[i + 1]]], [i])
        nj = np.setdiff1d(F[vf[start[j]:start[j + 1]]], [j])
        if len(ni) <= 3 or len(nj) <= 3:
            continue
        common = np.intersect1d(ni, nj)
        if len(common) != 2 or set(common.tolist()) != {int(opp[e, 0]), int(opp[e, 1])}:
            continue
        p = 0.5 * (V[i] + V[j])
        others = ring[(ring != i) & (ring != j)]
        if (np.linalg.norm(V[others] - p, axis=1) > high).any():
            continue
        kept = np.unique(around)
        kept = kept[~(np.isin(F[kept], [i, j]).sum(axis=1) == 2)]
        x = V[F[kept]]
        x[np.isin(F[kept], [i, j])] = p
        nn = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
        old = normals[kept]
        na, no = np.linalg.norm(nn, axis=1), np.linalg.norm(old, axis=1)
        if (np.einsum("ij,ij->i", nn, old) <= 0.5 * na * no).any() or (na <= 1e-6 * low ** 2).any():
            continue
        V[j] = p
        remap[i] = j
        locked[ring] = True
        count += 1
    if count == 0:
        return V, F, 0
    F = remap[F]
    F = F[~((F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0]))]
    V, F, _ = remove_unreferenced(V, F)
    return V, F, count


def _flip_valence(V: np.ndarray, F: np.ndarray):
    """One round of edge flips that bring the valences of the four vertices closer to 6.

    An edge ``(a, b)`` between triangles ``(a, b, c)`` and ``(b, a, d)``
    becomes ``(c, d)`` when that lowers ``sum |valence - 6|`` over a, b, c, d,
    ``c`` and ``d`` are not yet joined, and both new triangles face within 60
    degrees of the old pair's mean normal.
    """
    n = len(V)
    half, faces, opp = _edge_table(F, n)
    a, b = half[:, 0, 0], half[:, 0, 1]
    c, d = opp[:, 0], opp[:, 1]
    val = np.bincount(np.concatenate([a, b]), minlength=n)
    dev = lambda x: np.abs(x - 6)  # noqa: E731
    before = dev(val[a]) + dev(val[b]) + dev(val[c]) + dev(val[d])
    after = dev(val[a] - 1) + dev(val[b] - 1) + dev(val[c] + 1) + dev(val[d] + 1)
    cand = np.flatnonzero((after < before) & (val[a] > 3) & (val[b] > 3))
    if cand.size == 0:
        return F, 0
    edges = set((np.minimum(a, b) * n + np.maximum(a, b)).tolist())
    normals = _normals(V, F)
    locked = np.zeros(n, dtype=bool)
    F = F.copy()
    count = 0
    for e in cand[np.argsort(after[cand] - before[cand], kind="stable")]:
        i, j, k, m = int(a[e]), int(b[e]), int(c[e]), int(d[e])
        if locked[[i, j, k, m]].any() or min(k, m) * n + max(k, m) in edges:
            continue
        mean = normals[faces[e, 0]] / np.linalg.norm(normals[faces[e, 0]]) \
            + normals[faces[e, 1]] / np.linalg.norm(normals[faces[e, 1]])
        new = np.array([[k, i, m], [m, j, k]])
        nn = _normals(V, new)
        nl = np.linalg.norm(nn, axis=1)
        if (nl == 0).any() or (nn @ mean <= 0.5 * nl * np.linalg.norm(mean)).any():
            continue
        F[faces[e, 0]], F[faces[e, 1]] = new
        edges.add(min(k, m) * n + max(k, m))
        locked[[i, j, k, m]] = True
        count += 1
    return F, count


def _closest_on_triangles(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray):
    """Closest points (p, k, 3) on triangles ``A, B, C`` (p, k, 3) to points P (p, 1, 3)."""
    ab, ac = B - A, C - A
    n = np.cross(ab, ac)
    nn = np.einsum("...i,...i->...", n, n)
    nn = np.where(nn > 0, nn, 1.0)
    ap = P - A
    # barycentric coordinates of P's projection onto the triangle's plane
    v = np.einsum("...i,...i->...", np.cross(ap, ac), n) / nn
    w = np.einsum("...i,...i->...", np.cross(ab, ap), n) / nn
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)
    best = A + v[..., None] * ab + w[..., None] * ac
    dist = np.where(inside, 0.0, np.inf)
    for s, t in ((A, B), (B, C), (C, A)):
        st = t - s
        ll = np.einsum("...i,...i->...", st, st)
        u = np.clip(np.einsum("...i,...i->...", P - s, st) / np.where(ll > 0, ll, 1.0), 0, 1)
        q = s + u[..., None] * st
        dq = np.einsum("...i,...i->...", P - q, P - q)
        better = ~inside & (dq < dist)
        best = np.where(better[..., None], q, best)
        dist = np.where(better, dq, dist)
    dist = np.where(inside, np.einsum("...i,...i->...", P - best, P - best), dist)
    return best, dist


class _Projector:
    """Projection onto the input surface: the closest point among the ``k`` triangles
    whose centroids are nearest."""

    def __init__(self, V: np.ndarray, F: np.ndarray, k: int = 12):
        # scipy.spatial is slow to import and only needed when a surface is remeshed
        from scipy.spatial import cKDTree

        self.tri = V[F]
        self.k = min(k, len(F))
        self.tree = cKDTree(self.tri.mean(axis=1))

    def __call__(self, P: np.ndarray) -> np.ndarray:
        _, idx = self.tree.query(P, k=self.k)
        idx = idx.reshape(len(P), self.k)
        t = self.tri[idx]  # (p, k, 3, 3)
        q, d = _closest_on_triangles(P[:, None, :], t[:, :, 0], t[:, :, 1], t[:, :, 2])
        return q[np.arange(len(P)), np.argmin(d, axis=1)]


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals (n, 3) of a surface."""
    normals = _normals(V, F)
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], normals)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _relax(V: np.ndarray, F: np.ndarray, project: _Projector) -> np.ndarray:
    """Move each vertex tangentially to the area-weighted centroid of its neighbours, then
    project it back onto the input surface."""
    n = len(V)
    vn = _vertex_normals(V, F)
    # neighbour centroids weighted by the area of the triangles around each neighbour
    varea = np.bincount(F.ravel(), weights=np.repeat(triangle_areas(V, F), 3), minlength=n)
    half = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # each directed edge once (closed surface)
    w = varea[half[:, 1]]
    wsum = np.bincount(half[:, 0], weights=w, minlength=n)
    centroid = np.stack([np.bincount(half[:, 0], weights=w * V[half[:, 1], k], minlength=n)
                         for k in range(3)], axis=1) / wsum[:, None]
    move = centroid - V
    move -= np.einsum("ij,ij->i", move, vn)[:, None] * vn
    return project(V + move)


def edge_length_for(vertices: np.ndarray, triangles: np.ndarray, n_vertices: int) -> float:
    """The edge length of equilateral triangles covering the surface with ``n_vertices`` vertices.

    A closed surface of genus 0 with ``n`` vertices has about ``2 n`` triangles, each
    ``sqrt(3) / 4 L**2`` in area: ``L = sqrt(2 area / (sqrt(3) n))``.
    """
    area = float(triangle_areas(vertices, triangles).sum())
    return math.sqrt(2.0 * area / (math.sqrt(3.0) * max(int(n_vertices), 4)))


def remesh_isotropic(vertices: np.ndarray, triangles: np.ndarray, edge_length: float,
                     iterations: int = 8, name: str = "surface", keep_volume: bool = True):
    """Remesh a closed surface to near-equilateral triangles of about ``edge_length``.

    Parameters
    ----------
    vertices : (n, 3) float
    triangles : (t, 3) int, closed, manifold, outward oriented.
    edge_length : float, the target edge length L (edges end between 4/5 L and 4/3 L
        where the link condition and the normal checks allow).
    iterations : int, split / collapse / flip / relax rounds.
    keep_volume : bool, offset the result along its vertex normals by one distance
        (:func:`_restore_volume`) so that it encloses the input's volume.
    name : str, used in messages.

    Returns
    -------
    vertices : (m, 3) float64, on the input surface (up to the volume-restoring offset).
    triangles : (s, 3) int64, closed, manifold, oriented as the input.

    Raises
    ------
    MeshError
        The input is not a closed oriented manifold (naming an edge), the
        edge length is not positive, or the result is not closed (a bug).
    """
    V = as_vertices(vertices, f"{name}: vertices").astype(np.float64)
    F = as_cells(triangles, 3, f"{name}: triangle", len(V))
    require_finite(V, name)
    if not (edge_length > 0 and math.isfinite(edge_length)):
        raise MeshError(f"{name}: remeshing needs a positive edge length, got {edge_length}")
    check_closed_surface(F, name=name)
    V, F, _ = remove_unreferenced(V, F)
    project = _Projector(V, F)
    low, high = COLLAPSE_BELOW * edge_length, SPLIT_ABOVE * edge_length
    for it in range(iterations):
        splits = collapses = flips = 0
        for _ in range(20):
            V, F, k = _split_long(V, F, high)
            splits += k
            if k == 0:
                break
        for _ in range(20):
            V, F, k = _collapse_short(V, F, low, high)
            collapses += k
            if k == 0:
                break
        for _ in range(5):
            F, k = _flip_valence(V, F)
            flips += k
            if k == 0:
                break
        V = _relax(V, F, project)
        logger.debug("%s: remesh iteration %d: %d splits, %d collapses, %d flips, %d vertices",
                     name, it, splits, collapses, flips, len(V))
    check_closed_surface(F, name=f"{name} (remeshed)")
    if keep_volume:
        V = _restore_volume(V, F, enclosed_volume(vertices, triangles))
    return V, F


def _restore_volume(V: np.ndarray, F: np.ndarray, volume: float) -> np.ndarray:
    """Offset the vertices along their normals by one distance so the surface encloses ``volume``.

    Vertices on the input surface cut its convex parts with chords (and bridge
    its concave ones), which loses volume on a mostly convex body: the offset
    ``(volume - V) / area``, applied twice, wins it back.
    """
    for _ in range(2):
        area = float(triangle_areas(V, F).sum())
        V = V + ((volume - enclosed_volume(V, F)) / area) * _vertex_normals(V, F)
    return V


def volume_change(v0: np.ndarray, f0: np.ndarray, v1: np.ndarray, f1: np.ndarray) -> float:
    """Relative change of the enclosed volume from surface 0 to surface 1 (signed)."""
    vol0 = enclosed_volume(v0, f0)
    return float(enclosed_volume(v1, f1) / vol0 - 1.0)
