"""Folding a trained latent integrator and decoder into plain float64 arrays.

A trained :class:`latentsim.latent.LatentIntegrator`, the decoder half of an
:class:`latentsim.latent.Autoencoder` and the :class:`latentsim.latent.RelativeCoordinates`
decode (re-adding the Dirichlet mean, or each rod's root) become a handful of dense layers:

- eval-mode BatchNorm into the preceding Linear,
  ``W' = diag(gamma / sqrt(var + eps)) W``, ``b' = gamma (b - mean) / sqrt(var + eps) + beta``;
- the integrator's input standardisation into its first layer and its output
  scaling (``out_mean + out_std * y``) into its last;
- the decoder's residual-branch output layer into the PCA output layer, and the
  PCA skip path ``[z, 0]`` into the same matrix: ``u = W_cat [z; h_L] + b_cat``
  with ``W_cat = [W_pca[:, :r], W_pca W_o]`` (d x (r + w_L)) - unless the PCA
  layer is narrower than the last hidden layer (p < w_L), where that would widen
  the largest matrix: then ``u = W_pca ([z, 0] + W_o h_L + b_o) + b_pca``.

One frame is then (Li et al. 2025, Eq. 3, and the decode)::

    z_t = z_{t-1} + MLP_I([z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}])     (residual integrator)
    h_0 = z_t,  h_{i+1} = h_i + SiLU(W_i h_i + b_i)  (or without h_i where widths differ)
    u = W_cat [z_t; h_L] + b_cat,   x = decode_relative(u, x*_D)

The encoder (:func:`fold_encoder`; what turns a full-space frame into the latent that starts a
rollout, exactly as the pipeline encodes: the relative coordinates in float64, then the network)
folds the same way: its PCA input layer ``h_0 = W_in u + b_in`` is kept, the branch's hidden
layers get their BatchNorm folded, and the PCA skip ``z = h_0[:r] + W_o h_L + b_o`` becomes one
matrix on ``[h_0; h_L]``::

    h_0 = W_in u + b_in,  h_{i+1} = h_i + SiLU(W_i h_i + b_i)  (or without h_i),   z = W_out [h_0; h_L] + b_out

The folded dict (``int_W{i}``, ``int_b{i}``, ``dec_W{i}``, ``dec_b{i}``, optional
``dec_Wmid``/``dec_bmid``, ``dec_Wout``/``dec_bout``, the encoder's ``enc_Win``/``enc_bin``,
``enc_W{i}``/``enc_b{i}``, ``enc_Wout``/``enc_bout`` (format version 2 on), the coordinates'
``dirichlet``, ``free`` and ``root_slot`` index arrays, and a JSON-able ``header``) is what every
stepper is built from and what ``runtime.npz`` holds (:mod:`latentsim.runtime.files`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

__all__ = ["FORMAT", "VERSION", "fold_decoder", "fold_encoder", "fold_networks"]

FORMAT = "latentsim-latent-runtime"
VERSION = 2  # 2: the encoder (enc_* arrays, header "encoder"); version 1 files (no encoder) are still read


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
    if getattr(coords, "rigid", False):  # recorded only when set: other runtimes' files are as before
        out["header"]["rigid_frame"] = {"vertices": [int(v) for v in coords.frame_vertices],
                                        "rest_frame": [float(v) for v in coords.rest_frame.reshape(-1)]}  # fmt: skip
    return out


def fold_encoder(ae) -> dict:
    """Fold an eval-mode encoder (:meth:`latentsim.latent.Autoencoder.encode`) into float64 arrays.

    Returns ``enc_Win`` (p, d), ``enc_bin`` (p,) (the PCA input layer), ``enc_W{i}`` (w_{i+1}, w_i),
    ``enc_b{i}`` for each hidden layer of the branch (BatchNorm folded; SiLU, identity skip where
    ``encoder_skips[i]``), ``enc_Wout`` (r, p + w_L) acting on ``[h_0; h_L]`` ((r, p) acting on h_0
    without hidden layers), ``enc_bout`` (r,), and the ``header`` entries ``encoder`` (True) and ``encoder_skips``.
    """
    r, p = int(ae.latent_dim), int(ae.pca_dim)
    br = ae.enc_branch
    out: dict = {"enc_Win": _np(ae.pca_in.weight), "enc_bin": _np(ae.pca_in.bias)}
    for i, block in enumerate(br.blocks):
        out[f"enc_W{i}"], out[f"enc_b{i}"] = _fold_linear_bn(block[0], block[1])
    Wo, bo = _np(br.out.weight), _np(br.out.bias)  # (r, w_L), (r,)
    first = np.eye(r, p)  # the PCA skip: z = h_0[:r] + ...
    out["enc_Wout"] = np.concatenate([first, Wo], axis=1) if len(br.blocks) else first + Wo
    out["enc_bout"] = bo
    return {"arrays": out, "header": {"encoder": True, "encoder_skips": [bool(s) for s in br.skip]}}


def fold_networks(ae, integrator, coords) -> dict:
    """Fold an eval-mode integrator + decoder + relative coordinates into arrays.

    Parameters
    ----------
    ae : :class:`latentsim.latent.Autoencoder` (its encoder and decoder).
    integrator : :class:`latentsim.latent.LatentIntegrator`.
    coords : :class:`latentsim.latent.RelativeCoordinates`.

    Returns
    -------
    dict of float64/int64 arrays plus ``header`` (a JSON-able dict); the
    layout of :func:`export_runtime`'s ``.npz`` file, the encoder (:func:`fold_encoder`) included.
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
    enc = fold_encoder(ae)
    out.update(enc["arrays"])
    out["header"].update(enc["header"])
    return out
