r"""Compiled per-stencil kernels for the full-space Newton solver (numba).

The energies of ``rods``, ``shells`` and ``tets`` are written once in PyTorch
(batched, differentiable) and their closed-form derivatives in vectorised
NumPy; both stay the reference and the test oracles.  For the full-space
solver (one state, many Newton iterations), the per-call overhead of those
array programs dominates the small per-stencil work, so this module compiles
the same formulas stencil by stencil with numba:

- ``energy(x)``: the term's energy at x (n, 3), gathered inside the kernel;
- ``energy_gradient(x, grad)``: the energy, and the gradient added into the
  (3n,) ``grad``, in one pass (the line search: the accepted trial state's
  gradient then serves the next convergence test, and the Hessian is built
  only when that test fails);
- ``accumulate(x, grad, data, slots, project)``: per stencil, the gradient and
  the Hessian (exact, or eigenvalue-clamped as in the oracles), added straight
  into the (3n,) gradient and into the data array of the free-DoF Hessian (the
  CSR data, or the banded storage) at precomputed slot indices
  (``sparse.HessianPattern.stencil_slots``): no per-stencil blocks are
  materialised, no COO->CSR or CSR->band conversion runs;
- ``local(x, project)``: per-stencil g (E, 3k) and H (E, 3k, 3k), the
  layout of ``EnergyTerm.local_gradient_hessian``, for the tests.

Formulas (see the docstrings of the term classes for derivations):

* StVK tets, with D (4, 3) the barycentric gradients, F = sum_a x_a D_a^T,
  S = 2 mu E + lam tr(E) I, q_a = F D_a:
  g_a = W F S D_a, H_(a i)(b j) = W [ (D_a^T S D_b) d_ij + mu q_(b,i) q_(a,j)
  + mu (F F^T)_ij (D_a . D_b) + lam q_(a,i) q_(b,j) ]; the projection clamps
  the analytic eigensystem of dP/dF (``tets`` module docstring).
* StVK membrane triangles: the same with D -> G (3, 2), W -> Abar h.
* Rod stretch: the spring Hessian with c = 1 - |ebar|/|e| (clamped at 0).
* Rod bend, phi(A, B, C) = alpha (A B - C^2) / (c0 + C)^2 of a = e_{i-1},
  b = e_i: H_(a,b) = sum_kl phi_kl j_k j_l^T + [[2 phi_A, phi_C], [phi_C,
  2 phi_B]] (x) I3 with j_A = (2a, 0), j_B = (0, 2b), j_C = (b, a).
* Shell hinges: the gradient and Hessian of the dihedral angle of
  ``shells._hinge_gradient_hessian``.

Projection of rods, membranes and hinges: the exact eigenvalue clamp of the
stencil Hessian, computed on its translation-free (3k-3)-square block (these
energies are translation invariant) with a cyclic Jacobi eigensolver.

All kernels run in float64 on the CPU and are compiled once and cached on
disk (``cache=True``).  Each loops over an ``order`` of stencil indices: the
solver gives every term two halves whose stencils share no vertex (a median
cut of a reverse Cuthill-McKee vertex order) and the separator between them
(``split_stencils``); on two threads the halves run at once, since no
gradient entry or Hessian slot is written by both, then the separator.  Many
states at once (the self-supervised losses) split the states over threads
instead (``batch_energy_gradient``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

try:  # numba is a hard requirement of the fast path only; the oracles never need it
    import numba
    from numba import njit
except ImportError:  # pragma: no cover - depends on the install
    numba = None

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


def available() -> bool:
    """True when numba imports (else the solver uses the NumPy/PyTorch closed forms)."""
    return numba is not None


if numba is None:  # pragma: no cover
    def njit(**_):
        """Stand-in decorator: keeps the module importable; nothing below is called."""
        return lambda f: f


# ---------------------------------------------------------------------------
# shared pieces
# ---------------------------------------------------------------------------
# The helpers below are inlined into each run kernel (numba IR inlining) with the stencil size k as
# a literal: the loops then have fixed trip counts that LLVM unrolls.  Called, with k read from
# st.shape[1], they made a Hessian pass 2-3x slower (the grad+Hess+proj column of
# benchmarks/bench_simulator.py).
_INLINE = dict(_JIT, inline="always")


@njit(**_INLINE)
def _scatter(e, st, g, H, grad, data, slots, k):
    """Add stencil e's gradient g (3k,) and the upper triangle of H (3k, 3k); k = st.shape[1]."""
    n3 = 3 * k
    for a in range(k):
        v = st[e, a]
        for i in range(3):
            grad[3 * v + i] += g[3 * a + i]
    m = 0
    for p in range(n3):
        for q in range(p, n3):
            s = slots[e, m]
            if s >= 0:
                data[s] += H[p, q]
            m += 1


GRADIENT, SCATTER, STORE = 0, 1, 2  # modes of the run kernels


@njit(**_INLINE)
def _scatter_gradient(e, st, g, grad, k):
    """Add stencil e's gradient g (3k,); k = st.shape[1]."""
    for a in range(k):
        v = st[e, a]
        for i in range(3):
            grad[3 * v + i] += g[3 * a + i]


@njit(**_INLINE)
def _emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, k):
    """Stencil e's g and (symmetric) H: scattered into grad/data (SCATTER) or stored in g_out/H_out."""
    if mode == SCATTER:
        _scatter(e, st, g, H, grad, data, slots, k)
    else:
        g_out[e] = g
        H_out[e] = H


@njit(**_JIT)
def _jacobi_eigh(A, V, w):
    """Cyclic Jacobi eigen-decomposition of a small symmetric A (n, n), in place.

    On return w (n,) holds the eigenvalues (unsorted) and V (n, n) the
    eigenvectors in its columns; A is destroyed.  Off-diagonal entries at most
    1e-15 ||A||_F are treated as zero (round-off level: rotating them would
    only stir round-off, and dropping one moves the eigenvalues by that much);
    the sweeps stop when all are (quadratic convergence, 3-6 sweeps).
    """
    n = A.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            V[i, j] = 1.0 if i == j else 0.0
            scale += A[i, j] * A[i, j]
    small = 1e-15 * math.sqrt(scale)
    for _ in range(30):
        rotated = False
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = A[p, q]
                if abs(apq) <= small:
                    continue
                rotated = True
                d = 0.5 * (A[q, q] - A[p, p])
                t = apq / math.copysign(abs(d) + math.sqrt(d * d + apq * apq), d)
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = t * c
                for r in range(n):  # A <- A J
                    arp, arq = A[r, p], A[r, q]
                    A[r, p] = c * arp - s * arq
                    A[r, q] = s * arp + c * arq
                for r in range(n):  # A <- J^T A
                    apr, aqr = A[p, r], A[q, r]
                    A[p, r] = c * apr - s * aqr
                    A[q, r] = s * apr + c * aqr
                A[p, q] = 0.0
                A[q, p] = 0.0
                for r in range(n):  # V <- V J
                    vrp, vrq = V[r, p], V[r, q]
                    V[r, p] = c * vrp - s * vrq
                    V[r, q] = s * vrp + c * vrq
        if not rotated:
            break
    for i in range(n):
        w[i] = A[i, i]


@njit(**_JIT)
def _project_translation_free(H, B, M, BH, V, w, BV, frame, use_frame):
    """Eigenvalue clamp of a translation-invariant stencil Hessian H (3k, 3k), in place.

    H = B M B^T with B = Q (x) I3 (3k, 3k-3) orthonormal, M = B^T H B; clamping
    the eigenvalues of M clamps those of H exactly (``shells.project_psd_translation_free``).
    With ``use_frame``, M is first rotated into the orthonormal frame whose rows
    are ``frame`` (3, 3), in which it is known to have no coupling between the
    first two and the third spatial axis (the rod stencil frame: in-plane and
    out-of-plane motions); the coupling entries are dropped and the Jacobi
    sweeps only see the two diagonal blocks.
    """
    n, m = B.shape
    for i in range(n):  # BH = H B
        for j in range(m):
            acc = 0.0
            for r in range(n):
                acc += H[i, r] * B[r, j]
            BH[i, j] = acc
    for i in range(m):  # M = B^T (H B)
        for j in range(i, m):
            acc = 0.0
            for r in range(n):
                acc += B[r, i] * BH[r, j]
            M[i, j] = acc
            M[j, i] = acc
    if use_frame:  # M <- P M P^T, P = I (x) frame; BH[:m] is scratch
        for i in range(m):
            for j in range(m):
                bi, bj = i - i % 3, j - j % 3
                acc = 0.0
                for r in range(3):
                    acc += frame[i % 3, r] * M[bi + r, j]
                BH[i, j] = acc
        for i in range(m):
            for j in range(m):
                bj = j - j % 3
                acc = 0.0
                for r in range(3):
                    acc += BH[i, bj + r] * frame[j % 3, r]
                M[i, j] = acc if (i % 3 == 2) == (j % 3 == 2) else 0.0
    _jacobi_eigh(M, V, w)
    if use_frame:  # V <- P^T V
        for j in range(m):
            for i in range(m):
                bi = i - i % 3
                acc = 0.0
                for r in range(3):
                    acc += frame[r, i % 3] * V[bi + r, j]
                BH[i, j] = acc
        for i in range(m):
            for j in range(m):
                V[i, j] = BH[i, j]
    for i in range(n):  # BV = B V sqrt(max(w, 0))
        for k in range(m):
            acc = 0.0
            for r in range(m):
                acc += B[i, r] * V[r, k]
            BV[i, k] = acc * math.sqrt(max(w[k], 0.0))
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(m):
                acc += BV[i, k] * BV[j, k]
            H[i, j] = acc
            H[j, i] = acc


_NO_FRAME = np.eye(3)


def translation_free_basis(k: int) -> np.ndarray:
    """B = Q (x) I3 (3k, 3k-3), Q an orthonormal basis of the vectors orthogonal to (1, .., 1)."""
    ones = np.ones((k, 1))
    Qfull, _ = np.linalg.qr(np.concatenate([ones, np.eye(k)[:, : k - 1]], 1))
    return np.ascontiguousarray(np.kron(Qfull[:, 1:], np.eye(3)))


# ---------------------------------------------------------------------------
# StVK tetrahedra
# ---------------------------------------------------------------------------
@njit(**_INLINE)
def _tet_F(e, x, st, D, F):
    """F (3, 3) = sum_a x_a D_a^T of tet e."""
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for a in range(4):
                acc += x[st[e, a], i] * D[e, a, j]
            F[i, j] = acc


@njit(**_JIT)
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


@njit(**_JIT)
def _svd3(F, C, Vm, w, U, sig, V, b):
    """Rotation-variant SVD F = U diag(sig) V^T (``tets.rotation_variant_svd``); C, Vm, w, b scratch."""
    tiny = 2.2250738585072014e-308
    for i in range(3):
        for j in range(3):
            C[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
    _jacobi_eigh(C, Vm, w)
    o0, o1, o2 = 0, 1, 2  # sorting network, descending
    if w[o0] < w[o1]:
        o0, o1 = o1, o0
    if w[o1] < w[o2]:
        o1, o2 = o2, o1
    if w[o0] < w[o1]:
        o0, o1 = o1, o0
    for i in range(3):
        V[i, 0], V[i, 1], V[i, 2] = Vm[i, o0], Vm[i, o1], Vm[i, o2]
    det = (V[0, 0] * (V[1, 1] * V[2, 2] - V[2, 1] * V[1, 2]) - V[0, 1] * (V[1, 0] * V[2, 2] - V[2, 0] * V[1, 2])
           + V[0, 2] * (V[1, 0] * V[2, 1] - V[2, 0] * V[1, 1]))  # fmt: skip
    if det < 0.0:
        for i in range(3):
            V[i, 2] = -V[i, 2]
    for k in range(3):  # columns F v_k
        for i in range(3):
            b[i, k] = F[i, 0] * V[0, k] + F[i, 1] * V[1, k] + F[i, 2] * V[2, k]
    s0 = math.sqrt(b[0, 0] ** 2 + b[1, 0] ** 2 + b[2, 0] ** 2)
    if s0 > tiny:
        for i in range(3):
            U[i, 0] = b[i, 0] / s0
    else:  # F == 0: any frame works
        U[0, 0], U[1, 0], U[2, 0] = 1.0, 0.0, 0.0
    d = U[0, 0] * b[0, 1] + U[1, 0] * b[1, 1] + U[2, 0] * b[2, 1]
    for i in range(3):
        U[i, 1] = b[i, 1] - d * U[i, 0]
    s1 = math.sqrt(U[0, 1] ** 2 + U[1, 1] ** 2 + U[2, 1] ** 2)
    for i in range(3):
        U[i, 1] /= max(s1, tiny)
    d = U[0, 0] * U[0, 1] + U[1, 0] * U[1, 1] + U[2, 0] * U[2, 1]  # second Gram-Schmidt pass
    for i in range(3):
        U[i, 1] -= d * U[i, 0]
    nrm = max(math.sqrt(U[0, 1] ** 2 + U[1, 1] ** 2 + U[2, 1] ** 2), tiny)
    for i in range(3):
        U[i, 1] /= nrm
    if not (s1 > 1e-14 * s0 + tiny):  # collapsed to a segment: u0 x e_k, e_k the axis least along u0
        k = 0
        for i in range(1, 3):
            if abs(U[i, 0]) < abs(U[k, 0]):
                k = i
        e0, e1, e2 = 1.0 if k == 0 else 0.0, 1.0 if k == 1 else 0.0, 1.0 if k == 2 else 0.0
        p0 = U[1, 0] * e2 - U[2, 0] * e1
        p1 = U[2, 0] * e0 - U[0, 0] * e2
        p2 = U[0, 0] * e1 - U[1, 0] * e0
        nrm = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        U[0, 1], U[1, 1], U[2, 1] = p0 / nrm, p1 / nrm, p2 / nrm
    U[0, 2] = U[1, 0] * U[2, 1] - U[2, 0] * U[1, 1]
    U[1, 2] = U[2, 0] * U[0, 1] - U[0, 0] * U[2, 1]
    U[2, 2] = U[0, 0] * U[1, 1] - U[1, 0] * U[0, 1]
    sig[0], sig[1] = s0, s1
    sig[2] = U[0, 2] * b[0, 2] + U[1, 2] * b[1, 2] + U[2, 2] * b[2, 2]


@njit(**_INLINE)
def _tet_gh(e, x, st, D, vol, mu, lam, project, hess, g, H, F, S, P, q, FF, U, V, Lf, A, b, sig, w3, N):
    """Energy (returned), gradient g (12,) and, if ``hess``, Hessian H (12, 12) of tet e.

    The rest is scratch.  The exact Hessian is written to the upper triangle
    only (all that ``_scatter`` reads).
    """
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
    if not hess:
        return energy
    if not project:
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
        return energy
    # projected: the 9 analytic eigenpairs of dP/dF in the principal-stretch frame
    _svd3(F, S, P, w3, U, sig, V, b)
    s0, s1, s2 = sig[0] * sig[0], sig[1] * sig[1], sig[2] * sig[2]
    T = 0.5 * (s0 + s1 + s2 - 3.0)
    sw = math.sqrt(W)
    for i in range(3):
        for j in range(3):
            A[i, j] = l_ * sig[i] * sig[j]
        A[i, i] += m_ * (3.0 * sig[i] * sig[i] - 1.0) + l_ * T
    _jacobi_eigh(A, Lf, w3)
    for k in range(3):
        f = math.sqrt(max(w3[k], 0.0)) * sw
        for p in range(3):
            Lf[p, k] *= f
    DV = q  # DV[a, p] = D_a . v_p
    for a in range(4):
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
        base = m_ * (sig[p] * sig[p] + sig[qq] * sig[qq] - 1.0) + l_ * T
        cross = m_ * sig[p] * sig[qq]
        wf = math.sqrt(0.5 * max(base + cross, 0.0)) * sw
        wt = math.sqrt(0.5 * max(base - cross, 0.0)) * sw
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
    return energy


@njit(**_JIT)
def _tet_run(x, st, order, D, vol, mu, lam, project, grad, data, slots, g_out, H_out, mode):
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
        total += _tet_gh(e, x, st, D, vol, mu, lam, project, mode != GRADIENT, g, H, F, S, P, q, FF, U, V, Lf, A, b,
                         sig, w3, N)  # fmt: skip
        if mode == GRADIENT:
            _scatter_gradient(e, st, g, grad, 4)
        elif mode == SCATTER:
            _scatter(e, st, g, H, grad, data, slots, 4)
        else:
            g_out[e] = g
            for i in range(12):
                for j in range(i, 12):
                    H_out[e, i, j] = H[i, j]
                    H_out[e, j, i] = H[i, j]
    return total


# ---------------------------------------------------------------------------
# rods
# ---------------------------------------------------------------------------
@njit(**_JIT)
def stretch_energy(x, st, order, rest_length, ks):
    """sum_e 1/2 ks (|e|/|ebar| - 1)^2 |ebar|."""
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        i0, i1 = st[e, 0], st[e, 1]
        d0, d1, d2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
        lb = rest_length[e]
        r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / lb - 1.0
        total += 0.5 * ks[e] * r * r * lb
    return total


@njit(**_INLINE)
def _stretch_local(e, x, st, rest_length, ks, project, u, g):
    """Energy of stretching stencil e and its gradient g (6,); u (3,) left holding the unit edge.
    Returns (energy, s, c): the Hessian is [[K, -K], [-K, K]], K = s (1 - c) u u^T + s c I
    (c clamped at 0 when projecting)."""
    i0, i1 = st[e, 0], st[e, 1]
    ln = 0.0
    for i in range(3):
        u[i] = x[i1, i] - x[i0, i]
        ln += u[i] * u[i]
    ln = math.sqrt(ln)
    lb = rest_length[e]
    f = ks[e] * (ln / lb - 1.0)
    c = 1.0 - lb / ln
    if project and c < 0.0:
        c = 0.0
    for i in range(3):
        u[i] /= ln
        g[i] = -f * u[i]
        g[3 + i] = f * u[i]
    return 0.5 * f * (ln / lb - 1.0) * lb, ks[e] / lb, c


@njit(**_JIT)
def _stretch_scatter(x, st, order, rest_length, ks, project, grad, data, slots):
    """``_stretch_run`` for SCATTER: the upper triangle of each [[K, -K], [-K, K]] straight into
    the matrix, without the (6, 6) H that ``_scatter`` reads back (half the time of the pass; the
    same sums; a separate function: inside ``_stretch_run`` the same loop ran 1.5x slower)."""
    total = 0.0
    g = np.empty(6)
    K = np.empty((3, 3))
    u = np.empty(3)
    for ii in range(order.shape[0]):
        e = order[ii]
        en, s, c = _stretch_local(e, x, st, rest_length, ks, project, u, g)
        total += en
        _scatter_gradient(e, st, g, grad, 2)
        for i in range(3):
            for j in range(3):
                K[i, j] = s * (1.0 - c) * u[i] * u[j] + (s * c if i == j else 0.0)
        for p in range(6):
            for q in range(6):
                if q >= p:  # entry (p, q) of the row-major upper triangle
                    sl = slots[e, 6 * p - (p * (p - 1)) // 2 + q - p]
                    if sl >= 0:
                        data[sl] += -K[p % 3, q % 3] if (p < 3) != (q < 3) else K[p % 3, q % 3]
    return total


@njit(**_JIT)
def _stretch_run(x, st, order, rest_length, ks, project, grad, data, slots, g_out, H_out, mode):
    if mode == SCATTER:
        return _stretch_scatter(x, st, order, rest_length, ks, project, grad, data, slots)
    total = 0.0
    g = np.empty(6)
    H = np.empty((6, 6))
    u = np.empty(3)
    for ii in range(order.shape[0]):
        e = order[ii]
        en, s, c = _stretch_local(e, x, st, rest_length, ks, project, u, g)
        total += en
        if mode == GRADIENT:
            _scatter_gradient(e, st, g, grad, 2)
            continue
        for i in range(3):
            for j in range(3):
                K = s * (1.0 - c) * u[i] * u[j] + (s * c if i == j else 0.0)
                H[i, j] = K
                H[3 + i, 3 + j] = K
                H[i, 3 + j] = -K
                H[3 + i, j] = -K
        _emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 2)
    return total


@njit(**_JIT)
def bend_energy(x, st, order, alpha, c0):
    """sum_e alpha |a x b|^2 / (c0 + a.b)^2, a = x1 - x0, b = x2 - x1."""
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        i0, i1, i2 = st[e, 0], st[e, 1], st[e, 2]
        a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
        b0, b1, b2 = x[i2, 0] - x[i1, 0], x[i2, 1] - x[i1, 1], x[i2, 2] - x[i1, 2]
        w0, w1, w2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        tau = c0[e] + a0 * b0 + a1 * b1 + a2 * b2
        total += alpha[e] * (w0 * w0 + w1 * w1 + w2 * w2) / (tau * tau)
    return total


@njit(**_INLINE)
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


@njit(**_INLINE)
def _bend_gradient(e, x, st, alpha, c0, a, b, w, g):
    """Energy of bending stencil e and its gradient g (9,); a, b, w scratch (3,), left holding
    x1 - x0, x2 - x1 and a x b.  Returns (energy, A, B, C, f, it2, it3, tau) for ``_bend_h6``."""
    i0, i1, i2 = st[e, 0], st[e, 1], st[e, 2]
    for i in range(3):
        a[i] = x[i1, i] - x[i0, i]
        b[i] = x[i2, i] - x[i1, i]
    A_ = a[0] * a[0] + a[1] * a[1] + a[2] * a[2]
    B_ = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]
    C_ = a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
    w[0], w[1], w[2] = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
    f = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]  # A B - C^2 without cancellation
    tau = c0[e] + C_
    it2 = alpha[e] / (tau * tau)
    it3 = it2 / tau
    # dE/da = 2 it2 b x w - 2 f it3 b,  dE/db = 2 it2 w x a - 2 f it3 a;  g = (-dE/da, dE/da - dE/db, dE/db)
    for i in range(3):
        i1_, i2_ = (i + 1) % 3, (i + 2) % 3
        ga = 2.0 * it2 * (b[i1_] * w[i2_] - b[i2_] * w[i1_]) - 2.0 * f * it3 * b[i]
        gb = 2.0 * it2 * (w[i1_] * a[i2_] - w[i2_] * a[i1_]) - 2.0 * f * it3 * a[i]
        g[i] = -ga
        g[3 + i] = ga - gb
        g[6 + i] = gb
    return it2 * f, A_, B_, C_, f, it2, it3, tau


@njit(**_INLINE)
def _bend_h6(a, b, A_, B_, C_, f, it2, it3, tau, H6):
    """The bending Hessian H6 (6, 6) with respect to (a, b) (see ``_bend_gradient``).

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


@njit(**_JIT)
def _bend_scatter_exact(x, st, order, alpha, c0, grad, data, slots):
    """``_bend_run`` for SCATTER of the exact Hessian: the upper triangle of H9 = D^T H6 D goes
    straight into the matrix, block (I, J) by block, without a (9, 9) H (a separate function:
    inside ``_bend_run`` the same loop ran a third slower).  The same sums as ``_scatter``'s."""
    total = 0.0
    g = np.empty(9)
    H6 = np.empty((6, 6))
    a, b, w = np.empty(3), np.empty(3), np.empty(3)
    for ii in range(order.shape[0]):
        e = order[ii]
        en, A_, B_, C_, f, it2, it3, tau = _bend_gradient(e, x, st, alpha, c0, a, b, w, g)
        total += en
        _bend_h6(a, b, A_, B_, C_, f, it2, it3, tau, H6)
        _scatter_gradient(e, st, g, grad, 3)
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
    return total


@njit(**_JIT)
def _bend_run(x, st, order, alpha, c0, project, B, grad, data, slots, g_out, H_out, mode):
    if mode == SCATTER and not project:
        return _bend_scatter_exact(x, st, order, alpha, c0, grad, data, slots)
    total = 0.0
    g = np.empty(9)
    H = np.empty((9, 9))
    H6 = np.empty((6, 6))
    a, b, w = np.empty(3), np.empty(3), np.empty(3)
    M, V, BV = np.empty((6, 6)), np.empty((6, 6)), np.empty((9, 6))
    BH = np.empty((9, 6))
    wv = np.empty(6)
    frame = np.empty((3, 3))
    for ii in range(order.shape[0]):
        e = order[ii]
        en, A_, B_, C_, f, it2, it3, tau = _bend_gradient(e, x, st, alpha, c0, a, b, w, g)
        total += en
        if mode == GRADIENT:
            _scatter_gradient(e, st, g, grad, 3)
            continue
        _bend_h6(a, b, A_, B_, C_, f, it2, it3, tau, H6)
        # H9 = D^T H6 D for (a, b) = (x1 - x0, x2 - x1)
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
            _project_translation_free(H, B, M, BH, V, wv, BV, frame, True)
        _emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 3)
    return total


# ---------------------------------------------------------------------------
# shells
# ---------------------------------------------------------------------------
@njit(**_JIT)
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


@njit(**_JIT)
def _membrane_run(x, st, order, G, K, mu, lam, project, B, grad, data, slots, g_out, H_out, mode):
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
            _scatter_gradient(e, st, g, grad, 3)
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
            _project_translation_free(H, B, M, BH, V, wv, BV, _NO_FRAME, False)
        _emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 3)
    return total


@njit(**_INLINE)
def _wrap(d):
    """d - 2 pi round(d / 2 pi), rounding half to even like NumPy/PyTorch."""
    t = d / (2.0 * math.pi)
    r = math.floor(t + 0.5)
    if r - t == 0.5 and r % 2.0 != 0.0:  # exact half: to even
        r -= 1.0
    return d - 2.0 * math.pi * r


@njit(**_INLINE)
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


@njit(**_JIT)
def hinge_energy(x, st, order, k, rest_angle):
    """sum_h k (theta - thetabar)^2, the difference wrapped to (-pi, pi]."""
    ev, da, db, N1, N2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    total = 0.0
    for ii in range(order.shape[0]):
        e = order[ii]
        d = _wrap(_hinge_theta(e, x, st, ev, da, db, N1, N2) - rest_angle[e])
        total += k[e] * d * d
    return total


@njit(**_INLINE)
def _skew(v, S):
    S[0, 0], S[0, 1], S[0, 2] = 0.0, -v[2], v[1]
    S[1, 0], S[1, 1], S[1, 2] = v[2], 0.0, -v[0]
    S[2, 0], S[2, 1], S[2, 2] = -v[1], v[0], 0.0


@njit(**_INLINE)
def _matmul3(A, B, out, scale):
    for i in range(3):
        for j in range(3):
            out[i, j] = scale * (A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j])


@njit(**_JIT)
def _hinge_run(x, st, order, kk, rest_angle, project, B, grad, data, slots, g_out, H_out, mode):
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
        total += kk[e] * d * d
        if mode == GRADIENT:
            _scatter_gradient(e, st, g, grad, 4)
            continue
        # M_s = (I - 2 n n^T) / |N|^2, n = N / |N|
        for i in range(3):
            for j in range(3):
                dl = 1.0 if i == j else 0.0
                M1[i, j] = (dl - 2.0 * N1[i] * N1[j] / q1) / q1
                M2[i, j] = (dl - 2.0 * N2[i] * N2[j] / q2) / q2
        # ga_da = -L M1 [e]x ; ga_e = -(N1/q1) eh^T + L M1 [da]x
        _skew(ev, Sk)
        _matmul3(M1, Sk, T1, -L)  # ga_da
        _matmul3(M2, Sk, T2, L)  # gb_db
        for i in range(3):
            for j in range(3):
                Ja[2, i, j] = T1[i, j]
                Jb[3, i, j] = T2[i, j]
                Ja[3, i, j] = 0.0
                Jb[2, i, j] = 0.0
        _skew(da, Sk)
        _matmul3(M1, Sk, T1, L)
        _skew(db, Sk)
        _matmul3(M2, Sk, T2, -L)
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
            _project_translation_free(H, B, M, BH, V, wv, BV, _NO_FRAME, False)
        _emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, 4)
    return total


# ---------------------------------------------------------------------------
# inertia and gravity (the solver's share of the incremental potential)
# ---------------------------------------------------------------------------
@njit(**_JIT)
def inertia_gravity(x, x_prev, x_prev2, masses, g, inv_h2, grad):
    """Inertia ``1/(2h^2) ||x - 2x_{t-1} + x_{t-2}||_M^2`` plus gravity ``-sum_i m_i x_i . g``.

    The same terms as ``energy.dynamics.IncrementalPotential`` (lumped masses), in one pass
    over the vertices; adds their gradient into ``grad`` (3n,) unless it is empty, and
    returns the energy.
    """
    e_in = 0.0
    e_g = 0.0
    with_grad = grad.shape[0] > 0
    for v in range(x.shape[0]):
        m = masses[v]
        for i in range(3):
            a = x[v, i] - 2.0 * x_prev[v, i] + x_prev2[v, i]
            e_in += m * a * a
            e_g += m * x[v, i] * g[i]
            if with_grad:
                grad[3 * v + i] += m * (inv_h2 * a - g[i])
    return 0.5 * inv_h2 * e_in - e_g


@njit(**_JIT)
def add_at(data, slots, values):
    """data[slots[j]] += values[j] (slots distinct), without NumPy's fancy-index temporaries."""
    for j in range(slots.shape[0]):
        data[slots[j]] += values[j]


# ---------------------------------------------------------------------------
# the kernels of one energy term
# ---------------------------------------------------------------------------
_EMPTY_F = np.zeros(0)
_EMPTY_G = np.zeros((0, 0))
_EMPTY_H = np.zeros((0, 0, 0))
_EMPTY_S = np.zeros((0, 0), dtype=np.int32)


class TermKernel:
    """Compiled energy, gradient and Hessian of one ``EnergyTerm`` (see the module docstring).

    Built by ``term_kernel(term)``; holds float64 NumPy copies of the term's
    stencils and rest data.  The stencils are visited group by group
    (``groups``: all of them, or the two halves and the separator that
    :func:`split_stencils` makes); with ``threads = 2`` the two halves run
    concurrently (the kernels release the GIL; halves share no vertex, so no
    gradient entry or Hessian slot is written by both), then the separator.
    Every path visits the groups in the same order, so the result does not
    depend on ``threads``.
    """

    # fewer stencils than this: a thread hand-off costs more than it saves (hair rotation, 3,400 rod
    # stencils per term, ran slower on two threads; the armadillo, 12k tets, faster)
    MIN_PARALLEL = 5000

    def __init__(self, term, energy_fn, run_fn, args, k, basis=None):
        self.name = term.name
        self.stencils = np.ascontiguousarray(term.stencils.cpu().numpy(), dtype=np.int64)
        self.k = k
        self._energy = energy_fn
        self._run = run_fn
        self._args = args
        self._basis = basis  # translation-free basis (projection), None for tets / stretch
        self._all = np.arange(len(self.stencils), dtype=np.int64)
        self.groups = (self._all,)
        self.threads = 1
        self._serial, self._serial_of = None, None  # the groups concatenated, for one serial call

    def _visit(self, fn, total: bool = True) -> float:
        """sum of fn(order) over the groups, the two halves concurrently when threaded.

        Serially it is one call over the groups concatenated (the same visiting order, so the
        same scatter), except for a kernel large enough to run threaded whose energy is wanted
        (``total=True``): that energy is summed group by group, as the threaded path sums it,
        so its last bits do not depend on the thread count.
        """
        g = self.groups
        large = len(self._all) >= self.MIN_PARALLEL
        if len(g) == 3 and self.threads > 1 and large:
            other = _pool().submit(fn, g[0])
            second = fn(g[1])
            return other.result() + second + fn(g[2])
        if (total and large) or len(g) == 1:
            return sum(fn(order) for order in g)
        if self._serial_of is not g:
            self._serial, self._serial_of = np.concatenate(g), g
        return fn(self._serial)

    def _call(self, x, project, grad, data, slots, g_out, H_out, mode) -> float:
        x = np.ascontiguousarray(x, dtype=np.float64)
        extra = () if self._basis is None else (self._basis,)
        run, st, args = self._run, self.stencils, self._args
        return self._visit(lambda order: run(x, st, order, *args, project, *extra, grad, data, slots, g_out, H_out, mode),
                           total=mode != STORE)  # fmt: skip

    def energy(self, x: np.ndarray) -> float:
        """The term's energy at x (n, 3)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        fn, st, args = self._energy, self.stencils, self._args
        return float(self._visit(lambda order: fn(x, st, order, *args)))

    def accumulate(self, x, grad, data, slots, project: bool) -> float:
        """grad (3n,) += gradient; data[slots] += upper triangles of the stencil Hessians;
        returns the energy (the same sum, to the bit, as ``energy_gradient``'s).

        slots : (E, 3k (3k+1) / 2) int32 target indices of the upper-triangle
        entries of each stencil Hessian (row-major), -1 for dropped entries.
        """
        return self._call(x, bool(project), grad, data, slots, _EMPTY_G, _EMPTY_H, SCATTER)

    def energy_gradient(self, x, grad) -> float:
        """grad (3n,) += gradient; returns the energy (one pass, no Hessian)."""
        return self._call(x, False, grad, _EMPTY_F, _EMPTY_S, _EMPTY_G, _EMPTY_H, GRADIENT)

    def local(self, x, project: bool):
        """Per-stencil g (E, 3k) and H (E, 3k, 3k), like ``EnergyTerm.local_gradient_hessian``."""
        E, n3 = self.stencils.shape[0], 3 * self.k
        g, H = np.zeros((E, n3)), np.zeros((E, n3, n3))
        self._call(x, bool(project), _EMPTY_F, _EMPTY_F, _EMPTY_S, g, H, STORE)
        return g, H


_POOL = None


def _pool():
    """One worker thread, shared by every kernel (the caller's thread runs the other half)."""
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(1, thread_name_prefix="latentsim-kernels")
    return _POOL


def split_stencils(kernels, n_vertices: int, threads: int = 2) -> None:
    """Give each kernel two vertex-disjoint halves of its stencils and the separator.

    The vertices are ordered by reverse Cuthill-McKee on the graph of all the
    kernels' stencils (neighbours end up close in the order) and cut at the
    median: stencils wholly below the cut form the first half, wholly above
    the second, the rest (a layer about one stencil thick) the separator.
    ``threads`` (1 or 2) sets whether the halves run concurrently; the result
    is the same either way.
    """
    import scipy.sparse
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    rows, cols = [], []
    for k in kernels:
        st = k.stencils
        for a in range(st.shape[1]):
            for b in range(st.shape[1]):
                if a != b:
                    rows.append(st[:, a])
                    cols.append(st[:, b])
    rank = np.arange(n_vertices)
    if rows:
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = scipy.sparse.csr_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n_vertices, n_vertices))
        rank[reverse_cuthill_mckee(graph, symmetric_mode=True)] = np.arange(n_vertices)
    low = rank < n_vertices // 2
    for k in kernels:
        inside = low[k.stencils]
        first, second = inside.all(1), ~inside.any(1)
        k.groups = tuple(np.flatnonzero(m).astype(np.int64) for m in (first, second, ~(first | second)))
        k.threads = int(threads)


def _np(t, E=None):
    a = t.detach().cpu().numpy().astype(np.float64)
    if E is not None:
        a = np.broadcast_to(a, (E,))
    return np.ascontiguousarray(a)


def term_kernel(term) -> TermKernel | None:
    """The compiled kernels of ``term``, or None when numba is missing or the term has none."""
    if numba is None:
        return None
    from latentsim.physics.rods import RodBend, RodStretch
    from latentsim.physics.shells import ShellHinge, ShellMembraneStVK
    from latentsim.physics.tets import StVKTets

    E = int(term.stencils.shape[0])
    if isinstance(term, StVKTets):
        args = (_np(term.grad_op), _np(term.rest_volume, E), _np(term.mu, E), _np(term.lam, E))
        return TermKernel(term, tet_energy, _tet_run, args, 4)
    if isinstance(term, RodStretch):
        return TermKernel(term, stretch_energy, _stretch_run, (_np(term.rest_length), _np(term.ks)), 2)
    if isinstance(term, RodBend):
        args = (_np(4.0 * term.kb / term.rest_voronoi), _np(term.rest_product))
        return TermKernel(term, bend_energy, _bend_run, args, 3, translation_free_basis(3))
    if isinstance(term, ShellMembraneStVK):
        args = (np.ascontiguousarray(term._G_np), _np(term.rest_area * term.thickness), _np(term.mu), _np(term.lam))
        return TermKernel(term, membrane_energy, _membrane_run, args, 3, translation_free_basis(3))
    if isinstance(term, ShellHinge):
        args = (_np(term.kb * term.weight), _np(term.rest_angle))
        return TermKernel(term, hinge_energy, _hinge_run, args, 4, translation_free_basis(4))
    return None


# ---------------------------------------------------------------------------
# many states at once: the self-supervised losses
# ---------------------------------------------------------------------------
def batch_energy_gradient(kernels, x, gradient: bool = True, threads: int = 1):
    """Energies and gradients of the summed terms at each of B states, by the compiled kernels.

    Parameters
    ----------
    kernels : the ``TermKernel`` of every term.
    x : (B, n, 3) float64 states.
    gradient : also return the gradients (else only the energies, a cheaper pass).
    threads : states are split over this many threads (the kernels release the GIL); each state
        is computed whole by one thread, so the result does not depend on ``threads``.

    Returns
    -------
    E : (B,), G : (B, n, 3) or None
    """
    x = np.ascontiguousarray(x, dtype=np.float64)
    B = x.shape[0]
    E = np.zeros(B)
    G = np.zeros(x.shape) if gradient else None

    def work(lo, hi):
        for b in range(lo, hi):
            if gradient:
                g = G[b].reshape(-1)
                E[b] = sum(k.energy_gradient(x[b], g) for k in kernels)
            else:
                E[b] = sum(k.energy(x[b]) for k in kernels)

    threads = max(1, min(int(threads), B))
    if threads == 1:
        work(0, B)
    else:
        from concurrent.futures import ThreadPoolExecutor

        bounds = np.linspace(0, B, threads + 1).round().astype(int)
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(work, bounds[:-1], bounds[1:]))
    return E, G


class _CompiledEnergy(torch.autograd.Function):
    """E(x) summed over the kernels' terms, x (..., n, 3) -> (...); first derivatives only."""

    @staticmethod
    def forward(ctx, x, kernels, threads):
        lead = x.shape[:-2]
        flat = x.detach().reshape(-1, *x.shape[-2:]).numpy()
        E, G = batch_energy_gradient(kernels, flat, gradient=ctx.needs_input_grad[0], threads=threads)
        if G is not None:
            ctx.save_for_backward(torch.from_numpy(G).reshape(x.shape))
        return torch.from_numpy(E).reshape(lead)

    @staticmethod
    def backward(ctx, grad_energy):
        if torch.is_grad_enabled():  # create_graph: a second derivative would silently miss this energy
            raise RuntimeError("compiled energies have first derivatives only; use the terms' PyTorch energies (potential.kernels = None) for Hessians")
        (G,) = ctx.saved_tensors
        return grad_energy[..., None, None] * G, None, None


def compiled_energy(kernels, x: torch.Tensor, threads: int | None = None) -> torch.Tensor:
    """The elastic energy of x (..., n, 3) (CPU, float64) by the compiled kernels, differentiable
    once (its backward is the kernels' gradient; a second derivative raises).  ``threads``:
    default ``torch.get_num_threads()``, the thread budget the caller set for torch."""
    if x.device.type != "cpu" or x.dtype != torch.float64:
        raise ValueError(f"compiled energies take float64 CPU states, got {x.dtype} on {x.device}")
    return _CompiledEnergy.apply(x, kernels, int(threads or torch.get_num_threads()))


def with_compiled_elastic(potential):
    """A copy of ``potential`` (``IncrementalPotential``) whose elastic energy runs the compiled
    kernels of its terms (5-8x faster than the batched PyTorch energy under autograd on many
    states; first derivatives only), or ``potential`` itself when a term has no kernel or numba is
    missing.  The same formulas: ``tests/test_kernels.py`` checks them against the terms."""
    import dataclasses

    if not dataclasses.is_dataclass(potential):  # a wrapper (tests): leave it as it is
        return potential
    ks = [term_kernel(t) for t in potential.terms]
    if not ks or any(k is None for k in ks):
        return potential
    return dataclasses.replace(potential, kernels=ks)


__all__ = [
    "TermKernel",
    "available",
    "batch_energy_gradient",
    "compiled_energy",
    "split_stencils",
    "term_kernel",
    "translation_free_basis",
    "with_compiled_elastic",
]
