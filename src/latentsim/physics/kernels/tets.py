r"""Compiled StVK tetrahedra (``physics.tets.StVKTets``): energy, gradient, Hessian per stencil.

With D (4, 3) the barycentric gradients of tet e, F = sum_a x_a D_a^T,
E = (F^T F - I)/2, S = 2 mu E + lam tr(E) I, q_a = F D_a and W the rest volume:

    energy      W (mu ||E||^2 + lam/2 tr(E)^2),
    gradient    g_a = W F S D_a,
    Hessian     H_(a i)(b j) = W [ (D_a^T S D_b) d_ij + mu q_(b,i) q_(a,j)
                                   + mu (F F^T)_ij (D_a . D_b) + lam q_(a,i) q_(b,j) ];

the projection clamps the analytic eigensystem of dP/dF in the principal-stretch
frame of the rotation-variant SVD (Teran et al. 2005; Smith et al. 2019; the
``physics.tets`` module docstring): W sum_k max(lambda_k, 0) g_k g_k^T.
``tet_energy`` and ``tet_run`` follow the calling convention of
``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import GRADIENT, INLINE, JIT, SCATTER, jacobi_eigh, scatter, scatter_gradient, svd3


@njit(**INLINE)
def _tet_F(e, x, st, D, F):
    """F (3, 3) = sum_a x_a D_a^T of tet e."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for a in range(4):
                acc += x[st[e, a], i] * D[e, a, j]
            F[i, j] = acc


@njit(**JIT)
def tet_energy(x, st, order, D, vol, mu, lam):
    """sum_e W_e (mu ||E||^2 + lam/2 tr(E)^2)."""
    F = np.empty((3, 3))
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        _tet_F(e, x, st, D, F)
        nE2 = 0.0
        tr = 0.0
        for i in range(3):
            for j in range(3):
                c = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
                Eij = 0.5 * (c - (1.0 if i == j else 0.0))
                nE2 += Eij * Eij
                if i == j:
                    tr += Eij
        total += vol[e] * (mu[e] * nE2 + 0.5 * lam[e] * tr * tr)
    return total




@njit(**INLINE)
def _tet_energy_gradient(e, x, st, D, vol, mu, lam, g, F, S, P):
    """Energy (returned) and gradient g (12,) = W D P^T of tet e; leaves F and S = 2 mu E + lam tr(E) I."""
    _tet_F(e, x, st, D, F)
    W, m_, l_ = vol[e], mu[e], lam[e]
    # S = 2 mu E + lam tr(E) I, with E = (F^T F - I)/2
    tr = 0.0
    for i in range(3):
        for j in range(3):
            S[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
        tr += S[i, i]
    tr = 0.5 * (tr - 3.0)
    nE2 = 0.0
    for i in range(3):
        for j in range(3):
            Eij = 0.5 * (S[i, j] - (1.0 if i == j else 0.0))
            nE2 += Eij * Eij
            S[i, j] = 2.0 * m_ * Eij + (l_ * tr if i == j else 0.0)
    energy = W * (m_ * nE2 + 0.5 * l_ * tr * tr)
    for i in range(3):  # P = F S
        for j in range(3):
            P[i, j] = F[i, 0] * S[0, j] + F[i, 1] * S[1, j] + F[i, 2] * S[2, j]
    for a in range(4):
        for i in range(3):
            g[3 * a + i] = W * (P[i, 0] * D[e, a, 0] + P[i, 1] * D[e, a, 1] + P[i, 2] * D[e, a, 2])
    return energy


@njit(**INLINE)
def _tet_exact_hessian(e, D, vol, mu, lam, F, S, q, FF, H):
    """The exact Hessian of tet e from F and S, written to the upper triangle of H (12, 12) only
    (all that ``scatter`` reads); q, FF scratch."""
    W, m_, l_ = vol[e], mu[e], lam[e]
    # q_a = F D_a, FF = mu F F^T
    for a in range(4):
        for i in range(3):
            q[a, i] = F[i, 0] * D[e, a, 0] + F[i, 1] * D[e, a, 1] + F[i, 2] * D[e, a, 2]
    for i in range(3):
        for j in range(3):
            FF[i, j] = m_ * (F[i, 0] * F[j, 0] + F[i, 1] * F[j, 1] + F[i, 2] * F[j, 2])
    for a in range(4):
        for b_ in range(a, 4):
            dSd = 0.0
            dd = 0.0
            for k in range(3):
                dd += D[e, a, k] * D[e, b_, k]
                dSd += D[e, a, k] * (S[k, 0] * D[e, b_, 0] + S[k, 1] * D[e, b_, 1] + S[k, 2] * D[e, b_, 2])
            for i in range(3):  # (a == b: the lower half of the block is written, not read)
                for j in range(3):
                    h = m_ * q[b_, i] * q[a, j] + FF[i, j] * dd + l_ * q[a, i] * q[b_, j]
                    if i == j:
                        h += dSd
                    H[3 * a + i, 3 * b_ + j] = W * h


@njit(**INLINE)
def projected_from_eigensystem(e, D, W, A, fw, DV, U, V, Lf, w3, N, H):
    """The projected Hessian H (12, 12) of tet e from dP/dF's eigensystem in the principal-stretch
    frame (Teran et al. 2005; Smith, de Goes and Kim 2018), each eigenvalue clamped at 0.

    ``A`` (3, 3): the block of the three scaling modes (overwritten by its eigen-decomposition);
    ``fw`` (2, 3): the eigenvalues of the flip (row 0) and twist (row 1) modes of the stretch pairs
    (0,1), (0,2), (1,2); ``W`` the element's rest volume; ``U``, ``V`` the rotation-variant SVD of F.
    H = N^T N for the weighted mode vectors N (9, 12); ``DV``, ``Lf``, ``w3`` are scratch.
    """
    jacobi_eigh(A, Lf, w3)
    sw = math.sqrt(W)
    for k in range(3):
        f = math.sqrt(max(w3[k], 0.0)) * sw
        for p in range(3):
            Lf[p, k] *= f
    for a in range(4):  # DV[a, p] = D_a . v_p
        for p in range(3):
            DV[a, p] = D[e, a, 0] * V[0, p] + D[e, a, 1] * V[1, p] + D[e, a, 2] * V[2, p]
    for k in range(3):  # scaling modes sum_p L[p, k] g_pp, g_pq = (D v_q) (x) u_p
        for a in range(4):
            for c in range(3):
                N[k, 3 * a + c] = (Lf[0, k] * DV[a, 0] * U[c, 0] + Lf[1, k] * DV[a, 1] * U[c, 1]
                                   + Lf[2, k] * DV[a, 2] * U[c, 2])  # fmt: skip
    for m in range(3):  # flips and twists of the pairs (0,1), (0,2), (1,2)
        p = 0 if m < 2 else 1
        qq = 1 if m == 0 else 2
        wf = math.sqrt(0.5 * max(fw[0, m], 0.0)) * sw
        wt = math.sqrt(0.5 * max(fw[1, m], 0.0)) * sw
        for a in range(4):
            for c in range(3):
                gpq = DV[a, qq] * U[c, p]
                gqp = DV[a, p] * U[c, qq]
                N[3 + m, 3 * a + c] = (gpq + gqp) * wf
                N[6 + m, 3 * a + c] = (gpq - gqp) * wt
    for i in range(12):
        for j in range(i, 12):
            acc = 0.0
            for k in range(9):
                acc += N[k, i] * N[k, j]
            H[i, j] = acc
            H[j, i] = acc


@njit(**INLINE)
def _tet_projected_hessian(e, D, vol, mu, lam, F, H, S, P, DV, U, V, Lf, A, b, sig, w3, N):
    """The projected Hessian H (12, 12) of StVK tet e from F (:func:`projected_from_eigensystem`
    with StVK's eigenvalues); the rest is scratch (S, P and b are overwritten)."""
    W, m_, l_ = vol[e], mu[e], lam[e]
    svd3(F, S, P, w3, U, sig, V, b)
    s0, s1, s2 = sig[0] * sig[0], sig[1] * sig[1], sig[2] * sig[2]
    T = 0.5 * (s0 + s1 + s2 - 3.0)
    for i in range(3):
        for j in range(3):
            A[i, j] = l_ * sig[i] * sig[j]
        A[i, i] += m_ * (3.0 * sig[i] * sig[i] - 1.0) + l_ * T
    for m in range(3):  # flip and twist eigenvalues of the pairs (0,1), (0,2), (1,2)
        p = 0 if m < 2 else 1
        qq = 1 if m == 0 else 2
        base = m_ * (sig[p] * sig[p] + sig[qq] * sig[qq] - 1.0) + l_ * T
        cross = m_ * sig[p] * sig[qq]
        b[0, m] = base + cross
        b[1, m] = base - cross
    projected_from_eigensystem(e, D, W, A, b, DV, U, V, Lf, w3, N, H)


@njit(**JIT)
def tet_run(x, st, order, D, vol, mu, lam, project, grad, data, slots, g_out, H_out, mode):
    F, S, P, FF = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    U, V, Lf, A, b = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    q = np.empty((4, 3))
    w3, sig = np.empty(3), np.empty(3)
    N = np.empty((9, 12))
    g = np.empty(12)
    H = np.empty((12, 12))
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        total += _tet_energy_gradient(e, x, st, D, vol, mu, lam, g, F, S, P)
        if mode == GRADIENT:
            scatter_gradient(e, st, g, grad, 4)
            continue
        if project:
            _tet_projected_hessian(e, D, vol, mu, lam, F, H, S, P, q, U, V, Lf, A, b, sig, w3, N)
        else:
            _tet_exact_hessian(e, D, vol, mu, lam, F, S, q, FF, H)
        if mode == SCATTER:
            scatter(e, st, g, H, grad, data, slots, 4)
        else:
            g_out[e] = g
            for i in range(12):
                for j in range(i, 12):
                    H_out[e, i, j] = H[i, j]
                    H_out[e, j, i] = H[i, j]
    return total

