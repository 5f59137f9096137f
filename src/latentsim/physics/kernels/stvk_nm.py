r"""Compiled Neural Modes StVK energies (``physics.stvk_nm``): energy, gradient, Hessian per stencil.

Both terms are written in F-space: per element the energy density Psi(F),
its first Piola stress P = dPsi/dF and the F-space Hessian A = dP/dF
(vec(F) row-major, F_(i r) at i c + r with c = 2 columns for triangles and
3 for tets), mapped to the stencil by the barycentric gradients G (k, c),
F = sum_a x_a G_a^T:

    g_(a i)        = K sum_r P_(i r) G_(a r),
    H_(a i)(b j)   = K sum_(r, s) G_(a r) A_(i r)(j s) G_(b s),

K the rest measure (h Abar for triangles, the rest volume for tets).

* Membrane: Psi = mu ||E||^2 + lam/2 (J - 1)^2, J = sqrt(det C), C = F^T F
  (F 3x2, J the area ratio).  With f0, f1 the columns of F and d = det C:
  dd/df0 = 2 c11 f0 - 2 c01 f1, dd/df1 = 2 c00 f1 - 2 c01 f0, the blocks of
  Hess d 2 c11 I - 2 f1 f1^T, 4 f0 f1^T - 2 f1 f0^T - 2 c01 I (row f0, column f1),
  2 c00 I - 2 f0 f0^T; dJ = dd / (2J), Hess J = Hess d / (2J) - dd dd^T / (4 J^3).
* Tets: Psi = mu ||E||^2 + lam (J - 1)^2, J = det F: dJ/dF = cof F (columns
  f1 x f2, f2 x f0, f0 x f1), d^2 J / dF_ij dF_kl = eps_ikm eps_jln F_mn.

The StVK part mu ||E||^2 has P = 2 mu F E and
A_(i r)(j s) = 2 mu d_ij E_sr + mu F_is F_jr + mu d_rs (F F^T)_ij
(``kernels.tets``), the (J - 1)^2 part P = c (J - 1) dJ and
A = c (dJ dJ^T + (J - 1) Hess J) with c = lam (membrane) or 2 lam (tets).
The projection clamps the eigenvalues of the stencil Hessian on its
translation-free block (``core.project_psd`` with
``core.translation_free_basis``; exact, both energies are translation
invariant).  The ``*_energy`` and ``*_run`` kernels follow the calling
convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import GRADIENT, INLINE, JIT, NO_FRAME, emit, project_psd, scatter_gradient


@njit(**INLINE)
def _F(e, x, st, G, F, k, c):
    """F (3, c) = sum_a x_a G_a^T of stencil e (k vertices)."""
    for i in range(3):
        for r in range(c):
            acc = 0.0
            for a in range(k):
                acc += x[st[e, a], i] * G[e, a, r]
            F[i, r] = acc


@njit(**INLINE)
def _stvk_mu(F, mu, P, A, c, hessian):
    """mu ||E||^2 of F (3, c): returns it, P (3, c) = 2 mu F E, and A (3c, 3c) = its dP/dF when
    ``hessian``; P and A are overwritten."""
    E = np.empty((3, 3))
    nE2 = 0.0
    for r in range(c):
        for s in range(c):
            E[r, s] = 0.5 * (F[0, r] * F[0, s] + F[1, r] * F[1, s] + F[2, r] * F[2, s] - (1.0 if r == s else 0.0))
            nE2 += E[r, s] * E[r, s]
    for i in range(3):
        for r in range(c):
            acc = 0.0
            for t in range(c):
                acc += F[i, t] * E[t, r]
            P[i, r] = 2.0 * mu * acc
    if hessian:
        for i in range(3):
            for j in range(3):
                ff = F[i, 0] * F[j, 0] + F[i, 1] * F[j, 1]
                if c == 3:
                    ff += F[i, 2] * F[j, 2]
                for r in range(c):
                    for s in range(c):
                        h = mu * F[i, s] * F[j, r]
                        if i == j:
                            h += 2.0 * mu * E[s, r]
                        if r == s:
                            h += mu * ff
                        A[i * c + r, j * c + s] = h
    return mu * nE2


@njit(**INLINE)
def _to_stencil(e, G, P, A, K, g, H, k, c, hessian):
    """g (3k,) and H (3k, 3k) of stencil e from P (3, c) and A (3c, 3c), scaled by K."""
    for a in range(k):
        for i in range(3):
            acc = 0.0
            for r in range(c):
                acc += P[i, r] * G[e, a, r]
            g[3 * a + i] = K * acc
    if hessian:
        for a in range(k):
            for b in range(k):
                for i in range(3):
                    for j in range(3):
                        acc = 0.0
                        for r in range(c):
                            for s in range(c):
                                acc += G[e, a, r] * A[i * c + r, j * c + s] * G[e, b, s]
                        H[3 * a + i, 3 * b + j] = K * acc


# ---------------------------------------------------------------------------
# membrane: Abar h (mu ||E||^2 + lam/2 (J - 1)^2), J the area ratio
# ---------------------------------------------------------------------------
@njit(**INLINE)
def _membrane_density(F, mu, lam, P, A, hessian):
    """Psi, P (3, 2) and A (6, 6) of the membrane at F (3, 2)."""
    psi = _stvk_mu(F, mu, P, A, 2, hessian)
    c00 = F[0, 0] ** 2 + F[1, 0] ** 2 + F[2, 0] ** 2
    c11 = F[0, 1] ** 2 + F[1, 1] ** 2 + F[2, 1] ** 2
    c01 = F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1] + F[2, 0] * F[2, 1]
    J = math.sqrt(c00 * c11 - c01 * c01)
    psi += 0.5 * lam * (J - 1.0) ** 2
    dJ = np.empty(6)  # F-space index i * 2 + r
    for i in range(3):
        dJ[2 * i] = (c11 * F[i, 0] - c01 * F[i, 1]) / J  # dd/df0 / (2J)
        dJ[2 * i + 1] = (c00 * F[i, 1] - c01 * F[i, 0]) / J
        P[i, 0] += lam * (J - 1.0) * dJ[2 * i]
        P[i, 1] += lam * (J - 1.0) * dJ[2 * i + 1]
    if hessian:
        for i in range(3):
            for j in range(3):
                dl = 1.0 if i == j else 0.0
                h00 = 2.0 * c11 * dl - 2.0 * F[i, 1] * F[j, 1]
                h11 = 2.0 * c00 * dl - 2.0 * F[i, 0] * F[j, 0]
                h01 = 4.0 * F[i, 0] * F[j, 1] - 2.0 * F[i, 1] * F[j, 0] - 2.0 * c01 * dl
                h10 = 4.0 * F[i, 1] * F[j, 0] - 2.0 * F[i, 0] * F[j, 1] - 2.0 * c01 * dl
                for r in range(2):
                    for s in range(2):
                        hd = h00 if (r == 0 and s == 0) else (h11 if (r == 1 and s == 1) else (h01 if r == 0 else h10))
                        p, q = 2 * i + r, 2 * j + s
                        # Hess J = Hess d / (2J) - dd dd^T / (4 J^3) = Hess d / (2J) - dJ dJ^T / J
                        hJ = hd / (2.0 * J) - dJ[p] * dJ[q] / J
                        A[p, q] += lam * (dJ[p] * dJ[q] + (J - 1.0) * hJ)
    return psi


@njit(**JIT)
def membrane_nm_energy(x, st, order, G, K, mu, lam):
    """sum_t Abar h (mu ||E||^2 + lam/2 (J - 1)^2)."""
    F, P, A = np.empty((3, 2)), np.empty((3, 2)), np.empty((6, 6))
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        _F(e, x, st, G, F, 3, 2)
        total += K[e] * _membrane_density(F, mu[e], lam[e], P, A, False)
    return total


@njit(**JIT)
def membrane_nm_run(x, st, order, G, K, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    F, P, A = np.empty((3, 2)), np.empty((3, 2)), np.empty((6, 6))
    g, H = np.empty(9), np.empty((9, 9))
    M, V, BV, BH = np.empty((6, 6)), np.empty((6, 6)), np.empty((9, 6)), np.empty((9, 6))
    wv = np.empty(6)
    total = 0.0
    hessian = mode != GRADIENT
    for ii in range(order.shape[0]):
        e = order[ii]
        _F(e, x, st, G, F, 3, 2)
        total += K[e] * _membrane_density(F, mu[e], lam[e], P, A, hessian)
        _to_stencil(e, G, P, A, K[e], g, H, 3, 2, hessian)
        if not hessian:
            scatter_gradient(e, st, g, grad, 3)
            continue
        if project:
            project_psd(H, B, M, BH, V, wv, BV, NO_FRAME, False)
        emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 3)
    return total


# ---------------------------------------------------------------------------
# tets: V0 (mu ||E||^2 + lam (det F - 1)^2)
# ---------------------------------------------------------------------------
@njit(**INLINE)
def _levi(i, j, k):
    return 0.5 * (i - j) * (j - k) * (k - i)


@njit(**INLINE)
def _tet_density(F, mu, lam, P, A, hessian):
    """Psi, P (3, 3) and A (9, 9) of the tet at F (3, 3)."""
    psi = _stvk_mu(F, mu, P, A, 3, hessian)
    cof = np.empty((3, 3))
    for j in range(3):  # cof column j = f_{j+1} x f_{j+2}
        j1, j2 = (j + 1) % 3, (j + 2) % 3
        cof[0, j] = F[1, j1] * F[2, j2] - F[2, j1] * F[1, j2]
        cof[1, j] = F[2, j1] * F[0, j2] - F[0, j1] * F[2, j2]
        cof[2, j] = F[0, j1] * F[1, j2] - F[1, j1] * F[0, j2]
    J = F[0, 0] * cof[0, 0] + F[1, 0] * cof[1, 0] + F[2, 0] * cof[2, 0]
    psi += lam * (J - 1.0) ** 2
    c2 = 2.0 * lam
    for i in range(3):
        for r in range(3):
            P[i, r] += c2 * (J - 1.0) * cof[i, r]
    if hessian:
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    for l in range(3):
                        hJ = 0.0
                        for m in range(3):
                            eikm = _levi(i, k, m)
                            if eikm == 0.0:
                                continue
                            for n in range(3):
                                hJ += eikm * _levi(j, l, n) * F[m, n]
                        A[3 * i + j, 3 * k + l] += c2 * (cof[i, j] * cof[k, l] + (J - 1.0) * hJ)
    return psi


@njit(**JIT)
def tet_nm_energy(x, st, order, D, vol, mu, lam):
    """sum_e V0 (mu ||E||^2 + lam (det F - 1)^2)."""
    F, P, A = np.empty((3, 3)), np.empty((3, 3)), np.empty((9, 9))
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        _F(e, x, st, D, F, 4, 3)
        total += vol[e] * _tet_density(F, mu[e], lam[e], P, A, False)
    return total


@njit(**JIT)
def tet_nm_run(x, st, order, D, vol, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    F, P, A = np.empty((3, 3)), np.empty((3, 3)), np.empty((9, 9))
    g, H = np.empty(12), np.empty((12, 12))
    M, V, BV, BH = np.empty((9, 9)), np.empty((9, 9)), np.empty((12, 9)), np.empty((12, 9))
    wv = np.empty(9)
    total = 0.0
    hessian = mode != GRADIENT
    for ii in range(order.shape[0]):
        e = order[ii]
        _F(e, x, st, D, F, 4, 3)
        total += vol[e] * _tet_density(F, mu[e], lam[e], P, A, hessian)
        _to_stencil(e, D, P, A, vol[e], g, H, 4, 3, hessian)
        if not hessian:
            scatter_gradient(e, st, g, grad, 4)
            continue
        if project:
            project_psd(H, B, M, BH, V, wv, BV, NO_FRAME, False)
        emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 4)
    return total
