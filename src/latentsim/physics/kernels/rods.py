r"""Compiled rod stretching and bending (``physics.rods``): energy, gradient, Hessian per stencil.

* Stretch, e = x1 - x0, u = e/|e|: g = [-f, f], f = ks (|e|/|ebar| - 1) u, and
  H = [[K, -K], [-K, K]], K = ks/|ebar| [u u^T + c (I - u u^T)], c = 1 - |ebar|/|e|
  (clamped at 0 when projecting: the exact eigenvalue clamp).
* Bend, phi(A, B, C) = alpha (A B - C^2) / (c0 + C)^2 of the Gram invariants of
  a = e_{i-1}, b = e_i: H_(a,b) = sum_kl phi_kl j_k j_l^T + [[2 phi_A, phi_C],
  [phi_C, 2 phi_B]] (x) I3 with j_A = (2a, 0), j_B = (0, 2b), j_C = (b, a);
  H9 = D^T H_(a,b) D for the difference operator D.  The projection clamps the
  eigenvalues of its translation-free block (``core.project_psd``) in the
  stencil frame, where in-plane and out-of-plane motions decouple.

The ``*_energy``, ``*_energy_gradient`` (one state or many, ``core.as_lanes``) and ``*_run``
kernels follow the calling convention of ``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT, NO_FRAME, SCATTER, as_lanes, emit, energy_gradient_lanes, lane_count, project_psd, run_stencils, scatter_gradient


@njit(**JIT)
def stretch_energy(x, st, order, rest_length, ks):
    """sum_e 1/2 ks (|e|/|ebar| - 1)^2 |ebar| in each lane of x (n, 3) or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        i0, i1 = st[e, 0], st[e, 1]
        lb, k_ = rest_length[e], ks[e]
        for s in range(L):
            d0, d1, d2 = xl[i1, 0, s] - xl[i0, 0, s], xl[i1, 1, s] - xl[i0, 1, s], xl[i1, 2, s] - xl[i0, 2, s]
            r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / lb - 1.0
            total[s] += 0.5 * k_ * r * r * lb
    return total


@njit(**INLINE)
def _stretch_scratch(L):
    """The lanes of ``_stretch_energy_gradient``: g (6, L), u (3, L), |e| (L,)."""
    return np.empty((6, L)), np.empty((3, L)), np.empty(L)


@njit(**INLINE)
def _stretch_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)) and gradient g (6, L) of stretching stencil e in each lane of
    x (n, 3, L), in ``work`` (``_stretch_scratch``); u (3, L) left holding the unit edge, ln (L,)
    its length."""
    rest_length, ks = args
    g, u, ln = work
    i0, i1 = st[e, 0], st[e, 1]
    lb, k_ = rest_length[e], ks[e]
    for s in range(L):
        acc = 0.0
        for i in range(3):
            u[i, s] = x[i1, i, s] - x[i0, i, s]
            acc += u[i, s] * u[i, s]
        le = math.sqrt(acc)
        f = k_ * (le / lb - 1.0)
        for i in range(3):
            u[i, s] /= le
            g[i, s] = -f * u[i, s]
            g[3 + i, s] = f * u[i, s]
        total[s] += 0.5 * f * (le / lb - 1.0) * lb
        ln[s] = le


@njit(**JIT)
def stretch_energy_gradient(x, st, order, rest_length, ks, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_stretch_energy_gradient, _stretch_scratch, x, st, order, (rest_length, ks), grad, 2)


@njit(**INLINE)
def _stretch_stiffness(e, args, work, project):
    """(s, c) of edge e from ``_stretch_energy_gradient``'s one-lane ``work``: the Hessian is
    [[K, -K], [-K, K]], K = s (1 - c) u u^T + s c I (c clamped at 0 when projecting)."""
    rest_length, ks = args
    lb = rest_length[e]
    c = 1.0 - lb / work[2][0]
    if project and c < 0.0:
        c = 0.0
    return ks[e] / lb, c


@njit(**JIT)
def _stretch_scatter(x, st, order, rest_length, ks, project, grad, data, slots):
    """``stretch_run`` for SCATTER: the upper triangle of each [[K, -K], [-K, K]] straight into
    the matrix, without the (6, 6) H that ``scatter`` reads back (half the time of the pass; the
    same sums; a separate function: inside ``stretch_run`` the same loop ran 1.5x slower)."""
    xl, args = as_lanes(x), (rest_length, ks)
    g = np.empty(6)
    K = np.empty((3, 3))
    u = np.empty(3)
    work = g.reshape((6, 1)), u.reshape((3, 1)), np.empty(1)
    total = np.zeros(1)
    for ii in range(order.shape[0]):
        e = order[ii]
        _stretch_energy_gradient(e, xl, st, args, work, total, 1)
        s, c = _stretch_stiffness(e, args, work, project)
        scatter_gradient(e, st, g, grad, 2)
        for i in range(3):
            for j in range(3):
                K[i, j] = s * (1.0 - c) * u[i] * u[j] + (s * c if i == j else 0.0)
        for p in range(6):
            for q in range(6):
                if q >= p:  # entry (p, q) of the row-major upper triangle
                    sl = slots[e, 6 * p - (p * (p - 1)) // 2 + q - p]
                    if sl >= 0:
                        data[sl] += -K[p % 3, q % 3] if (p < 3) != (q < 3) else K[p % 3, q % 3]
    return total[0]


@njit(**INLINE)
def _stretch_run_scratch():
    """``core.run_stencils``' scratch: g (6,), H (6, 6), ``_stretch_scratch(1)`` on g, u."""
    g, H, u = np.empty(6), np.empty((6, 6)), np.empty(3)
    return g, H, (g.reshape((6, 1)), u.reshape((3, 1)), np.empty(1)), (u,)


@njit(**INLINE)
def _stretch_hessian(e, args, work, extra, project, B, H):
    """H = [[K, -K], [-K, K]] of edge e (``_stretch_stiffness``)."""
    u = extra[0]
    s, c = _stretch_stiffness(e, args, work, project)
    for i in range(3):
        for j in range(3):
            K = s * (1.0 - c) * u[i] * u[j] + (s * c if i == j else 0.0)
            H[i, j] = K
            H[3 + i, 3 + j] = K
            H[i, 3 + j] = -K
            H[3 + i, j] = -K


@njit(**JIT)
def stretch_run(x, st, order, rest_length, ks, project, grad, data, slots, g_out, H_out, mode):
    """Per edge the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``stretch_energy_gradient``'s, to the bit."""
    if mode == SCATTER:
        return _stretch_scatter(x, st, order, rest_length, ks, project, grad, data, slots)
    return run_stencils(_stretch_energy_gradient, _stretch_hessian, _stretch_run_scratch, emit,
                        x, st, order, (rest_length, ks), project, NO_FRAME, grad, data, slots, g_out, H_out, mode, 2)  # fmt: skip


@njit(**JIT)
def bend_energy(x, st, order, alpha, c0):
    """sum_e alpha |a x b|^2 / (c0 + a.b)^2, a = x1 - x0, b = x2 - x1, in each lane of x (n, 3)
    or (n, 3, L): (L,)."""
    L = lane_count(x)
    xl = as_lanes(x)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        i0, i1, i2 = st[e, 0], st[e, 1], st[e, 2]
        al, ce = alpha[e], c0[e]
        for s in range(L):
            a0, a1, a2 = xl[i1, 0, s] - xl[i0, 0, s], xl[i1, 1, s] - xl[i0, 1, s], xl[i1, 2, s] - xl[i0, 2, s]
            b0, b1, b2 = xl[i2, 0, s] - xl[i1, 0, s], xl[i2, 1, s] - xl[i1, 1, s], xl[i2, 2, s] - xl[i1, 2, s]
            w0, w1, w2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            tau = ce + a0 * b0 + a1 * b1 + a2 * b2
            total[s] += al * (w0 * w0 + w1 * w1 + w2 * w2) / (tau * tau)
    return total


@njit(**INLINE)
def _rod_frame(a, b, frame):
    """Rows u1 = a/|a|, u2 (in the plane of a and b), n = u1 x u2 of a bending stencil."""
    la = math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2)
    for i in range(3):
        frame[0, i] = a[i] / la
    d = b[0] * frame[0, 0] + b[1] * frame[0, 1] + b[2] * frame[0, 2]
    for i in range(3):
        frame[1, i] = b[i] - d * frame[0, i]
    # second Gram-Schmidt pass: for nearly straight stencils the first leaves u2 off by eps / sin(angle)
    d = frame[1, 0] * frame[0, 0] + frame[1, 1] * frame[0, 1] + frame[1, 2] * frame[0, 2]
    for i in range(3):
        frame[1, i] -= d * frame[0, i]
    nb = math.sqrt(frame[1, 0] ** 2 + frame[1, 1] ** 2 + frame[1, 2] ** 2)
    if not nb > 1e-12 * math.sqrt(b[0] ** 2 + b[1] ** 2 + b[2] ** 2):  # straight: any perpendicular
        k = 0
        for i in range(1, 3):
            if abs(frame[0, i]) < abs(frame[0, k]):
                k = i
        for i in range(3):
            frame[1, i] = (1.0 if i == k else 0.0) - frame[0, k] * frame[0, i]
        nb = math.sqrt(frame[1, 0] ** 2 + frame[1, 1] ** 2 + frame[1, 2] ** 2)
    for i in range(3):
        frame[1, i] /= nb
    frame[2, 0] = frame[0, 1] * frame[1, 2] - frame[0, 2] * frame[1, 1]
    frame[2, 1] = frame[0, 2] * frame[1, 0] - frame[0, 0] * frame[1, 2]
    frame[2, 2] = frame[0, 0] * frame[1, 1] - frame[0, 1] * frame[1, 0]


@njit(**INLINE)
def _bend_scratch(L):
    """The lanes of ``_bend_energy_gradient``: g (9, L), a, b, w (3, L), aux (7, L)."""
    return np.empty((9, L)), np.empty((3, L)), np.empty((3, L)), np.empty((3, L)), np.empty((7, L))


@njit(**INLINE)
def _bend_energy_gradient(e, x, st, args, work, total, L):
    """Energy (added into total (L,)) and gradient g (9, L) of bending stencil e in each lane of
    x (n, 3, L), in ``work`` (``_bend_scratch``); a, b, w (3, L) left holding x1 - x0, x2 - x1 and
    a x b, aux (7, L) holding (A, B, C, f, it2, it3, tau) for ``_bend_h6``."""
    alpha, c0 = args
    g, a, b, w, aux = work
    i0, i1, i2 = st[e, 0], st[e, 1], st[e, 2]
    al, ce = alpha[e], c0[e]
    for s in range(L):
        for i in range(3):
            a[i, s] = x[i1, i, s] - x[i0, i, s]
            b[i, s] = x[i2, i, s] - x[i1, i, s]
        A_ = a[0, s] * a[0, s] + a[1, s] * a[1, s] + a[2, s] * a[2, s]
        B_ = b[0, s] * b[0, s] + b[1, s] * b[1, s] + b[2, s] * b[2, s]
        C_ = a[0, s] * b[0, s] + a[1, s] * b[1, s] + a[2, s] * b[2, s]
        w[0, s] = a[1, s] * b[2, s] - a[2, s] * b[1, s]
        w[1, s] = a[2, s] * b[0, s] - a[0, s] * b[2, s]
        w[2, s] = a[0, s] * b[1, s] - a[1, s] * b[0, s]
        f = w[0, s] * w[0, s] + w[1, s] * w[1, s] + w[2, s] * w[2, s]  # A B - C^2 without cancellation
        tau = ce + C_
        it2 = al / (tau * tau)
        it3 = it2 / tau
        # dE/da = 2 it2 b x w - 2 f it3 b,  dE/db = 2 it2 w x a - 2 f it3 a;  g = (-dE/da, dE/da - dE/db, dE/db)
        for i in range(3):
            i1_, i2_ = (i + 1) % 3, (i + 2) % 3
            ga = 2.0 * it2 * (b[i1_, s] * w[i2_, s] - b[i2_, s] * w[i1_, s]) - 2.0 * f * it3 * b[i, s]
            gb = 2.0 * it2 * (w[i1_, s] * a[i2_, s] - w[i2_, s] * a[i1_, s]) - 2.0 * f * it3 * a[i, s]
            g[i, s] = -ga
            g[3 + i, s] = ga - gb
            g[6 + i, s] = gb
        aux[0, s], aux[1, s], aux[2, s], aux[3, s], aux[4, s], aux[5, s], aux[6, s] = A_, B_, C_, f, it2, it3, tau
        total[s] += it2 * f


@njit(**JIT)
def bend_energy_gradient(x, st, order, alpha, c0, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_bend_energy_gradient, _bend_scratch, x, st, order, (alpha, c0), grad, 3)


@njit(**INLINE)
def _bend_h6(a, b, A_, B_, C_, f, it2, it3, tau, H6):
    """The bending Hessian H6 (6, 6) with respect to (a, b) (see ``_bend_energy_gradient``).

    H6 = sum_lm Phi_lm grad(A, B, C)_l grad(A, B, C)_m^T + the second derivatives of (A, B, C),
    with grad A = (2a, 0), grad B = (0, 2b), grad C = (b, a) and Phi_00 = Phi_11 = 0, block by block.
    """
    p1 = it2 * B_
    p2 = it2 * A_
    p3 = -2.0 * (C_ * it2 + f * it3)
    P01 = it2
    P02 = -2.0 * B_ * it3
    P12 = -2.0 * A_ * it3
    P22 = -2.0 * it2 + 8.0 * C_ * it3 + 6.0 * f * it3 / tau
    for i in range(3):
        for k in range(3):
            d = 1.0 if i == k else 0.0
            ab = a[i] * b[k]
            ba = b[i] * a[k]
            H6[i, k] = 2.0 * P02 * (ab + ba) + P22 * b[i] * b[k] + 2.0 * p1 * d
            H6[3 + i, 3 + k] = 2.0 * P12 * (ab + ba) + P22 * a[i] * a[k] + 2.0 * p2 * d
            hab = 4.0 * P01 * ab + 2.0 * P02 * a[i] * a[k] + 2.0 * P12 * b[i] * b[k] + P22 * ba + p3 * d
            H6[i, 3 + k] = hab
            H6[3 + k, i] = hab


@njit(**JIT)
def _bend_scatter_exact(x, st, order, alpha, c0, grad, data, slots):
    """``bend_run`` for SCATTER of the exact Hessian: the upper triangle of H9 = D^T H6 D goes
    straight into the matrix, block (I, J) by block, without a (9, 9) H (a separate function:
    inside ``bend_run`` the same loop ran a third slower).  The same sums as ``scatter``'s."""
    xl, args = as_lanes(x), (alpha, c0)
    total = np.zeros(1)
    g = np.empty(9)
    H6 = np.empty((6, 6))
    a, b, w, aux = np.empty(3), np.empty(3), np.empty(3), np.empty(7)
    work = g.reshape((9, 1)), a.reshape((3, 1)), b.reshape((3, 1)), w.reshape((3, 1)), aux.reshape((7, 1))
    for ii in range(order.shape[0]):
        e = order[ii]
        _bend_energy_gradient(e, xl, st, args, work, total, 1)
        _bend_h6(a, b, aux[0], aux[1], aux[2], aux[3], aux[4], aux[5], aux[6], H6)
        scatter_gradient(e, st, g, grad, 3)
        for i in range(3):
            for jj in range(3):
                haa, hab = H6[i, jj], H6[i, 3 + jj]
                hba, hbb = H6[3 + i, jj], H6[3 + i, 3 + jj]
                for I, J, v in ((0, 0, haa), (0, 1, hab - haa), (0, 2, -hab), (1, 1, haa + hbb - hab - hba),
                                (1, 2, hab - hbb), (2, 2, hbb)):  # fmt: skip
                    p, q = 3 * I + i, 3 * J + jj
                    if q >= p:  # entry (p, q) of the row-major upper triangle
                        sl = slots[e, 9 * p - (p * (p - 1)) // 2 + q - p]
                        if sl >= 0:
                            data[sl] += v
    return total[0]


@njit(**INLINE)
def _bend_run_scratch():
    """``core.run_stencils``' scratch: g (9,), H (9, 9), ``_bend_scratch(1)`` on g, a, b, w, aux
    and the Hessian's (a, b, aux, H6, M, V, BV, BH, wv, frame)."""
    g, H, H6 = np.empty(9), np.empty((9, 9)), np.empty((6, 6))
    a, b, w, aux = np.empty(3), np.empty(3), np.empty(3), np.empty(7)
    work = g.reshape((9, 1)), a.reshape((3, 1)), b.reshape((3, 1)), w.reshape((3, 1)), aux.reshape((7, 1))
    M, V, BV, BH = np.empty((6, 6)), np.empty((6, 6)), np.empty((9, 6)), np.empty((9, 6))
    return g, H, work, (a, b, aux, H6, M, V, BV, BH, np.empty(6), np.empty((3, 3)))


@njit(**INLINE)
def _bend_hessian(e, args, work, extra, project, B, H):
    """H9 = D^T H6 D of stencil e for (a, b) = (x1 - x0, x2 - x1), projected in the stencil frame."""
    a, b, aux, H6, M, V, BV, BH, wv, frame = extra
    _bend_h6(a, b, aux[0], aux[1], aux[2], aux[3], aux[4], aux[5], aux[6], H6)
    for i in range(3):
        for jj in range(3):
            haa, hab = H6[i, jj], H6[i, 3 + jj]
            hba, hbb = H6[3 + i, jj], H6[3 + i, 3 + jj]
            H[i, jj] = haa
            H[i, 3 + jj] = hab - haa
            H[i, 6 + jj] = -hab
            H[3 + i, jj] = hba - haa
            H[3 + i, 3 + jj] = haa + hbb - hab - hba
            H[3 + i, 6 + jj] = hab - hbb
            H[6 + i, jj] = -hba
            H[6 + i, 3 + jj] = hba - hbb
            H[6 + i, 6 + jj] = hbb
    if project:
        _rod_frame(a, b, frame)
        project_psd(H, B, M, BH, V, wv, BV, frame, True)


@njit(**JIT)
def bend_run(x, st, order, alpha, c0, project, B, grad, data, slots, g_out, H_out, mode):
    """Per stencil the gradient and the (exact or projected) Hessian, scattered (SCATTER) or
    stored (STORE); returns the energy, the sum of ``bend_energy_gradient``'s, to the bit."""
    if mode == SCATTER and not project:
        return _bend_scatter_exact(x, st, order, alpha, c0, grad, data, slots)
    return run_stencils(_bend_energy_gradient, _bend_hessian, _bend_run_scratch, emit,
                        x, st, order, (alpha, c0), project, B, grad, data, slots, g_out, H_out, mode, 3)  # fmt: skip
