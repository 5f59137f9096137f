"""The encoder in NumPy: full-space positions to the latent that starts a rollout.

What the pipeline does to a frame before it rolls out (``latentsim.latent.encode_positions``),
on the folded arrays of :func:`latentsim.runtime.fold.fold_encoder`: the relative coordinates in
float64 (each encoded vertex less its origin: its rod's root, or the mean prescribed position),
cast to the network dtype, then the network::

    u = x[free] - x*_origin,   h_0 = W_in u + b_in,   h_{i+1} = h_i + SiLU(W_i h_i + b_i)  (or without h_i),
    z = W_out [h_0; h_L] + b_out

Encoding happens once per motion (its first two frames), so it allocates; any leading axes
broadcast (a whole sequence encodes in one call).
"""

from __future__ import annotations

import numpy as np
from scipy.special import expit

__all__ = ["Encoder", "missing_encoder"]


def missing_encoder(header: dict, source=None) -> str:
    """The message of a runtime without an encoder (format version 1, or a decoder-only fold)."""
    where = f"{source}: " if source is not None else ""
    if int(header.get("integrator_layers", 0)) == 0:
        return f"{where}a decoder-only runtime (fold_decoder) holds no encoder"
    return (
        f"{where}this runtime file (format version {header.get('version')}) was written before runtime files held the "
        "encoder, so it cannot encode positions; rerun the rollout job that wrote it (e.g. "
        "`snakemake --cores 1 --forcerun rollout <its path>` with the run's config), or start from stored latents"
    )


class Encoder:
    """Positions (..., n, 3) float64 -> latents (..., r) in the network dtype (the trained autoencoder's encoder).

    Parameters
    ----------
    folded : a folded dict holding the encoder (:func:`latentsim.runtime.fold_networks`, or a
        ``runtime.npz`` of format version 2 on).
    dtype : network dtype, ``np.float32`` (default, as the pipeline encodes) or ``np.float64``.
    """

    def __init__(self, folded: dict, dtype=np.float32):
        hdr = folded["header"]
        if not hdr.get("encoder"):
            raise ValueError(missing_encoder(hdr))
        self.dtype = np.dtype(dtype)
        self.r, self.n, self.mode = int(hdr["latent_dim"]), int(hdr["n_vertices"]), str(hdr["mode"])
        self.dirichlet = np.asarray(folded["dirichlet"], dtype=np.int64)
        self.free = np.asarray(folded["free"], dtype=np.int64)
        self.root_slot = np.asarray(folded["root_slot"], dtype=np.int64)
        self.skips = [bool(s) for s in hdr["encoder_skips"]]

        def cast(key):
            return np.ascontiguousarray(folded[key], dtype=self.dtype)

        self.W_in, self.b_in = cast("enc_Win"), cast("enc_bin")
        self.W = [cast(f"enc_W{i}") for i in range(len(self.skips))]
        self.b = [cast(f"enc_b{i}") for i in range(len(self.skips))]
        self.W_out, self.b_out = cast("enc_Wout"), cast("enc_bout")

    def relative(self, x, xD) -> np.ndarray:
        """The relative coordinates u (..., d) float64 of positions x (..., n, 3) with Dirichlet positions xD (..., m, 3)."""
        x, xD = np.asarray(x, dtype=np.float64), np.asarray(xD, dtype=np.float64)
        m = len(self.dirichlet)
        if x.shape[-2:] != (self.n, 3):
            raise ValueError(f"positions: need shape (..., {self.n}, 3) (the runtime's {self.n} vertices), got {x.shape}")
        if xD.shape[-2:] != (m, 3):
            raise ValueError(f"Dirichlet positions: need shape (..., {m}, 3) (the runtime's {m} prescribed vertices), got {xD.shape}")
        if self.mode == "roots":
            origin = xD[..., self.root_slot, :]
        elif m:
            origin = xD.mean(-2, keepdims=True)
        else:
            origin = np.zeros((1, 3))
        u = x[..., self.free, :] - origin
        return u.reshape(u.shape[:-2] + (-1,))

    def encode(self, x, xD) -> np.ndarray:
        """Latents z (..., r) in the network dtype of positions x (..., n, 3) with Dirichlet positions xD (..., m, 3)."""
        u = self.relative(x, xD).astype(self.dtype)
        h0 = u @ self.W_in.T + self.b_in
        h = h0
        for W, b, skip in zip(self.W, self.b, self.skips):
            a = h @ W.T + b
            y = a * expit(a)
            h = h + y if skip else y
        hL = np.concatenate([h0, h], axis=-1) if self.W else h0
        return hL @ self.W_out.T + self.b_out
