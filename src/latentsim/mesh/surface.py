"""Triangle surfaces: the boundary of a tet mesh, the closed-surface check, vertex welding.

A closed surface bounding a volume is what TetGen fills: every undirected edge
is used by exactly two triangles, once in each direction, and triangle
``(a, b, c)`` has its normal ``cross(b - a, c - a)`` pointing out of the volume.
:func:`surface_of` returns the boundary of positively oriented tets in that
orientation.
"""

from __future__ import annotations

import numpy as np

from latentsim.mesh.geometry import TET_FACES, remove_unreferenced, repeats_vertex
from latentsim.mesh.validation import MeshError, as_cells


def surface_of(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a tetrahedral mesh.

    A face is on the boundary when exactly one tet has it.  For positively
    oriented tets the returned triangles have outward normals.

    Parameters
    ----------
    tets : (e, 4) int

    Returns
    -------
    triangles : (t, 3) int64, in order of the owning tet (faces opposite
        vertex 0, 1, 2, 3 of each tet).

    Raises
    ------
    MeshError
        If a face is shared by more than two tets (non-conforming mesh).
    """
    tets = as_cells(tets, 4, "tet")
    faces = tets[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    c = counts[inverse]
    if (c > 2).any():
        f = int(np.flatnonzero(c > 2)[0])
        raise MeshError(
            f"face {key[f].tolist()} is shared by {int(c[f])} tets (tet {f // 4} among them): "
            "mesh is not conforming"
        )
    return faces[c == 1]


def check_closed_surface(triangles: np.ndarray, name: str = "surface") -> None:
    """Check that triangles form a closed, manifold, consistently oriented surface.

    Every undirected edge must be used by exactly two triangles, once in each
    direction.  Several closed components are allowed.  (Self-intersections
    and vertices where two sheets touch are not detected here; TetGen reports
    intersections itself.)

    Parameters
    ----------
    triangles : (t, 3) int

    Raises
    ------
    MeshError
        Naming a bad edge ``(a, b)`` and its triangles: a degenerate triangle,
        an edge in more than two triangles (non-manifold), an edge in only one
        triangle (open surface), or an edge used twice in the same direction
        (inconsistent orientation).  Non-manifold edges are reported before
        open ones, open before orientation problems.
    """
    tri = as_cells(triangles, 3, f"{name}: triangle")
    if len(tri) == 0:
        raise MeshError(f"{name}: no triangles")
    degenerate = np.flatnonzero(repeats_vertex(tri))
    if degenerate.size:
        t = int(degenerate[0])
        raise MeshError(f"{name}: triangle {t} {tri[t].tolist()} repeats a vertex")
    directed = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    owner = np.repeat(np.arange(len(tri)), 3)
    key = np.sort(directed, axis=1)
    forward = np.where(directed[:, 0] < directed[:, 1], 1, -1)
    uniq, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()

    def describe(edge_ids: np.ndarray, problem: str) -> str:
        e = int(edge_ids[0])
        a, b = uniq[e].tolist()
        more = f" ({edge_ids.size - 1} more such edges)" if edge_ids.size > 1 else ""
        return f"{name}: edge ({a}, {b}) {problem} triangles {owner[inverse == e].tolist()}{more}"

    nonmanifold = np.flatnonzero(counts > 2)
    if nonmanifold.size:
        raise MeshError(describe(nonmanifold, "is non-manifold, shared by"))
    boundary = np.flatnonzero(counts == 1)
    if boundary.size:
        raise MeshError(describe(boundary, "is open (boundary), used only by"))
    direction_sum = np.bincount(inverse, weights=forward, minlength=len(uniq))
    flipped = np.flatnonzero(direction_sum != 0)
    if flipped.size:
        raise MeshError(describe(flipped, "has inconsistent orientation, same direction in"))


def _weld_representatives(vertices: np.ndarray, tol: float) -> np.ndarray:
    """(n,) int: for each vertex the smallest index of its cluster of vertices within ``tol``.

    Union-find over the pairs closer than ``tol`` (clusters are chained:
    a - b and b - c close put a, b, c together).
    """
    # scipy.spatial is slow to import and only needed when a surface is decimated
    from scipy.spatial import cKDTree

    rep = np.arange(len(vertices))
    for i, j in sorted(cKDTree(vertices).query_pairs(tol)):
        ri, rj = rep[i], rep[j]
        while rep[ri] != ri:
            ri = rep[ri]
        while rep[rj] != rj:
            rj = rep[rj]
        rep[max(ri, rj)] = min(ri, rj)
    for i in range(len(rep)):  # path compression
        r = i
        while rep[r] != r:
            r = rep[r]
        rep[i] = r
    return rep


def weld(vertices: np.ndarray, triangles: np.ndarray, tol: float):
    """Merge vertices closer than ``tol`` and drop the triangles that collapse.

    Quadric decimation leaves needle triangles between (almost) coincident
    vertices; TetGen turns those into zero-volume slivers.

    Parameters
    ----------
    vertices : (n, 3) float
    triangles : (t, 3) int
    tol : float, distance below which vertices merge

    Returns
    -------
    vertices : (m, 3), the kept vertices (each cluster keeps its first).
    triangles : (s, 3) int64, renumbered, without collapsed or doubled faces.
    """
    F = _weld_representatives(vertices, tol)[triangles]
    F = F[~repeats_vertex(F)]
    # two needles sharing an edge collapse into the same face twice with opposite orientation
    key = np.sort(F, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    F = F[np.sort(first[counts == 1])]
    V, F, _ = remove_unreferenced(vertices, F)
    return V, F
