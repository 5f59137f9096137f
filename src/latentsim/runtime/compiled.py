"""Compiled latent runtime: one frame as one numba kernel call.

The same folded weights as :class:`latentsim.runtime.NumpyStepper` (an exported
``.npz`` runtime), stepped by a single compiled function instead of a dozen
NumPy calls.  At the scenes' sizes a NumPy call costs about as much as the
arithmetic it does (0.5-1.5 us each), so the NumPy step has a floor of 13-57 us
whatever the network (``benchmarks/bench_step_floor.py``); here a step costs
one call (~0.6 us) plus its arithmetic and memory traffic.

Layout (built from a :class:`NumpyStepper`, which decides the output layout):

- ``F`` (network dtype): every layer as its augmented ``[W^T; b^T]`` matrix
  (``(in + 1, out)``, row-major), integrator layers, decoder hidden layers, the
  optional mid layer, and the output layer (over all ``n`` vertices in the
  ``full`` layout, over the free ones in ``scatter``);
- ``I`` (int64): a header (the ``_R``... indices below), one row
  ``(offset, in, out, flags)`` per layer, then the output's chunks and runs and
  the coordinates' index lists.

Each layer is evaluated as ``y = A[in] + sum_i h_i A[i]``: the inner loop runs
over the contiguous outputs (vectorised).  The output layer is summed in chunks
of ``_CHUNK`` values, in a buffer that stays in L1; each chunk is then written to
the float64 positions in *runs* that share one origin (the Dirichlet mean, or one
rod's root: a rod's vertices are consecutive), a constant added per run; the
prescribed vertices are copied back in runs of consecutive indices.
"""

from __future__ import annotations

import os
from functools import partial

import numpy as np

from latentsim.runtime.files import read_runtime
from latentsim.runtime.numpy_stepper import NumpyStepper

try:  # numba is pinned in envs/requirements.txt; without it this runtime is simply not offered
    import numba
    from numba import njit
except ImportError:  # pragma: no cover - depends on the install
    numba = None

    def njit(*_a, **_k):
        """Stand-in decorator: keeps the module importable; nothing below is called."""
        return lambda f: f


__all__ = ["CompiledStepper", "available", "deployable_steppers", "load_runtime"]

# fastmath without "nnan"/"ninf": a diverging rollout must still produce the NaN that stops it
_FAST = {"reassoc", "contract", "arcp", "nsz", "afn"}
_JIT = {"cache": True, "nogil": True, "boundscheck": False, "fastmath": _FAST, "error_model": "numpy"}
_CHUNK = 384  # output values per chunk (a multiple of 3: whole vertices)
_SILU_CLAMP = -80.0  # exp(80) is finite in float32; silu(a) ~ 0 below

# the header of I: the index of each entry
_R, _K, _NINT, _NDEC, _MID, _RESID, _SCATTER, _W, _D, _TABLE, _SEG, _NSEG, _FREE, _SLOT, _DRUN, _NDRUN, _M, _FAST32, _CHK, _NCHK, _FUSED = range(21)
_HLEN = 21
# the per-layer flags
F_SILU, F_SKIP = 1, 2


def available() -> bool:
    """True when numba imports."""
    return numba is not None


@njit(inline="always", **_JIT)
def _accumulate(A, h, nin, c0, c1, y):
    """y[:] = A[nin, c0:c1] + sum_i h[i] A[i, c0:c1], four rows of A per pass over y.

    The loops run over array views (``A[i, c0:c1]``): with offsets into the flat
    arrays in the index they do not vectorise (3-10x slower); four rows a pass
    load and store y a quarter as often (1.09 -> 0.71 us for 34 x 576).
    """
    nc = c1 - c0
    bias = A[nin, c0:c1]
    for j in range(nc):
        y[j] = bias[j]
    i = 0
    while i + 4 <= nin:
        a0, a1, a2, a3 = A[i, c0:c1], A[i + 1, c0:c1], A[i + 2, c0:c1], A[i + 3, c0:c1]
        g0, g1, g2, g3 = h[i], h[i + 1], h[i + 2], h[i + 3]
        for j in range(nc):
            y[j] += g0 * a0[j] + g1 * a1[j] + g2 * a2[j] + g3 * a3[j]
        i += 4
    while i < nin:
        a, g = A[i, c0:c1], h[i]
        for j in range(nc):
            y[j] += g * a[j]
        i += 1


@njit(inline="always", **_JIT)
def _silu32(y, n):
    """y[:n] = y / (1 + exp(-y)) for a float32 network, with exp evaluated in float64 as
    (Taylor_8(a / 256))^256, a = -y clamped to [-80, 80]: no library call, so the loop
    vectorises (4.1 -> 0.9 ns a value); relative error below 7.4e-8 over [-80, 80], under
    float32's epsilon (1.2e-7; the libm path's 5.9e-8).  A NaN stays NaN (comparisons are
    false for it, and it propagates through the polynomial)."""
    for o in range(n):
        t = np.float64(y[o])
        a = -t
        if a > 80.0:
            a = 80.0
        if a < -80.0:
            a = -80.0
        q = a * (1.0 / 256.0)
        e = 1.0 + q * (1.0 + q * (1.0 / 2 + q * (1.0 / 6 + q * (1.0 / 24 + q * (1.0 / 120 + q * (1.0 / 720 + q * (1.0 / 5040 + q / 40320)))))))
        for _ in range(8):
            e = e * e
        y[o] = t / (1.0 + e)


@njit(inline="always", **_JIT)
def _affine(F, off, nin, nout, S, src, dst, flags, fast32):
    """S[dst:dst+nout] = act(A[nin] + sum_i S[src+i] A[i]) (+ S[src:src+nout] with a skip)."""
    A = F[off : off + (nin + 1) * nout].reshape((nin + 1, nout))
    h = S[src : src + nin]
    y = S[dst : dst + nout]
    _accumulate(A, h, nin, 0, nout, y)
    if flags & F_SILU and fast32:
        _silu32(y, nout)
    elif flags & F_SILU:
        for o in range(nout):
            t = y[o]
            if t < _SILU_CLAMP:  # False for a NaN, which must reach the output (a diverging rollout stops on it)
                t = _SILU_CLAMP
            y[o] = t / (1.0 + np.exp(-t))
    if flags & F_SKIP:
        for o in range(nout):
            y[o] += h[o]


@njit(inline="always", **_JIT)
def _integrate(F, I, S, z1, z2, p0, p1, p2, zout):
    """zout (r,) <- the integrator's next latent from z1, z2 (r,) and p0, p1, p2 (k,), through its layers
    in the ping-pong buffers a = S[0:w], b = S[w:2w] (plus z1 where the integrator is residual)."""
    r, k, w, T = I[_R], I[_K], I[_W], I[_TABLE]
    a, b = 0, w
    for i in range(r):
        S[a + i] = z1[i]
        S[a + r + i] = z2[i]
    for i in range(k):
        S[a + 2 * r + i] = p0[i]
        S[a + 2 * r + k + i] = p1[i]
        S[a + 2 * r + 2 * k + i] = p2[i]
    src, dst = a, b
    for l in range(I[_NINT]):
        row = T + 4 * l
        _affine(F, I[row], I[row + 1], I[row + 2], S, src, dst, I[row + 3], I[_FAST32])
        src, dst = dst, src
    for i in range(r):
        zi = S[src + i]
        if I[_RESID]:
            zi += z1[i]
        zout[i] = zi


@njit(inline="always", **_JIT)
def _decode_hidden(F, I, S, z):
    """The decoder's hidden layers (and its optional mid layer) from z (r,); returns the offset in S of the
    output layer's input: [z; h_L] at zh = S[2w:], or the mid layer's output at a = S[0:]."""
    r, w, T = I[_R], I[_W], I[_TABLE]
    n_int, n_dec, mid = I[_NINT], I[_NDEC], I[_MID]
    a, b, zh = 0, w, 2 * w
    for i in range(r):
        S[zh + i] = z[i]
    # decoder hidden layers from z; the last writes h_L behind z, so the output layer reads [z; h_L]
    src = zh
    for l in range(n_dec):
        row = T + 4 * (n_int + l)
        dst = zh + r if l == n_dec - 1 else (a if src != a else b)
        _affine(F, I[row], I[row + 1], I[row + 2], S, src, dst, I[row + 3], I[_FAST32])
        src = dst
    src = zh
    if mid:
        row = T + 4 * (n_int + n_dec)
        _affine(F, I[row], I[row + 1], I[row + 2], S, zh, a, I[row + 3], I[_FAST32])
        src = a
    return src


@njit(inline="always", **_JIT)
def _dirichlet_origin(I, xD, x, fused):
    """(o0, o1, o2): the mean of the m prescribed positions xD (m, 3), the origin of the segments that have no
    root of their own (zeros without any).  ``fused``: the same pass also copies them into x (n, 3)."""
    m = I[_M]
    o0 = o1 = o2 = 0.0
    dr = I[_DRUN]
    if fused:  # the prescribed vertices are the mean's and are copied back: one pass over xD does both
        for g in range(I[_NDRUN]):
            v0, j0, cnt = I[dr + 3 * g], I[dr + 3 * g + 1], I[dr + 3 * g + 2]
            xo, xi = x[v0 : v0 + cnt], xD[j0 : j0 + cnt]
            for j in range(cnt):
                t0, t1, t2 = xi[j, 0], xi[j, 1], xi[j, 2]
                xo[j, 0], xo[j, 1], xo[j, 2] = t0, t1, t2
                o0 += t0
                o1 += t1
                o2 += t2
        o0, o1, o2 = o0 / m, o1 / m, o2 / m
    elif m:
        for j in range(m):
            o0 += xD[j, 0]
            o1 += xD[j, 1]
            o2 += xD[j, 2]
        o0, o1, o2 = o0 / m, o1 / m, o2 / m
    return o0, o1, o2


@njit(inline="always", **_JIT)
def _scatter_chunk(I, u, c0, c1, xD, x, o0, o1, o2):
    """The ``scatter`` layout: the chunk u (c1 - c0,) of free vertices' rows, each to its vertex of x (n, 3),
    plus its own root (a row of xD (m, 3)) where the roots are slotted, else the origin (o0, o1, o2)."""
    nc = c1 - c0
    vs = I[I[_FREE] + c0 // 3 : I[_FREE] + c1 // 3]
    if I[_SLOT] >= 0:  # roots: each free vertex's own root
        ss = I[I[_SLOT] + c0 // 3 : I[_SLOT] + c1 // 3]
        for f in range(nc // 3):
            v, s = vs[f], ss[f]
            x[v, 0] = u[3 * f] + xD[s, 0]
            x[v, 1] = u[3 * f + 1] + xD[s, 1]
            x[v, 2] = u[3 * f + 2] + xD[s, 2]
    else:
        for f in range(nc // 3):
            v = vs[f]
            x[v, 0] = u[3 * f] + o0
            x[v, 1] = u[3 * f + 1] + o1
            x[v, 2] = u[3 * f + 2] + o2


@njit(inline="always", **_JIT)
def _runs_chunk(I, u, c0, r0, r1, xD, xf, o0, o1, o2):
    """The ``full`` layout: the chunk u (starting at value c0) into the flat positions xf (3n,), its runs r0..r1
    of one origin each: the mean (o0, o1, o2), or one rod's root (a row of xD (m, 3))."""
    sg = I[_SEG]
    for rr in range(r0, r1):
        s0, s1, sl = I[sg + 3 * rr], I[sg + 3 * rr + 1], I[sg + 3 * rr + 2]
        q0, q1, q2 = (xD[sl, 0], xD[sl, 1], xD[sl, 2]) if sl >= 0 else (o0, o1, o2)
        nv = (s1 - s0) // 3
        xo, uo = xf[s0:s1].reshape((nv, 3)), u[s0 - c0 : s1 - c0]
        for j in range(nv):
            xo[j, 0] = uo[3 * j] + q0
            xo[j, 1] = uo[3 * j + 1] + q1
            xo[j, 2] = uo[3 * j + 2] + q2


@njit(inline="always", **_JIT)
def _copy_prescribed(I, xD, x):
    """x (n, 3) <- the prescribed positions xD (m, 3), in runs (vertex, slot, count) of consecutive indices."""
    xf, xDf = x.reshape(-1), xD.reshape(-1)
    dr = I[_DRUN]
    for g in range(I[_NDRUN]):
        v0, j0, cnt = 3 * I[dr + 3 * g], 3 * I[dr + 3 * g + 1], 3 * I[dr + 3 * g + 2]
        xo, xi = xf[v0 : v0 + cnt], xDf[j0 : j0 + cnt]
        for j in range(cnt):  # a loop: numba's slice assignment checks and buffers (2x slower here)
            xo[j] = xi[j]


@njit(**_JIT)
def _kernel(F, I, S, z1, z2, p0, p1, p2, xD, x, zout, what):
    """One frame. what: 1 integrate (z1.. -> zout), 2 decode (z1 -> x), 3 both (zout, then x).

    Scratch S: [a (w) | b (w) | z, h_L (r + w) | segment buffer (_CHUNK)].
    """
    r, w, D, T = I[_R], I[_W], I[_D], I[_TABLE]
    if what & 1:
        _integrate(F, I, S, z1, z2, p0, p1, p2, zout)
    if not what & 2:
        return
    src = _decode_hidden(F, I, S, zout if what & 1 else z1)
    row = T + 4 * (I[_NINT] + I[_NDEC] + I[_MID])
    off, nin = I[row], I[row + 1]
    A = F[off : off + (nin + 1) * D].reshape((nin + 1, D))
    h = S[src : src + nin]
    buf = S[3 * w + r : 3 * w + r + _CHUNK]
    fused = I[_FUSED]
    o0, o1, o2 = _dirichlet_origin(I, xD, x, fused)
    xf = x.reshape(-1)
    ck = I[_CHK]
    for g in range(I[_NCHK]):
        c0, c1, r0, r1 = I[ck + 4 * g], I[ck + 4 * g + 1], I[ck + 4 * g + 2], I[ck + 4 * g + 3]
        u = buf[: c1 - c0]
        _accumulate(A, h, nin, c0, c1, u)
        if I[_SCATTER]:  # the free vertices' rows, each to its vertex
            _scatter_chunk(I, u, c0, c1, xD, x, o0, o1, o2)
        else:
            _runs_chunk(I, u, c0, r0, r1, xD, xf, o0, o1, o2)
    if not fused:
        _copy_prescribed(I, xD, x)


@njit(**_JIT)
def _carry_out(x, R, c):
    """x (n, 3) float64 <- x R^T + c in place (R (3, 3), c (1, 3)): positions decoded in a rigid frame carried out
    into the world (:class:`~latentsim.runtime.RigidFrameStepper`), one pass instead of a matmul and an add."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2]
    c0, c1, c2 = c[0, 0], c[0, 1], c[0, 2]
    for i in range(x.shape[0]):
        a, b, d = x[i, 0], x[i, 1], x[i, 2]
        x[i, 0] = r00 * a + r01 * b + r02 * d + c0
        x[i, 1] = r10 * a + r11 * b + r12 * d + c1
        x[i, 2] = r20 * a + r21 * b + r22 * d + c2


@njit(**_JIT)
def _output_pass(A, h, y):
    """y[:] = A[nin] + sum_i h[i] A[i] over every output of the layer A (nin + 1, D): one vectorised pass of an
    output layer over every DoF, its arithmetic and memory traffic and nothing else (no integrator, no
    hidden layers, no origins, no prescribed vertices): the floor under a step that decodes through it."""
    _accumulate(A, h, A.shape[0] - 1, 0, A.shape[1], y)


def _runs(keys: np.ndarray, cap: int) -> list:
    """Split 0..len(keys) into [start, end) runs of equal consecutive keys, each at most cap long."""
    out, start = [], 0
    for i in range(1, len(keys) + 1):
        if i == len(keys) or keys[i] != keys[start] or i - start == cap:
            out.append((start, i))
            start = i
    return out


def _chunks(D: int, runs: list) -> tuple[np.ndarray, np.ndarray]:
    """Cut the output's D values into chunks of _CHUNK and the runs (start, end, slot) at the chunks' bounds.

    Returns (chunk rows (c0, c1, first run, end run), run rows (start, end, slot)): each chunk is summed once
    into the L1 buffer, then each of its runs written with its own origin.
    """
    chunks, out, k = [], [], 0
    for c0 in range(0, D, _CHUNK):
        c1, first = min(c0 + _CHUNK, D), len(out)
        while k < len(runs) and runs[k][0] < c1:
            s0, s1, sl = runs[k]
            out.append((max(s0, c0), min(s1, c1), sl))
            if s1 > c1:  # the run goes on in the next chunk
                break
            k += 1
        chunks.append((c0, c1, first, len(out)))
    return np.asarray(chunks, np.int64).reshape(-1, 4), np.asarray(out, np.int64).reshape(-1, 3)


def _index_runs(dst: np.ndarray, src: np.ndarray) -> np.ndarray:
    """(dst0, src0, count) rows covering dst[i] <- src[i] where both step by one."""
    rows, start = [], 0
    for i in range(1, len(dst) + 1):
        if i == len(dst) or dst[i] != dst[i - 1] + 1 or src[i] != src[i - 1] + 1:
            rows.append((dst[start], src[start], i - start))
            start = i
    return np.asarray(rows, np.int64).reshape(-1, 3)


def _layers(ref: NumpyStepper) -> list:
    """[(augmented matrix, flags)] of every layer in the kernel's order: integrator, decoder hidden, mid, output."""
    layers = [(A, F_SILU) for A in ref._int_A[:-1]] + [(ref._int_A[-1], 0)] if ref._int_A else []
    layers += [(A, F_SILU | (F_SKIP if s else 0)) for A, s in zip(ref._dec_A, ref.skips)]
    if ref.mid:
        layers.append((ref._mid_A, 0))
    layers.append((ref.output.A, 0))  # over all n vertices, or over the free ones (scatter)
    return layers


def _pack(layers: list, dtype) -> tuple[np.ndarray, np.ndarray]:
    """(F, table): the layers' matrices one after another in one flat array, and a row (offset, in, out, flags) each."""
    offsets = np.cumsum([0] + [A.size for A, _ in layers])
    F = np.empty(offsets[-1], dtype=dtype)
    for (A, _), off in zip(layers, offsets):
        F[off : off + A.size] = A.reshape(-1)
    table = np.array([[off, A.shape[0] - 1, A.shape[1], fl] for (A, fl), off in zip(layers, offsets)], np.int64)
    return F, table


def _output_index(ref: NumpyStepper) -> dict:
    """The output's index lists, by their header entry: chunks and segments (runs of one origin), the free vertices
    and their roots (scatter), and the runs of prescribed vertices copied back."""
    D, scatter, slot = ref.output.A.shape[1], ref.layout == "scatter", ref.output.slot
    m = len(ref.dirichlet)
    # segments of the output layer: (first value, end, root slot or -1 for the Dirichlet mean); scattered roots
    # are looked up per vertex in the scatter loop
    seg_slot = slot if slot is not None and not scatter else np.full(D // 3, -1, np.int64)
    chunks, seg = _chunks(D, [(3 * s, 3 * e, seg_slot[s]) for s, e in _runs(seg_slot, len(seg_slot))])
    empty = np.zeros(0, np.int64)
    free = ref.free if scatter else empty
    vslot = slot if slot is not None and scatter else empty
    # the prescribed vertices are copied back unless the output layer already gives them (roots, full)
    druns = _index_runs(ref.dirichlet, np.arange(m)) if ref.output.copy_back else np.zeros((0, 3), np.int64)
    return {_CHK: chunks, _SEG: seg, _FREE: free, _SLOT: vslot, _DRUN: druns}


class CompiledStepper:
    """The folded latent step as one numba kernel call per frame.

    A :class:`latentsim.runtime.Stepper`, with the same results as :class:`latentsim.runtime.NumpyStepper` (to
    rounding: the sums run in another order): :meth:`integrate`, :meth:`decode`,
    :meth:`step`; the returned arrays are internal buffers unless ``out=`` is
    given.  Inputs should be C-contiguous arrays of the network dtype (``z``,
    ``p``) and float64 (``xD``): they go to the kernel as they are (another
    dtype or layout compiles another specialisation).  The first call of each
    specialisation compiles (cached on disk).  :meth:`encode` is the NumPy stepper's
    (:meth:`latentsim.runtime.NumpyStepper.encode`); ``source`` names the file in its errors.
    """

    def __init__(self, folded: dict, dtype=np.float32, source=None):
        if not available():
            raise RuntimeError("the compiled runtime needs numba (pinned in envs/requirements.txt)")
        ref = NumpyStepper(folded, dtype, source)  # validates the header and decides the output layout
        self.encode = ref.encode  # NumpyStepper.encode: encoding is once per motion, not per frame
        self.header, self.dtype = ref.header, ref.dtype
        self.r, self.k, self.n, self.mode, self.layout = ref.r, ref.k, ref.n, ref.mode, ref.layout
        self.n_integrator_layers = len(ref._int_A)
        self.dirichlet = np.asarray(ref.dirichlet, np.int64)
        layers = _layers(ref)
        w = max([2 * self.r + 3 * self.k] + [max(A.shape[0] - 1, A.shape[1]) for A, _ in layers[:-1]])
        self._F, table = _pack(layers, self.dtype)
        self._output_layer = tuple(int(v) for v in table[-1, :3])  # (offset, in, out) of the output layer in F
        out = _output_index(ref)
        scatter, roots, m = ref.layout == "scatter", ref.mode == "roots", len(self.dirichlet)
        hdr = np.zeros(_HLEN, np.int64)
        hdr[[_R, _K, _NINT, _NDEC, _MID, _RESID, _SCATTER, _W, _D]] = [self.r, self.k, self.n_integrator_layers, len(ref._dec_A),
                                                                       int(ref.mid), int(ref.residual), int(scatter), w, layers[-1][0].shape[1]]  # fmt: skip
        hdr[_M] = m if not roots else 0  # the mean origin: not used with roots
        # hard_mean, scattered: the mean summed while copying the prescribed vertices back, before the free
        # ones are written (in the full layout the output layer also writes the prescribed ones: copied after)
        hdr[_FUSED] = int(ref.output.copy_back and scatter and not roots and m > 0)
        hdr[_FAST32] = int(self.dtype == np.float32)  # float32 networks: SiLU without a libm call (_silu32)
        parts, at = [hdr, table.reshape(-1)], _HLEN + table.size
        hdr[_TABLE] = _HLEN
        for key, arr in out.items():
            hdr[key] = at if arr.size or key != _SLOT else -1
            parts.append(arr.reshape(-1))
            at += arr.size
        hdr[_NCHK], hdr[_NSEG], hdr[_NDRUN] = len(out[_CHK]), len(out[_SEG]), len(out[_DRUN])
        self._I = np.concatenate(parts).astype(np.int64)
        self.chunks, self.segments, self.dirichlet_runs = len(out[_CHK]), len(out[_SEG]), len(out[_DRUN])
        self.fused_mean = bool(hdr[_FUSED])  # the mean summed in the copy-back pass (hard_mean, scattered)
        self._S = np.zeros(3 * w + self.r + _CHUNK, dtype=self.dtype)
        self._z = np.zeros(self.r, dtype=self.dtype)
        self._x = np.zeros((self.n, 3))
        self._zero_k = np.zeros(self.k, dtype=self.dtype)
        self._xD0 = np.zeros((m, 3))
        self._x0 = np.zeros((1, 3))

    inputs = NumpyStepper.inputs  # the same arrays: network-dtype latents and parameters, float64 positions

    def output_pass(self):
        """A call without arguments doing one pass of this runtime's own output layer (its input width, every DoF
        it writes) into float64 values, with :func:`_output_pass`: the bare decode that every step of this model
        does at least (``latent.timing.time_steppers`` times it as ``floor_ms``).  Returns (call, output), the
        output array the call writes (for tests)."""
        off, nin, D = self._output_layer
        A = self._F[off : off + (nin + 1) * D].reshape((nin + 1, D))
        h = np.full(nin, 0.5, dtype=self.dtype)
        y = np.empty(D)
        return partial(_output_pass, A, h, y), y

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None) -> np.ndarray:
        """z_t (r,) from z_{t-1}, z_{t-2} (r,) and p_t, p_{t-1}, p_{t-2} (k,)."""
        if not self.n_integrator_layers:
            raise ValueError("this runtime holds a decoder only (no integrator layers)")
        z = self._z if out is None else out
        _kernel(self._F, self._I, self._S, z_prev, z_prev2, p, p_prev, p_prev2, self._xD0, self._x0, z, 1)
        return z

    def _check_x(self, x, name: str) -> None:
        if not (x.flags.c_contiguous and x.shape == (self.n, 3) and x.dtype == np.float64):
            raise ValueError(f"{name}: need a C-contiguous float64 ({self.n}, 3) array, got {x.dtype} {x.shape}")

    def decode(self, z, xD, out=None) -> np.ndarray:
        """Positions (n, 3) float64 of latent z (r,) with Dirichlet positions xD (m, 3)."""
        if out is not None:
            self._check_x(out, "out")
        x = self._x if out is None else out
        k0 = self._zero_k
        _kernel(self._F, self._I, self._S, z, z, k0, k0, k0, xD, x, self._z, 2)
        return x

    def carry_out(self, x, R, c) -> np.ndarray:
        """Positions x (n, 3) (C-contiguous float64, as :meth:`decode` writes them) carried by the rigid motion
        x R^T + c in place (R (3, 3), c (1, 3)); x."""
        self._check_x(x, "x")
        _carry_out(x, np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(c, dtype=np.float64).reshape(1, 3))
        return x

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        """One frame: (z_t (r,), x_t (n, 3)); see :meth:`integrate`, :meth:`decode`."""
        if not self.n_integrator_layers:
            raise ValueError("this runtime holds a decoder only (no integrator layers)")
        if x_out is not None:
            self._check_x(x_out, "x_out")
        z = self._z if z_out is None else z_out
        x = self._x if x_out is None else x_out
        _kernel(self._F, self._I, self._S, z_prev, z_prev2, p, p_prev, p_prev2, xD, x, z, 3)
        return z, x


def load_runtime(path, dtype=np.float32) -> CompiledStepper:
    """The compiled stepper of an exported ``.npz`` runtime (:func:`latentsim.runtime.export_runtime`)."""
    return CompiledStepper(read_runtime(path), dtype=dtype, source=os.fspath(path))


def deployable_steppers(folded: dict, dtype=np.float32) -> dict:
    """{"numpy": NumpyStepper, "compiled": CompiledStepper (where numba imports)} of one folded runtime:
    the deployable steppers that the rollout stage, the sweep and the floor benchmark time side by side."""
    steppers = {"numpy": NumpyStepper(folded, dtype)}
    if available():
        steppers["compiled"] = CompiledStepper(folded, dtype)
    return steppers
