"""The NumPy latent runtime: one frame of the folded networks with preallocated buffers.

The folded layers (:mod:`latentsim.runtime.fold`) are each held as ``A = [W^T; b^T]``
and evaluated as ``[h; 1] @ A`` (one BLAS call, no bias add), every buffer allocated
once (``np.dot(..., out=)``, in-place ufuncs)::

    z_t = z_{t-1} + [q; 1] @ A_L(SiLU(... SiLU([q; 1] @ A_0))),   q = [z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}]
    h_{i+1} = h_i + SiLU([h_i; 1] @ A_i)   (without h_i where widths differ),   h_0 = z_t
    u = [z_t; h_L; 1] @ A_out,   x = u + x*_origin   (the Dirichlet mean, or each rod's root)

The output layer is laid out over the decoded vertices (:class:`OutputLayout`) so that
decoding scatters little.  Networks are float32 (default) or float64; positions float64.
For reduced solvers and Li et al.'s Table 2 the stepper also gives forward-mode
derivatives of the decode: one vertex's Jacobian-vector product
(:meth:`NumpyStepper.jvp_vertex`), the whole Jacobian (:meth:`NumpyStepper.decode_jacobian`),
both through the one tangent layer :func:`_tangent_layer`, and the weighted second
derivatives (:meth:`NumpyStepper.decode_curvature`).
"""

from __future__ import annotations

import numpy as np
from scipy.special import expit

from latentsim.runtime.encoder import Encoder, missing_encoder
from latentsim.runtime.fold import FORMAT

__all__ = ["FULL_LAYOUT_MAX_GROWTH", "HARD_MODES", "NumpyStepper", "OutputLayout"]

HARD_MODES = ("roots", "hard_mean")  # relative-coordinate modes that re-apply the Dirichlet vertices
FULL_LAYOUT_MAX_GROWTH = 1.25  # hard modes: decode over all n vertices if n <= this x the free ones
_SILU_CLAMP = 80.0  # exp(80) is finite in float32; silu(a) ~ 0 below -80 anyway (allocating paths)


def _silu(a: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
    """out = a * sigmoid(a), using t as scratch (no allocation; t must not be a).

    ``scipy.special.expit`` is one ufunc, stable for any a (no overflow), in the
    network's dtype: two calls where exp, negate, clamp, add and divide took five.
    """
    expit(a, out=t)
    np.multiply(a, t, out=out)


def _silu_layer(h: np.ndarray, A: np.ndarray, a: np.ndarray, t: np.ndarray, dst: np.ndarray, skip: bool) -> None:
    """dst = SiLU([h; 1] @ A) (+ h without its 1, an identity skip): one hidden layer, no allocation.

    h : (in + 1,) ending in 1; A : (in + 1, out); a, t : (out,) scratch; dst : (out,).
    """
    np.dot(h, A, out=a)
    if skip:
        _silu(a, t, out=t)
        np.add(h[:-1], t, out=dst)
    else:
        _silu(a, t, out=dst)


def _silu_slope(a: np.ndarray):
    """(s, silu'(a)) with s = sigmoid(a) = 1 / (1 + exp(-a)) (exponent clamped at 80), silu'(a) = s (1 + a (1 - s))."""
    s = 1.0 / (1.0 + np.exp(np.minimum(-a, _SILU_CLAMP)))
    return s, s * (1.0 + a * (1.0 - s))


def _tangent_layer(S, W, b, skip: bool, A, s, t, out) -> None:
    """Forward mode through one hidden layer, no allocation.

    S : (1 + j, in) rows ``[h; dh_1; ...; dh_j]``; W : (out, in); b : (out,).
    out (1 + j, out) = ``[SiLU(a); silu'(a) * (W dh_i)]`` (+ S with an identity skip), a = W h + b;
    A (1 + j, out), s, t (out,) scratch.  The same operations as :func:`_silu_slope`.
    """
    np.dot(S, W.T, out=A)
    A[0] += b
    a = A[0]
    np.negative(a, out=s)
    np.minimum(s, _SILU_CLAMP, out=s)
    np.exp(s, out=s)
    s += 1.0
    np.divide(1.0, s, out=s)  # sigmoid(a)
    np.subtract(1.0, s, out=t)
    t *= a
    t += 1.0
    t *= s  # silu'(a)
    np.multiply(a, s, out=out[0])
    np.multiply(A[1:], t, out=out[1:])
    if skip:
        out += S


def _augmented(W: np.ndarray, b: np.ndarray, dtype) -> np.ndarray:
    """[W^T; b^T] (in + 1, out), C-contiguous, so that [x; 1] @ A = W x + b.

    One ``np.dot`` per layer gives the affine map (no separate bias add), and the
    row-vector-times-matrix layout is the faster BLAS product for these shapes
    (2x on the armadillo's 50 x 10,416 output layer).
    """
    W = np.asarray(W)
    A = np.empty((W.shape[1] + 1, W.shape[0]), dtype=dtype)
    A[:-1] = W.T
    A[-1] = b
    return A


def _with_one(n: int, dtype) -> np.ndarray:
    """A buffer [v; 1] of n + 1 entries whose last entry stays 1 (the bias input)."""
    v = np.zeros(n + 1, dtype=dtype)
    v[-1] = 1.0
    return v


def _flat(vertices: np.ndarray) -> np.ndarray:
    """The 3 coordinates' indices of each vertex, (3 len,)."""
    return (3 * vertices[:, None] + np.arange(3)).reshape(-1)


class OutputLayout:
    """The output layer and the relative-coordinates decode, x = u + origin.

    ``name`` is ``"full"`` (the output layer ``A`` over all n vertices: in the hard modes
    the free vertices' columns in place, the Dirichlet ones zero, so that nothing is
    scattered) or ``"scatter"`` (over the free vertices, which are then scattered; used
    where the Dirichlet vertices are many, e.g. the bunny's ears-only encoding, and the
    full layout would widen the largest matrix).  In the hard modes the prescribed
    vertices are then copied back (``copy_back``), except where the full layout's roots
    already give them (a root is its own root, u = 0 there).
    """

    def __init__(self, out_A, mode, n, dirichlet, free, root_slot, dtype):
        hard, m = mode in HARD_MODES, len(dirichlet)
        self.name = "full" if not hard or n <= FULL_LAYOUT_MAX_GROWTH * len(free) else "scatter"
        self.mode, self.n_dirichlet = mode, m
        if mode == "roots" and len(root_slot) and (root_slot.min() < 0 or root_slot.max() >= m):
            raise ValueError("root_slot out of range of the Dirichlet list")
        self.free_flat = None  # scatter: the free vertices' coordinates
        self.slot = None  # roots: each decoded vertex's root, its slot in xD
        if not hard:
            self.A = out_A
        elif self.name == "full":
            self.A = np.zeros((out_A.shape[0], 3 * n), dtype=dtype)
            self.A[:, _flat(free)] = out_A
            if mode == "roots":  # x_v = u_v + x*_{root(v)}, with a root its own root (u_v = 0)
                self.slot = np.empty(n, dtype=np.int64)
                self.slot[free] = root_slot
                self.slot[dirichlet] = np.arange(m)
        else:
            self.A = out_A
            self.free_flat = _flat(free)
            if mode == "roots":
                self.slot = root_slot
        self.slot_flat = None if self.slot is None else _flat(self.slot)  # each decoded value's origin in the flat xD
        self.u = np.empty(self.A.shape[1], dtype=dtype)
        self.y = None if self.free_flat is None else np.empty(self.A.shape[1])  # float64 before the scatter
        self.orig = None if self.slot_flat is None else np.empty(self.A.shape[1])
        self.origin = np.zeros(3)
        self.copy_back = hard and not (mode == "roots" and self.name == "full")
        self.dir_flat = _flat(dirichlet) if hard else None

    def write(self, hidden: np.ndarray, xD: np.ndarray, xf: np.ndarray) -> None:
        """xf (3n,) float64 = the decode of the output layer's input ``hidden`` with Dirichlet positions xD (m, 3)."""
        np.dot(hidden, self.A, out=self.u)
        y = xf if self.y is None else self.y
        np.copyto(y, self.u)
        if self.slot_flat is not None:
            # mode="clip": indices were checked at construction (np.take's default mode="raise" buffers its output)
            np.take(xD.reshape(-1), self.slot_flat, out=self.orig, mode="clip")
            y += self.orig
        elif self.n_dirichlet:
            np.mean(xD, axis=0, out=self.origin)
            y3 = y.reshape(-1, 3)
            for j in range(3):  # per column: an (n, 3) + (3,) broadcast allocates the ufunc's buffers
                y3[:, j] += self.origin[j]
        # scatters by index assignment (np.put is 2-3x slower)
        if self.free_flat is not None:
            xf[self.free_flat] = y
        if self.copy_back:
            xf[self.dir_flat] = xD.reshape(-1)  # the prescribed vertices themselves


class NumpyStepper:
    """Plain-NumPy latent step with preallocated buffers (a :class:`latentsim.runtime.Stepper`).

    Parameters
    ----------
    folded : output of :func:`latentsim.runtime.fold_networks` (or the loaded ``.npz``).
    dtype : network dtype, ``np.float32`` (default) or ``np.float64``.
        Positions are always float64: the network output is added to the
        float64 Dirichlet origin.
    source : where ``folded`` was read from (a path), named in error messages.

    Beyond the :class:`latentsim.runtime.Stepper` protocol, :meth:`encode` gives the latent of a
    full-space frame (the autoencoder's encoder, :class:`latentsim.runtime.encoder.Encoder`), where
    the runtime holds one (format version 2 on).

    ``int_W``/``int_b``, ``dec_W``/``dec_b``, ``W_mid``/``b_mid`` and ``W_out``/``b_out``
    are (out, in) and (out,) views of the augmented ``[W^T; b^T]`` matrices.

    The returned arrays of :meth:`integrate`, :meth:`decode` and :meth:`step`
    are internal buffers, overwritten by the next call; pass ``out=`` (or copy)
    to keep them.  Inputs are copied into the buffers first, so passing the
    previous output back in as ``z_prev`` is safe.
    """

    def __init__(self, folded: dict, dtype=np.float32, source=None):
        hdr = folded["header"]
        if hdr.get("format") != FORMAT:
            raise ValueError(f"not a latent runtime: format {hdr.get('format')!r}")
        self.header, self.source = hdr, source
        self.encoder = Encoder(folded, dtype) if hdr.get("encoder") else None
        self.dtype = np.dtype(dtype)
        self.r, self.k = int(hdr["latent_dim"]), int(hdr["bc_dim"])
        self.n, self.mode, self.residual = int(hdr["n_vertices"]), hdr["mode"], bool(hdr["residual"])
        self.d = int(hdr["encoded_dim"])
        self.hard = self.mode in HARD_MODES
        self.dirichlet = np.asarray(folded["dirichlet"], dtype=np.int64)
        self.free = np.asarray(folded["free"], dtype=np.int64)
        self.root_slot = np.asarray(folded["root_slot"], dtype=np.int64)
        self._x = np.empty((self.n, 3))
        self._build_integrator(folded)
        self._build_decoder(folded)
        self.output = OutputLayout(self._out_A, self.mode, self.n, self.dirichlet, self.free, self.root_slot, self.dtype)
        self.layout = self.output.name
        self._jvp = self._tangent_buffers(2)  # forward-mode Jvp: rows (h, dh) of each layer

    def _build_integrator(self, folded: dict) -> None:
        """Layers and buffers of the integrator: input [z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}, 1], hidden [h; 1]."""
        dt, L = self.dtype, int(self.header["integrator_layers"])
        self._int_A = [_augmented(folded[f"int_W{i}"], folded[f"int_b{i}"], dt) for i in range(L)]
        self.int_W = [A[:-1].T for A in self._int_A]
        self.int_b = [A[-1] for A in self._int_A]
        self._q = _with_one(2 * self.r + 3 * self.k, dt)
        self._ia = [np.empty(A.shape[1], dtype=dt) for A in self._int_A[:-1]]  # pre-activations
        self._it = [np.empty(A.shape[1], dtype=dt) for A in self._int_A[:-1]]  # SiLU scratch
        self._ih = [_with_one(A.shape[1], dt) for A in self._int_A[:-1]]
        self._z = np.empty(self.r, dtype=dt)

    def _build_decoder(self, folded: dict) -> None:
        """Layers and buffers of the decoder: [z; 1] -> hidden [h_i; 1] -> [z; h_L; 1] (-> [y; 1] with a mid layer)."""
        dt = self.dtype
        self.skips = [bool(s) for s in self.header["decoder_skips"]]
        nh = len(self.skips)
        self._dec_A = [_augmented(folded[f"dec_W{i}"], folded[f"dec_b{i}"], dt) for i in range(nh)]
        self.dec_W = [A[:-1].T for A in self._dec_A]
        self.dec_b = [A[-1] for A in self._dec_A]
        self.widths = [A.shape[1] for A in self._dec_A]
        self._z1 = _with_one(self.r, dt)
        self._zh = _with_one(self.r + (self.widths[-1] if nh else 0), dt)
        self._h = [_with_one(w, dt) for w in self.widths[:-1]]
        self._da = [np.empty(w, dtype=dt) for w in self.widths]
        self._dt = [np.empty(w, dtype=dt) for w in self.widths]
        self.mid = bool(self.header.get("decoder_mid", False))
        if self.mid:
            self._mid_A = _augmented(folded["dec_Wmid"], folded["dec_bmid"], dt)
            self.W_mid, self.b_mid = self._mid_A[:-1].T, self._mid_A[-1]
            self._y = _with_one(self._mid_A.shape[1], dt)
            self._y2 = np.empty((2, self._mid_A.shape[1]), dtype=dt)
        self._out_A = _augmented(folded["dec_Wout"], folded["dec_bout"], dt)
        self.W_out, self.b_out = self._out_A[:-1].T, self._out_A[-1]
        self._u = np.empty(self.d, dtype=dt)
        self._o2 = np.empty((2, 3), dtype=dt)

    def inputs(self, z_prev, z_prev2, p, p_prev, p_prev2, xD) -> tuple:
        """New C-contiguous arrays of one frame's arguments: latents and parameters in the network dtype, xD float64."""
        net = tuple(np.array(a, dtype=self.dtype, order="C") for a in (z_prev, z_prev2, p, p_prev, p_prev2))
        return net + (np.array(xD, dtype=np.float64, order="C"),)

    def encode(self, x, xD) -> np.ndarray:
        """Latent z (r,) in the network dtype of positions x (n, 3) with Dirichlet positions xD (m, 3)
        (leading axes broadcast: (..., n, 3) -> (..., r)); as the pipeline encodes. Allocates.

        Raises ``ValueError`` naming the file where the runtime holds no encoder (format version 1).
        """
        if self.encoder is None:
            raise ValueError(missing_encoder(self.header, self.source))
        return self.encoder.encode(x, xD)

    # -- integrator ------------------------------------------------------------
    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None) -> np.ndarray:
        """z_t (r,) from z_{t-1}, z_{t-2} (r,) and p_t, p_{t-1}, p_{t-2} (k,)."""
        if not self._int_A:
            raise ValueError("this runtime holds a decoder only (no integrator layers)")
        r, k, q = self.r, self.k, self._q
        q[:r] = z_prev
        q[r : 2 * r] = z_prev2
        q[2 * r : 2 * r + k] = p
        q[2 * r + k : 2 * r + 2 * k] = p_prev
        q[2 * r + 2 * k : -1] = p_prev2
        h = q
        for i in range(len(self._int_A) - 1):
            _silu_layer(h, self._int_A[i], self._ia[i], self._it[i], self._ih[i][:-1], False)
            h = self._ih[i]
        z = self._z
        np.dot(h, self._int_A[-1], out=z)
        if self.residual:
            z += q[:r]
        if out is None:
            return z
        np.copyto(out, z)
        return out

    # -- decoder -----------------------------------------------------------------
    def _hidden(self, z) -> np.ndarray:
        """The output layer's input: [z; h_L; 1] (or [y; 1] after a mid layer)."""
        r, zh = self.r, self._zh
        zh[:r] = z
        nh = len(self._dec_A)
        if nh:
            h = self._z1
            h[:r] = z
            for i in range(nh):
                last = i == nh - 1
                dst = zh[r:-1] if last else self._h[i][:-1]
                _silu_layer(h, self._dec_A[i], self._da[i], self._dt[i], dst, self.skips[i])
                h = zh if last else self._h[i]
        if self.mid:
            np.dot(zh, self._mid_A, out=self._y[:-1])
            return self._y
        return zh

    def decode_network(self, z) -> np.ndarray:
        """Encoded vector u (d,) of latent z (r,) (the autoencoder's decoder)."""
        np.dot(self._hidden(z), self._out_A, out=self._u)
        return self._u

    def decode(self, z, xD, out=None) -> np.ndarray:
        """Positions (n, 3) float64 of latent z (r,) with Dirichlet positions xD (m, 3).

        ``xD`` should be a C-contiguous float64 array (else it is converted, which
        allocates); ``out``, if given, a C-contiguous (n, 3) float64 array.
        """
        x = self._x if out is None else out
        if out is not None and not (out.flags.c_contiguous and out.shape == (self.n, 3)):
            raise ValueError(f"out: need a C-contiguous ({self.n}, 3) array, got shape {out.shape}")
        self.output.write(self._hidden(z), xD, x.reshape(-1))
        return x

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        """One frame: (z_t (r,), x_t (n, 3)); see :meth:`integrate`, :meth:`decode`."""
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=z_out)
        return z, self.decode(z, xD, out=x_out)

    def decode_from_u(self, u, xD) -> np.ndarray:
        """Positions (n, 3) from an encoded vector u (d,) (allocates)."""
        u = np.asarray(u, dtype=np.float64).reshape(-1, 3)
        xD = np.asarray(xD, dtype=np.float64)
        if self.hard:
            x = np.empty((self.n, 3))
            x[self.free] = u + (xD[self.root_slot] if self.mode == "roots" else xD.mean(0))
            x[self.dirichlet] = xD
            return x
        return u + (xD.mean(0) if len(xD) else 0.0)

    # -- derivatives -------------------------------------------------------------
    def _tangent_buffers(self, rows: int):
        """Forward-mode buffers for ``rows`` = 1 + tangents: [z, h_L] rows (rows, r + w_L) and per layer (A, s, t, out)."""
        dt, r, nh = self.dtype, self.r, len(self.widths)
        zs = np.zeros((rows, r + (self.widths[-1] if nh else 0)), dtype=dt)
        layers = [
            (np.empty((rows, w), dtype=dt), np.empty(w, dtype=dt), np.empty(w, dtype=dt), zs[:, r:] if i == nh - 1 else np.empty((rows, w), dtype=dt))
            for i, w in enumerate(self.widths)
        ]  # fmt: skip
        return zs, layers

    def _tangents(self, z, V, buffers) -> np.ndarray:
        """Forward mode through the hidden layers: rows [z; V] -> [z, h_L; V, dh_L] (1 + j, r + w_L); V (j, r)."""
        zs, layers = buffers
        r = self.r
        zs[0, :r] = z
        zs[1:, :r] = V
        S = zs[:, :r]
        for W, b, skip, (A, s, t, out) in zip(self.dec_W, self.dec_b, self.skips, layers):
            _tangent_layer(S, W, b, skip, A, s, t, out)
            S = out
        return zs

    def _row_of_vertex(self, vertex: int) -> int:
        if self.hard:
            hits = np.flatnonzero(self.free == vertex)
            return int(hits[0]) if len(hits) else -1
        return int(vertex)

    def jvp_vertex(self, z, v, vertex: int, xD=None):
        """Forward-mode Jacobian-vector product of one decoded vertex.

        Propagates (h, dh) together through the folded layers (one (2, w)
        matrix product per layer) and evaluates only the 3 output rows of the
        vertex.  Returns ``(x_v, dx_v)``, each (3,): the decoded position
        (float64, with the Dirichlet origin added when ``xD`` (m, 3) is given,
        else the network output u_v) and d x_v / d z . v.
        """
        row = self._row_of_vertex(vertex)
        if row < 0:  # a prescribed rod root: x_v = x*_D, no dependence on z
            slot = int(np.flatnonzero(self.dirichlet == vertex)[0])
            x_v = np.asarray(xD[slot], dtype=np.float64) if xD is not None else np.zeros(3)
            return x_v.copy(), np.zeros(3)
        zs = self._tangents(z, v, self._jvp)
        rows = slice(3 * row, 3 * row + 3)
        if self.mid:
            np.dot(zs, self.W_mid.T, out=self._y2)
            self._y2[0] += self.b_mid
            zs = self._y2
        np.dot(zs, self.W_out[rows].T, out=self._o2)
        x_v = self._o2[0].astype(np.float64) + self.b_out[rows]
        if xD is not None:
            xD = np.asarray(xD, dtype=np.float64)
            x_v += xD[self.root_slot[row]] if self.mode == "roots" else (xD.mean(0) if len(xD) else 0.0)
        return x_v, self._o2[1].astype(np.float64)

    def decode_jacobian(self, z, xD):
        """Positions x (n, 3) float64 and J = dx/dz (3n, r) float64, by forward mode.

        All r tangent directions travel through the layers as one (1 + r, w)
        matrix; Dirichlet rows of J are zero in ``roots`` mode.  Allocates
        (meant for reduced solvers, not for the per-frame runtime).
        """
        r = self.r
        full = self._tangents(z, np.eye(r), self._tangent_buffers(1 + r))
        if self.mid:
            full = full @ self.W_mid.T
            full[0] += self.b_mid
        Y = np.asarray(full @ self.W_out.T, dtype=np.float64)  # (1 + r, d)
        u = Y[0] + self.b_out
        x = self.decode_from_u(u, xD)
        J = np.zeros((self.n, 3, r))
        Ju = Y[1:].T.reshape(-1, 3, r)
        if self.hard:
            J[self.free] = Ju
        else:
            J[:] = Ju
        return x, J.reshape(3 * self.n, r)

    def decode_curvature(self, z, w) -> np.ndarray:
        """sum_i w_i d^2 u_i / dz dz (r, r): the Hessian of w . Decoder(z), by second-order forward mode.

        The last layer is linear, so the weights are contracted first (c = W^T w) and only the
        hidden layers carry second derivatives, (w_l, r, r) per layer, with SiLU'' =
        s (1 - s) (2 + a (1 - 2 s)).  Allocates (meant for reduced Newton solvers).
        """
        r = self.r
        c = np.asarray(w, dtype=np.float64) @ np.asarray(self.W_out, dtype=np.float64)  # no copy in float64
        if self.mid:
            c = c @ np.asarray(self.W_mid, dtype=np.float64)
        if not len(self.dec_W):
            return np.zeros((r, r))
        h = np.asarray(z, dtype=np.float64).copy()
        dh = np.eye(r)  # (w, r): d h / d z
        d2h = np.zeros((r, r, r))  # (w, r, r)
        for i, (W, b) in enumerate(zip(self.dec_W, self.dec_b)):
            W = np.asarray(W, dtype=np.float64)
            a = W @ h + b
            da = W @ dh
            d2a = np.tensordot(W, d2h, axes=1)
            s, d1 = _silu_slope(a)
            d2 = s * (1.0 - s) * (2.0 + a * (1.0 - 2.0 * s))
            y, dy = a * s, d1[:, None] * da
            d2y = d2[:, None, None] * da[:, :, None] * da[:, None, :] + d1[:, None, None] * d2a
            if self.skips[i]:
                h, dh, d2h = h + y, dh + dy, d2h + d2y
            else:
                h, dh, d2h = y, dy, d2y
        C = np.tensordot(c[r:], d2h, axes=1)  # z enters [z; h_L] linearly
        return 0.5 * (C + C.T)
