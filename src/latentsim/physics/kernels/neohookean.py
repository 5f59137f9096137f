r"""Compiled stable neo-Hookean tetrahedra (``physics.neohookean.StableNeoHookeanTets``).

With D (4, 3) the barycentric gradients of tet e, F = sum_a x_a D_a^T,
I_C = ||F||_F^2, J = det F, cof F = dJ/dF (columns f1 x f2, f2 x f0, f0 x f1),
Lame parameters (mu, lam) of the energy (already reparametrised, see
``physics.neohookean``), alpha = 1 + 3 mu / (4 lam) and W the rest volume:

    energy      W [mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 log(I_C + 1) - Psi(I)],
    stress      P = s F + p cof F,   s = mu I_C / (I_C + 1),  p = lam (J - alpha),
    gradient    g_a = W P D_a,
    Hessian     H_(a i)(b j) = W [ s (D_a . D_b) d_ij + h q_(a,i) q_(b,j) + lam c_(a,i) c_(b,j)
                                   + p eps_ijm (F (D_a x D_b))_m ],
                q_a = F D_a,  c_a = (cof F) D_a,  h = 2 mu / (I_C + 1)^2.

The projection clamps the analytic eigensystem of dP/dF in the principal-stretch
frame of the rotation-variant SVD F = U diag(sigma) V^T (Smith, de Goes, Kim
2018, section 4; the same frame as the StVK kernels of ``kernels.tets``):

    scaling (3): eigenpairs (lambda_k, w_k) of A_ij = s d_ij + h sigma_i sigma_j
                 + lam J_i J_j + p sigma_k [i != j, k the third index],
                 J_i = dJ/dsigma_i (the product of the other two),
                 eigenmatrix U diag(w_k) V^T;
    flip  (ij):  s - p sigma_k,  eigenmatrix U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2;
    twist (ij):  s + p sigma_k,  eigenmatrix U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2;

H_e^+ = W sum_k max(lambda_k, 0) g_k g_k^T with g_k = B^T vec(Q_k).  ``snh_energy``,
``snh_energy_gradient`` (one state or many, ``core.as_lanes``) and ``snh_run`` follow the
calling convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT, NO_FRAME, as_lanes, emit_upper, energy_gradient_lanes, lane_count, run_stencils, svd3
from latentsim.physics.kernels.tets import _tet_F, projected_from_eigensystem

LOG4 = math.log(4.0)


@njit(**INLINE)
def _cofactor(F, C, J, L):
    """C (3, 3, L) = cof F = dJ/dF (columns f1 x f2, f2 x f0, f0 x f1 of the columns f_j of F) and
    J (L,) = det F, in each lane of F (3, 3, L)."""
    for j in range(3):
        a, b = (j + 1) % 3, (j + 2) % 3
        for s in range(L):
            C[0, j, s] = F[1, a, s] * F[2, b, s] - F[2, a, s] * F[1, b, s]
            C[1, j, s] = F[2, a, s] * F[0, b, s] - F[0, a, s] * F[2, b, s]
            C[2, j, s] = F[0, a, s] * F[1, b, s] - F[1, a, s] * F[0, b, s]
    for s in range(L):
        J[s] = F[0, 0, s] * C[0, 0, s] + F[1, 0, s] * C[1, 0, s] + F[2, 0, s] * C[2, 0, s]


@njit(**INLINE)
def _squared_norm(F, Ic, L):
    """Ic (L,) = ||F||_F^2 in each lane of F (3, 3, L)."""
    for s in range(L):
        acc = 0.0
        for i in range(3):
            for j in range(3):
                acc += F[i, j, s] * F[i, j, s]
        Ic[s] = acc


@njit(**INLINE)
def _density(Ic, J, m_, l_):
    """Psi(F) - Psi(I) from the invariants I_C and J."""
    ratio = m_ / l_ if l_ != 0.0 else 0.0  # lam = 0: a zero-weight cubature element (mu = 0 too)
    alpha = 1.0 + 0.75 * ratio
    rest = 0.28125 * m_ * ratio - 0.5 * m_ * LOG4  # lam/2 (1 - alpha)^2 - mu/2 log 4
    return 0.5 * m_ * (Ic - 3.0) + 0.5 * l_ * (J - alpha) ** 2 - 0.5 * m_ * math.log(Ic + 1.0) - rest


@njit(**JIT)
def snh_energy(x, st, order, D, vol, mu, lam):
    """sum_e W_e (Psi(F_e) - Psi(I)) in each lane of x (n, 3) or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    F, C = np.empty((3, 3, L)), np.empty((3, 3, L))
    J, Ic = np.empty(L), np.empty(L)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        _tet_F(e, xl, st, D, F, L)
        _cofactor(F, C, J, L)
        _squared_norm(F, Ic, L)
        W, m_, l_ = vol[e], mu[e], lam[e]
        for s in range(L):
            total[s] += W * _density(Ic[s], J[s], m_, l_)
    return total


@njit(**INLINE)
def _snh_scratch(L):
    """The lanes of ``_snh_energy_gradient``: g (12, L), F, C, P (3, 3, L), inv (4, L)."""
    return np.empty((12, L)), np.empty((3, 3, L)), np.empty((3, 3, L)), np.empty((3, 3, L)), np.empty((4, L))


@njit(**INLINE)
def _snh_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)) and gradient g (12, L) = W D P^T of tet e in each lane of
    x (n, 3, L); leaves F, C = cof F (3, 3, L) and inv (4, L) = (I_C, J, s, p) in ``work``
    (``_snh_scratch``)."""
    D, vol, mu, lam = args
    g, F, C, P, inv = work
    _tet_F(e, x, st, D, F, L)
    W, m_, l_ = vol[e], mu[e], lam[e]
    _cofactor(F, C, inv[1], L)
    _squared_norm(F, inv[0], L)
    alpha = 1.0 + 0.75 * (m_ / l_ if l_ != 0.0 else 0.0)
    for s in range(L):
        Ic = inv[0, s]
        inv[2, s] = m_ * Ic / (Ic + 1.0)
        inv[3, s] = l_ * (inv[1, s] - alpha)
    for i in range(3):
        for j in range(3):
            for s in range(L):
                P[i, j, s] = inv[2, s] * F[i, j, s] + inv[3, s] * C[i, j, s]
    for a in range(4):
        d0, d1, d2 = D[e, a, 0], D[e, a, 1], D[e, a, 2]
        for i in range(3):
            for s in range(L):
                g[3 * a + i, s] = W * (P[i, 0, s] * d0 + P[i, 1, s] * d1 + P[i, 2, s] * d2)
    for s in range(L):
        total[s] += W * _density(inv[0, s], inv[1, s], m_, l_)


@njit(**JIT)
def snh_energy_gradient(x, st, order, D, vol, mu, lam, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_snh_energy_gradient, _snh_scratch, x, st, order, (D, vol, mu, lam), grad, 4)


@njit(**INLINE)
def _snh_exact_hessian(e, D, vol, mu, lam, F, C, inv, q, c, H):
    """The exact Hessian of tet e, written to the upper triangle of H (12, 12) only (all that
    ``scatter`` reads); q, c (4, 3) scratch."""
    W, l_ = vol[e], lam[e]
    Ic, s, p = inv[0], inv[2], inv[3]
    h = 2.0 * mu[e] / ((Ic + 1.0) * (Ic + 1.0))
    for a in range(4):
        for i in range(3):
            q[a, i] = F[i, 0] * D[e, a, 0] + F[i, 1] * D[e, a, 1] + F[i, 2] * D[e, a, 2]
            c[a, i] = C[i, 0] * D[e, a, 0] + C[i, 1] * D[e, a, 1] + C[i, 2] * D[e, a, 2]
    for a in range(4):
        for b_ in range(a, 4):
            dd = D[e, a, 0] * D[e, b_, 0] + D[e, a, 1] * D[e, b_, 1] + D[e, a, 2] * D[e, b_, 2]
            # n = D_a x D_b, w = F n: the second derivative of J
            n0 = D[e, a, 1] * D[e, b_, 2] - D[e, a, 2] * D[e, b_, 1]
            n1 = D[e, a, 2] * D[e, b_, 0] - D[e, a, 0] * D[e, b_, 2]
            n2 = D[e, a, 0] * D[e, b_, 1] - D[e, a, 1] * D[e, b_, 0]
            w0 = p * (F[0, 0] * n0 + F[0, 1] * n1 + F[0, 2] * n2)
            w1 = p * (F[1, 0] * n0 + F[1, 1] * n1 + F[1, 2] * n2)
            w2 = p * (F[2, 0] * n0 + F[2, 1] * n1 + F[2, 2] * n2)
            for i in range(3):
                for j in range(3):
                    v = h * q[a, i] * q[b_, j] + l_ * c[a, i] * c[b_, j]
                    if i == j:
                        v += s * dd
                    H[3 * a + i, 3 * b_ + j] = W * v
            H[3 * a + 0, 3 * b_ + 1] += W * w2
            H[3 * a + 1, 3 * b_ + 0] -= W * w2
            H[3 * a + 2, 3 * b_ + 0] += W * w1
            H[3 * a + 0, 3 * b_ + 2] -= W * w1
            H[3 * a + 1, 3 * b_ + 2] += W * w0
            H[3 * a + 2, 3 * b_ + 1] -= W * w0


@njit(**INLINE)
def _snh_projected_hessian(e, D, vol, mu, lam, F, inv, H, S, P, DV, U, V, Lf, A, b, sig, w3, N):
    """The projected Hessian H (12, 12) of neo-Hookean tet e from F
    (:func:`~latentsim.physics.kernels.tets.projected_from_eigensystem` with this energy's
    eigenvalues: flips s - p sigma_k, twists s + p sigma_k); the rest is scratch."""
    W, l_ = vol[e], lam[e]
    Ic, s, p = inv[0], inv[2], inv[3]
    h = 2.0 * mu[e] / ((Ic + 1.0) * (Ic + 1.0))
    svd3(F, S, P, w3, U, sig, V, b)
    Jd0, Jd1, Jd2 = sig[1] * sig[2], sig[0] * sig[2], sig[0] * sig[1]
    A[0, 0] = s + h * sig[0] * sig[0] + l_ * Jd0 * Jd0
    A[1, 1] = s + h * sig[1] * sig[1] + l_ * Jd1 * Jd1
    A[2, 2] = s + h * sig[2] * sig[2] + l_ * Jd2 * Jd2
    A[0, 1] = A[1, 0] = h * sig[0] * sig[1] + l_ * Jd0 * Jd1 + p * sig[2]
    A[0, 2] = A[2, 0] = h * sig[0] * sig[2] + l_ * Jd0 * Jd2 + p * sig[1]
    A[1, 2] = A[2, 1] = h * sig[1] * sig[2] + l_ * Jd1 * Jd2 + p * sig[0]
    for m in range(3):  # the pairs (0,1), (0,2), (1,2); k the third index
        k = 2 - m
        b[0, m] = s - p * sig[k]
        b[1, m] = s + p * sig[k]
    projected_from_eigensystem(e, D, W, A, b, DV, U, V, Lf, w3, N, H)


@njit(**INLINE)
def _snh_run_scratch():
    """``core.run_stencils``' scratch: g (12,), H (12, 12), ``_snh_scratch(1)`` on g, F, C, P, inv
    and the Hessians' (F, C, P, S, inv, q, c, U, V, Lf, A, b, w3, sig, N)."""
    F, C, P, S = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    U, V, Lf, A, b = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    q, c = np.empty((4, 3)), np.empty((4, 3))
    w3, sig, inv = np.empty(3), np.empty(3), np.empty(4)
    N = np.empty((9, 12))
    g = np.empty(12)
    H = np.empty((12, 12))
    work = g.reshape((12, 1)), F.reshape((3, 3, 1)), C.reshape((3, 3, 1)), P.reshape((3, 3, 1)), inv.reshape((4, 1))
    return g, H, work, (F, C, P, S, inv, q, c, U, V, Lf, A, b, w3, sig, N)


@njit(**INLINE)
def _snh_hessian(e, args, work, extra, project, basis, H):
    """The projected or the exact Hessian of tet e (its upper triangle at least) from F, cof F and
    the invariants."""
    D, vol, mu, lam = args
    F, C, P, S, inv, q, c, U, V, Lf, A, b, w3, sig, N = extra
    if project:
        _snh_projected_hessian(e, D, vol, mu, lam, F, inv, H, S, P, q, U, V, Lf, A, b, sig, w3, N)
    else:
        _snh_exact_hessian(e, D, vol, mu, lam, F, C, inv, q, c, H)


@njit(**JIT)
def snh_run(x, st, order, D, vol, mu, lam, project, grad, data, slots, g_out, H_out, mode):
    """Per tet the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``snh_energy_gradient``'s, to the bit."""
    return run_stencils(_snh_energy_gradient, _snh_hessian, _snh_run_scratch, emit_upper,
                        x, st, order, (D, vol, mu, lam), project, NO_FRAME, grad, data, slots, g_out, H_out, mode, 4)  # fmt: skip
