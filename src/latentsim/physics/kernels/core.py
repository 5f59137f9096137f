r"""Shared pieces of the compiled per-stencil kernels (numba), written once.

- scatter: a stencil's gradient g (3k,) and the upper triangle of its Hessian
  H (3k, 3k) added into the (3n,) gradient and into the data array of the
  free-DoF Hessian at precomputed slots (``solve.sparse.HessianPattern.stencil_slots``);
- ``jacobi_eigh``: THE small symmetric eigensolver (cyclic Jacobi), used for
  3x3 (the SVD, the StVK scaling block) up to 9x9 (hinge projection) matrices;
- ``svd3``: the rotation-variant 3x3 SVD F = U diag(sigma) V^T (Irving et al.
  2004; Teran et al. 2005) built on it, and ``rotation_variant_svd``, its
  batched form;
- ``project_psd``: THE eigenvalue clamp of a stencil Hessian (Teran et al.
  2005), on the span of an orthonormal basis: the identity for a plain clamp,
  ``translation_free_basis(k)`` for translation-invariant energies;
- small 3-vector helpers (``skew``, ``matmul3``);
- lanes: the energy and energy + gradient kernels take one state x (n, 3) or
  L states x (n, 3, L), the state index innermost (``as_lanes``,
  ``lane_count``).  Every per-stencil quantity then has a trailing lane axis
  and every innermost loop runs over the lanes, contiguous in memory, so the
  L states' identical arithmetic is vectorised; each lane performs exactly the
  operations of a one-state pass, in the same order (no fast-math, no
  reassociation), so the bits do not depend on L.  For one state L is the
  constant 1 and the lane loops vanish at compile time.  ``energy_gradient_lanes``
  is the loop of every energy + gradient kernel, ``run_stencils`` that of a run kernel
  (gradient and Hessian per stencil, scattered or stored: ``emit``, ``emit_upper``).

Everything runs in float64 and is compiled once and cached on disk
(``cache=True``); the kernels release the GIL (``nogil``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numba.extending import overload

JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
# The helpers below marked INLINE are inlined into each run kernel (numba IR inlining) with the
# stencil size k as a literal: the loops then have fixed trip counts that LLVM unrolls.  Called,
# with k read from st.shape[1], they made a Hessian pass 2-3x slower (the grad+Hess+proj column
# of benchmarks/bench_simulator.py).
INLINE = dict(JIT, inline="always")


SCATTER, STORE = 1, 2  # modes of the run kernels: scatter, store per stencil


# ---------------------------------------------------------------------------
# lanes: one state (n, 3) or L states (n, 3, L), the state index innermost
# ---------------------------------------------------------------------------
def as_lanes(x):
    """x (n, 3) as a view (n, 3, 1), one lane; x (n, 3, L) as it is."""


@overload(as_lanes, inline="always")
def _as_lanes(x):
    if x.ndim == 2:
        return lambda x: x.reshape((x.shape[0], x.shape[1], 1))
    return lambda x: x


def lane_count(x):
    """The number of lanes of x: the constant 1 for x (n, 3), L for x (n, 3, L)."""


@overload(lane_count, inline="always")
def _lane_count(x):
    if x.ndim == 2:
        return lambda x: 1
    return lambda x: x.shape[2]


@njit(**INLINE)
def scatter_lanes(e, st, g, grad, k, L):
    """Add stencil e's gradient g (3k, L) into grad (n, 3, L), lane by lane; k = st.shape[1]."""
    for a in range(k):
        v = st[e, a]
        for i in range(3):
            for s in range(L):
                grad[v, i, s] += g[3 * a + i, s]


@njit(**INLINE)
def energy_gradient_lanes(local, scratch, x, st, order, args, grad, k):
    """The body of every ``*_energy_gradient`` kernel: the energies (L,) of the stencils ``order``
    in each lane of x (n, 3) or (n, 3, L), their gradients added into grad (x's shape).

    Per stencil e, ``local(e, x, st, args, work, total, L)`` adds its energies into total (L,)
    and leaves its gradients (3k, L) in ``work[0]``; ``work = scratch(L)`` holds its lanes, and
    ``args`` the term's rest data.  A run kernel calls the same ``local`` with one lane.
    """
    L = lane_count(x)
    xl, gl = as_lanes(x), as_lanes(grad)
    work = scratch(L)
    total = np.zeros(L)
    for ii in range(order.shape[0]):
        e = order[ii]
        local(e, xl, st, args, work, total, L)
        scatter_lanes(e, st, work[0], gl, k, L)
    return total


# ---------------------------------------------------------------------------
# scatter into the gradient and the sparse Hessian
# ---------------------------------------------------------------------------
@njit(**INLINE)
def scatter_gradient(e, st, g, grad, k):
    """Add stencil e's gradient g (3k,) into grad (3n,); k = st.shape[1]."""
    for a in range(k):
        v = st[e, a]
        for i in range(3):
            grad[3 * v + i] += g[3 * a + i]


@njit(**INLINE)
def scatter(e, st, g, H, grad, data, slots, k):
    """Add stencil e's gradient g (3k,) and the upper triangle of H (3k, 3k); k = st.shape[1]."""
    scatter_gradient(e, st, g, grad, k)
    n3 = 3 * k
    m = 0
    for p in range(n3):
        for q in range(p, n3):
            s = slots[e, m]
            if s >= 0:
                data[s] += H[p, q]
            m += 1


@njit(**INLINE)
def emit(e, st, g, H, grad, data, slots, g_out, H_out, mode, k):
    """Stencil e's g and (symmetric) H: scattered into grad/data (SCATTER) or stored in g_out/H_out."""
    if mode == SCATTER:
        scatter(e, st, g, H, grad, data, slots, k)
    else:
        g_out[e] = g
        H_out[e] = H


@njit(**INLINE)
def emit_upper(e, st, g, H, grad, data, slots, g_out, H_out, mode, k):
    """``emit`` of a Hessian H of which only the upper triangle is written (all that ``scatter``
    reads): stored (STORE) mirrored into the lower one."""
    if mode == SCATTER:
        scatter(e, st, g, H, grad, data, slots, k)
    else:
        g_out[e] = g
        n3 = 3 * k
        for i in range(n3):
            for j in range(i, n3):
                H_out[e, i, j] = H[i, j]
                H_out[e, j, i] = H[i, j]


@njit(**INLINE)
def run_stencils(local, hessian, scratch, out, x, st, order, args, project, basis, grad, data, slots, g_out, H_out, mode, k):
    """The body of a run kernel: per stencil e of ``order`` in the one state x (n, 3), its energy
    (summed and returned), gradient g and (exact or projected) Hessian H, emitted by ``out``
    (``emit``, or ``emit_upper`` for a Hessian written only in its upper triangle).

    ``scratch()`` returns (g (3k,), H (3k, 3k), work, extra): ``work`` the one-lane scratch of
    ``local`` (``energy_gradient_lanes``' per-stencil function), whose first entry is g as (3k, 1);
    ``extra`` the scratch of ``hessian(e, args, work, extra, project, basis, H)``, which writes H
    from what ``local`` left in ``work`` (``basis``: the projection's, ``project_psd``; ``NO_FRAME``
    for a kernel that projects without one).  The energy is, to the bit, the sum of the energy + gradient
    kernel's (the same ``local``).
    """
    xl = as_lanes(x)
    g, H, work, extra = scratch()
    total = np.zeros(1)
    for ii in range(order.shape[0]):
        e = order[ii]
        local(e, xl, st, args, work, total, 1)
        hessian(e, args, work, extra, project, basis, H)
        out(e, st, g, H, grad, data, slots, g_out, H_out, mode, k)
    return total[0]


@njit(**JIT)
def add_at(data, slots, values):
    """data[slots[j]] += values[j] (slots distinct), without NumPy's fancy-index temporaries."""
    for j in range(slots.shape[0]):
        data[slots[j]] += values[j]



# ---------------------------------------------------------------------------
# the eigensolver, the PSD projection, the SVD
# ---------------------------------------------------------------------------
@njit(**JIT)
def jacobi_eigh(A, V, w):
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


@njit(**JIT)
def project_psd(H, B, M, BH, V, w, BV, frame, use_frame):
    """The PSD projection: eigenvalue clamp of a symmetric stencil Hessian H (n, n), in place.

    H lives on the span of the orthonormal columns of B (n, m): H = B M B^T with
    M = B^T H B (m, m), so clamping the eigenvalues of M (cyclic Jacobi) clamps
    those of H exactly, H <- (B V w+^1/2)(B V w+^1/2)^T.  B = I (n, n) is the
    plain clamp; a translation-invariant stencil energy takes the
    translation-free basis B = Q (x) I3 (3k, 3k-3) of
    :func:`translation_free_basis` and so diagonalises a (3k-3)-square M
    (``base.project_psd_translation_free`` is the same in PyTorch).  M, BH (n, m),
    V (m, m), w (m,) and BV (n, m) are scratch.  With ``use_frame``, M is first rotated into the orthonormal frame whose rows
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
    jacobi_eigh(M, V, w)
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


NO_FRAME = np.eye(3)  # ``frame`` of project_psd when ``use_frame`` is False


def translation_free_basis(k: int) -> np.ndarray:
    """B = Q (x) I3 (3k, 3k-3), Q an orthonormal basis of the vectors orthogonal to (1, .., 1)."""
    ones = np.ones((k, 1))
    Qfull, _ = np.linalg.qr(np.concatenate([ones, np.eye(k)[:, : k - 1]], 1))
    return np.ascontiguousarray(np.kron(Qfull[:, 1:], np.eye(3)))



@njit(**JIT)
def svd3(F, C, Vm, w, U, sig, V, b):
    """Rotation-variant SVD F = U diag(sig) V^T (``rotation_variant_svd``); C, Vm, w, b scratch."""
    tiny = 2.2250738585072014e-308
    for i in range(3):
        for j in range(3):
            C[i, j] = F[0, i] * F[0, j] + F[1, i] * F[1, j] + F[2, i] * F[2, j]
    jacobi_eigh(C, Vm, w)
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



@njit(**JIT)
def _svd3_batch(F, U, sig, V):
    """svd3 of every F[e] (N, 3, 3) into U, V (N, 3, 3) and sig (N, 3)."""
    C, Vm, b = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    w = np.empty(3)
    for e in range(F.shape[0]):
        svd3(F[e], C, Vm, w, U[e], sig[e], V[e], b)


def rotation_variant_svd(F: np.ndarray):
    """Rotation-variant SVD F = U diag(sigma) V^T of a batch of 3x3 matrices (``svd3``).

    det U = det V = +1; sigma_0 >= sigma_1 >= |sigma_2|, and sigma_2 < 0 iff
    det F < 0 (Irving et al. 2004; Teran et al. 2005).  V comes from a Jacobi
    eigen-decomposition of F^T F, U from a Gram-Schmidt QR of F V, completed
    to a rotation for flat or collapsed elements.

    Parameters
    ----------
    F : (N, 3, 3) array-like.

    Returns
    -------
    U (N, 3, 3), sigma (N, 3), V (N, 3, 3) float64 arrays.
    """
    F = np.ascontiguousarray(F, dtype=np.float64)
    U, sig, V = np.empty_like(F), np.empty(F.shape[:2]), np.empty_like(F)
    _svd3_batch(F, U, sig, V)
    return U, sig, V


# ---------------------------------------------------------------------------
# small vector helpers
# ---------------------------------------------------------------------------
@njit(**INLINE)
def skew(v, S):
    S[0, 0], S[0, 1], S[0, 2] = 0.0, -v[2], v[1]
    S[1, 0], S[1, 1], S[1, 2] = v[2], 0.0, -v[0]
    S[2, 0], S[2, 1], S[2, 2] = -v[1], v[0], 0.0


@njit(**INLINE)
def matmul3(A, B, out, scale):
    for i in range(3):
        for j in range(3):
            out[i, j] = scale * (A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j])

