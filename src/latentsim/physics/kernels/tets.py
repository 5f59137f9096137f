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
``tet_energy``, ``tet_energy_gradient`` (one state or many, ``core.as_lanes``) and
``tet_run`` follow the calling convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT, NO_FRAME, as_lanes, emit_upper, energy_gradient_lanes, jacobi_eigh, lane_count, run_stencils, svd3


@njit(**INLINE)
def _tet_F(e, x, st, D, F, L):
    """F (3, 3, L) = sum_a x_a D_a^T of tet e in each lane of x (n, 3, L)."""
    v0, v1, v2, v3 = st[e, 0], st[e, 1], st[e, 2], st[e, 3]
    for i in range(3):
        for j in range(3):
            d0, d1, d2, d3 = D[e, 0, j], D[e, 1, j], D[e, 2, j], D[e, 3, j]
            for s in range(L):
                acc = 0.0
                acc += x[v0, i, s] * d0
                acc += x[v1, i, s] * d1
                acc += x[v2, i, s] * d2
                acc += x[v3, i, s] * d3
                F[i, j, s] = acc


@njit(**JIT)
def tet_energy(x, st, order, D, vol, mu, lam):
    """sum_e W_e (mu ||E||^2 + lam/2 tr(E)^2) in each lane of x (n, 3) or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    F = np.empty((3, 3, L))
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        _tet_F(e, xl, st, D, F, L)
        W, m_, l_ = vol[e], mu[e], lam[e]
        for s in range(L):
            nE2 = 0.0
            tr = 0.0
            for i in range(3):
                for j in range(3):
                    c = F[0, i, s] * F[0, j, s] + F[1, i, s] * F[1, j, s] + F[2, i, s] * F[2, j, s]
                    Eij = 0.5 * (c - (1.0 if i == j else 0.0))
                    nE2 += Eij * Eij
                    if i == j:
                        tr += Eij
            total[s] += W * (m_ * nE2 + 0.5 * l_ * tr * tr)
    return total


@njit(**INLINE)
def stvk_stress(F, S, tr, nE2, m_, l_, W, total, c, L):
    """S (c, c, L) = 2 mu E + lam tr(E) I with E = (F^T F - I)/2 of F (3, c, L), and total (L,) +=
    W (mu ||E||^2 + lam/2 tr(E)^2), lane by lane: tets (c = 3) and shell membranes (c = 2,
    ``kernels.shells``); tr, nE2 (L,) scratch."""
    for i in range(c):
        for j in range(c):
            for s in range(L):
                S[i, j, s] = F[0, i, s] * F[0, j, s] + F[1, i, s] * F[1, j, s] + F[2, i, s] * F[2, j, s]
    for s in range(L):
        t = 0.0
        for i in range(c):
            t += S[i, i, s]
        tr[s] = 0.5 * (t - c)
        nE2[s] = 0.0
    for i in range(c):
        for j in range(c):
            if i == j:
                for s in range(L):
                    Eij = 0.5 * (S[i, j, s] - 1.0)
                    nE2[s] += Eij * Eij
                    S[i, j, s] = 2.0 * m_ * Eij + l_ * tr[s]
            else:
                for s in range(L):
                    Eij = 0.5 * (S[i, j, s] - 0.0)
                    nE2[s] += Eij * Eij
                    S[i, j, s] = 2.0 * m_ * Eij + 0.0
    for s in range(L):
        total[s] += W * (m_ * nE2[s] + 0.5 * l_ * tr[s] * tr[s])


@njit(**INLINE)
def _tet_scratch(L):
    """The lanes of ``_tet_energy_gradient``: g (12, L), F, S, P (3, 3, L), tr, nE2 (L,)."""
    return np.empty((12, L)), np.empty((3, 3, L)), np.empty((3, 3, L)), np.empty((3, 3, L)), np.empty(L), np.empty(L)


@njit(**INLINE)
def _tet_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)) and gradient g (12, L) = W D P^T of tet e in each lane of
    x (n, 3, L); leaves F and S = 2 mu E + lam tr(E) I (3, 3, L) in ``work`` (``_tet_scratch``)."""
    D, vol, mu, lam = args
    g, F, S, P, tr, nE2 = work
    _tet_F(e, x, st, D, F, L)
    W = vol[e]
    stvk_stress(F, S, tr, nE2, mu[e], lam[e], W, total, 3, L)
    for i in range(3):  # P = F S
        for j in range(3):
            for s in range(L):
                P[i, j, s] = F[i, 0, s] * S[0, j, s] + F[i, 1, s] * S[1, j, s] + F[i, 2, s] * S[2, j, s]
    for a in range(4):
        d0, d1, d2 = D[e, a, 0], D[e, a, 1], D[e, a, 2]
        for i in range(3):
            for s in range(L):
                g[3 * a + i, s] = W * (P[i, 0, s] * d0 + P[i, 1, s] * d1 + P[i, 2, s] * d2)


@njit(**JIT)
def tet_energy_gradient(x, st, order, D, vol, mu, lam, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_tet_energy_gradient, _tet_scratch, x, st, order, (D, vol, mu, lam), grad, 4)


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


@njit(**INLINE)
def _tet_run_scratch():
    """``core.run_stencils``' scratch: g (12,), H (12, 12), ``_tet_scratch(1)`` on g, F, S, P and
    the Hessians' (F, S, P, FF, q, U, V, Lf, A, b, w3, sig, N)."""
    F, S, P, FF = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    U, V, Lf, A, b = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    q = np.empty((4, 3))
    w3, sig = np.empty(3), np.empty(3)
    N = np.empty((9, 12))
    g = np.empty(12)
    H = np.empty((12, 12))
    work = g.reshape((12, 1)), F.reshape((3, 3, 1)), S.reshape((3, 3, 1)), P.reshape((3, 3, 1)), np.empty(1), np.empty(1)
    return g, H, work, (F, S, P, FF, q, U, V, Lf, A, b, w3, sig, N)


@njit(**INLINE)
def _tet_hessian(e, args, work, extra, project, basis, H):
    """The projected or the exact Hessian of tet e (its upper triangle at least) from F and S."""
    D, vol, mu, lam = args
    F, S, P, FF, q, U, V, Lf, A, b, w3, sig, N = extra
    if project:
        _tet_projected_hessian(e, D, vol, mu, lam, F, H, S, P, q, U, V, Lf, A, b, sig, w3, N)
    else:
        _tet_exact_hessian(e, D, vol, mu, lam, F, S, q, FF, H)


@njit(**JIT)
def tet_run(x, st, order, D, vol, mu, lam, project, grad, data, slots, g_out, H_out, mode):
    """Per tet the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``tet_energy_gradient``'s, to the bit."""
    return run_stencils(_tet_energy_gradient, _tet_hessian, _tet_run_scratch, emit_upper,
                        x, st, order, (D, vol, mu, lam), project, NO_FRAME, grad, data, slots, g_out, H_out, mode, 4)  # fmt: skip
