r"""Compiled shell membranes and hinges (``physics.shells``): energy, gradient, Hessian per stencil.

* StVK membrane triangles: the tets' formulas (``kernels.tets``) with the
  barycentric gradients G (3, 2) in the rest frame and W -> Abar h:
  g_a = K P G_a, H_(a i)(b j) = K [ (G S G^T)_ab d_ij + mu q_(b,i) q_(a,j)
  + mu (F F^T)_ij (G G^T)_ab + lam q_(a,i) q_(b,j) ].
* Hinges, energy k (theta - thetabar)^2 of the dihedral angle theta
  (``physics.shells.ShellHinge``): g = 2 k d grad theta and
  H = 2 k (grad theta grad theta^T + d Hess theta), d = theta - thetabar wrapped,
  with grad_a theta = -L N1/|N1|^2, grad_b theta = -L N2/|N2|^2 and the Hessian
  of theta from d(N/|N|^2) = (I - 2 n n^T)/|N|^2 dN.

Both projections clamp the eigenvalues of the translation-free block
(``core.project_psd`` with ``core.translation_free_basis``).  The ``*_energy``
and ``*_run`` kernels follow the calling convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import GRADIENT, INLINE, JIT, NO_FRAME, emit, matmul3, project_psd, scatter_gradient, skew


@njit(**JIT)
def membrane_energy(x, st, order, G, K, mu, lam):
    """sum_t Abar h (mu ||E||^2 + lam/2 tr(E)^2), F = sum_a x_a G_a^T (3, 2)."""
    F = np.empty((3, 2))
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        for i in range(3):
            for q in range(2):
                F[i, q] = x[st[e, 0], i] * G[e, 0, q] + x[st[e, 1], i] * G[e, 1, q] + x[st[e, 2], i] * G[e, 2, q]
        e00 = 0.5 * (F[0, 0] ** 2 + F[1, 0] ** 2 + F[2, 0] ** 2 - 1.0)
        e11 = 0.5 * (F[0, 1] ** 2 + F[1, 1] ** 2 + F[2, 1] ** 2 - 1.0)
        e01 = 0.5 * (F[0, 0] * F[0, 1] + F[1, 0] * F[1, 1] + F[2, 0] * F[2, 1])
        tr = e00 + e11
        total += K[e] * (mu[e] * (e00 * e00 + e11 * e11 + 2.0 * e01 * e01) + 0.5 * lam[e] * tr * tr)
    return total


@njit(**JIT)
def membrane_run(x, st, order, G, K, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    total = 0.0
    F = np.empty((3, 2))
    S = np.empty((2, 2))
    q = np.empty((3, 3))
    FF = np.empty((3, 3))
    g = np.empty(9)
    H = np.empty((9, 9))
    M, V, BV, BH = np.empty((6, 6)), np.empty((6, 6)), np.empty((9, 6)), np.empty((9, 6))
    wv = np.empty(6)
    for ii in range(order.shape[0]):
        e = order[ii]
        for i in range(3):
            for r in range(2):
                F[i, r] = x[st[e, 0], i] * G[e, 0, r] + x[st[e, 1], i] * G[e, 1, r] + x[st[e, 2], i] * G[e, 2, r]
        m_, l_, Ke = mu[e], lam[e], K[e]
        for r in range(2):
            for s in range(2):
                S[r, s] = F[0, r] * F[0, s] + F[1, r] * F[1, s] + F[2, r] * F[2, s]
        tr = 0.5 * (S[0, 0] + S[1, 1] - 2.0)
        nE2 = 0.0
        for r in range(2):
            for s in range(2):
                Ers = 0.5 * (S[r, s] - (1.0 if r == s else 0.0))
                nE2 += Ers * Ers
                S[r, s] = 2.0 * m_ * Ers + (l_ * tr if r == s else 0.0)
        total += Ke * (m_ * nE2 + 0.5 * l_ * tr * tr)
        for a in range(3):
            for i in range(3):
                acc = 0.0
                for r in range(2):
                    acc += (F[i, 0] * S[0, r] + F[i, 1] * S[1, r]) * G[e, a, r]
                g[3 * a + i] = Ke * acc
                q[a, i] = F[i, 0] * G[e, a, 0] + F[i, 1] * G[e, a, 1]
        if mode == GRADIENT:
            scatter_gradient(e, st, g, grad, 3)
            continue
        for i in range(3):
            for jj in range(3):
                FF[i, jj] = m_ * (F[i, 0] * F[jj, 0] + F[i, 1] * F[jj, 1])
        for a in range(3):
            for b in range(a, 3):
                gsg = 0.0
                gg = G[e, a, 0] * G[e, b, 0] + G[e, a, 1] * G[e, b, 1]
                for r in range(2):
                    for s in range(2):
                        gsg += G[e, a, r] * S[r, s] * G[e, b, s]
                for i in range(3):
                    for jj in range(3):
                        h = m_ * q[b, i] * q[a, jj] + FF[i, jj] * gg + l_ * q[a, i] * q[b, jj]
                        if i == jj:
                            h += gsg
                        H[3 * a + i, 3 * b + jj] = Ke * h
                        H[3 * b + jj, 3 * a + i] = Ke * h
        if project:
            project_psd(H, B, M, BH, V, wv, BV, NO_FRAME, False)
        emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 3)
    return total



@njit(**INLINE)
def _wrap(d):
    """d - 2 pi round(d / 2 pi), rounding half to even like NumPy/PyTorch."""
    t = d / (2.0 * math.pi)
    r = math.floor(t + 0.5)
    if r - t == 0.5 and r % 2.0 != 0.0:  # exact half: to even
        r -= 1.0
    return d - 2.0 * math.pi * r


@njit(**INLINE)
def _hinge_theta(e, x, st, ev, da, db, N1, N2):
    """Fills e, d_a, d_b, N1 = e x d_a, N2 = d_b x e; returns theta."""
    i0 = st[e, 0]
    for i in range(3):
        ev[i] = x[st[e, 1], i] - x[i0, i]
        da[i] = x[st[e, 2], i] - x[i0, i]
        db[i] = x[st[e, 3], i] - x[i0, i]
    N1[0], N1[1], N1[2] = ev[1] * da[2] - ev[2] * da[1], ev[2] * da[0] - ev[0] * da[2], ev[0] * da[1] - ev[1] * da[0]
    N2[0], N2[1], N2[2] = db[1] * ev[2] - db[2] * ev[1], db[2] * ev[0] - db[0] * ev[2], db[0] * ev[1] - db[1] * ev[0]
    L = math.sqrt(ev[0] ** 2 + ev[1] ** 2 + ev[2] ** 2)
    c0 = N1[1] * N2[2] - N1[2] * N2[1]
    c1 = N1[2] * N2[0] - N1[0] * N2[2]
    c2 = N1[0] * N2[1] - N1[1] * N2[0]
    s = (c0 * ev[0] + c1 * ev[1] + c2 * ev[2]) / L
    c = N1[0] * N2[0] + N1[1] * N2[1] + N1[2] * N2[2]
    return math.atan2(s, c)


@njit(**JIT)
def hinge_energy(x, st, order, k, rest_angle):
    """sum_h k (theta - thetabar)^2, the difference wrapped to (-pi, pi]."""
    ev, da, db, N1, N2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        d = _wrap(_hinge_theta(e, x, st, ev, da, db, N1, N2) - rest_angle[e])
        total += k[e] * d * d
    return total




@njit(**INLINE)
def _hinge_gradient(e, x, st, kk, rest_angle, ev, da, db, N1, N2, gr, g):
    """Energy of hinge e, grad theta gr (4, 3) and the gradient g (12,) = 2 k d grad theta.

    Leaves e, d_a, d_b, N1, N2 in ev, da, db, N1, N2; returns (energy, d, L2, L, q1, q2, t_a, t_b)
    for ``_hinge_theta_hessian``."""
    theta = _hinge_theta(e, x, st, ev, da, db, N1, N2)
    d = _wrap(theta - rest_angle[e])
    L2 = ev[0] ** 2 + ev[1] ** 2 + ev[2] ** 2
    L = math.sqrt(L2)
    q1 = N1[0] ** 2 + N1[1] ** 2 + N1[2] ** 2
    q2 = N2[0] ** 2 + N2[1] ** 2 + N2[2] ** 2
    ta = (da[0] * ev[0] + da[1] * ev[1] + da[2] * ev[2]) / L2
    tb = (db[0] * ev[0] + db[1] * ev[1] + db[2] * ev[2]) / L2
    for i in range(3):
        gr[2, i] = -L / q1 * N1[i]
        gr[3, i] = -L / q2 * N2[i]
        gr[1, i] = -ta * gr[2, i] - tb * gr[3, i]
        gr[0, i] = -(gr[1, i] + gr[2, i] + gr[3, i])
    k2 = 2.0 * kk[e]
    for r in range(4):
        for i in range(3):
            g[3 * r + i] = k2 * d * gr[r, i]
    return kk[e] * d * d, d, L2, L, q1, q2, ta, tb


@njit(**INLINE)
def _hinge_theta_hessian(ev, da, db, N1, N2, gr, L2, L, q1, q2, ta, tb, M1, M2, Sk, T1, T2, Ja, Jb, Ta, Tb, J):
    """J[r, c] = d grad_r theta / d x_c (4, 4, 3, 3), the Hessian of theta (unsymmetrised), from
    ``_hinge_gradient``'s quantities; the rest is scratch (Ja, Jb, Ta, Tb: the Jacobians of g_a,
    g_b, t_a, t_b)."""
    # M_s = (I - 2 n n^T) / |N|^2, n = N / |N|
    for i in range(3):
        for j in range(3):
            dl = 1.0 if i == j else 0.0
            M1[i, j] = (dl - 2.0 * N1[i] * N1[j] / q1) / q1
            M2[i, j] = (dl - 2.0 * N2[i] * N2[j] / q2) / q2
    # ga_da = -L M1 [e]x ; ga_e = -(N1/q1) eh^T + L M1 [da]x
    skew(ev, Sk)
    matmul3(M1, Sk, T1, -L)  # ga_da
    matmul3(M2, Sk, T2, L)  # gb_db
    for i in range(3):
        for j in range(3):
            Ja[2, i, j] = T1[i, j]
            Jb[3, i, j] = T2[i, j]
            Ja[3, i, j] = 0.0
            Jb[2, i, j] = 0.0
    skew(da, Sk)
    matmul3(M1, Sk, T1, L)
    skew(db, Sk)
    matmul3(M2, Sk, T2, -L)
    for i in range(3):
        for j in range(3):
            Ja[1, i, j] = -(N1[i] / q1) * ev[j] / L + T1[i, j]  # ga_e
            Jb[1, i, j] = -(N2[i] / q2) * ev[j] / L + T2[i, j]  # gb_e
            Ja[0, i, j] = -(Ja[1, i, j] + Ja[2, i, j])
            Jb[0, i, j] = -(Jb[1, i, j] + Jb[3, i, j])
    for j in range(3):
        Ta[2, j] = ev[j] / L2  # ta_da
        Ta[1, j] = da[j] / L2 - 2.0 * ta / L2 * ev[j]  # ta_e
        Ta[0, j] = -(Ta[1, j] + Ta[2, j])
        Ta[3, j] = 0.0
        Tb[3, j] = ev[j] / L2
        Tb[1, j] = db[j] / L2 - 2.0 * tb / L2 * ev[j]
        Tb[0, j] = -(Tb[1, j] + Tb[3, j])
        Tb[2, j] = 0.0
    for c in range(4):
        for i in range(3):
            for j in range(3):
                j1 = -ta * Ja[c, i, j] - gr[2, i] * Ta[c, j] - tb * Jb[c, i, j] - gr[3, i] * Tb[c, j]
                J[1, c, i, j] = j1
                J[2, c, i, j] = Ja[c, i, j]
                J[3, c, i, j] = Jb[c, i, j]
                J[0, c, i, j] = -(j1 + Ja[c, i, j] + Jb[c, i, j])


@njit(**JIT)
def hinge_run(x, st, order, kk, rest_angle, project, B, grad, data, slots, g_out, H_out, mode):
    total = 0.0
    ev, da, db, N1, N2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    gr = np.empty((4, 3))  # grad theta per vertex
    g = np.empty(12)
    H = np.empty((12, 12))
    M1, M2, Sk, T1, T2 = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Ja = np.zeros((4, 3, 3))  # d ga / d x_c
    Jb = np.zeros((4, 3, 3))
    Ta = np.zeros((4, 3))  # d ta / d x_c
    Tb = np.zeros((4, 3))
    J = np.empty((4, 4, 3, 3))  # J[r, c] = d grad_r theta / d x_c
    M, V, BV, BH = np.empty((9, 9)), np.empty((9, 9)), np.empty((12, 9)), np.empty((12, 9))
    wv = np.empty(9)
    for ii in range(order.shape[0]):
        e = order[ii]
        en, d, L2, L, q1, q2, ta, tb = _hinge_gradient(e, x, st, kk, rest_angle, ev, da, db, N1, N2, gr, g)
        total += en
        if mode == GRADIENT:
            scatter_gradient(e, st, g, grad, 4)
            continue
        _hinge_theta_hessian(ev, da, db, N1, N2, gr, L2, L, q1, q2, ta, tb, M1, M2, Sk, T1, T2, Ja, Jb, Ta, Tb, J)
        k2 = 2.0 * kk[e]
        # H = 2k (grad grad^T + d sym(Hess theta))
        for r in range(4):
            for i in range(3):
                p = 3 * r + i
                for c in range(4):
                    for j in range(3):
                        qq = 3 * c + j
                        if qq < p:
                            continue
                        ht = 0.5 * (J[r, c, i, j] + J[c, r, j, i])
                        h = k2 * (gr[r, i] * gr[c, j] + d * ht)
                        H[p, qq] = h
                        H[qq, p] = h
        if project:
            project_psd(H, B, M, BH, V, wv, BV, NO_FRAME, False)
        emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 4)
    return total
