r"""Discrete elastic rods without twist: stretching and bending of hair.

Model (Bergou, Wardetzky, Robinson, Audoly & Grinspun 2008, "Discrete elastic
rods", ACM TOG 27(3), sections 4-6).  A rod is a polyline x_0 .. x_{m-1} with
edges e_i = x_{i+1} - x_i and rest edges ebar_i.  We model *isotropic,
naturally straight* rods (round hair): for an isotropic cross-section and a
straight rest shape the bending energy depends on the curvature binormal only
(not on the material frame), and with a free end (the hair tip) the
quasistatic twist relaxes to zero, so twist and material frames drop out:

stretching (per edge)
    E_s = 1/2 ks (|e| / |ebar| - 1)^2 |ebar|,          ks = Y pi r^2   [N]

bending (per interior vertex i, stencil (i-1, i, i+1))
    kappa_b = 2 e_{i-1} x e_i / (|ebar_{i-1}| |ebar_i| + e_{i-1} . e_i)
    E_b     = kb |kappa_b|^2 / lbar_i,  lbar_i = |ebar_{i-1}| + |ebar_i|,
    kb      = Y pi r^4 / 4 = E I   [N m^2].

|kappa_b| = 2 tan(phi/2) for the turning angle phi when the edges have their
rest lengths.  With the Voronoi length l_i = lbar_i / 2 and the pointwise
curvature |kappa_b| / l_i, E_b = 1/2 E I (|kappa_b| / l_i)^2 l_i: the
continuum density 1/2 E I kappa^2 integrated over the Voronoi cell of vertex
i.  A rod bent to a circular arc of radius R and length L therefore has
E_b -> E I L / (2 R^2) under refinement (first order: the end cells are
missing).

The twist-free energy depends on |kappa_b| only, which is the right model
(and rotation invariant) only for straight rest shapes: ``RodBend`` raises
``ValueError`` for a rest stencil that is not straight.

Newton derivatives.  Both terms have compiled per-stencil gradients and
exact or eigenvalue-clamped (Teran et al. 2005) Hessians (``kernels.rods``,
named by ``kernel_spec``), equal to the autograd oracle
``base.autograd_gradient_hessian`` (which the tests use):

* stretch: the spring Hessian w.r.t. e is
  K = ks/|ebar| [u u^T + (1 - |ebar|/|e|)(I - u u^T)], u = e/|e|, and the 6x6
  stencil Hessian [[K, -K], [-K, K]] has the eigenvalues 2 x those of K, so
  the exact clamp is 1 - |ebar|/|e| -> max(0, .) (compressed springs).
* bend: E_b = phi(A, B, C) is a function of the Gram invariants A = a.a,
  B = b.b, C = a.b of a = e_{i-1}, b = e_i only.  (i) Translations are removed
  exactly by the orthonormal translation-free coordinates y = B^T x,
  B = Q (x) I3 (9, 6); (ii) in the stencil frame (u1 = a/|a|, u2 in the plane
  of a and b, n = u1 x u2) the 6x6 Hessian in y splits into a 4x4 in-plane
  block and a 2x2 out-of-plane block.  Both changes of basis are orthogonal,
  so clamping the eigenvalues of the two blocks (``kernels.core.project_psd``
  with the stencil frame, cyclic Jacobi) is the exact clamp of the 9x9
  stencil Hessian.
"""

from __future__ import annotations

import math

import torch

from latentsim.physics.base import EnergyTerm, subset_weights
from latentsim.physics.kernels import rods as rod_kernels
from latentsim.physics.kernels.core import translation_free_basis
from latentsim.physics.kernels.dispatch import KernelSpec, float64_array

__all__ = [
    "rod_stiffness",
    "rod_topology",
    "rod_roots",
    "lumped_masses_rods",
    "RodStretch",
    "RodBend",
]


# --------------------------------------------------------------------------
# material, topology, masses
# --------------------------------------------------------------------------
def rod_stiffness(youngs_modulus, radius):
    """Stretching and bending stiffness of a round elastic rod.

    Parameters
    ----------
    youngs_modulus : float or tensor, Y [Pa].
    radius : float or tensor, r [m].

    Returns
    -------
    ks : Y pi r^2, stretching stiffness [N].
    kb : Y pi r^4 / 4 = E I, bending stiffness [N m^2].
    """
    ks = youngs_modulus * math.pi * radius**2
    kb = youngs_modulus * math.pi * radius**4 / 4.0
    return ks, kb


def rod_topology(n_rods: int, vertices_per_rod: int):
    """Edges and bending triples of ``n_rods`` rods stored contiguously.

    Rod r owns vertices r*m .. r*m + m - 1 (m = ``vertices_per_rod``); vertex
    r*m is its root.

    Returns
    -------
    edges : (n_rods (m-1), 2) long, [i, i+1].
    triples : (n_rods (m-2), 3) long, [i-1, i, i+1].
    """
    m = int(vertices_per_rod)
    if m < 2:
        raise ValueError(f"a rod needs at least 2 vertices, got {m}")
    base = torch.arange(n_rods, dtype=torch.long)[:, None] * m
    j = torch.arange(m - 1, dtype=torch.long)
    edges = torch.stack([base + j, base + j + 1], dim=-1).reshape(-1, 2)
    k = torch.arange(max(m - 2, 0), dtype=torch.long)
    triples = torch.stack([base + k, base + k + 1, base + k + 2], dim=-1).reshape(-1, 3)
    return edges, triples


def rod_roots(n_rods: int, vertices_per_rod: int) -> torch.Tensor:
    """(n_rods,) long indices of the root vertices r*m of contiguous rods."""
    return torch.arange(n_rods, dtype=torch.long) * int(vertices_per_rod)


def lumped_masses_rods(rest_positions, edges, density, radius) -> torch.Tensor:
    """Lumped vertex masses of rods: density pi r^2 |ebar| per edge, half to each end.

    Parameters
    ----------
    rest_positions : (n, 3); edges : (E, 2) long;
    density : float or (E,) [kg/m^3]; radius : float or (E,) [m].

    Returns
    -------
    (n,) float64 masses summing to sum_e density pi r^2 |ebar_e|.
    """
    X = torch.as_tensor(rest_positions, dtype=torch.float64)
    edges = torch.as_tensor(edges, dtype=torch.long)
    length = (X[edges[:, 1]] - X[edges[:, 0]]).norm(dim=-1)
    rho = torch.as_tensor(density, dtype=torch.float64)
    r = torch.as_tensor(radius, dtype=torch.float64)
    m_e = (rho * math.pi * r**2 * length).expand(edges.shape[0])
    m = torch.zeros(X.shape[0], dtype=torch.float64)
    m.index_add_(0, edges[:, 0], 0.5 * m_e)
    m.index_add_(0, edges[:, 1], 0.5 * m_e)
    return m


def _per_stencil(value, count: int, name: str) -> torch.Tensor:
    """Broadcast a float or (E,) parameter to a float64 (E,) tensor."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.ndim > 1 or (t.ndim == 1 and t.shape[0] not in (1, count)):
        raise ValueError(f"{name} must be a scalar or have shape ({count},), got {tuple(t.shape)}")
    return t.expand(count).clone()


def _check_stencils(stencils, k: int, n: int, name: str) -> torch.Tensor:
    s = torch.as_tensor(stencils, dtype=torch.long)
    if s.ndim != 2 or s.shape[1] != k:
        raise ValueError(f"{name} must have shape (E, {k}), got {tuple(s.shape)}")
    if s.numel() and (int(s.min()) < 0 or int(s.max()) >= n):
        raise ValueError(f"{name} index out of range for {n} vertices")
    return s


# --------------------------------------------------------------------------
# stretching
# --------------------------------------------------------------------------
class RodStretch(EnergyTerm):
    """Edge springs E_s = 1/2 ks (|e|/|ebar| - 1)^2 |ebar|.

    Parameters
    ----------
    rest_positions : (n, 3) rest vertex positions.
    edges : (E, 2) long vertex pairs.
    ks : float or (E,) stretching stiffness Y pi r^2 [N].

    Attributes
    ----------
    stencils : (E, 2) long.
    rest_length : (E,) |ebar| [m].
    ks : (E,) [N].
    """

    name = "rod_stretch"

    def __init__(self, rest_positions, edges, ks):
        X = torch.as_tensor(rest_positions, dtype=torch.float64)
        self.stencils = _check_stencils(edges, 2, X.shape[0], "edges")
        self.rest_positions = X
        E = self.stencils.shape[0]
        self.rest_length = (X[self.stencils[:, 1]] - X[self.stencils[:, 0]]).norm(dim=-1)
        bad = torch.nonzero(self.rest_length <= 0).flatten()
        if bad.numel():
            i = int(bad[0])
            raise ValueError(f"rod edge {i} {self.stencils[i].tolist()} has zero rest length")
        self.ks = _per_stencil(ks, E, "ks")

    def weighted_subset(self, index, weights) -> "RodStretch":
        """sum_{e in index} w_e E_e: stiffness w_e ks_e (a cubature, see ``base.subset_weights``)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        return RodStretch(self.rest_positions, self.stencils[idx], self.ks[idx] * w)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """xe (..., E, 2, 3) -> (..., E)."""
        Lbar = self.rest_length.to(xe)
        length = (xe[..., 1, :] - xe[..., 0, :]).norm(dim=-1)
        return 0.5 * self.ks.to(xe) * (length / Lbar - 1.0) ** 2 * Lbar

    def kernel_spec(self) -> KernelSpec:
        """The compiled spring kernels (``kernels.rods``).

        With e = x1 - x0, l = |e|, u = e/l:
        g = [-f, f],  f = ks (l/|ebar| - 1) u,
        H = [[K, -K], [-K, K]],
        K = ks/|ebar| [u u^T + c (I - u u^T)],  c = 1 - |ebar|/l,
        with c clamped at 0 when projecting (exact eigenvalue clamp).
        """
        return KernelSpec(rod_kernels.stretch_energy, rod_kernels.stretch_energy_gradient, rod_kernels.stretch_run,
                          (float64_array(self.rest_length), float64_array(self.ks)), 2)


# --------------------------------------------------------------------------
# bending
# --------------------------------------------------------------------------
class RodBend(EnergyTerm):
    """Twist-free discrete elastic rod bending, E_b = kb |kappa_b|^2 / lbar.

    kappa_b = 2 e_{i-1} x e_i / (|ebar_{i-1}||ebar_i| + e_{i-1}.e_i) is the
    curvature binormal of Bergou et al. (2008) and lbar = |ebar_{i-1}| + |ebar_i|.
    Valid for isotropic, naturally straight rods (round hair): the rest
    stencils must be straight.

    Parameters
    ----------
    rest_positions : (n, 3) rest vertex positions.
    triples : (E, 3) long [i-1, i, i+1].
    kb : float or (E,) bending stiffness E I = Y pi r^4 / 4 [N m^2].
    straight_tol : largest allowed sin(turning angle) of a rest stencil.

    Attributes
    ----------
    stencils : (E, 3) long.
    rest_product : (E,) |ebar_{i-1}| |ebar_i|.
    rest_voronoi : (E,) lbar = |ebar_{i-1}| + |ebar_i|.
    kb : (E,).

    Raises
    ------
    ValueError
        if a rest stencil is not straight (turning angle > ``straight_tol``)
        or has a zero-length edge.
    """

    name = "rod_bend"

    def __init__(self, rest_positions, triples, kb, straight_tol: float = 1e-6):
        X = torch.as_tensor(rest_positions, dtype=torch.float64)
        self.stencils = _check_stencils(triples, 3, X.shape[0], "triples")
        self.rest_positions, self.straight_tol = X, straight_tol
        E = self.stencils.shape[0]
        xe = X[self.stencils]
        a = xe[:, 1] - xe[:, 0]
        b = xe[:, 2] - xe[:, 1]
        la, lb = a.norm(dim=-1), b.norm(dim=-1)
        zero = torch.nonzero((la <= 0) | (lb <= 0)).flatten()
        if zero.numel():
            i = int(zero[0])
            raise ValueError(f"rod bending stencil {i} {self.stencils[i].tolist()} has a zero-length edge")
        sin_t = torch.linalg.cross(a, b).norm(dim=-1) / (la * lb)
        cos_t = (a * b).sum(-1) / (la * lb)
        bent = torch.nonzero((sin_t > straight_tol) | (cos_t <= 0)).flatten()
        if bent.numel():
            i = int(bent[0])
            angle = float(torch.atan2(sin_t[i], cos_t[i]))
            raise ValueError(
                f"rest bending stencil {i} {self.stencils[i].tolist()} is not straight "
                f"(turning angle {angle:.3g} rad > {straight_tol:g}); the twist-free rod "
                "model needs naturally straight rods"
            )
        self.rest_product = la * lb
        self.rest_voronoi = la + lb
        self.kb = _per_stencil(kb, E, "kb")

    def curvature_binormal(self, xe: torch.Tensor) -> torch.Tensor:
        """kappa_b, xe (..., E, 3, 3) -> (..., E, 3)."""
        a = xe[..., 1, :] - xe[..., 0, :]
        b = xe[..., 2, :] - xe[..., 1, :]
        den = self.rest_product.to(xe) + (a * b).sum(-1)
        return 2.0 * torch.linalg.cross(a, b) / den[..., None]

    def weighted_subset(self, index, weights) -> "RodBend":
        """sum_{e in index} w_e E_e: stiffness w_e kb_e (a cubature, see ``base.subset_weights``)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        return RodBend(self.rest_positions, self.stencils[idx], self.kb[idx] * w, self.straight_tol)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """xe (..., E, 3, 3) -> (..., E); uses |a x b|^2 (no square root)."""
        a = xe[..., 1, :] - xe[..., 0, :]
        b = xe[..., 2, :] - xe[..., 1, :]
        den = self.rest_product.to(xe) + (a * b).sum(-1)
        w = torch.linalg.cross(a, b)
        alpha = 4.0 * self.kb.to(xe) / self.rest_voronoi.to(xe)
        return alpha * (w * w).sum(-1) / den**2

    # -- compiled derivatives ------------------------------------------------
    def kernel_spec(self) -> KernelSpec:
        """The compiled bending kernels (``kernels.rods``).

        With phi(A, B, C) = alpha (A B - C^2) / tau^2, tau = |ebar_{i-1}||ebar_i| + C,
        alpha = 4 kb / lbar, and its partial derivatives phi_A, .., phi_CC:

        gradient  dE/da = 2 phi_A a + phi_C b,  dE/db = 2 phi_B b + phi_C a,
                  g = [-dE/da, dE/da - dE/db, dE/db];
        Hessian   in the stencil frame (u1, u2, n), where a = (a1, 0, 0) and
                  b = (b1, b2, 0), H_ab is block diagonal:
                  in-plane (a_x, a_y, b_x, b_y):  J^T Phi J + P (x) I2,
                  out-of-plane (a_z, b_z):        P = [[2 phi_A, phi_C], [phi_C, 2 phi_B]],
                  J (3, 4) = d(A, B, C)/d(in-plane coordinates), Phi the 3x3
                  matrix of second derivatives of phi.

        The projection clamps the eigenvalues of the translation-free block,
        in the stencil frame (the exact clamp of the 9x9 Hessian).
        """
        args = (float64_array(4.0 * self.kb / self.rest_voronoi), float64_array(self.rest_product))
        return KernelSpec(rod_kernels.bend_energy, rod_kernels.bend_energy_gradient, rod_kernels.bend_run,
                          args, 3, translation_free_basis(3))
