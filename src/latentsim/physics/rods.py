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

Newton derivatives.  Both terms provide closed-form, vectorised per-stencil
gradients and eigenvalue-clamped (Teran et al. 2005) Hessians equal to the
autograd oracle ``base.autograd_gradient_hessian`` (which the tests use):

* stretch: the spring Hessian w.r.t. e is
  K = ks/|ebar| [u u^T + (1 - |ebar|/|e|)(I - u u^T)], u = e/|e|, and the 6x6
  stencil Hessian [[K, -K], [-K, K]] has the eigenvalues 2 x those of K, so
  the exact clamp is 1 - |ebar|/|e| -> max(0, .) (compressed springs).
* bend: E_b = phi(A, B, C) is a function of the Gram invariants A = a.a,
  B = b.b, C = a.b of a = e_{i-1}, b = e_i only.  (i) Translations are removed
  exactly by orthonormal difference coordinates y, (a, b) = R^T y with
  d^T = Q R the QR factors of the difference operator d = [[-1, 1, 0],
  [0, -1, 1]]; (ii) in the stencil frame (u1 = a/|a|, u2 in the plane of a
  and b, n = u1 x u2) the 6x6 Hessian in y splits into a 4x4 in-plane block
  and a 2x2 out-of-plane block R [[2 phi_A, phi_C], [phi_C, 2 phi_B]] R^T.
  Both changes of basis are orthogonal, so clamping the eigenvalues of the
  two blocks -- the 2x2 analytically, the 4x4 with a vectorised cyclic Jacobi
  solver (batched LAPACK ``eigh`` is dominated by per-matrix overhead) -- is
  the exact clamp of the 9x9 stencil Hessian.  The kernel runs in float64
  NumPy with the stencil axis last.  It is ~4x faster than the autograd
  oracle on the 3,400 stencils of a 3,600-vertex hair scene (see
  ``benchmarks/bench_rod_shell_hessian.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from latentsim.physics.base import EnergyTerm, subset_weights

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
        self._rest_length_np = self.rest_length.numpy()
        self._ks_np = self.ks.numpy()

    def weighted_subset(self, index, weights) -> "RodStretch":
        """sum_{e in index} w_e E_e: stiffness w_e ks_e (a cubature, see ``base.subset_weights``)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        return RodStretch(self.rest_positions, self.stencils[idx], self.ks[idx] * w)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """xe (..., E, 2, 3) -> (..., E)."""
        Lbar = self.rest_length.to(xe)
        length = (xe[..., 1, :] - xe[..., 0, :]).norm(dim=-1)
        return 0.5 * self.ks.to(xe) * (length / Lbar - 1.0) ** 2 * Lbar

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True):
        """Closed-form gradient (E, 6) and Hessian (E, 6, 6) of every edge.

        With e = x1 - x0, l = |e|, u = e/l:
        g = [-f, f],  f = ks (l/|ebar| - 1) u,
        H = [[K, -K], [-K, K]],
        K = ks/|ebar| [u u^T + c (I - u u^T)],  c = 1 - |ebar|/l,
        with c clamped at 0 when ``project`` (exact eigenvalue clamp).
        """
        x = xe.detach().cpu().numpy().astype(np.float64, copy=False)
        Lbar, ks = self._rest_length_np, self._ks_np
        e = x[:, 1] - x[:, 0]
        length = np.sqrt(np.einsum("ei,ei->e", e, e))
        u = e / length[:, None]
        f = (ks * (length / Lbar - 1.0))[:, None] * u
        g = np.concatenate([-f, f], axis=1)
        c = 1.0 - Lbar / length
        if project:
            c = np.maximum(c, 0.0)
        s = ks / Lbar
        K = ((s * (1.0 - c))[:, None, None] * u[:, :, None]) * u[:, None, :]
        for i in range(3):
            K[:, i, i] += s * c
        H = np.empty((x.shape[0], 6, 6))
        H[:, :3, :3] = K
        H[:, 3:, 3:] = K
        H[:, :3, 3:] = -K
        H[:, 3:, :3] = -K
        return (
            torch.from_numpy(g).to(dtype=xe.dtype, device=xe.device),
            torch.from_numpy(H).to(dtype=xe.dtype, device=xe.device),
        )


# --------------------------------------------------------------------------
# bending
# --------------------------------------------------------------------------
# Difference operator (a, b) = (x1 - x0, x2 - x1) = d x, d = [[-1, 1, 0],
# [0, -1, 1]], and its QR factors d^T = Q R: y = Q^T x are orthonormal
# translation-free coordinates with (a, b) = R^T y.  The bending Hessian is
# H9 = (Q (x) I3) M (Q (x) I3)^T with M = (R (x) I3) H_ab (R (x) I3)^T, so
# clamping M clamps H9 exactly.
_D = torch.tensor([[-1.0, 1.0, 0.0], [0.0, -1.0, 1.0]], dtype=torch.float64)
_R_np = torch.linalg.qr(_D.T)[1].numpy().copy()  # (2, 2) upper triangular
_Rinv_np = np.linalg.inv(_R_np)


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
        self._alpha_np = (4.0 * self.kb / self.rest_voronoi).numpy()
        self._rest_product_np = self.rest_product.numpy()

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

    # -- closed-form derivatives ---------------------------------------------
    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True):
        """Closed-form gradient (E, 9) and (projected) Hessian (E, 9, 9).

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

        Both blocks are moved to the translation-free coordinates (R, see the
        module docstring) and diagonalised -- the 4x4 by a vectorised Jacobi
        method, the 2x2 analytically -- and ``project`` clamps their
        eigenvalues at 0 (the exact clamp of the 9x9 Hessian).  Computed in
        float64 NumPy; returns tensors of ``xe``'s dtype and device.

        Parameters
        ----------
        xe : (E, 3, 3) positions of all E stencils (in ``stencils`` order).
        project : clamp the eigenvalues (default) or return the exact Hessian.

        Returns
        -------
        g : (E, 9), H : (E, 9, 9) symmetric.
        """
        x = xe.detach().cpu().numpy().astype(np.float64, copy=False)
        g, H = _bend_gradient_hessian(
            x, self._alpha_np, self._rest_product_np, project=project
        )
        return (
            torch.from_numpy(g).to(dtype=xe.dtype, device=xe.device),
            torch.from_numpy(H).to(dtype=xe.dtype, device=xe.device),
        )


def _dot(u, v):
    """Row-wise dot product of (3, E) arrays -> (E,)."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cross(u, v):
    """Cross product of (3, E) arrays -> (3, E)."""
    return np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]])


def _unit_perpendicular(u: np.ndarray) -> np.ndarray:
    """A unit vector orthogonal to each column of u (3, E) (unit columns)."""
    k = np.argmin(np.abs(u), axis=0)
    axis = np.zeros_like(u)
    axis[k, np.arange(u.shape[1])] = 1.0
    v = axis - _dot(axis, u) * u
    return v / np.sqrt(_dot(v, v))


def _bend_gradient_hessian(x: np.ndarray, alpha: np.ndarray, c0: np.ndarray, project: bool = True):
    """NumPy kernel of ``RodBend.local_gradient_hessian``.

    x (E, 3, 3) float64 -> g (E, 9), H (E, 9, 9).  Internally every array has
    the stencil axis last ("structure of arrays"), which keeps NumPy's inner
    loops long.
    """
    E = x.shape[0]
    xt = np.ascontiguousarray(x.transpose(1, 2, 0))  # (vertex, coord, E)
    a = xt[1] - xt[0]
    b = xt[2] - xt[1]
    A, B, C = _dot(a, a), _dot(b, b), _dot(a, b)
    w = _cross(a, b)
    f = _dot(w, w)  # = A B - C^2 without cancellation
    tau = c0 + C
    it2 = alpha / (tau * tau)
    it3 = it2 / tau
    p1 = it2 * B
    p2 = it2 * A
    p3 = -2.0 * (C * it2 + f * it3)
    p12 = it2
    p13 = -2.0 * B * it3
    p23 = -2.0 * A * it3
    p33 = -2.0 * it2 + 8.0 * C * it3 + 6.0 * f * it3 / tau

    # dE/da = 2 phi_1 a + phi_3 b = alpha (2 b x w / tau^2 - 2 f b / tau^3), etc.,
    # written with cross products (accurate for nearly straight stencils)
    ga = 2.0 * it2 * _cross(b, w) - 2.0 * f * it3 * b
    gb = 2.0 * it2 * _cross(w, a) - 2.0 * f * it3 * a
    g = np.concatenate([-ga, ga - gb, gb]).T  # (E, 9)

    # stencil frame: u1 along a, u2 in span(a, b), n = u1 x u2
    a1 = np.sqrt(A)
    u1 = a / a1
    b1 = C / a1
    wp = b - b1 * u1
    # second Gram-Schmidt pass: for nearly straight stencils the first leaves
    # wp.u1 ~ eps |b|, i.e. u2 off orthogonal by eps / sin(angle)
    wp = wp - _dot(wp, u1) * u1
    b2 = np.sqrt(_dot(wp, wp))
    ok = b2 > 1e-12 * np.sqrt(B)
    u2 = wp / np.where(ok, b2, 1.0)
    if not ok.all():  # straight stencil: any unit vector orthogonal to u1
        idx = np.nonzero(~ok)[0]
        u2[:, idx] = _unit_perpendicular(u1[:, idx])
        b2 = np.where(ok, b2, 0.0)
    n = _cross(u1, u2)

    # In-plane Hessian w.r.t. (a_x, a_y, b_x, b_y): sum_kl Phi_kl j_k j_l^T + P (x) I2,
    # with j_k the gradients of (A, B, C).  Transformed to the translation-free
    # orthonormal coordinates y, (a, b) = R^T y:  M = R4 H R4^T, R4 = R (x) I2,
    # i.e. j_k -> R4 j_k and P -> R P R^T.
    zero = np.zeros(E)
    r00, r01, r10, r11 = _R_np[0, 0], _R_np[0, 1], _R_np[1, 0], _R_np[1, 1]

    def to_y(ja_x, ja_y, jb_x, jb_y):
        return np.stack(
            [r00 * ja_x + r01 * jb_x, r00 * ja_y + r01 * jb_y, r10 * ja_x + r11 * jb_x, r10 * ja_y + r11 * jb_y]
        )

    yA = to_y(2.0 * a1, zero, zero, zero)
    yB = to_y(zero, zero, 2.0 * b1, 2.0 * b2)
    yC = to_y(b1, b2, a1, zero)
    Min = yA[:, None] * (p12 * yB + p13 * yC)[None] + yB[:, None] * (p23 * yC)[None]
    Min = Min + Min.transpose(1, 0, 2) + yC[:, None] * (p33 * yC)[None]  # (4, 4, E)
    # R P R^T with P = [[2 p1, p3], [p3, 2 p2]]
    n00 = r00 * r00 * 2.0 * p1 + 2.0 * r00 * r01 * p3 + r01 * r01 * 2.0 * p2
    n01 = r00 * r10 * 2.0 * p1 + (r00 * r11 + r01 * r10) * p3 + r01 * r11 * 2.0 * p2
    n11 = r10 * r10 * 2.0 * p1 + 2.0 * r10 * r11 * p3 + r11 * r11 * 2.0 * p2
    for s_ in range(2):
        Min[s_, s_] += n00
        Min[2 + s_, 2 + s_] += n11
        Min[s_, 2 + s_] += n01
        Min[2 + s_, s_] += n01

    lam_in, v = _jacobi_eigh_soa(Min)  # (E, 4), (4, 4, E)
    lam_n, V_n = _eigh_sym2(n00, n01, n11)
    lam = np.concatenate([lam_in, lam_n], axis=1)
    if project:
        lam = np.maximum(lam, 0.0)

    # Reassemble.  M+ = sum_k lam_k v_k v_k^T in the (y, frame) coordinates,
    # back to (a, b): H_ab = (R^-1 (x) I) M+ (R^-T (x) I), then rotate the frame
    # blocks to world and expand H9 = D^T H_ab D (D the difference operator).
    lt = np.ascontiguousarray(lam.T)  # (6, E)
    lv = [lt[:4] * v[i] for i in range(4)]
    m = [[None] * 4 for _ in range(4)]
    for i in range(4):
        for j in range(i, 4):
            m[i][j] = m[j][i] = (lv[i] * v[j]).sum(0)
    Vn = V_n.transpose(1, 2, 0)  # (2, 2, E)
    mn = [[(lt[4:] * Vn[p_] * Vn[q_]).sum(0) for q_ in range(2)] for p_ in range(2)]
    i00, i01, i11 = _Rinv_np[0, 0], _Rinv_np[0, 1], _Rinv_np[1, 1]

    def ab_blocks(mpq):
        """(h_aa, h_ab, h_ba, h_bb) from the 2x2 p-blocks mpq[p][q] of one frame entry."""
        haa = i00 * i00 * mpq[0][0] + i00 * i01 * (mpq[0][1] + mpq[1][0]) + i01 * i01 * mpq[1][1]
        hab = i00 * i11 * mpq[0][1] + i01 * i11 * mpq[1][1]
        hba = i00 * i11 * mpq[1][0] + i01 * i11 * mpq[1][1]
        hbb = i11 * i11 * mpq[1][1]
        return haa, hab, hba, hbb

    # frame entry (s, t), s, t in {u1, u2}: in-plane index 2 p + s
    fr = {
        (s_, t_): ab_blocks([[m[2 * p_ + s_][2 * q_ + t_] for q_ in range(2)] for p_ in range(2)])
        for s_ in range(2)
        for t_ in range(2)
    }
    fn = ab_blocks(mn)
    O11 = u1[:, None] * u1[None]
    O22 = u2[:, None] * u2[None]
    O12 = u1[:, None] * u2[None]
    O21 = O12.transpose(1, 0, 2)
    Onn = n[:, None] * n[None]

    def world(k):
        return fr[0, 0][k] * O11 + fr[1, 1][k] * O22 + fr[0, 1][k] * O12 + fr[1, 0][k] * O21 + fn[k] * Onn

    Haa, Hab, Hbb = world(0), world(1), world(3)
    Hba = Hab.transpose(1, 0, 2)
    H = np.empty((3, 3, 3, 3, E))  # (vertex i, coord, vertex j, coord, E)
    H[0, :, 0] = Haa
    H[0, :, 1] = Hab - Haa
    H[0, :, 2] = -Hab
    H[1, :, 1] = Haa + Hbb - Hab - Hba
    H[1, :, 2] = Hab - Hbb
    H[2, :, 2] = Hbb
    H[1, :, 0] = H[0, :, 1].transpose(1, 0, 2)
    H[2, :, 0] = H[0, :, 2].transpose(1, 0, 2)
    H[2, :, 1] = H[1, :, 2].transpose(1, 0, 2)
    return np.ascontiguousarray(g), np.ascontiguousarray(H.reshape(81, E).T).reshape(E, 9, 9)


def _eigh_sym2(p, q, s):
    """Eigen-decomposition of symmetric 2x2 [[p, q], [q, s]] (analytic).

    Returns lam (E, 2) and V (E, 2, 2) with eigenvectors in the columns.
    """
    m = 0.5 * (p + s)
    d = np.hypot(0.5 * (p - s), q)
    th = 0.5 * np.arctan2(2.0 * q, p - s)
    c, sn = np.cos(th), np.sin(th)
    lam = np.stack([m + d, m - d], 1)
    V = np.stack([np.stack([c, -sn], 1), np.stack([sn, c], 1)], 1)
    return lam, V


def _jacobi_eigh_soa(a, tol: float = 1e-15, max_sweeps: int = 12):
    """Cyclic Jacobi eigen-decomposition of a batch of small symmetric matrices.

    Vectorised over the batch, with every matrix entry held as its own
    contiguous (E,) array ("structure of arrays"): LAPACK's batched ``eigh``
    is dominated by per-matrix overhead for 4x4 matrices.  Sweeps until the
    off-diagonal Frobenius norm of every matrix is below ``tol`` times its
    Frobenius norm (quadratic convergence: 4 sweeps for 4x4 in practice).

    Parameters
    ----------
    a : (n, n, E) array or n x n nested list of (E,) arrays, a symmetric
        float64 matrix batch (batch axis last).

    Returns
    -------
    lam : (E, n) eigenvalues (unsorted);
    V : (n, n, E) eigenvectors, eigenvector k of matrix e is V[:, k, e].
    """
    n = len(a)
    a = [[np.ascontiguousarray(a[i][j], dtype=np.float64) for j in range(n)] for i in range(n)]
    E = a[0][0].shape[0]
    cols = [np.zeros((n, E)) for _ in range(n)]  # cols[k][i] = V[i, k]
    for k in range(n):
        cols[k][k] = 1.0
    scale2 = sum(a[i][j] * a[i][j] for i in range(n) for j in range(n))
    thresh = 0.5 * tol * tol * scale2
    tiny = np.finfo(np.float64).tiny
    zero = np.zeros(E)
    for _ in range(max_sweeps):
        off = sum(a[i][j] * a[i][j] for i in range(n) for j in range(i + 1, n))
        if np.all(off <= thresh):
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p][q]
                # t = tan of the rotation angle: the smaller root of
                # t^2 + 2 (d / apq) t - 1 = 0, written without dividing by apq
                d = 0.5 * (a[q][q] - a[p][p])
                t = apq / np.copysign(np.abs(d) + np.sqrt(d * d + apq * apq) + tiny, d)
                c = 1.0 / np.sqrt(1.0 + t * t)
                s = t * c
                ta = t * apq
                a[p][p] = a[p][p] - ta
                a[q][q] = a[q][q] + ta
                a[p][q] = a[q][p] = zero
                for r in range(n):
                    if r != p and r != q:
                        arp, arq = a[r][p], a[r][q]
                        a[r][p] = a[p][r] = c * arp - s * arq
                        a[r][q] = a[q][r] = s * arp + c * arq
                vp, vq = cols[p], cols[q]
                cols[p] = c * vp - s * vq
                cols[q] = s * vp + c * vq
    return np.stack([a[i][i] for i in range(n)], 1), np.stack(cols, 1)


def _jacobi_eigh(A: np.ndarray, tol: float = 1e-15, max_sweeps: int = 12):
    """Array interface of ``_jacobi_eigh_soa``: A (E, n, n) -> lam (E, n), V (E, n, n) (columns)."""
    n = A.shape[-1]
    lam, V = _jacobi_eigh_soa([[A[:, i, j] for j in range(n)] for i in range(n)], tol, max_sweeps)
    return lam, V.transpose(2, 0, 1)
