"""Procedural meshes: rod bundles (hair), triangulated cloth grids, tetrahedralised boxes (beams).

* :func:`rod_bundle` and :func:`rod_stencils`: straight rods hanging from a grid
  or a ring of roots, with their edge (stretching) and vertex-triple (bending) stencils,
  the discrete elastic rods of Li et al. 2025's hair scenes;
* :func:`cloth_grid`: a rectangle of ``nx x ny`` cells, two triangles each
  (the Neural Modes square is 10 x 10);
* :func:`beam_tets`: a box of hexahedral cells split into 6 (Kuhn) or 5 tets,
  conforming and positively oriented.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from itertools import permutations

import numpy as np

from latentsim.mesh.geometry import reorient, tet_volumes
from latentsim.mesh.validation import (
    MeshError,
    finite_float,
    positive_int,
    unit_vector,
    vector3,
)

# ---------------------------------------------------------------------------
# Rods
# ---------------------------------------------------------------------------


def rod_stencils(n_rods: int, per_rod: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stencils of ``n_rods`` rods of ``per_rod`` contiguous vertices each (rod ``r`` owns
    ``r*per_rod .. r*per_rod + per_rod - 1``, its root first).

    Returns
    -------
    edges : (n_rods * (per_rod - 1), 2) int64, consecutive vertices, rod by rod.
    triples : (n_rods * (per_rod - 2), 3) int64, three consecutive vertices (bending).
    root_of : (n_rods * per_rod,) int64, the root vertex of each vertex's rod.
    """
    base = (np.arange(n_rods) * per_rod)[:, None]
    e = np.arange(per_rod - 1)
    edges = np.stack([base + e, base + e + 1], axis=-1).reshape(-1, 2)
    b = np.arange(per_rod - 2)
    triples = np.stack([base + b, base + b + 1, base + b + 2], axis=-1).reshape(-1, 3)
    root_of = np.repeat(base[:, 0], per_rod)
    return edges.astype(np.int64), triples.astype(np.int64), root_of.astype(np.int64)


def rod_bundle(
    n_rods: int,
    vertices_per_rod: int,
    length: float,
    spacing: float,
    direction: Sequence[float] = (0.0, -1.0, 0.0),
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    ring_radius: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight rods hanging from a grid or a ring of roots in the xz plane.

    Roots sit on a ``ceil(sqrt(n_rods))``-column grid with the given spacing,
    filled row by row (x fastest, then z), the full grid centred on ``origin``
    in the plane ``y = origin[1]``; or, with ``ring_radius``, evenly on the
    circle of that radius about ``origin`` in that plane (root ``r`` at the
    angle ``2 pi r / n_rods`` from +x towards +z; ``spacing`` is then unused):
    hair around a head.  Each rod runs ``length`` from its root along
    ``direction`` with uniformly spaced vertices.

    Parameters
    ----------
    n_rods : int >= 1
    vertices_per_rod : int >= 2
        ``m``; rod ``r`` owns vertices ``r*m .. r*m + m - 1`` and vertex
        ``r*m`` is its root.
    length, spacing : float > 0
    direction : (3,) array-like, normalised internally.
    origin : (3,) array-like, centre of the root grid or ring.
    ring_radius : float > 0 or None (a grid).

    Returns
    -------
    vertices : (n_rods * m, 3) float64
    edges : (n_rods * (m - 1), 2) int64, consecutive vertices of each rod,
        root first, rod by rod (those of :func:`rod_stencils`).
    roots : (n_rods,) int64, ``arange(n_rods) * m``.
    """
    n = positive_int(n_rods, "n_rods")
    m = positive_int(vertices_per_rod, "vertices_per_rod", 2)
    length = finite_float(length, "length", positive=True)
    spacing = finite_float(spacing, "spacing", positive=True)
    d = unit_vector(direction, "rod direction")
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    r = np.arange(n)
    roots_xyz = np.zeros((n, 3))
    if ring_radius is None:
        roots_xyz[:, 0] = (r % cols - (cols - 1) / 2.0) * spacing
        roots_xyz[:, 2] = (r // cols - (rows - 1) / 2.0) * spacing
    else:
        rho = finite_float(ring_radius, "ring_radius", positive=True)
        angle = 2.0 * np.pi * r / n
        roots_xyz[:, 0], roots_xyz[:, 2] = rho * np.cos(angle), rho * np.sin(angle)
    roots_xyz += vector3(origin, "rod origin")
    s = np.linspace(0.0, length, m)
    vertices = (roots_xyz[:, None, :] + s[None, :, None] * d[None, None, :]).reshape(-1, 3)
    edges = rod_stencils(n, m)[0]
    roots = (r * m).astype(np.int64)
    return vertices, edges, roots


# ---------------------------------------------------------------------------
# Cloth
# ---------------------------------------------------------------------------


def cloth_grid(
    nx: int, ny: int, width: float, height: float, plane: str = "xz"
) -> tuple[np.ndarray, np.ndarray]:
    """Regular triangulated rectangle (a cloth sheet), centred on the origin.

    ``nx`` x ``ny`` square cells, each split along the same diagonal into two
    triangles: ``(nx+1)(ny+1)`` vertices and ``2 nx ny`` triangles (10 x 10
    gives the 121 / 200 of the Neural Modes square).

    Parameters
    ----------
    nx, ny : int >= 1
        Cells along the first and second axis of ``plane``.
    width, height : float > 0
        Extent along the first and second axis of ``plane``.
    plane : {"xz", "xy"}
        ``"xz"``: horizontal sheet at y = 0, width along x, height along z,
        triangle normals +y.  ``"xy"``: vertical sheet at z = 0, width along
        x, height along y, normals +z.

    Returns
    -------
    vertices : ((nx+1)(ny+1), 3) float64; vertex ``j*(nx+1) + i`` is at
        column ``i`` (first axis), row ``j`` (second axis).
    triangles : (2 nx ny, 3) int64, all with the positive normal above.
    """
    nx = positive_int(nx, "nx")
    ny = positive_int(ny, "ny")
    width = finite_float(width, "width", positive=True)
    height = finite_float(height, "height", positive=True)
    if plane not in ("xz", "xy"):
        raise MeshError(f"cloth plane must be 'xz' or 'xy', got {plane!r}")
    u = np.linspace(-width / 2, width / 2, nx + 1)
    w = np.linspace(-height / 2, height / 2, ny + 1)
    uu, ww = np.meshgrid(u, w)  # (ny+1, nx+1), row j, column i
    vertices = np.zeros(((nx + 1) * (ny + 1), 3))
    ax_u = 0
    ax_w = 1 if plane == "xy" else 2
    vertices[:, ax_u] = uu.ravel()
    vertices[:, ax_w] = ww.ravel()
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    v00 = (j * (nx + 1) + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    # normal of (v00, v10, v11) is e_u x e_w: +z for xy, -y for xz
    if plane == "xy":
        tris = np.concatenate([np.column_stack([v00, v10, v11]), np.column_stack([v00, v11, v01])])
    else:
        tris = np.concatenate([np.column_stack([v00, v11, v10]), np.column_stack([v00, v01, v11])])
    return vertices, tris.astype(np.int64)


# ---------------------------------------------------------------------------
# Beams
# ---------------------------------------------------------------------------

# local corner c of a hexahedral cell = bx + 2 by + 4 bz, at offset (bx, by, bz)
_CUBE_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=np.int64)


def _box_lattice(nx, ny, nz, length, width, height) -> tuple[np.ndarray, np.ndarray]:
    """Grid nodes of the box: integer lattice (i, j, k) and positions, both ((nx+1)(ny+1)(nz+1), 3), i fastest."""
    gi, gj, gk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1),
                             indexing="ij")
    lattice = np.column_stack([gi.ravel("F"), gj.ravel("F"), gk.ravel("F")])  # i fastest
    vertices = np.column_stack([
        lattice[:, 0] * (length / nx),
        lattice[:, 1] * (width / ny) - width / 2,
        lattice[:, 2] * (height / nz) - height / 2,
    ]).astype(np.float64)
    # exact end points (no accumulated round-off)
    vertices[lattice[:, 0] == nx, 0] = length
    vertices[lattice[:, 1] == ny, 1] = width / 2
    vertices[lattice[:, 2] == nz, 2] = height / 2
    return lattice, vertices


def _kuhn_tets(cell_vertices: np.ndarray) -> np.ndarray:
    """6 tets per cell along its corner 0 - corner 7 diagonal: one per order of the axes.

    ``cell_vertices`` (cells, 8) are the global vertices of each cell's corners.
    """
    patterns = []
    for perm in permutations(range(3)):
        path, corner = [0], 0
        for axis in perm:
            corner |= 1 << axis
            path.append(corner)
        patterns.append(path)
    return np.concatenate([cell_vertices[:, p] for p in patterns])


def _five_tets(cell_vertices: np.ndarray, even_cell: np.ndarray) -> np.ndarray:
    """5 tets per cell: a central tet on the corners of even global parity, plus four corner tets.

    ``even_cell`` (cells,) bool: ``(i + j + k) % 2 == 0`` of the cell; the
    pattern alternates between neighbouring cells, so the split is conforming.
    """
    tets_list = []
    for cell_even in (True, False):
        sel = even_cell if cell_even else ~even_cell
        if not sel.any():
            continue
        # corners whose *global* parity is even form the central tet
        central = [c for c in range(8) if (_CUBE_CORNERS[c].sum() % 2 == 0) == cell_even]
        pats = [central] + [[c, c ^ 1, c ^ 2, c ^ 4] for c in range(8) if c not in central]
        tets_list.extend(cell_vertices[sel][:, p] for p in pats)
    return np.concatenate(tets_list)


def beam_tets(
    nx: int,
    ny: int,
    nz: int,
    length: float,
    width: float,
    height: float,
    tets_per_cell: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Box ``[0, length] x [-width/2, width/2] x [-height/2, height/2]`` of tets.

    The box is cut into ``nx x ny x nz`` hexahedral cells (along x, y, z).
    With ``tets_per_cell=6`` each cell gets the Kuhn/Freudenthal split along
    its (0,0,0)-(1,1,1) diagonal; with ``5`` each cell gets a central tet on
    the corners of even global parity ``(i+j+k) % 2 == 0`` plus four corner
    tets, the pattern alternating between neighbouring cells.  Both are
    conforming (every interior face is shared by exactly two tets) and every
    tet is positively oriented (orientation fixed on exact integer lattice
    coordinates).

    Parameters
    ----------
    nx, ny, nz : int >= 1
    length, width, height : float > 0
    tets_per_cell : {5, 6}

    Returns
    -------
    vertices : ((nx+1)(ny+1)(nz+1), 3) float64; vertex
        ``i + (nx+1) * (j + (ny+1) * k)`` is grid node ``(i, j, k)``.
    tets : (tets_per_cell * nx * ny * nz, 4) int64, positively oriented.
    """
    nx, ny, nz = (positive_int(v, name) for v, name in ((nx, "nx"), (ny, "ny"), (nz, "nz")))
    length = finite_float(length, "length", positive=True)
    width = finite_float(width, "width", positive=True)
    height = finite_float(height, "height", positive=True)
    if tets_per_cell not in (5, 6):
        raise MeshError(f"tets_per_cell must be 5 or 6, got {tets_per_cell!r}")
    lattice, vertices = _box_lattice(nx, ny, nz, length, width, height)
    ci, cj, ck = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    ci, cj, ck = ci.ravel("F"), cj.ravel("F"), ck.ravel("F")
    # global vertex index of each cell corner: (cells, 8)
    cv = ((ci[:, None] + _CUBE_CORNERS[None, :, 0])
          + (nx + 1) * ((cj[:, None] + _CUBE_CORNERS[None, :, 1])
                        + (ny + 1) * (ck[:, None] + _CUBE_CORNERS[None, :, 2])))
    if tets_per_cell == 6:
        tets = _kuhn_tets(cv)
    else:
        tets = _five_tets(cv, (ci + cj + ck) % 2 == 0)
    tets = tets.astype(np.int64)
    # orientation on the integer lattice: exact
    sign = np.sign(tet_volumes(lattice.astype(np.float64), tets))
    if (sign == 0).any():  # pragma: no cover - construction guarantees non-degenerate tets
        raise MeshError("beam_tets produced a degenerate tet")
    return vertices, reorient(tets, sign < 0)
