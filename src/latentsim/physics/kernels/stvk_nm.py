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
invariant).  The ``*_energy``, ``*_energy_gradient`` (one state or many,
``core.as_lanes``) and ``*_run`` kernels follow the calling convention of
``dispatch.TermKernel``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from latentsim.physics.kernels.core import INLINE, JIT, NO_FRAME, as_lanes, emit, energy_gradient_lanes, lane_count, project_psd, run_stencils


@njit(**INLINE)
def _F(e, x, st, G, F, k, c, L):
    """F (3, c, L) = sum_a x_a G_a^T of stencil e (k vertices) in each lane of x (n, 3, L)."""
    for i in range(3):
        for r in range(c):
            for s in range(L):
                F[i, r, s] = 0.0
            for a in range(k):
                v, w = st[e, a], G[e, a, r]
                for s in range(L):
                    F[i, r, s] += x[v, i, s] * w


@njit(**INLINE)
def _stvk_mu(F, mu, E, P, psi, c, L):
    """mu ||E||^2 of F (3, c, L) into psi (L,), E (c, c, L) and P (3, c, L) = 2 mu F E."""
    for s in range(L):
        psi[s] = 0.0
    for r in range(c):
        for q in range(c):
            d = 1.0 if r == q else 0.0
            for s in range(L):
                E[r, q, s] = 0.5 * (F[0, r, s] * F[0, q, s] + F[1, r, s] * F[1, q, s] + F[2, r, s] * F[2, q, s] - d)
                psi[s] += E[r, q, s] * E[r, q, s]
    for i in range(3):
        for r in range(c):
            for s in range(L):
                acc = 0.0
                for t in range(c):
                    acc += F[i, t, s] * E[t, r, s]
                P[i, r, s] = 2.0 * mu * acc
    for s in range(L):
        psi[s] = mu * psi[s]


@njit(**INLINE)
def _stvk_mu_hessian(F, mu, E, A, c):
    """A (3c, 3c) = dP/dF of mu ||E||^2 at one F (3, c), E (c, c) from ``_stvk_mu``."""
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


@njit(**INLINE)
def _to_stencil(e, G, P, K, g, k, c, L):
    """g (3k, L) of stencil e from P (3, c, L), scaled by K."""
    for a in range(k):
        for i in range(3):
            for s in range(L):
                acc = 0.0
                for r in range(c):
                    acc += P[i, r, s] * G[e, a, r]
                g[3 * a + i, s] = K * acc


@njit(**INLINE)
def _to_stencil_hessian(e, G, A, K, H, k, c):
    """H (3k, 3k) of stencil e from A (3c, 3c), scaled by K."""
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
def _membrane_density(F, mu, lam, E, P, aux, psi, L):
    """Psi (L,), P (3, 2, L) of the membrane at F (3, 2, L); leaves E (2, 2, L) and
    aux (10, L) = (c00, c11, c01, J, dJ), dJ at F-space index i * 2 + r."""
    _stvk_mu(F, mu, E, P, psi, 2, L)
    for s in range(L):
        c00 = F[0, 0, s] ** 2 + F[1, 0, s] ** 2 + F[2, 0, s] ** 2
        c11 = F[0, 1, s] ** 2 + F[1, 1, s] ** 2 + F[2, 1, s] ** 2
        c01 = F[0, 0, s] * F[0, 1, s] + F[1, 0, s] * F[1, 1, s] + F[2, 0, s] * F[2, 1, s]
        J = math.sqrt(c00 * c11 - c01 * c01)
        aux[0, s], aux[1, s], aux[2, s], aux[3, s] = c00, c11, c01, J
        psi[s] += 0.5 * lam * (J - 1.0) ** 2
    for i in range(3):
        for s in range(L):
            c00, c11, c01, J = aux[0, s], aux[1, s], aux[2, s], aux[3, s]
            aux[4 + 2 * i, s] = (c11 * F[i, 0, s] - c01 * F[i, 1, s]) / J  # dd/df0 / (2J)
            aux[5 + 2 * i, s] = (c00 * F[i, 1, s] - c01 * F[i, 0, s]) / J
            P[i, 0, s] += lam * (J - 1.0) * aux[4 + 2 * i, s]
            P[i, 1, s] += lam * (J - 1.0) * aux[5 + 2 * i, s]


@njit(**INLINE)
def _membrane_hessian(F, mu, lam, E, aux, A):
    """A (6, 6) = dP/dF of the membrane at one F (3, 2), from ``_membrane_density``'s E (2, 2)
    and aux (10,)."""
    _stvk_mu_hessian(F, mu, E, A, 2)
    c00, c11, c01, J = aux[0], aux[1], aux[2], aux[3]
    dJ = aux[4:]
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


# ---------------------------------------------------------------------------
# tets: V0 (mu ||E||^2 + lam (det F - 1)^2)
# ---------------------------------------------------------------------------
@njit(**INLINE)
def _levi(i, j, k):
    return 0.5 * (i - j) * (j - k) * (k - i)


@njit(**INLINE)
def _tet_density(F, mu, lam, E, P, aux, psi, L):
    """Psi (L,), P (3, 3, L) of the tet at F (3, 3, L); leaves E (3, 3, L) and
    aux (10, L) = (cof F row by row, J = det F)."""
    _stvk_mu(F, mu, E, P, psi, 3, L)
    for j in range(3):  # cof column j = f_{j+1} x f_{j+2}
        j1, j2 = (j + 1) % 3, (j + 2) % 3
        for s in range(L):
            aux[j, s] = F[1, j1, s] * F[2, j2, s] - F[2, j1, s] * F[1, j2, s]
            aux[3 + j, s] = F[2, j1, s] * F[0, j2, s] - F[0, j1, s] * F[2, j2, s]
            aux[6 + j, s] = F[0, j1, s] * F[1, j2, s] - F[1, j1, s] * F[0, j2, s]
    for s in range(L):
        aux[9, s] = F[0, 0, s] * aux[0, s] + F[1, 0, s] * aux[3, s] + F[2, 0, s] * aux[6, s]
        psi[s] += lam * (aux[9, s] - 1.0) ** 2
    c2 = 2.0 * lam
    for i in range(3):
        for r in range(3):
            for s in range(L):
                P[i, r, s] += c2 * (aux[9, s] - 1.0) * aux[3 * i + r, s]


@njit(**INLINE)
def _tet_hessian(F, mu, lam, E, aux, A):
    """A (9, 9) = dP/dF of the tet at one F (3, 3), from ``_tet_density``'s E (3, 3) and aux (10,)."""
    _stvk_mu_hessian(F, mu, E, A, 3)
    c2 = 2.0 * lam
    J = aux[9]
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
                    A[3 * i + j, 3 * k + l] += c2 * (aux[3 * i + j] * aux[3 * k + l] + (J - 1.0) * hJ)


# ---------------------------------------------------------------------------
# the kernels of both, k vertices and c = k - 1 columns of F: 3 and 2 (membrane), 4 and 3 (tet)
# ---------------------------------------------------------------------------
@njit(**INLINE)
def _density(F, mu, lam, E, P, aux, psi, c, L):
    """``_membrane_density`` (c = 2) or ``_tet_density`` (c = 3)."""
    if c == 2:
        _membrane_density(F, mu, lam, E, P, aux, psi, L)
    else:
        _tet_density(F, mu, lam, E, P, aux, psi, L)


@njit(**INLINE)
def _scratch(k, c, L):
    """The lanes of ``_energy_gradient``: g (3k, L), F (3, c, L), E (c, c, L), P (3, c, L),
    aux (10, L), psi (L,)."""
    return np.empty((3 * k, L)), np.empty((3, c, L)), np.empty((c, c, L)), np.empty((3, c, L)), np.empty((10, L)), np.empty(L)


@njit(**INLINE)
def _energy_gradient(e, x, st, args, work, total, k, c, L):
    """Energy (added into total (L,)) and gradient g (3k, L) of stencil e in each lane of
    x (n, 3, L), in ``work`` (``_scratch``), which keeps F, E, P and aux."""
    G, K, mu, lam = args
    g, F, E, P, aux, psi = work
    _F(e, x, st, G, F, k, c, L)
    _density(F, mu[e], lam[e], E, P, aux, psi, c, L)
    Ke = K[e]
    for s in range(L):
        total[s] += Ke * psi[s]
    _to_stencil(e, G, P, Ke, g, k, c, L)


@njit(**INLINE)
def _energy(x, st, order, args, k, c):
    """The summed energies of the stencils ``order`` in each lane of x (n, 3) or (n, 3, L)."""
    L = lane_count(x)
    xl = as_lanes(x)
    G, K, mu, lam = args
    _, F, E, P, aux, psi = _scratch(k, c, L)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        _F(e, xl, st, G, F, k, c, L)
        _density(F, mu[e], lam[e], E, P, aux, psi, c, L)
        Ke = K[e]
        for s in range(L):
            total[s] += Ke * psi[s]
    return total


@njit(**INLINE)
def _run_scratch(k, c):
    """``core.run_stencils``' scratch: g (3k,), H (3k, 3k), ``_scratch(k, c, 1)`` on g, F, E, P, aux
    and the Hessian's (F, E, aux, A, M, V, BV, BH, wv)."""
    n3, m = 3 * k, 3 * k - 3
    F, E, P, aux, A = np.empty((3, c)), np.empty((c, c)), np.empty((3, c)), np.empty(10), np.empty((3 * c, 3 * c))
    g, H = np.empty(n3), np.empty((n3, n3))
    work = g.reshape((n3, 1)), F.reshape((3, c, 1)), E.reshape((c, c, 1)), P.reshape((3, c, 1)), aux.reshape((10, 1)), np.empty(1)
    M, V, BV, BH = np.empty((m, m)), np.empty((m, m)), np.empty((n3, m)), np.empty((n3, m))
    return g, H, work, (F, E, aux, A, M, V, BV, BH, np.empty(m))


@njit(**INLINE)
def _hessian(e, args, extra, project, B, H, k, c):
    """The exact or projected Hessian H (3k, 3k) of stencil e from what ``_energy_gradient`` left."""
    G, K, mu, lam = args
    F, E, aux, A, M, V, BV, BH, wv = extra
    if c == 2:
        _membrane_hessian(F, mu[e], lam[e], E, aux, A)
    else:
        _tet_hessian(F, mu[e], lam[e], E, aux, A)
    _to_stencil_hessian(e, G, A, K[e], H, k, c)
    if project:
        project_psd(H, B, M, BH, V, wv, BV, NO_FRAME, False)


@njit(**JIT)
def membrane_nm_energy(x, st, order, G, K, mu, lam):
    """sum_t Abar h (mu ||E||^2 + lam/2 (J - 1)^2) in each lane of x (n, 3) or (n, 3, L): (L,)."""
    return _energy(x, st, order, (G, K, mu, lam), 3, 2)


@njit(**INLINE)
def _membrane_nm_scratch(L):
    return _scratch(3, 2, L)


@njit(**INLINE)
def _membrane_nm_energy_gradient(e, x, st, args, work, total, L):
    _energy_gradient(e, x, st, args, work, total, 3, 2, L)


@njit(**JIT)
def membrane_nm_energy_gradient(x, st, order, G, K, mu, lam, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_membrane_nm_energy_gradient, _membrane_nm_scratch, x, st, order, (G, K, mu, lam), grad, 3)


@njit(**INLINE)
def _membrane_nm_run_scratch():
    return _run_scratch(3, 2)


@njit(**INLINE)
def _membrane_nm_hessian(e, args, work, extra, project, B, H):
    _hessian(e, args, extra, project, B, H, 3, 2)


@njit(**JIT)
def membrane_nm_run(x, st, order, G, K, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    """Per triangle the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``membrane_nm_energy_gradient``'s, to the bit."""
    return run_stencils(_membrane_nm_energy_gradient, _membrane_nm_hessian, _membrane_nm_run_scratch, emit,
                        x, st, order, (G, K, mu, lam), project, B, grad, data, slots, g_out, H_out, mode, 3)  # fmt: skip


@njit(**JIT)
def tet_nm_energy(x, st, order, D, vol, mu, lam):
    """sum_e V0 (mu ||E||^2 + lam (det F - 1)^2) in each lane of x (n, 3) or (n, 3, L): (L,)."""
    return _energy(x, st, order, (D, vol, mu, lam), 4, 3)


@njit(**INLINE)
def _tet_nm_scratch(L):
    return _scratch(4, 3, L)


@njit(**INLINE)
def _tet_nm_energy_gradient(e, x, st, args, work, total, L):
    _energy_gradient(e, x, st, args, work, total, 4, 3, L)


@njit(**JIT)
def tet_nm_energy_gradient(x, st, order, D, vol, mu, lam, grad):
    """Energies (returned, (L,)) and gradients (added into grad, x's shape) in each lane of
    x (n, 3) or (n, 3, L)."""
    return energy_gradient_lanes(_tet_nm_energy_gradient, _tet_nm_scratch, x, st, order, (D, vol, mu, lam), grad, 4)


@njit(**INLINE)
def _tet_nm_run_scratch():
    return _run_scratch(4, 3)


@njit(**INLINE)
def _tet_nm_hessian(e, args, work, extra, project, B, H):
    _hessian(e, args, extra, project, B, H, 4, 3)


@njit(**JIT)
def tet_nm_run(x, st, order, D, vol, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
    """Per tet the gradient and the (exact or projected) Hessian, scattered (SCATTER) or stored
    (STORE); returns the energy, the sum of ``tet_nm_energy_gradient``'s, to the bit."""
    return run_stencils(_tet_nm_energy_gradient, _tet_nm_hessian, _tet_nm_run_scratch, emit,
                        x, st, order, (D, vol, mu, lam), project, B, grad, data, slots, g_out, H_out, mode, 4)  # fmt: skip
