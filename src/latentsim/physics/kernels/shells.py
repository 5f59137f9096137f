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
(``core.project_psd`` with ``core.translation_free_basis``).  The ``*_energy``,
``*_energy_gradient`` (one state or many, ``core.as_lanes``) and ``*_run`` kernels follow the
calling convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT, NO_FRAME, as_lanes, emit, energy_gradient_lanes, lane_count, matmul3, project_psd, run_stencils, skew
from latentsim.physics.kernels.tets import stvk_stress


@njit(**INLINE)
def _membrane_F(e, x, st, G, F, L):
    """F (3, 2, L) = sum_a x_a G_a^T of triangle e in each lane of x (n, 3, L)."""
    v0, v1, v2 = st[e, 0], st[e, 1], st[e, 2]
    for i in range(3):
        for r in range(2):
            g0, g1, g2 = G[e, 0, r], G[e, 1, r], G[e, 2, r]
            for s in range(L):
                F[i, r, s] = x[v0, i, s] * g0 + x[v1, i, s] * g1 + x[v2, i, s] * g2


@njit(**JIT)
def membrane_energy(x, st, order, G, K, mu, lam):
    """sum_t Abar h (mu ||E||^2 + lam/2 tr(E)^2), F = sum_a x_a G_a^T (3, 2), in each lane of
    x (n, 3) or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    F = np.empty((3, 2, L))
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        _membrane_F(e, xl, st, G, F, L)
        Ke, m_, l_ = K[e], mu[e], lam[e]
        for s in range(L):
            e00 = 0.5 * (F[0, 0, s] ** 2 + F[1, 0, s] ** 2 + F[2, 0, s] ** 2 - 1.0)
            e11 = 0.5 * (F[0, 1, s] ** 2 + F[1, 1, s] ** 2 + F[2, 1, s] ** 2 - 1.0)
            e01 = 0.5 * (F[0, 0, s] * F[0, 1, s] + F[1, 0, s] * F[1, 1, s] + F[2, 0, s] * F[2, 1, s])
            tr = e00 + e11
            total[s] += Ke * (m_ * (e00 * e00 + e11 * e11 + 2.0 * e01 * e01) + 0.5 * l_ * tr * tr)
    return total


@njit(**INLINE)
def _membrane_scratch(L):
    """The lanes of ``_membrane_energy_gradient``: g (9, L), F (3, 2, L), S (2, 2, L), tr, nE2 (L,)."""
    return np.empty((9, L)), np.empty((3, 2, L)), np.empty((2, 2, L)), np.empty(L), np.empty(L)


@njit(**INLINE)
def _membrane_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)) and gradient g (9, L) = K P G^T of triangle e in each lane
    of x (n, 3, L); leaves F (3, 2, L) and S = 2 mu E + lam tr(E) I (2, 2, L) in ``work``
    (``_membrane_scratch``)."""
    G, K, mu, lam = args
    g, F, S, tr, nE2 = work
    _membrane_F(e, x, st, G, F, L)
    Ke = K[e]
    stvk_stress(F, S, tr, nE2, mu[e], lam[e], Ke, total, 2, L)
    for a in range(3):
        ga0, ga1 = G[e, a, 0], G[e, a, 1]
        for i in range(3):
            for s in range(L):
                acc = 0.0
                acc += (F[i, 0, s] * S[0, 0, s] + F[i, 1, s] * S[1, 0, s]) * ga0
                acc += (F[i, 0, s] * S[0, 1, s] + F[i, 1, s] * S[1, 1, s]) * ga1
                g[3 * a + i, s] = Ke * acc


@njit(**JIT)
def membrane_energy_gradient(x, st, order, G, K, mu, lam, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_membrane_energy_gradient, _membrane_scratch, x, st, order, (G, K, mu, lam), grad, 3)


@njit(**INLINE)
def _membrane_run_scratch():
    """``core.run_stencils``' scratch: g (9,), H (9, 9), ``_membrane_scratch(1)`` on g, F, S and
    the Hessian's (F, S, q, FF, M, V, BV, BH, wv)."""
    F, S, q, FF = np.empty((3, 2)), np.empty((2, 2)), np.empty((3, 3)), np.empty((3, 3))
    g, H = np.empty(9), np.empty((9, 9))
    M, V, BV, BH = np.empty((6, 6)), np.empty((6, 6)), np.empty((9, 6)), np.empty((9, 6))
    work = g.reshape((9, 1)), F.reshape((3, 2, 1)), S.reshape((2, 2, 1)), np.empty(1), np.empty(1)
    return g, H, work, (F, S, q, FF, M, V, BV, BH, np.empty(6))


@njit(**INLINE)
def _membrane_hessian(e, args, work, extra, project, B, H):
    """The exact or projected Hessian H (9, 9) of triangle e from F and S."""
    G, K, mu, lam = args
    F, S, q, FF, M, V, BV, BH, wv = extra
    m_, l_, Ke = mu[e], lam[e], K[e]
    for a in range(3):
        for i in range(3):
            q[a, i] = F[i, 0] * G[e, a, 0] + F[i, 1] * G[e, a, 1]
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


@njit(**JIT)
def membrane_run(x, st, order, G, K, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    """Per triangle the gradient and the (exact or projected) Hessian, scattered (SCATTER) or
    stored (STORE); returns the energy, the sum of ``membrane_energy_gradient``'s, to the bit."""
    return run_stencils(_membrane_energy_gradient, _membrane_hessian, _membrane_run_scratch, emit,
                        x, st, order, (G, K, mu, lam), project, B, grad, data, slots, g_out, H_out, mode, 3)  # fmt: skip


@njit(**INLINE)
def _wrap(d):
    """d - 2 pi round(d / 2 pi), rounding half to even like NumPy/PyTorch."""
    t = d / (2.0 * math.pi)
    r = math.floor(t + 0.5)
    if r - t == 0.5 and r % 2.0 != 0.0:  # exact half: to even
        r -= 1.0
    return d - 2.0 * math.pi * r


@njit(**INLINE)
def _hinge_theta(e, x, st, ev, da, db, N1, N2, theta, L):
    """Fills e, d_a, d_b, N1 = e x d_a, N2 = d_b x e (3, L) and theta (L,) of hinge e in each lane
    of x (n, 3, L) (theta first holds sin theta |N1| |N2|)."""
    i0, i1, i2, i3 = st[e, 0], st[e, 1], st[e, 2], st[e, 3]
    for i in range(3):
        for s in range(L):
            ev[i, s] = x[i1, i, s] - x[i0, i, s]
            da[i, s] = x[i2, i, s] - x[i0, i, s]
            db[i, s] = x[i3, i, s] - x[i0, i, s]
    for s in range(L):
        N1[0, s] = ev[1, s] * da[2, s] - ev[2, s] * da[1, s]
        N1[1, s] = ev[2, s] * da[0, s] - ev[0, s] * da[2, s]
        N1[2, s] = ev[0, s] * da[1, s] - ev[1, s] * da[0, s]
        N2[0, s] = db[1, s] * ev[2, s] - db[2, s] * ev[1, s]
        N2[1, s] = db[2, s] * ev[0, s] - db[0, s] * ev[2, s]
        N2[2, s] = db[0, s] * ev[1, s] - db[1, s] * ev[0, s]
        Le = math.sqrt(ev[0, s] ** 2 + ev[1, s] ** 2 + ev[2, s] ** 2)
        c0 = N1[1, s] * N2[2, s] - N1[2, s] * N2[1, s]
        c1 = N1[2, s] * N2[0, s] - N1[0, s] * N2[2, s]
        c2 = N1[0, s] * N2[1, s] - N1[1, s] * N2[0, s]
        theta[s] = (c0 * ev[0, s] + c1 * ev[1, s] + c2 * ev[2, s]) / Le
    for s in range(L):  # atan2 alone: the loops above stay vectorised
        theta[s] = math.atan2(theta[s], N1[0, s] * N2[0, s] + N1[1, s] * N2[1, s] + N1[2, s] * N2[2, s])


@njit(**JIT)
def hinge_energy(x, st, order, k, rest_angle):
    """sum_h k (theta - thetabar)^2, the difference wrapped to (-pi, pi], in each lane of
    x (n, 3) or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    ev, da, db, N1, N2 = np.empty((3, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L))
    theta = np.empty(L)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        _hinge_theta(e, xl, st, ev, da, db, N1, N2, theta, L)
        ke, ra = k[e], rest_angle[e]
        for s in range(L):
            d = _wrap(theta[s] - ra)
            total[s] += ke * d * d
    return total


@njit(**INLINE)
def _hinge_scratch(L):
    """The lanes of ``_hinge_energy_gradient``: g (12, L), e, d_a, d_b, N1, N2 (3, L),
    grad theta (4, 3, L), aux (7, L)."""
    return (np.empty((12, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L)),
            np.empty((4, 3, L)), np.empty((7, L)))  # fmt: skip


@njit(**INLINE)
def _hinge_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)), grad theta gr (4, 3, L) and the gradient g (12, L) =
    2 k d grad theta of hinge e in each lane of x (n, 3, L), in ``work`` (``_hinge_scratch``).

    Leaves e, d_a, d_b, N1, N2 (3, L) in ev, da, db, N1, N2 and, for ``_hinge_theta_hessian``,
    aux (7, L) = (d, |e|^2, |e|, |N1|^2, |N2|^2, t_a, t_b); aux[0] first holds theta."""
    kk, rest_angle = args
    g, ev, da, db, N1, N2, gr, aux = work
    _hinge_theta(e, x, st, ev, da, db, N1, N2, aux[0], L)
    ra, ke = rest_angle[e], kk[e]
    k2 = 2.0 * ke
    for s in range(L):
        d = _wrap(aux[0, s] - ra)
        L2 = ev[0, s] ** 2 + ev[1, s] ** 2 + ev[2, s] ** 2
        Le = math.sqrt(L2)
        q1 = N1[0, s] ** 2 + N1[1, s] ** 2 + N1[2, s] ** 2
        q2 = N2[0, s] ** 2 + N2[1, s] ** 2 + N2[2, s] ** 2
        ta = (da[0, s] * ev[0, s] + da[1, s] * ev[1, s] + da[2, s] * ev[2, s]) / L2
        tb = (db[0, s] * ev[0, s] + db[1, s] * ev[1, s] + db[2, s] * ev[2, s]) / L2
        aux[0, s], aux[1, s], aux[2, s], aux[3, s], aux[4, s], aux[5, s], aux[6, s] = d, L2, Le, q1, q2, ta, tb
        for i in range(3):
            gr[2, i, s] = -Le / q1 * N1[i, s]
            gr[3, i, s] = -Le / q2 * N2[i, s]
            gr[1, i, s] = -ta * gr[2, i, s] - tb * gr[3, i, s]
            gr[0, i, s] = -(gr[1, i, s] + gr[2, i, s] + gr[3, i, s])
        for r in range(4):
            for i in range(3):
                g[3 * r + i, s] = k2 * d * gr[r, i, s]
        total[s] += ke * d * d


@njit(**JIT)
def hinge_energy_gradient(x, st, order, kk, rest_angle, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_hinge_energy_gradient, _hinge_scratch, x, st, order, (kk, rest_angle), grad, 4)


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


@njit(**INLINE)
def _hinge_run_scratch():
    """``core.run_stencils``' scratch: g (12,), H (12, 12), ``_hinge_scratch(1)`` on g, ev, da, db,
    N1, N2, gr, aux and the Hessian's."""
    ev, da, db, N1, N2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    gr = np.empty((4, 3))  # grad theta per vertex
    aux = np.empty(7)
    g, H = np.empty(12), np.empty((12, 12))
    work = (g.reshape((12, 1)), ev.reshape((3, 1)), da.reshape((3, 1)), db.reshape((3, 1)), N1.reshape((3, 1)),
            N2.reshape((3, 1)), gr.reshape((4, 3, 1)), aux.reshape((7, 1)))  # fmt: skip
    M1, M2, Sk, T1, T2 = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    Ja = np.zeros((4, 3, 3))  # d ga / d x_c
    Jb = np.zeros((4, 3, 3))
    Ta = np.zeros((4, 3))  # d ta / d x_c
    Tb = np.zeros((4, 3))
    J = np.empty((4, 4, 3, 3))  # J[r, c] = d grad_r theta / d x_c
    M, V, BV, BH = np.empty((9, 9)), np.empty((9, 9)), np.empty((12, 9)), np.empty((12, 9))
    return g, H, work, (ev, da, db, N1, N2, gr, aux, M1, M2, Sk, T1, T2, Ja, Jb, Ta, Tb, J, M, V, BV, BH, np.empty(9))


@njit(**INLINE)
def _hinge_hessian(e, args, work, extra, project, B, H):
    """The exact or projected Hessian H (12, 12) of hinge e: 2k (grad grad^T + d sym(Hess theta))."""
    kk = args[0]
    ev, da, db, N1, N2, gr, aux, M1, M2, Sk, T1, T2, Ja, Jb, Ta, Tb, J, M, V, BV, BH, wv = extra
    d, L2, Le, q1, q2, ta, tb = aux[0], aux[1], aux[2], aux[3], aux[4], aux[5], aux[6]
    _hinge_theta_hessian(ev, da, db, N1, N2, gr, L2, Le, q1, q2, ta, tb, M1, M2, Sk, T1, T2, Ja, Jb, Ta, Tb, J)
    k2 = 2.0 * kk[e]
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


@njit(**JIT)
def hinge_run(x, st, order, kk, rest_angle, project, B, grad, data, slots, g_out, H_out, mode):
    """Per hinge the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``hinge_energy_gradient``'s, to the bit."""
    return run_stencils(_hinge_energy_gradient, _hinge_hessian, _hinge_run_scratch, emit,
                        x, st, order, (kk, rest_angle), project, B, grad, data, slots, g_out, H_out, mode, 4)  # fmt: skip
