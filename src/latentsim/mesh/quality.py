"""Mesh quality checks: :func:`check_mesh` and the element measures it reports.

Per tet: signed volume, the six dihedral angles (180 deg minus the angle
between the outward normals of the two faces meeting at an edge) and the edge
lengths; per triangle: area and interior angles.  A tet counts as (near)
degenerate when ``|volume| <= tol * rms_edge**3`` and a triangle when it
repeats a vertex or ``area <= tol * mean(edge**2)``, i.e. scale-free shape
measures.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from latentsim.mesh.geometry import (
    TET_FACES,
    repeats_vertex,
    tet_volumes,
    triangle_areas,
)
from latentsim.mesh.validation import (
    MeshError,
    as_cells,
    as_vertices,
    nonfinite_problem,
    out_of_range,
)

logger = logging.getLogger(__name__)

# the edge shared by faces opposite vertices k and l of a tet; pairs (k, l)
_FACE_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


class _Problems(list):
    """The problems found so far; adding one raises instead when ``strict``."""

    def __init__(self, strict: bool):
        super().__init__()
        self.strict = strict

    def add(self, msg: str) -> None:
        if self.strict:
            raise MeshError(msg)
        logger.warning(msg)
        self.append(msg)


def dihedral_angles(x: np.ndarray) -> np.ndarray:
    """The six dihedral angles (e, 6) in degrees of tets with corners x (e, 4, 3)."""
    faces = x[:, TET_FACES]  # (e, 4, 3, 3)
    normals = np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0])
    nn = np.linalg.norm(normals, axis=2, keepdims=True)
    unit = normals / np.where(nn > 0, nn, 1.0)
    cos = np.einsum("eij,eij->ei", unit[:, _FACE_PAIRS[:, 0]], unit[:, _FACE_PAIRS[:, 1]])
    return 180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _tet_quality(p: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    """Dihedral angles (e, 6) in degrees and edge lengths: min, max, rms (e,) of tets (e, 4)."""
    x = p[tets]  # (e, 4, 3)
    dihedral = dihedral_angles(x)
    edges = x[:, [0, 0, 0, 1, 1, 2]] - x[:, [1, 2, 3, 2, 3, 3]]
    elen = np.linalg.norm(edges, axis=2)
    # circumradius: centre offset from x0 = (|a|^2 b x c + |b|^2 c x a + |c|^2 a x b) / (2 a.(b x c))
    a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    num = ((a * a).sum(1)[:, None] * np.cross(b, c) + (b * b).sum(1)[:, None] * np.cross(c, a)
           + (c * c).sum(1)[:, None] * np.cross(a, b))
    den = 2.0 * np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    with np.errstate(divide="ignore", invalid="ignore"):
        radius = np.where(den > 0, np.linalg.norm(num, axis=1) / den, np.inf)
        radius_edge = radius / elen.min(axis=1)
    return {"dihedral": dihedral, "edge_min": elen.min(axis=1), "edge_max": elen.max(axis=1),
            "edge_rms": np.sqrt((elen ** 2).mean(axis=1)), "radius_edge": radius_edge}


def tet_min_dihedral(p: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Each tet's smallest dihedral angle (e,) in degrees, of tets (e, 4) on vertices p (n, 3)."""
    return dihedral_angles(p[tets]).min(axis=1)


def _checked_cells(tets, triangles, n: int, name: str, problems: _Problems) -> dict:
    """{"tet": (e, 4), "triangle": (t, 3)} int64 of the given cells, rows out of range dropped."""
    cells = {}
    for label, arr, k in (("tet", tets, 4), ("triangle", triangles, 3)):
        if arr is None:
            continue
        a = as_cells(arr, k, f"{name}: {label}")
        bad, problem = out_of_range(a, n, f"{name}: {label}")
        if problem:
            problems.add(problem)
            a = a[np.setdiff1d(np.arange(len(a)), bad)]
        cells[label] = a
    return cells


def _count_unreferenced(cells: dict, n: int, name: str, unreferenced: str,
                        problems: _Problems) -> int:
    """Number of vertices no cell uses, logged or a problem as ``unreferenced`` says."""
    if not cells:
        return 0
    used = np.zeros(n, dtype=bool)
    for a in cells.values():
        used[a.ravel()] = True
    unref = np.flatnonzero(~used)
    if unref.size and unreferenced != "ignore":
        msg = f"{name}: {unref.size} unreferenced vertices (first: {unref[:5].tolist()})"
        if unreferenced == "error":
            problems.add(msg)
        else:
            logger.warning(msg)
    return int(unref.size)


def _tet_stats(p: np.ndarray, t: np.ndarray, finite: np.ndarray, degenerate_tol: float,
               min_dihedral_deg: float | None, name: str, problems: _Problems) -> dict[str, Any]:
    """Inverted, (near) zero-volume and sliver tets, volumes, dihedral angles, edge ratios."""
    good = finite[t].all(axis=1)
    vol = np.full(len(t), np.nan)
    vol[good] = tet_volumes(p, t[good])
    q = _tet_quality(p, t[good]) if good.any() else None
    inverted = np.flatnonzero(vol < 0)
    scale = np.full(len(t), np.nan)
    if q is not None:
        scale[good] = q["edge_rms"] ** 3
    degenerate = np.flatnonzero(np.abs(vol) <= degenerate_tol * scale)
    degenerate = np.setdiff1d(degenerate, inverted)
    stats: dict[str, Any] = {"n_inverted": int(inverted.size),
                             "n_degenerate_tets": int(degenerate.size)}
    if inverted.size:
        i = int(inverted[0])
        problems.add(f"{name}: tet {i} {t[i].tolist()} is inverted, volume {vol[i]:.6g} "
                     f"({inverted.size} inverted tets)")
    if degenerate.size:
        i = int(degenerate[0])
        problems.add(f"{name}: tet {i} {t[i].tolist()} has (near) zero volume {vol[i]:.6g} "
                     f"({degenerate.size} such tets)")
    if good.any():
        vg = vol[good]
        smallest = np.nanmin(q["dihedral"], axis=1)  # (e_good,) each tet's smallest angle
        absv = np.abs(vg)
        stats.update(volume_total=float(vg.sum()), volume_min=float(vg.min()),
                     volume_max=float(vg.max()),
                     volume_ratio=float(absv.max() / absv.min()) if absv.min() > 0
                     else float("inf"),
                     dihedral_min_deg=float(np.nanmin(q["dihedral"])),
                     dihedral_median_deg=float(np.nanmedian(smallest)),
                     dihedral_max_deg=float(np.nanmax(q["dihedral"])),
                     radius_edge_max=float(np.nanmax(q["radius_edge"])))
        if min_dihedral_deg is not None:
            below = np.flatnonzero(smallest < min_dihedral_deg)
            stats["n_below_min_dihedral"] = int(below.size)
            if below.size:
                w = int(below[np.argmin(smallest[below])])
                i = int(np.flatnonzero(good)[w])
                problems.add(
                    f"{name}: tet {i} {t[i].tolist()} has a dihedral angle of "
                    f"{smallest[w]:.4g} degrees, below the bound of {min_dihedral_deg:g} "
                    f"({below.size} tets below it; mesh.quality.gate_min_dihedral_deg)")
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = q["edge_max"] / q["edge_min"]
        stats["edge_ratio_max"] = float(np.nanmax(ratio)) if np.isfinite(ratio).any() \
            else float("inf")
    return stats


def _triangle_stats(p: np.ndarray, f: np.ndarray, finite: np.ndarray, degenerate_tol: float,
                    name: str, problems: _Problems) -> dict[str, Any]:
    """Degenerate triangles, areas and the smallest interior angle."""
    good = finite[f].all(axis=1)
    area = np.full(len(f), np.nan)
    area[good] = triangle_areas(p, f[good])
    x = p[f[good]]
    e = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 1], x[:, 0] - x[:, 2]], axis=1)
    elen = np.linalg.norm(e, axis=2)
    scale = np.full(len(f), np.nan)
    scale[good] = (elen ** 2).mean(axis=1)
    degenerate = np.flatnonzero(repeats_vertex(f) | (area <= degenerate_tol * scale))
    stats: dict[str, Any] = {"n_degenerate_triangles": int(degenerate.size)}
    if degenerate.size:
        i = int(degenerate[0])
        problems.add(f"{name}: triangle {i} {f[i].tolist()} is degenerate, area {area[i]:.6g} "
                     f"({degenerate.size} degenerate triangles)")
    if good.any():
        ag = area[good]
        stats.update(area_total=float(ag.sum()), area_min=float(ag.min()),
                     area_max=float(ag.max()))
        # interior angle at each corner: between the two edges leaving it
        with np.errstate(divide="ignore", invalid="ignore"):
            cosang = np.stack([
                np.einsum("ij,ij->i", -e[:, 2], e[:, 0]),
                np.einsum("ij,ij->i", -e[:, 0], e[:, 1]),
                np.einsum("ij,ij->i", -e[:, 1], e[:, 2]),
            ], axis=1) / (elen[:, [2, 0, 1]] * elen)
        ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
        stats["angle_min_deg"] = float(np.nanmin(ang)) if np.isfinite(ang).any() else 0.0
    return stats


def check_mesh(
    vertices: np.ndarray,
    tets: np.ndarray | None = None,
    triangles: np.ndarray | None = None,
    name: str = "mesh",
    *,
    unreferenced: str = "warn",
    degenerate_tol: float = 1e-10,
    min_dihedral_deg: float | None = None,
    strict: bool = True,
) -> dict[str, Any]:
    """Check a mesh and return quality statistics for logging.

    Checks, in order: array shapes, NaN/inf coordinates, indices in range,
    unreferenced vertices (``unreferenced="warn"``: logged as a warning;
    ``"error"``: a problem; ``"ignore"``), inverted tets (negative volume),
    zero-volume tets (``volume <= degenerate_tol * rms_edge**3``, i.e. a shape
    measure ~1e-9 of a regular tet's), degenerate triangles (repeated vertex
    or ``area <= degenerate_tol * rms_edge**2``), and, when ``min_dihedral_deg``
    is given, tets with a dihedral angle below it (slivers; the message names
    the worst one).  Every message names the mesh
    and the first bad vertex/element index (and its volume or area) and how
    many there are.

    Parameters
    ----------
    vertices : (n, 3)
    tets : (e, 4) int, optional
    triangles : (t, 3) int, optional
    name : str, used in messages
    unreferenced : "warn" | "error" | "ignore"
    degenerate_tol : float
    min_dihedral_deg : float, optional
        The quality gate [degrees]: the smallest dihedral angle a tet may have.
    strict : bool
        Raise :class:`MeshError` on the first problem (default).  If False,
        problems are collected in ``stats["problems"]`` and statistics are
        computed for what can be computed.

    Returns
    -------
    dict with plain Python numbers: ``n_vertices``, ``n_tets``,
    ``n_triangles``, ``n_unreferenced``, ``bbox_min``, ``bbox_max``; for tets
    ``volume_total``, ``volume_min``, ``volume_max``, ``n_inverted``,
    ``n_degenerate_tets``, ``dihedral_min_deg``, ``dihedral_median_deg`` (the
    median over tets of each tet's smallest dihedral angle),
    ``dihedral_max_deg``, ``edge_ratio_max`` (longest / shortest edge of a
    tet), ``radius_edge_max`` (circumradius / shortest edge; 0.612 for a
    regular tet), ``volume_ratio`` (largest / smallest tet volume), and with
    a gate ``n_below_min_dihedral``; for triangles
    ``area_total``, ``area_min``, ``area_max``, ``n_degenerate_triangles``,
    ``angle_min_deg``; and ``problems`` (list of str, empty when all is well).
    """
    if unreferenced not in ("warn", "error", "ignore"):
        raise MeshError(f"unreferenced must be 'warn', 'error' or 'ignore', got {unreferenced!r}")
    problems = _Problems(strict)
    p = as_vertices(vertices, f"{name}: vertices")
    n = len(p)
    stats: dict[str, Any] = {"name": name, "n_vertices": n,
                             "n_tets": 0 if tets is None else int(len(tets)),
                             "n_triangles": 0 if triangles is None else int(len(triangles))}
    finite = np.isfinite(p).all(axis=1)
    nonfinite = nonfinite_problem(p, name)
    if nonfinite:
        problems.add(nonfinite)
    if finite.any():
        stats["bbox_min"] = p[finite].min(axis=0).tolist()
        stats["bbox_max"] = p[finite].max(axis=0).tolist()
    cells = _checked_cells(tets, triangles, n, name, problems)
    stats["n_unreferenced"] = _count_unreferenced(cells, n, name, unreferenced, problems)
    if len(cells.get("tet", ())):
        stats.update(_tet_stats(p, cells["tet"], finite, degenerate_tol, min_dihedral_deg, name,
                                problems))
    if len(cells.get("triangle", ())):
        stats.update(_triangle_stats(p, cells["triangle"], finite, degenerate_tol, name,
                                     problems))
    stats["problems"] = list(problems)
    return stats
