"""Isotropic remeshing before TetGen, the sliver moves after it, and the default quality gate.

The surface with slivers is a latitude-longitude sphere with many meridians and few
parallels: every triangle is a needle (smallest angles 6 to 10 degrees),
which TetGen, keeping the surface, has to fill with slivers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from latentsim import mesh as M
from latentsim.mesh.build import (
    GATE_MIN_DIHEDRAL_DEG,
    GATE_MIN_DIHEDRAL_DEG_FILE_TETS,
    quality_gate,
)
from latentsim.mesh.geometry import enclosed_volume
from latentsim.mesh.quality import tet_min_dihedral
from latentsim.mesh.remesh import COLLAPSE_BELOW, SPLIT_ABOVE, edge_length_for

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def _needle_sphere(meridians: int = 60, parallels: int = 6):
    """A unit latitude-longitude sphere (closed, outward): ``meridians * (parallels - 1) + 2``
    vertices, long thin triangles everywhere."""
    theta = np.pi * np.arange(1, parallels) / parallels  # polar angles of the parallels
    phi = 2 * np.pi * np.arange(meridians) / meridians
    ring = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                     np.repeat(np.cos(theta)[:, None], meridians, axis=1)], axis=2).reshape(-1, 3)
    V = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    top, bottom = 0, len(V) - 1

    def at(i, j):  # vertex of parallel i, meridian j
        return 1 + i * meridians + j % meridians

    F = []
    for j in range(meridians):
        F.append([top, at(0, j), at(0, j + 1)])
        F.append([bottom, at(parallels - 2, j + 1), at(parallels - 2, j)])
        for i in range(parallels - 2):
            F.append([at(i, j), at(i + 1, j), at(i + 1, j + 1)])
            F.append([at(i, j), at(i + 1, j + 1), at(i, j + 1)])
    return V, np.array(F, dtype=np.int64)


def _triangle_angles(V, F):
    x = V[F]
    ang = []
    for k in range(3):
        a, b = x[:, (k + 1) % 3] - x[:, k], x[:, (k + 2) % 3] - x[:, k]
        cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        ang.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return np.stack(ang, axis=1)


def test_needle_sphere_is_what_the_tests_need():
    V, F = _needle_sphere()
    M.check_closed_surface(F)
    assert enclosed_volume(V, F) > 0
    assert _triangle_angles(V, F).min() < 6.0


def test_remesh_gives_a_closed_surface_of_near_equilateral_triangles_on_the_input():
    V, F = _needle_sphere()
    L = edge_length_for(V, F, 300)
    V2, F2 = M.remesh_isotropic(V, F, L, name="needles")
    M.check_closed_surface(F2, name="remeshed")
    # Euler characteristic of a sphere: V - E + F = 2
    assert len(V2) - 3 * len(F2) // 2 + len(F2) == 2
    assert 0.8 * 300 <= len(V2) <= 1.2 * 300
    assert _triangle_angles(V2, F2).min() > 20.0
    edges = np.linalg.norm(V2[F2[:, [1, 2, 0]]] - V2[F2], axis=2).ravel()
    inside = (edges >= 0.9 * COLLAPSE_BELOW * L) & (edges <= SPLIT_ABOVE * L)
    assert inside.mean() > 0.95
    # volume kept; vertices on the input (the polyhedron lies within 1.5% of the unit sphere)
    assert enclosed_volume(V2, F2) == pytest.approx(enclosed_volume(V, F), rel=1e-4)
    r = np.linalg.norm(V2, axis=1)
    assert np.abs(r - 1).max() < 0.03


def test_remesh_rejects_an_open_surface_and_a_bad_length():
    V, F = _needle_sphere()
    with pytest.raises(M.MeshError, match=r"cap: edge \(\d+, \d+\) is open"):
        M.remesh_isotropic(V, F[1:], 0.2, name="cap")
    with pytest.raises(M.MeshError, match="needles: remeshing needs a positive edge length, got 0"):
        M.remesh_isotropic(V, F, 0.0, name="needles")


def test_fill_of_a_needle_surface_reaches_5_degrees_only_remeshed():
    V, F = _needle_sphere()
    target = 400
    before, tets_before = M.tetrahedralize_to(V, F, target, "needles", remesh=False)
    assert tet_min_dihedral(before, tets_before).min() < 5.0  # the slivers the remeshing removes
    nodes, tets = M.tetrahedralize_to(V, F, target, "needles")
    assert abs(len(nodes) - target) <= 0.1 * target
    angle = tet_min_dihedral(nodes, tets)
    assert angle.min() >= 5.0
    assert M.tet_volumes(nodes, tets).min() > 0
    surface = M.surface_of(tets)
    M.check_closed_surface(surface, name="filled")
    assert M.tet_volumes(nodes, tets).sum() == pytest.approx(enclosed_volume(V, F), rel=0.01)
    M.check_mesh(nodes, tets, name="needles", min_dihedral_deg=GATE_MIN_DIHEDRAL_DEG)


def test_improve_slivers_raises_the_smallest_angle_and_keeps_the_fixed_vertices():
    V, F = M.remesh_isotropic(*_needle_sphere(), 0.35)
    nodes, tets = M.tetrahedralize(V, F, target_vertices=150, quality=None)
    fixed = np.zeros(len(nodes), dtype=bool)
    fixed[M.surface_of(tets)] = True
    assert (~fixed).sum() > 10
    # pull an interior vertex onto the plane of a face of one of its tets: slivers around it
    v = int(np.flatnonzero(~fixed)[0])
    t = int(np.flatnonzero((tets == v).any(axis=1))[0])
    face = nodes[tets[t][tets[t] != v]]
    n = np.cross(face[1] - face[0], face[2] - face[0])
    n /= np.linalg.norm(n)
    bent = nodes.copy()
    bent[v] -= 0.97 * ((bent[v] - face[0]) @ n) * n
    assert M.tet_volumes(bent, tets).min() > 0
    before = tet_min_dihedral(bent, tets).min()
    assert before < 5.0
    out, moved = M.improve_slivers(bent, tets, fixed)
    assert moved > 0
    assert tet_min_dihedral(out, tets).min() > max(2 * before, 5.0)
    assert M.tet_volumes(out, tets).min() > 0
    np.testing.assert_array_equal(out[fixed], bent[fixed])


@pytest.mark.parametrize("cfg, gate", [
    ({"generator": "file", "file": "x.vtu", "target_vertices": 0}, GATE_MIN_DIHEDRAL_DEG_FILE_TETS),
    ({"generator": "file", "file": "x.obj", "target_vertices": 300}, GATE_MIN_DIHEDRAL_DEG),
    ({"generator": "beam_tets"}, GATE_MIN_DIHEDRAL_DEG),
    ({"generator": "file", "target_vertices": 0, "quality": {"gate_min_dihedral_deg": 2.0}}, 2.0),
    ({"generator": "file", "target_vertices": 300, "quality": {"gate_min_dihedral_deg": 0}}, 0.0),
])
def test_quality_gate_default_depends_on_who_made_the_tets(cfg, gate):
    assert quality_gate(cfg) == gate
    assert GATE_MIN_DIHEDRAL_DEG == 5.0 and math.isclose(GATE_MIN_DIHEDRAL_DEG_FILE_TETS, 0.01)
