"""Deployable latent runtime: step a frame without the training code.

A trained :class:`latentsim.latent.LatentIntegrator`, the decoder half of an
:class:`latentsim.latent.Autoencoder` and the :class:`RelativeCoordinates`
decode (re-adding the Dirichlet mean, or each rod's root) are *folded* into a
handful of dense layers:

- eval-mode BatchNorm into the preceding Linear,
  ``W' = diag(gamma / sqrt(var + eps)) W``, ``b' = gamma (b - mean) / sqrt(var + eps) + beta``;
- the integrator's input standardisation into its first layer and its output
  scaling (``out_mean + out_std * y``) into its last;
- the decoder's residual-branch output layer into the PCA output layer, and the
  PCA skip path ``[z, 0]`` into the same matrix: ``u = W_cat [z; h_L] + b_cat``
  with ``W_cat = [W_pca[:, :r], W_pca W_o]`` (d x (r + w_L)) - unless the PCA
  layer is narrower than the last hidden layer (p < w_L), where that would widen
  the largest matrix: then ``u = W_pca ([z, 0] + W_o h_L + b_o) + b_pca``.

One frame is then (paper Eq. 3 and the decode)::

    z_t = z_{t-1} + MLP_I([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}])     (residual integrator)
    h_0 = z_t,  h_{i+1} = h_i + SiLU(W_i h_i + b_i)  (or without h_i where widths differ)
    u = W_cat [z_t; h_L] + b_cat,   x = decode_relative(u, x*_D)

Two runtimes evaluate the same folded weights:

- :class:`NumpyStepper` - plain NumPy, float32 (default) or float64 networks,
  every buffer preallocated (``np.dot(..., out=)``, in-place ufuncs), each layer
  one product ``[h; 1] @ [W^T; b^T]``, the output layer laid out over the decoded
  vertices so that decoding scatters little; positions are float64.  It also gives the forward-mode Jacobian-vector product of one
  decoded vertex (:meth:`NumpyStepper.jvp_vertex`), and for reduced solvers
  the full decoder Jacobian (:meth:`NumpyStepper.decode_jacobian`) and the
  weighted second derivatives (:meth:`NumpyStepper.decode_curvature`).
- a TorchScript module (:func:`torchscript_module`), saved with
  ``torch.jit.save`` and loadable with ``torch.jit.load`` alone.

Files (:func:`export_runtime` / :func:`load_runtime`): ``*.npz`` (NumPy, no
pickle) or ``*.pt`` (TorchScript); see ``docs/artefacts.md``.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings

import numpy as np
import torch
import torch.nn.functional as F
from scipy.special import expit
from torch import nn

__all__ = [
    "FORMAT",
    "EagerStepper",
    "NumpyStepper",
    "TorchStepper",
    "export_runtime",
    "fold_decoder",
    "fold_networks",
    "jvp_vertex_torch",
    "load_runtime",
    "rollout_runtime",
    "time_jvp",
    "time_step",
    "torchscript_module",
]

FORMAT = "latentsim-latent-runtime"
HARD_MODES = ("roots", "hard_mean")  # relative-coordinate modes that re-apply the Dirichlet vertices
FULL_LAYOUT_MAX_GROWTH = 1.25  # hard modes: decode over all n vertices if n <= this x the free ones
VERSION = 1


# ---------------------------------------------------------------------------
# folding the trained modules into dense layers (float64 NumPy arrays)
# ---------------------------------------------------------------------------
def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().to(torch.float64).numpy().copy()


def _fold_linear_bn(lin: nn.Linear, bn: nn.BatchNorm1d):
    """(W, b) of Linear followed by eval-mode BatchNorm."""
    W, b = _np(lin.weight), _np(lin.bias)
    scale = _np(bn.weight) / np.sqrt(_np(bn.running_var) + bn.eps)
    return scale[:, None] * W, scale * (b - _np(bn.running_mean)) + _np(bn.bias)


def fold_decoder(ae, coords) -> dict:
    """Fold an eval-mode decoder + relative coordinates into float64 arrays.

    Returns the ``dec_*`` layers, the coordinate index arrays and a ``header``
    (with ``integrator_layers = 0``: a decoder-only runtime, e.g. for reduced
    solvers, whose :meth:`NumpyStepper.integrate` is unavailable).  Where the
    residual branch's output layer is exactly zero (``decoder_linear``: an
    autoencoder that kept its PCA start), only the PCA layer's first r columns
    are kept: the same map, without the branch's dead layers.
    """
    r = int(ae.latent_dim)
    if coords.dim != ae.input_dim:
        raise ValueError(f"coordinates encode {coords.dim} values, the autoencoder expects {ae.input_dim}")
    out: dict = {}
    br = ae.dec_branch
    Wp, bp = _np(ae.pca_out.weight), _np(ae.pca_out.bias)  # (d, p), (d,)
    Wo, bo = _np(br.out.weight), _np(br.out.bias)  # (p, w_L), (p,)
    d, p = Wp.shape
    wl = Wo.shape[1]
    # A branch whose output layer is exactly zero adds nothing (an autoencoder that kept its PCA start, or an
    # untrained one): the decoder is the linear map z -> W_p[:, :r] z + b_p, and its hidden layers are skipped.
    linear = bool(len(br.blocks)) and not Wo.any() and not bo.any()
    # hidden layers (Linear + BatchNorm folded, SiLU, identity skip where widths match)
    skips = [] if linear else [bool(s) for s in br.skip]
    for i, block in enumerate([] if linear else br.blocks):
        out[f"dec_W{i}"], out[f"dec_b{i}"] = _fold_linear_bn(block[0], block[1])
    if linear:
        out["dec_Wout"], out["dec_bout"] = np.ascontiguousarray(Wp[:, :r]), bp
    elif not len(br.blocks):  # no hidden layer: the branch is one linear map of z
        out["dec_Wout"], out["dec_bout"] = Wp[:, :r] + Wp @ Wo, Wp @ bo + bp
    elif d * (r + wl) <= p * (r + wl) + d * p:  # one (d, r + w_L) matrix on [z; h_L]
        out["dec_Wout"], out["dec_bout"] = np.concatenate([Wp[:, :r], Wp @ Wo], axis=1), Wp @ bo + bp
    else:  # a narrow PCA layer (p < w_L): folding would widen the largest matrix; keep both
        out["dec_Wmid"] = np.concatenate([np.eye(p)[:, :r], Wo], axis=1)  # [z; h_L] -> [z, 0] + W_o h_L
        out["dec_bmid"] = bo
        out["dec_Wout"], out["dec_bout"] = Wp, bp
    out["dirichlet"] = coords.dirichlet.numpy().astype(np.int64)
    out["free"] = coords.free.numpy().astype(np.int64)
    out["root_slot"] = (coords.root_slot.numpy() if coords.root_slot is not None else np.zeros(0)).astype(np.int64)
    out["header"] = {
        "format": FORMAT,
        "version": VERSION,
        "latent_dim": r,
        "bc_dim": 0,
        "residual": False,
        "integrator_layers": 0,
        "decoder_skips": skips,
        "decoder_mid": "dec_Wmid" in out,
        "decoder_linear": linear,
        "encoded_dim": int(coords.dim),
        "n_vertices": int(coords.n),
        "mode": coords.mode,
        "autoencoder_hparams": dict(ae.hparams),
    }
    return out


def fold_networks(ae, integrator, coords) -> dict:
    """Fold an eval-mode integrator + decoder + relative coordinates into arrays.

    Parameters
    ----------
    ae : :class:`latentsim.latent.Autoencoder` (only its decoder is used).
    integrator : :class:`latentsim.latent.LatentIntegrator`.
    coords : :class:`latentsim.latent.RelativeCoordinates`.

    Returns
    -------
    dict of float64/int64 arrays plus ``header`` (a JSON-able dict); the
    layout of :func:`export_runtime`'s ``.npz`` file.
    """
    if integrator.latent_dim != ae.latent_dim:
        raise ValueError(f"integrator latent dim {integrator.latent_dim} != autoencoder latent dim {ae.latent_dim}")
    out = fold_decoder(ae, coords)
    # integrator: standardisation folded into the first layer, output scaling into the last
    lins = [m for m in integrator.mlp if isinstance(m, nn.Linear)]
    mu, sd = _np(integrator.in_mean), _np(integrator.in_std)
    om, osd = _np(integrator.out_mean), _np(integrator.out_std)
    for i, lin in enumerate(lins):
        W, b = _np(lin.weight), _np(lin.bias)
        if i == 0:
            W = W / sd[None, :]
            b = b - W @ mu
        if i == len(lins) - 1:
            W, b = osd[:, None] * W, osd * b + om
        out[f"int_W{i}"], out[f"int_b{i}"] = W, b
    out["header"].update(
        bc_dim=int(integrator.bc_dim),
        residual=bool(integrator.residual),
        integrator_layers=len(lins),
        integrator_hparams=dict(integrator.hparams),
    )
    return out


# ---------------------------------------------------------------------------
# NumPy runtime
# ---------------------------------------------------------------------------
_SILU_CLAMP = 80.0  # exp(80) is finite in float32; silu(a) ~ 0 below -80 anyway (allocating paths)


def _silu(a: np.ndarray, t: np.ndarray, out: np.ndarray) -> None:
    """out = a * sigmoid(a), using t as scratch (no allocation; t must not be a).

    ``scipy.special.expit`` is one ufunc, stable for any a (no overflow), in the
    network's dtype: two calls where exp, negate, clamp, add and divide took five.
    """
    expit(a, out=t)
    np.multiply(a, t, out=out)


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


class NumpyStepper:
    """Plain-NumPy latent step with preallocated buffers.

    Parameters
    ----------
    folded : output of :func:`fold_networks` (or the loaded ``.npz``).
    dtype : network dtype, ``np.float32`` (default) or ``np.float64``.
        Positions are always float64: the network output is added to the
        float64 Dirichlet origin.

    Each layer is held as ``[W^T; b^T]`` and evaluated as ``[h; 1] @ A`` (one
    BLAS call, no bias add).  :meth:`decode` multiplies by the output layer laid
    out over all ``n`` vertices (the encoded-vector order and, in the hard modes,
    the Dirichlet vertices' zero columns folded in), so decoding scatters nothing.
    ``int_W``/``int_b``, ``dec_W``/``dec_b``, ``W_mid``/``b_mid`` and
    ``W_out``/``b_out`` are (out, in) and (out,) views of the same arrays.

    The returned arrays of :meth:`integrate`, :meth:`decode` and :meth:`step`
    are internal buffers, overwritten by the next call; pass ``out=`` (or copy)
    to keep them.  Inputs are copied into the buffers first, so passing the
    previous output back in as ``z_prev`` is safe.
    """

    def __init__(self, folded: dict, dtype=np.float32):
        hdr = folded["header"]
        if hdr.get("format") != FORMAT:
            raise ValueError(f"not a latent runtime: format {hdr.get('format')!r}")
        self.header = hdr
        self.dtype = np.dtype(dtype)
        dt = self.dtype
        self.r, self.k = int(hdr["latent_dim"]), int(hdr["bc_dim"])
        self.n, self.mode, self.residual = int(hdr["n_vertices"]), hdr["mode"], bool(hdr["residual"])
        self.d = int(hdr["encoded_dim"])

        def layer(prefix: str, i: int):
            return _augmented(folded[f"{prefix}W{i}"], folded[f"{prefix}b{i}"], dt)

        # integrator: input [z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}, 1]; hidden outputs [h; 1]
        L = int(hdr["integrator_layers"])
        self._int_A = [layer("int_", i) for i in range(L)]
        self.int_W = [A[:-1].T for A in self._int_A]
        self.int_b = [A[-1] for A in self._int_A]
        self._q = _with_one(2 * self.r + 3 * self.k, dt)
        self._ia = [np.empty(A.shape[1], dtype=dt) for A in self._int_A[:-1]]  # pre-activations
        self._it = [np.empty(A.shape[1], dtype=dt) for A in self._int_A[:-1]]  # SiLU scratch
        self._ih = [_with_one(A.shape[1], dt) for A in self._int_A[:-1]]
        self._z = np.empty(self.r, dtype=dt)
        # decoder: [z; 1] -> hidden [h_i; 1] -> [z; h_L; 1] (-> [y; 1] with a mid layer) -> u
        self.skips = [bool(s) for s in hdr["decoder_skips"]]
        nh = len(self.skips)
        self._dec_A = [layer("dec_", i) for i in range(nh)]
        self.dec_W = [A[:-1].T for A in self._dec_A]
        self.dec_b = [A[-1] for A in self._dec_A]
        widths = [A.shape[1] for A in self._dec_A]
        self._z1 = _with_one(self.r, dt)
        self._zh = _with_one(self.r + (widths[-1] if nh else 0), dt)
        self._h = [_with_one(w, dt) for w in widths[:-1]]
        self._da = [np.empty(w, dtype=dt) for w in widths]
        self._dt = [np.empty(w, dtype=dt) for w in widths]
        self.mid = bool(hdr.get("decoder_mid", False))
        if self.mid:
            self._mid_A = _augmented(folded["dec_Wmid"], folded["dec_bmid"], dt)
            self.W_mid, self.b_mid = self._mid_A[:-1].T, self._mid_A[-1]
            self._y = _with_one(self._mid_A.shape[1], dt)
            self._y2 = np.empty((2, self._mid_A.shape[1]), dtype=dt)
        self._out_A = _augmented(folded["dec_Wout"], folded["dec_bout"], dt)
        self.W_out, self.b_out = self._out_A[:-1].T, self._out_A[-1]
        self._u = np.empty(self.d, dtype=dt)
        # relative coordinates
        self.dirichlet = np.asarray(folded["dirichlet"], dtype=np.int64)
        self.free = np.asarray(folded["free"], dtype=np.int64)
        self.root_slot = np.asarray(folded["root_slot"], dtype=np.int64)
        m, n = len(self.dirichlet), self.n
        self._x = np.empty((n, 3))
        self._origin = np.zeros(3)
        self.hard = self.mode in HARD_MODES
        # the hard modes' output layout: "full" multiplies by the output layer over all n vertices
        # (free vertices' columns in place, the Dirichlet ones zero) and scatters nothing; where
        # the Dirichlet vertices are many (the bunny's ears-only encoding), that would widen the
        # largest matrix, so "scatter" decodes the free vertices and scatters them and x*_D
        self.layout = "full" if not self.hard or n <= FULL_LAYOUT_MAX_GROWTH * len(self.free) else "scatter"
        if self.hard:
            if self.mode == "roots" and len(self.root_slot) and (self.root_slot.min() < 0 or self.root_slot.max() >= m):
                raise ValueError("root_slot out of range of the Dirichlet list")
            self._dir_flat = (3 * self.dirichlet[:, None] + np.arange(3)).reshape(-1)
        if not self.hard:
            self._full_A, self._uf = self._out_A, self._u
        elif self.layout == "full":
            cols = (3 * self.free[:, None] + np.arange(3)).reshape(-1)
            self._full_A = np.zeros((self._out_A.shape[0], 3 * n), dtype=dt)
            self._full_A[:, cols] = self._out_A
            self._uf = np.empty(3 * n, dtype=dt)
            if self.mode == "roots":  # x_v = u_v + x*_{root(v)}, with a root its own root (u_v = 0)
                slot = np.empty(n, dtype=np.int64)
                slot[self.free] = self.root_slot
                slot[self.dirichlet] = np.arange(m)
                self._slot_flat = (3 * slot[:, None] + np.arange(3)).reshape(-1)
                self._orig = np.empty(3 * n)
        else:
            self._free_flat = (3 * self.free[:, None] + np.arange(3)).reshape(-1)
            self._ub = np.empty(3 * len(self.free))
            if self.mode == "roots":
                self._slot_flat = (3 * self.root_slot[:, None] + np.arange(3)).reshape(-1)
                self._orig = np.empty(3 * len(self.free))
        # forward-mode Jvp buffers: rows (h, dh) of each layer
        self._S = [np.empty((2, w), dtype=dt) for w in widths]
        self._A2 = [np.empty((2, w), dtype=dt) for w in widths]
        self._sig = [np.empty(w, dtype=dt) for w in widths]
        self._zs = np.zeros((2, self._zh.shape[0] - 1), dtype=dt)
        self._o2 = np.empty((2, 3), dtype=dt)

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
            a = self._ia[i]
            np.dot(h, self._int_A[i], out=a)
            _silu(a, self._it[i], out=self._ih[i][:-1])
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
                a = self._da[i]
                np.dot(h, self._dec_A[i], out=a)
                last = i == nh - 1
                dst = zh[r:-1] if last else self._h[i][:-1]
                if self.skips[i]:
                    _silu(a, self._dt[i], out=self._dt[i])
                    np.add(h[:-1], self._dt[i], out=dst)
                else:
                    _silu(a, self._dt[i], out=dst)
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
        xf = x.reshape(-1)
        # the gather uses mode="clip" (indices were checked at construction):
        # np.take with the default mode="raise" buffers its output
        if self.layout == "scatter":
            np.dot(self._hidden(z), self._out_A, out=self._u)
            y = self._ub
            np.copyto(y, self._u)
        else:
            np.dot(self._hidden(z), self._full_A, out=self._uf)
            y = xf
            np.copyto(y, self._uf)
        if self.mode == "roots":
            np.take(xD.reshape(-1), self._slot_flat, out=self._orig, mode="clip")
            y += self._orig
        elif len(self.dirichlet):
            np.mean(xD, axis=0, out=self._origin)
            y3 = y.reshape(-1, 3)
            for j in range(3):  # per column: an (n, 3) + (3,) broadcast allocates the ufunc's buffers
                y3[:, j] += self._origin[j]
        # scatters by index assignment (np.put is 2-3x slower)
        if self.layout == "scatter":
            xf[self._free_flat] = y
        if self.hard and not (self.mode == "roots" and self.layout == "full"):
            xf[self._dir_flat] = xD.reshape(-1)  # the prescribed vertices themselves
        return x

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        """One frame: (z_t (r,), x_t (n, 3)); see :meth:`integrate`, :meth:`decode`."""
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=z_out)
        return z, self.decode(z, xD, out=x_out)

    # -- derivatives -------------------------------------------------------------
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
        r, zs = self.r, self._zs
        zs[0, :r] = z
        zs[1, :r] = v
        nh = len(self.dec_W)
        S = zs[:, :r]
        for i in range(nh):
            A = self._A2[i]
            np.dot(S, self.dec_W[i].T, out=A)  # rows: W h, W dh
            A[0] += self.dec_b[i]
            a, sig = A[0], self._sig[i]
            # sigmoid s, silu = a s, silu' = s (1 + a (1 - s))
            expit(a, out=sig)
            dst = self._S[i] if i < nh - 1 else zs[:, r:]
            np.multiply(a, sig, out=dst[0])  # silu(a)
            np.subtract(a, dst[0], out=A[0])  # a - a s = a (1 - s)
            A[0] += 1.0
            A[0] *= sig  # silu'(a)
            np.multiply(A[1], A[0], out=dst[1])
            if self.skips[i]:
                dst += S
            S = dst
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
        S = np.zeros((1 + r, r), dtype=self.dtype)
        S[0] = z
        S[1:] = np.eye(r)
        Zs = S
        for i in range(len(self.dec_W)):
            A = S @ self.dec_W[i].T
            A[0] += self.dec_b[i]
            a = A[0]
            s = 1.0 / (1.0 + np.exp(np.minimum(-a, _SILU_CLAMP)))
            out = np.empty_like(A)
            out[0] = a * s
            out[1:] = A[1:] * (s * (1.0 + a * (1.0 - s)))
            if self.skips[i]:
                out += S
            S = out
        full = np.concatenate([Zs, S], axis=1) if len(self.dec_W) else Zs
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
            s = 1.0 / (1.0 + np.exp(np.minimum(-a, _SILU_CLAMP)))
            d1 = s * (1.0 + a * (1.0 - s))
            d2 = s * (1.0 - s) * (2.0 + a * (1.0 - 2.0 * s))
            y, dy = a * s, d1[:, None] * da
            d2y = d2[:, None, None] * da[:, :, None] * da[:, None, :] + d1[:, None, None] * d2a
            if self.skips[i]:
                h, dh, d2h = h + y, dh + dy, d2h + d2y
            else:
                h, dh, d2h = y, dy, d2y
        C = np.tensordot(c[r:], d2h, axes=1)  # z enters [z; h_L] linearly
        return 0.5 * (C + C.T)

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


# ---------------------------------------------------------------------------
# TorchScript runtime
# ---------------------------------------------------------------------------
class _SkipBlock(nn.Module):
    """h -> h + SiLU(W h + b) (skip) or SiLU(W h + b)."""

    def __init__(self, lin: nn.Linear, skip: bool):
        super().__init__()
        self.lin = lin
        self.skip = bool(skip)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        y = F.silu(self.lin(h))
        if self.skip:
            return h + y
        return y


class _ScriptedStep(nn.Module):
    """Folded integrator + decoder + relative-coordinates decode (single frame)."""

    def __init__(self, folded: dict, dtype: torch.dtype = torch.float32):
        super().__init__()
        hdr = folded["header"]

        def linear(W, b):
            lin = nn.Linear(W.shape[1], W.shape[0], dtype=torch.float64)
            with torch.no_grad():
                lin.weight.copy_(torch.as_tensor(W))
                lin.bias.copy_(torch.as_tensor(b))
            return lin.to(dtype).requires_grad_(False)

        L = int(hdr["integrator_layers"])
        self.int_layers = nn.ModuleList([linear(folded[f"int_W{i}"], folded[f"int_b{i}"]) for i in range(L)])
        skips = [bool(s) for s in hdr["decoder_skips"]]
        self.has_hidden = len(skips) > 0
        self.dec_layers = nn.ModuleList(
            [_SkipBlock(linear(folded[f"dec_W{i}"], folded[f"dec_b{i}"]), s) for i, s in enumerate(skips)]
        )
        self.has_mid = bool(hdr.get("decoder_mid", False))
        # (a 1 x 1 placeholder where there is no middle layer: TorchScript wants the attribute)
        self.dec_mid = linear(folded["dec_Wmid"], folded["dec_bmid"]) if self.has_mid else linear(np.zeros((1, 1)), np.zeros(1))
        self.dec_out = linear(folded["dec_Wout"], folded["dec_bout"])
        self.mode = str(hdr["mode"])
        self.residual = bool(hdr["residual"])
        self.n = int(hdr["n_vertices"])
        self.register_buffer("dirichlet", torch.as_tensor(np.asarray(folded["dirichlet"], dtype=np.int64)))
        self.register_buffer("free", torch.as_tensor(np.asarray(folded["free"], dtype=np.int64)))
        self.register_buffer("root_slot", torch.as_tensor(np.asarray(folded["root_slot"], dtype=np.int64)))
        self.register_buffer("net_dtype_probe", torch.zeros(0, dtype=dtype))

    @torch.jit.export
    def integrate(self, z_prev: torch.Tensor, z_prev2: torch.Tensor, p: torch.Tensor, p_prev: torch.Tensor, p_prev2: torch.Tensor) -> torch.Tensor:
        dt = self.net_dtype_probe.dtype
        zin = z_prev.to(dt)
        h = torch.cat([zin, z_prev2.to(dt), p.to(dt), p_prev.to(dt), p_prev2.to(dt)], -1)
        last = len(self.int_layers) - 1
        for i, lin in enumerate(self.int_layers):
            h = lin(h)
            if i < last:
                h = F.silu(h)
        if self.residual:
            h = zin + h
        return h

    @torch.jit.export
    def decode(self, z: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        dt = self.net_dtype_probe.dtype
        z = z.to(dt)
        h = z
        for block in self.dec_layers:
            h = block(h)
        if self.has_hidden:
            h = torch.cat([z, h], -1)
        if self.has_mid:
            h = self.dec_mid(h)
        u = self.dec_out(h).to(torch.float64).reshape(-1, 3)
        xD = xD.to(torch.float64)
        if self.mode == "roots" or self.mode == "hard_mean":
            origin = xD.index_select(0, self.root_slot) if self.mode == "roots" else xD.mean(0, keepdim=True)
            x = torch.empty((self.n, 3), dtype=torch.float64, device=u.device)
            x.index_copy_(0, self.free, u + origin)
            x.index_copy_(0, self.dirichlet, xD)
            return x
        if xD.shape[0] > 0:
            return u + xD.mean(0)
        return u

    def forward(self, z_prev: torch.Tensor, z_prev2: torch.Tensor, p: torch.Tensor, p_prev: torch.Tensor, p_prev2: torch.Tensor, xD: torch.Tensor):
        """(z_{t-1}, z_{t-2} (r,), p_t, p_{t-1}, p_{t-2} (k,), xD (m, 3)) -> (z_t (r,), x_t (n, 3) float64)."""
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2)
        return z, self.decode(z, xD)


def torchscript_module(folded: dict, dtype: torch.dtype = torch.float32) -> torch.jit.ScriptModule:
    """The folded step as a scripted, frozen, eval-mode module.

    ``module(z1, z2, p, p1, p2, xD) -> (z, x)``; also ``module.integrate(...)``
    and ``module.decode(z, xD)``.  Save with ``torch.jit.save``.
    """
    with _quiet_jit():
        mod = torch.jit.script(_ScriptedStep(folded, dtype).eval())
        return torch.jit.freeze(mod, preserved_attrs=["integrate", "decode"])


@contextlib.contextmanager
def _quiet_jit():
    """torch 2.x flags TorchScript as deprecated on every call; the format still works."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*torch\.jit\.\w+` is deprecated", category=DeprecationWarning)
        yield


class TorchStepper:
    """A TorchScript (or any) step module behind the :class:`NumpyStepper` interface.

    Accepts and returns tensors; :func:`time_step` and :func:`rollout_runtime`
    treat both steppers alike.
    """

    def __init__(self, module):
        self.module = module

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None):
        with torch.inference_mode():
            z = self.module.integrate(z_prev, z_prev2, p, p_prev, p_prev2)
        if out is not None:
            out[...] = z
            return out
        return z

    def decode(self, z, xD, out=None):
        with torch.inference_mode():
            x = self.module.decode(z, xD)
        if out is not None:
            out[...] = x
            return out
        return x

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2, out=z_out)
        return z, self.decode(z, xD, out=x_out)


class EagerStepper:
    """The training modules themselves (eval mode, ``torch.inference_mode``) behind the
    stepper interface: the eager-PyTorch baseline of :func:`time_step`.  Inputs are
    tensors of one frame, z (r,), p (k,), xD (m, 3)."""

    def __init__(self, ae, integrator, coords):
        from latentsim.latent import decode_latents

        self.ae, self.integrator, self.coords = ae.eval(), integrator.eval(), coords
        self._decode = decode_latents

    def integrate(self, z_prev, z_prev2, p, p_prev, p_prev2, out=None):
        with torch.inference_mode():
            return self.integrator(z_prev[None], z_prev2[None], p[None], p_prev[None], p_prev2[None])[0]

    def decode(self, z, xD, out=None):
        with torch.inference_mode():
            return self._decode(self.ae, self.coords, z[None], xD[None])[0]

    def step(self, z_prev, z_prev2, p, p_prev, p_prev2, xD, z_out=None, x_out=None):
        z = self.integrate(z_prev, z_prev2, p, p_prev, p_prev2)
        return z, self.decode(z, xD)


# ---------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------
def export_runtime(ae, integrator, coords, path, dtype: torch.dtype = torch.float32) -> dict:
    """Write the deployable runtime of a trained integrator + decoder.

    ``path`` ending in ``.npz``: the folded float64 weights and index arrays
    plus a JSON header (NumPy only, ``allow_pickle=False``).  Ending in ``.pt``:
    a frozen TorchScript module in ``dtype`` (``torch.jit.load`` alone runs it).
    Written under a temporary name and renamed.  Returns the folded dict.
    """
    path = os.fspath(path)
    folded = fold_networks(ae, integrator, coords)
    os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
    if path.endswith(".npz"):
        tmp = path[:-4] + ".tmp.npz"
        arrays = {k: v for k, v in folded.items() if k != "header"}
        np.savez(tmp, header=np.asarray(json.dumps(folded["header"])), **arrays)
    elif path.endswith(".pt"):
        tmp = path + ".tmp"
        module = torchscript_module(folded, dtype)
        with _quiet_jit():
            torch.jit.save(module, tmp)
    else:
        raise ValueError(f"runtime path {path!r}: use a .npz (NumPy) or .pt (TorchScript) file name")
    os.replace(tmp, path)
    return folded


def _read_npz(path) -> dict:
    with np.load(os.fspath(path), allow_pickle=False) as f:
        folded = {k: f[k] for k in f.files if k != "header"}
        folded["header"] = json.loads(str(f["header"]))
    if folded["header"].get("format") != FORMAT:
        raise ValueError(f"{path}: not a latent runtime file")
    if int(folded["header"].get("version", -1)) > VERSION:
        raise ValueError(f"{path}: runtime format version {folded['header']['version']} is newer than {VERSION}")
    return folded


def load_runtime(path, dtype=np.float32):
    """Load a runtime file: ``.npz`` -> :class:`NumpyStepper` (network ``dtype``);
    ``.pt`` -> :class:`TorchStepper` over ``torch.jit.load``."""
    path = os.fspath(path)
    if path.endswith(".npz"):
        return NumpyStepper(_read_npz(path), dtype=dtype)
    if path.endswith(".pt"):
        with _quiet_jit():
            return TorchStepper(torch.jit.load(path, map_location="cpu"))
    raise ValueError(f"runtime path {path!r}: use a .npz or .pt file")


# ---------------------------------------------------------------------------
# rollout and timing
# ---------------------------------------------------------------------------
def rollout_runtime(stepper: NumpyStepper, z0, z1, bc, dirichlet_positions) -> dict:
    """Autoregressive rollout with the NumPy runtime (no divergence test).

    z0, z1 : (r,); bc : (T, k); dirichlet_positions : (T, m, 3).
    Returns ``latents`` (T, r) in the network dtype and ``positions`` (T, n, 3) float64.
    """
    bc = np.asarray(bc, dtype=stepper.dtype)
    xD = np.asarray(dirichlet_positions, dtype=np.float64)
    T = bc.shape[0]
    Z = np.full((T, stepper.r), np.nan, dtype=stepper.dtype)
    X = np.full((T, stepper.n, 3), np.nan)
    Z[0], Z[1] = z0, z1
    stepper.decode(Z[0], xD[0], out=X[0])
    stepper.decode(Z[1], xD[1], out=X[1])
    for t in range(2, T):
        stepper.step(Z[t - 1], Z[t - 2], bc[t], bc[t - 1], bc[t - 2], xD[t], z_out=Z[t], x_out=X[t])
        if not np.isfinite(Z[t]).all():
            break
    return {"latents": Z, "positions": X}


def _median_ms(samples) -> float:
    return float(np.median(np.asarray(samples)) * 1e3)


def time_step(stepper, z_prev, z_prev2, p, p_prev, p_prev2, xD, repeats: int = 200, warmup: int = 10) -> dict:
    """Median wall time [ms] of integration, decoding and the whole step.

    Works with :class:`NumpyStepper` (NumPy inputs), :class:`TorchStepper` and
    :class:`EagerStepper` (tensor inputs).  ``step_ms`` times one whole
    :meth:`step` call (not the sum of the two halves' medians).
    """
    ti, td, ts = [], [], []
    z = stepper.integrate(z_prev, z_prev2, p, p_prev, p_prev2)
    z = z.copy() if isinstance(z, np.ndarray) else z.clone()
    for i in range(max(int(repeats), 1) + warmup):
        t0 = time.perf_counter()
        stepper.integrate(z_prev, z_prev2, p, p_prev, p_prev2)
        t1 = time.perf_counter()
        stepper.decode(z, xD)
        t2 = time.perf_counter()
        stepper.step(z_prev, z_prev2, p, p_prev, p_prev2, xD)
        t3 = time.perf_counter()
        if i >= warmup:
            ti.append(t1 - t0)
            td.append(t2 - t1)
            ts.append(t3 - t2)
    return {"integrate_ms": _median_ms(ti), "decode_ms": _median_ms(td), "step_ms": _median_ms(ts)}


def jvp_vertex_torch(ae, z: torch.Tensor, v: torch.Tensor, vertex_row: int):
    """The paper's Jvp (Li et al. Table 2): ``torch.func.jvp`` of the decoder,
    restricted to the 3 outputs of one vertex (row ``vertex_row`` of the
    encoded vector).  z, v : (r,).  Returns (u_v, du_v), each (3,)."""
    rows = slice(3 * vertex_row, 3 * vertex_row + 3)

    def f(zz):
        return ae.decode(zz[None])[0, rows]

    return torch.func.jvp(f, (z,), (v,))


def time_jvp(fn, repeats: int = 200, warmup: int = 10) -> float:
    """Median wall time [ms] of ``fn()``."""
    samples = []
    for i in range(max(int(repeats), 1) + warmup):
        t0 = time.perf_counter()
        fn()
        if i >= warmup:
            samples.append(time.perf_counter() - t0)
    return _median_ms(samples)
