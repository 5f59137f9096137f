"""Geometric measures and bookkeeping of vertex/cell arrays (NumPy).

* signed tet volume ``V = det[b - a, c - a, d - a] / 6 = dot(cross(b - a, c - a), d - a) / 6``,
  positive for a positively oriented tet (the package's convention);
* triangle area ``|cross(b - a, c - a)| / 2``;
* enclosed volume of a closed outward-oriented surface by the divergence theorem,
  ``sum dot(a, cross(b, c)) / 6``;
* reorienting tets (swapping their last two vertices), dropping unreferenced vertices.

(:func:`latentsim.physics.tets.tet_volumes` is the same signed volume in PyTorch,
for the differentiable energies.)
"""

from __future__ import annotations

import numpy as np

#: Faces of a tet (a, b, c, d) opposite vertex 0, 1, 2, 3, ordered so that their
#: normals point out of a positively oriented tet.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def tet_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (e,) of tets (e, 4): ``det[b-a, c-a, d-a] / 6``."""
    p = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets)
    a, b, c, d = (p[t[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def triangle_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Areas (t,) of triangles (t, 3)."""
    p = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    a, b, c = (p[t[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def enclosed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed, outward-oriented surface (divergence theorem).

    Sum over triangles of ``dot(a, cross(b, c)) / 6``; positive for outward
    normals.  Centred on the vertex mean to limit round-off.
    """
    p = np.asarray(vertices, dtype=np.float64)
    p = p - p.mean(axis=0)
    t = np.asarray(triangles)
    a, b, c = (p[t[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def repeats_vertex(triangles: np.ndarray) -> np.ndarray:
    """(t,) bool: the triangles (t, 3) that name one vertex twice (degenerate by topology)."""
    f = np.asarray(triangles)
    return (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])


def reorient(tets: np.ndarray, flip: np.ndarray) -> np.ndarray:
    """Copy of ``tets`` (e, 4) with the rows where ``flip`` (e,) bool is set turned inside out.

    Swapping the last two vertices changes the sign of the volume and keeps
    the faces; it is how every reader and generator makes tets positive.
    """
    out = np.array(tets, copy=True)
    out[flip] = out[flip][:, [0, 1, 3, 2]]
    return out


def remove_unreferenced(vertices: np.ndarray, *cells: np.ndarray):
    """Drop vertices no cell references and renumber the cells.

    Parameters
    ----------
    vertices : (n, 3)
    *cells : (e, k) int arrays

    Returns
    -------
    vertices : (m, 3), then each cell array renumbered, then ``kept`` (m,) int64:
    the old index of every kept vertex.
    """
    vertices = np.asarray(vertices)
    used = np.zeros(len(vertices), dtype=bool)
    for c in cells:
        used[np.asarray(c).ravel()] = True
    kept = np.flatnonzero(used).astype(np.int64)
    new_index = np.full(len(vertices), -1, dtype=np.int64)
    new_index[kept] = np.arange(len(kept))
    return (vertices[kept], *(new_index[np.asarray(c)] for c in cells), kept)


def cells_around_vertices(cells: np.ndarray, n: int):
    """The cells around each vertex, as compressed rows.

    Parameters
    ----------
    cells : (e, k) int, e.g. triangles (k = 3) or tets (k = 4)
    n : int, the number of vertices

    Returns
    -------
    start : (n + 1,) int64; the cells around vertex ``v`` are
        ``ids[start[v]:start[v + 1]]``.
    ids : (e * k,) int64, cell indices.
    """
    cells = np.asarray(cells)
    flat = cells.ravel()
    order = np.argsort(flat, kind="stable")
    return np.searchsorted(flat[order], np.arange(n + 1)), order // cells.shape[1]
