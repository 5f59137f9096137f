"""Latent-space dynamics: autoencoder, neural integrator, self-supervised loss.

Implements the learning core of Li et al. 2025, "Self-supervised Learning of
Latent Space Dynamics" (sections 3.2-3.3):

1. :class:`RelativeCoordinates` - positions expressed relative to the
   Dirichlet boundary conditions (root-relative for rods, relative to the mean
   Dirichlet position for cloth and solids), the vector the autoencoder sees.
2. :class:`Autoencoder` - a symmetric MLP ResNet (BatchNorm + SiLU/Swish)
   whose outer linear layers are initialised from PCA (Fulton et al. 2019).
   The PCA path *is* the skip path: an untrained, PCA-initialised autoencoder
   is exactly PCA with ``latent_dim`` components; the residual MLP branches
   (zero-initialised output layers) learn the nonlinear correction.
3. :class:`LatentIntegrator` - an MLP (SiLU) mapping
   ``[z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}]`` to ``z_t`` (paper Eq. 3).
4. :func:`integrator_loss` - the self-supervised loss (Eq. 4): the incremental
   potential of the decoded prediction, with training noise (Eq. 5) and data
   balancing (Eq. 6); or the supervised L2 baseline.
5. :func:`fit_autoencoder`, :func:`fit_integrator` (with checkpoint/resume),
   :func:`rollout` (autoregressive inference with divergence detection).

Physics is never re-implemented here: every energy comes from an
:class:`latentsim.physics.incremental_potential.IncrementalPotential`.  Networks run in
float32; decoded states are cast to float64 before the potential is evaluated.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import math
import os
import time
import warnings
from typing import Any, Callable, Sequence

import torch
from torch import nn
from tqdm import tqdm

from latentsim.physics.kernels import with_compiled_elastic

log = logging.getLogger(__name__)

__all__ = [
    "AE_DEFAULTS",
    "INTEGRATOR_DEFAULTS",
    "Autoencoder",
    "LatentIntegrator",
    "RelativeCoordinates",
    "TrainingDiverged",
    "balancing_weights",
    "build_triplets",
    "decode_latents",
    "encode_positions",
    "fit_autoencoder",
    "fit_integrator",
    "integrator_loss",
    "load_autoencoder",
    "load_integrator",
    "pca_basis",
    "resolve_device",
    "rollout",
    "save_module",
]


# ---------------------------------------------------------------------------
# devices, errors, config helpers
# ---------------------------------------------------------------------------
def resolve_device(spec: str | torch.device = "auto") -> torch.device:
    """Turn ``"auto" | "cpu" | "cuda" | "cuda:N"`` into a :class:`torch.device`.

    ``"auto"`` picks CUDA when available, else the CPU.  Raises ``ValueError``
    for unknown strings and when CUDA is requested but not available.
    """
    if isinstance(spec, torch.device):
        spec = str(spec)
    if not isinstance(spec, str):
        raise ValueError(f"device must be a string such as 'auto', 'cpu', 'cuda'; got {spec!r}")
    s = spec.strip().lower()
    if s == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if s == "cpu":
        return torch.device("cpu")
    if s == "cuda" or (s.startswith("cuda:") and s[5:].isdigit()):
        if not torch.cuda.is_available():
            raise ValueError(f"device {spec!r} requested but CUDA is not available")
        dev = torch.device(s)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {spec!r} requested but only {torch.cuda.device_count()} CUDA device(s) exist")
        return dev
    raise ValueError(f"unknown device {spec!r}: use 'auto', 'cpu', 'cuda' or 'cuda:N'")


class TrainingDiverged(RuntimeError):
    """A training loss (or gradient) became NaN/inf.

    Attributes
    ----------
    epoch : 1-based epoch in which the non-finite value appeared.
    batch : 0-based minibatch index within that epoch.
    """

    def __init__(self, epoch: int, batch: int = -1, what: str = "loss"):
        self.epoch = int(epoch)
        self.batch = int(batch)
        super().__init__(
            f"training diverged: non-finite {what} in epoch {self.epoch}"
            + (f", batch {self.batch}" if self.batch >= 0 else "")
            + " (last good checkpoint, if any, left intact)"
        )


AE_DEFAULTS: dict[str, Any] = {
    "latent_dim": 8,
    "widths": [200, 200, 200],
    "pca_dim": None,  # None -> widths[0]; always capped at the data dimension
    "epochs": 1000,
    "lr": 1e-4,
    "batch_size": 500,
    "train_pca": True,  # PCA layers are an initialisation, trained with the rest
    "pca_samples": 4000,  # at most this many rows enter the PCA (random subset)
}

INTEGRATOR_DEFAULTS: dict[str, Any] = {
    "widths": [256, 256, 256],
    "epochs": 1000,
    "lr": 1e-4,
    "lr_final": None,  # None: constant lr; else cosine decay from lr to lr_final over the epochs
    "batch_size": 500,
    "mode": "self_supervised",  # or "supervised"
    "noise_scale": 0.1,  # Eq. 5; 0 disables the training noise
    "supervised_weight": 0.0,  # self-supervised mode: weight of an added L2 term on the ground-truth latents (0: the paper)
    "balancing": True,  # Eq. 6
    "balancing_eps": 1e-2,  # [m/s] floor of |v_{t-1}| in Eq. 6
    "use_penalty": None,  # None -> penalty iff the coordinates do not impose Dirichlet exactly
    "residual": True,  # z_t = z_{t-1} + learned increment
    "checkpoint_path": None,
    "checkpoint_every": 10,  # epochs
}


def _merge(defaults: dict, config: dict | None, what: str) -> dict:
    cfg = dict(defaults)
    for k, v in (config or {}).items():
        if k not in defaults:
            warnings.warn(f"{what}: ignoring unknown config key {k!r}", stacklevel=3)
            continue
        cfg[k] = v
    return cfg


# ---------------------------------------------------------------------------
# relative coordinates
# ---------------------------------------------------------------------------
class RelativeCoordinates:
    """Full positions <-> the vector the autoencoder sees (paper sec. 3.2).

    Modes
    -----
    ``"roots"`` (rods): every free vertex is written relative to its rod's root
        vertex, ``u_i = x_i - x*_{root(i)}``.  The Dirichlet vertices are left
        out of ``u`` and re-applied from their prescribed positions on decode,
        so boundary conditions hold exactly (``hard_dirichlet = True``).
    ``"mean"`` (cloth, solids): every vertex (Dirichlet ones included) is
        written relative to the mean prescribed Dirichlet position,
        ``u_i = x_i - mean_j x*_j``.  Decoded Dirichlet vertices are *not*
        overwritten (``hard_dirichlet = False``): the loss enforces them by the
        quadratic penalty.  With no Dirichlet vertex the origin is 0.
    ``"hard_mean"`` (solids mostly prescribed, e.g. ears on a rigid head): the
        free vertices relative to the mean prescribed position, the Dirichlet
        vertices left out of ``u`` and re-applied on decode
        (``hard_dirichlet = True``).  With the paper's ``"mean"`` encoding such a
        scene's latent must carry the prescribed majority, held only by the
        stiff penalty, and its loss is dominated by it.

    The origin is always taken from the prescribed positions ``xD`` (m, 3) of
    the Dirichlet vertices (which the simulator imposes exactly), so
    ``decode(encode(x, xD), xD) == x`` whenever ``x[dirichlet] == xD``.

    Parameters
    ----------
    n_vertices : number of vertices n.
    dirichlet : (m,) indices of the Dirichlet vertices (order of ``xD``).
    mode : ``"roots"`` or ``"mean"``.
    root_of : (n,) index of each vertex's root vertex (``"roots"`` mode only);
        every root must be a Dirichlet vertex.

    Attributes
    ----------
    dim : length d of the encoded vector.
    encoded_vertices : (n_enc,) vertex indices present in the encoded vector.
    """

    def __init__(self, n_vertices: int, dirichlet, mode: str = "mean", root_of=None):
        self.n = int(n_vertices)
        self.dirichlet = torch.as_tensor(dirichlet, dtype=torch.long).reshape(-1).cpu()
        if mode not in ("roots", "mean", "hard_mean"):
            raise ValueError(f"RelativeCoordinates mode must be 'roots', 'mean' or 'hard_mean', got {mode!r}")
        self.mode = mode
        m = self.dirichlet.numel()
        if m and (self.dirichlet.min() < 0 or self.dirichlet.max() >= self.n):
            raise ValueError("dirichlet indices out of range")
        if mode == "roots":
            if root_of is None:
                raise ValueError("mode 'roots' needs a per-vertex root_of index array")
            root_of = torch.as_tensor(root_of, dtype=torch.long).reshape(-1).cpu()
            if root_of.numel() != self.n:
                raise ValueError(f"root_of has {root_of.numel()} entries, expected {self.n}")
            # position of each vertex's root within the Dirichlet list
            slot = torch.full((self.n,), -1, dtype=torch.long)
            slot[self.dirichlet] = torch.arange(m)
            root_slot = slot[root_of]
            if (root_slot < 0).any():
                raise ValueError("every root in root_of must be a Dirichlet vertex")
            is_d = torch.zeros(self.n, dtype=torch.bool)
            is_d[self.dirichlet] = True
            self.free = torch.nonzero(~is_d).reshape(-1)
            self.root_slot = root_slot[self.free]  # (n_free,)
            self.encoded_vertices = self.free
            self.hard_dirichlet = True
        elif mode == "hard_mean":
            if not m:
                raise ValueError("mode 'hard_mean' needs Dirichlet vertices")
            is_d = torch.zeros(self.n, dtype=torch.bool)
            is_d[self.dirichlet] = True
            self.free = torch.nonzero(~is_d).reshape(-1)
            self.root_slot = None
            self.encoded_vertices = self.free
            self.hard_dirichlet = True
        else:
            self.free = torch.arange(self.n)
            self.root_slot = None
            self.encoded_vertices = self.free
            self.hard_dirichlet = False
        self.dim = 3 * int(self.encoded_vertices.numel())

    def _origin(self, xD: torch.Tensor) -> torch.Tensor:
        """(..., m, 3) -> (..., n_enc, 3) origin of each encoded vertex."""
        if self.mode == "roots":
            return xD[..., self.root_slot.to(xD.device), :]
        if xD.shape[-2] == 0:
            return torch.zeros(xD.shape[:-2] + (1, 3), dtype=xD.dtype, device=xD.device)
        return xD.mean(-2, keepdim=True)

    def encode(self, x: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """Positions x (..., n, 3), prescribed xD (..., m, 3) -> u (..., d)."""
        xe = x[..., self.encoded_vertices.to(x.device), :]
        u = xe - self._origin(xD)
        return u.reshape(u.shape[:-2] + (self.dim,))

    def decode(self, u: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
        """u (..., d), prescribed xD (..., m, 3) -> positions (..., n, 3).

        Broadcasts over leading axes; the dtype is that of ``u`` (promoted
        with ``xD``).
        """
        lead = torch.broadcast_shapes(u.shape[:-1], xD.shape[:-2])
        dtype = torch.promote_types(u.dtype, xD.dtype)
        xe = u.reshape(u.shape[:-1] + (-1, 3)).to(dtype) + self._origin(xD.to(dtype))
        if not self.hard_dirichlet:
            return xe.expand(lead + xe.shape[-2:])
        x = torch.empty(lead + (self.n, 3), dtype=dtype, device=u.device)
        x[..., self.free.to(u.device), :] = xe
        x[..., self.dirichlet.to(u.device), :] = xD.to(dtype)
        return x


# ---------------------------------------------------------------------------
# autoencoder
# ---------------------------------------------------------------------------
def pca_basis(U: torch.Tensor, p: int, max_samples: int | None = None, seed: int = 0):
    """Top-p principal directions of the rows of U.

    Parameters
    ----------
    U : (N, d) data.
    p : number of components (p <= d).  If the data have fewer than p
        non-trivial directions (e.g. N - 1 < p), the basis is completed by
        orthonormal directions of the complement (std 0).
    max_samples : use a random subset of at most this many rows.

    Returns
    -------
    mean : (d,) float64, components : (p, d) float64 orthonormal rows,
    std : (p,) float64 standard deviation of the data along each component.
    """
    U = U.detach().to(torch.float64).cpu()
    N, d = U.shape
    if p > d:
        raise ValueError(f"pca dimension {p} exceeds the data dimension {d}")
    g = torch.Generator().manual_seed(seed)
    if max_samples is not None and N > max_samples:
        U = U[torch.randperm(N, generator=g)[:max_samples]]
        N = max_samples
    mean = U.mean(0)
    Xc = U - mean
    # eigen-decomposition of the smaller of the Gram (N x N) and covariance
    # (d x d) matrices: much faster than an SVD of the N x d data
    if N <= d:
        lam, W = torch.linalg.eigh(Xc @ Xc.T)
        lam, W = lam.flip(0), W.flip(1)
        keep = int(((lam > 1e-12 * lam[0].clamp_min(1e-300)) & (lam > 0)).sum()) if N else 0
        keep = min(keep, p)
        V = Xc.T @ W[:, :keep] / lam[:keep].sqrt()  # (d, keep), orthonormal up to round-off
        Q, Rq = torch.linalg.qr(V)
        sgn = torch.sign(torch.diagonal(Rq))
        sgn[sgn == 0] = 1.0
        Vh = (Q * sgn).T  # re-orthonormalised, directions of V kept
        std = (lam[:keep] / N).sqrt()
    else:
        lam, V = torch.linalg.eigh(Xc.T @ Xc)
        Vh = V.flip(1)[:, :p].T
        std = (lam.flip(0)[:p].clamp_min(0) / N).sqrt()
    r = Vh.shape[0]
    if r < p:  # complete with an orthonormal basis of the complement
        R = torch.randn(p - r, d, generator=g, dtype=torch.float64)
        for _ in range(2):  # project out the data directions (twice, for round-off)
            R = R - (R @ Vh.T) @ Vh
        Q, _ = torch.linalg.qr(R.T)
        Vh = torch.cat([Vh, Q.T], 0)
        std = torch.cat([std, torch.zeros(p - r, dtype=std.dtype)])
    return mean, Vh[:p].contiguous(), std[:p]


class _ResidualMLP(nn.Module):
    """Linear -> BatchNorm -> SiLU blocks, residual where widths match, then a
    zero-initialised linear output layer (so the branch starts as 0)."""

    def __init__(self, in_dim: int, widths: Sequence[int], out_dim: int):
        super().__init__()
        self.blocks = nn.ModuleList()
        self.skip: list[bool] = []
        prev = in_dim
        for w in widths:
            self.blocks.append(nn.Sequential(nn.Linear(prev, w), nn.BatchNorm1d(w), nn.SiLU()))
            self.skip.append(prev == w)
            prev = w
        self.out = nn.Linear(prev, out_dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        for block, skip in zip(self.blocks, self.skip):
            y = block(h)
            h = h + y if skip else y
        return self.out(h)


class Autoencoder(nn.Module):
    """Symmetric MLP ResNet autoencoder with PCA-initialised outer layers.

    Architecture (d = input dim, p = PCA dim, r = latent dim, widths w_1..w_L)::

        encoder:  h = W_e u + b_e                      (d -> p, PCA init)
                  z = h[:r] + F_e(h)                    F_e: p -> w_1 .. w_L -> r
        decoder:  h' = [z, 0_{p-r}] + F_d(z)            F_d: r -> w_L .. w_1 -> p
                  u' = W_d h' + b_d                     (p -> d, PCA init)

    ``F_e``, ``F_d`` are residual MLPs (Linear-BatchNorm-SiLU blocks with
    identity skips where consecutive widths match) whose output layers are
    zero-initialised.  After :meth:`init_pca`, ``W_e = V^T / s``,
    ``b_e = -W_e mean``, ``W_d = s V``, ``b_d = mean`` (V: top-p principal
    directions, s: std along the first one, so latents are O(1)); an
    untrained autoencoder is therefore exactly rank-r PCA and training only
    has to learn the nonlinear residual (Fulton et al. 2019).

    Parameters
    ----------
    input_dim : d.
    latent_dim : r.
    widths : hidden widths of the encoder branch (decoder uses them reversed).
    pca_dim : p; ``None`` -> ``widths[0]`` (or r without hidden layers);
        capped at d; must be >= r.
    """

    def __init__(self, input_dim: int, latent_dim: int, widths: Sequence[int] = (200, 200, 200), pca_dim: int | None = None):
        super().__init__()
        widths = [int(w) for w in widths]
        if pca_dim is None:
            pca_dim = widths[0] if widths else latent_dim
        p = min(int(pca_dim), int(input_dim))
        if p < latent_dim:
            raise ValueError(f"pca_dim (after capping at the input dimension) {p} < latent_dim {latent_dim}")
        self.hparams = {"input_dim": int(input_dim), "latent_dim": int(latent_dim), "widths": widths, "pca_dim": p}
        self.input_dim, self.latent_dim, self.pca_dim = int(input_dim), int(latent_dim), p
        self.pca_in = nn.Linear(input_dim, p)
        self.enc_branch = _ResidualMLP(p, widths, latent_dim)
        self.dec_branch = _ResidualMLP(latent_dim, list(reversed(widths)), p)
        self.pca_out = nn.Linear(p, input_dim)

    @torch.no_grad()
    def init_pca(self, U: torch.Tensor, max_samples: int | None = 4000, seed: int = 0) -> dict:
        """Initialise the outer layers from PCA of U (N, d); returns PCA stats."""
        mean, V, std = pca_basis(U, self.pca_dim, max_samples=max_samples, seed=seed)
        s = float(std[0]) if float(std[0]) > 0 else 1.0
        W = V / s
        dev, dt = self.pca_in.weight.device, self.pca_in.weight.dtype
        self.pca_in.weight.copy_(W.to(dev, dt))
        self.pca_in.bias.copy_((-(W @ mean)).to(dev, dt))
        self.pca_out.weight.copy_((V.T * s).to(dev, dt))
        self.pca_out.bias.copy_(mean.to(dev, dt))
        return {"scale": s, "explained_std": std.tolist()}

    def _flat(self, a: torch.Tensor, dim: int):
        return a.reshape(-1, dim), a.shape[:-1]

    def encode(self, u: torch.Tensor) -> torch.Tensor:
        """u (..., d) -> z (..., r)."""
        h, lead = self._flat(u.to(self.pca_in.weight.dtype), self.input_dim)
        h = self.pca_in(h)
        z = h[:, : self.latent_dim] + self.enc_branch(h)
        return z.reshape(lead + (self.latent_dim,))

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """z (..., r) -> u (..., d)."""
        zf, lead = self._flat(z.to(self.pca_out.weight.dtype), self.latent_dim)
        pad = zf.new_zeros(zf.shape[0], self.pca_dim - self.latent_dim)
        h = torch.cat([zf, pad], -1) + self.dec_branch(zf)
        return self.pca_out(h).reshape(lead + (self.input_dim,))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(u))


def _batches(N: int, batch_size: int, gen: torch.Generator, min_size: int = 1):
    perm = torch.randperm(N, generator=gen)
    out = [perm[i : i + batch_size] for i in range(0, N, batch_size)]
    if len(out) > 1 and out[-1].numel() < min_size:
        out = out[:-1]  # BatchNorm cannot train on a single sample
    return out


def fit_autoencoder(U: torch.Tensor, config: dict | None = None, seed: int = 0, device="cpu", progress: bool = False, snapshots=()):
    """Train an :class:`Autoencoder` on encoded frames (paper Eq. 2).

    Parameters
    ----------
    U : (N, d) encoded training frames (output of :meth:`RelativeCoordinates.encode`).
    config : keys of :data:`AE_DEFAULTS` (latent_dim, widths, pca_dim, epochs,
        lr, batch_size, train_pca, pca_samples).
    seed : seeds weight init and minibatch order (bitwise reproducible on CPU).
    device : anything :func:`resolve_device` accepts.
    progress : show a tqdm bar over epochs.
    snapshots : epochs (0 = the PCA initialisation) after which to keep the weights this call
        would have returned had it stopped there (learning curves, early stopping).

    Returns
    -------
    model : the trained autoencoder in eval mode, on ``device``.
    history : dict with ``loss`` (per-epoch mean of the normalised training
        MSE, i.e. MSE of u / s), ``mse_initial`` (MSE per coordinate of the
        PCA-initialised model, in data units^2), ``mse_final`` (of the model
        returned), ``kept`` ('trained', or 'pca' when training ended worse than
        the PCA initialisation, whose weights are then returned), ``pca_scale``
        s, ``pca_dim``, ``epochs``; with ``snapshots``, ``snapshots`` {epoch: {"state"
        (state dict, on the CPU), "mse", "kept", "seconds" (training time so far)}}.
    """
    cfg = _merge(AE_DEFAULTS, config, "fit_autoencoder")
    device = resolve_device(device)
    U = torch.as_tensor(U).detach()
    if U.ndim != 2:
        raise ValueError(f"U must be (N, d), got shape {tuple(U.shape)}")
    N, d = U.shape
    fork = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=fork):
        torch.manual_seed(seed)
        model = Autoencoder(d, int(cfg["latent_dim"]), cfg["widths"], cfg["pca_dim"])
        stats = model.init_pca(U, max_samples=cfg["pca_samples"], seed=seed)
    model = model.to(device)
    for prm in list(model.pca_in.parameters()) + list(model.pca_out.parameters()):
        prm.requires_grad_(bool(cfg["train_pca"]))
    s = stats["scale"]
    Ud = U.to(device=device, dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], lr=float(cfg["lr"]))

    @torch.no_grad()
    def eval_mse() -> float:
        model.eval()
        err = 0.0
        for i in range(0, N, 4096):
            r = model(Ud[i : i + 4096]) - Ud[i : i + 4096]
            err += float((r.double() ** 2).sum())
        return err / (N * d)

    history = {"loss": [], "mse_initial": eval_mse(), "pca_scale": s, "pca_dim": model.pca_dim, "epochs": int(cfg["epochs"])}
    pca_state = copy.deepcopy(model.state_dict())
    wanted = {int(k) for k in snapshots}
    if any(k < 0 or k > int(cfg["epochs"]) for k in wanted):
        raise ValueError(f"snapshots {sorted(wanted)} outside epochs 0..{cfg['epochs']}")
    t_start = time.perf_counter()

    def snapshot(epoch: int) -> None:
        # what this call returns had it stopped here: the PCA start when training made it worse
        mse = eval_mse()
        kept = "trained" if mse <= history["mse_initial"] else "pca"
        state = model.state_dict() if kept == "trained" else pca_state
        history.setdefault("snapshots", {})[epoch] = {
            "state": {k: v.detach().cpu().clone() for k, v in state.items()},
            "mse": mse if kept == "trained" else history["mse_initial"],
            "kept": kept,
            "seconds": time.perf_counter() - t_start,
        }

    if 0 in wanted:
        snapshot(0)
    bar = tqdm(range(int(cfg["epochs"])), desc="autoencoder", disable=not progress, leave=False)
    for epoch in bar:
        model.train()
        tot, cnt = 0.0, 0
        for idx in _batches(N, int(cfg["batch_size"]), gen, min_size=2):
            idx = idx.to(device)
            ub = Ud[idx]
            loss = (((model(ub) - ub) / s) ** 2).mean()
            if not torch.isfinite(loss):
                raise TrainingDiverged(epoch + 1)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            tot += float(loss.detach()) * idx.numel()
            cnt += idx.numel()
        history["loss"].append(tot / max(cnt, 1))
        bar.set_postfix(loss=f"{history['loss'][-1]:.3e}")
        if epoch + 1 in wanted:
            snapshot(epoch + 1)
    history["mse_final"] = eval_mse()
    # Never return a model worse than its own PCA initialisation (small data sets whose PCA is
    # already near exact can get worse under SGD noise): keep the PCA start instead, and say so.
    history["kept"] = "trained"
    if not history["mse_final"] <= history["mse_initial"]:
        model.load_state_dict(pca_state)
        history["kept"] = "pca"
        history["mse_final"] = eval_mse()
    model.eval()
    return model, history


# ---------------------------------------------------------------------------
# latent integrator
# ---------------------------------------------------------------------------
class LatentIntegrator(nn.Module):
    """z_t = I(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2}) (paper Eq. 3).

    An MLP with SiLU (Swish) activations.  Inputs are standardised with
    statistics stored as buffers (:meth:`fit_normalization`).  With
    ``residual=True`` (default) the network predicts the increment,
    ``z_t = z_{t-1} + mu_dz + sigma_dz * MLP(q)``, where mu_dz, sigma_dz are
    the mean/std of ``z_t - z_{t-1}`` over the training triplets: latents
    change little per frame, so a zero MLP output already means "keep the
    previous latent (plus the mean drift)".  With ``residual=False`` the
    output is ``z_t = mu_z + sigma_z * MLP(q)`` (statistics of z_t).

    Parameters
    ----------
    latent_dim : r.
    bc_dim : k, length of one boundary-condition vector p_t (may be 0).
    widths : hidden widths.
    residual : see above.
    """

    def __init__(self, latent_dim: int, bc_dim: int, widths: Sequence[int] = (256, 256, 256), residual: bool = True):
        super().__init__()
        widths = [int(w) for w in widths]
        self.hparams = {"latent_dim": int(latent_dim), "bc_dim": int(bc_dim), "widths": widths, "residual": bool(residual)}
        self.latent_dim, self.bc_dim, self.residual = int(latent_dim), int(bc_dim), bool(residual)
        in_dim = 2 * latent_dim + 3 * bc_dim
        layers: list[nn.Module] = []
        prev = in_dim
        for w in widths:
            layers += [nn.Linear(prev, w), nn.SiLU()]
            prev = w
        layers.append(nn.Linear(prev, latent_dim))
        self.mlp = nn.Sequential(*layers)
        self.register_buffer("in_mean", torch.zeros(in_dim))
        self.register_buffer("in_std", torch.ones(in_dim))
        self.register_buffer("out_mean", torch.zeros(latent_dim))
        self.register_buffer("out_std", torch.ones(latent_dim))

    @staticmethod
    def _std(a: torch.Tensor) -> torch.Tensor:
        s = a.std(0, unbiased=False) if a.shape[0] > 1 else torch.ones_like(a[0])
        return torch.where(s > 1e-12, s, torch.ones_like(s))

    @torch.no_grad()
    def fit_normalization(self, z, z_prev, z_prev2, p, p_prev, p_prev2) -> None:
        """Set the normalisation buffers from training triplets (each (N, .))."""
        q = torch.cat([z_prev, z_prev2, p, p_prev, p_prev2], -1).to(self.in_mean)
        self.in_mean.copy_(q.mean(0))
        self.in_std.copy_(self._std(q))
        tgt = (z - z_prev) if self.residual else z
        tgt = tgt.to(self.out_mean)
        self.out_mean.copy_(tgt.mean(0))
        self.out_std.copy_(self._std(tgt))

    def forward(self, z_prev, z_prev2, p, p_prev, p_prev2) -> torch.Tensor:
        """All inputs (B, .) -> z_t (B, r)."""
        dt = self.in_mean.dtype
        z_prev = z_prev.to(dt)
        q = torch.cat([z_prev, z_prev2.to(dt), p.to(dt), p_prev.to(dt), p_prev2.to(dt)], -1)
        y = self.out_mean + self.out_std * self.mlp((q - self.in_mean) / self.in_std)
        return z_prev + y if self.residual else y


# ---------------------------------------------------------------------------
# save / load
# ---------------------------------------------------------------------------
def save_module(path: str | os.PathLike, module: nn.Module, extra: dict | None = None) -> None:
    """Atomically save ``{"hparams", "state_dict", "extra"}`` (temp file + os.replace)."""
    blob = {"kind": type(module).__name__, "hparams": module.hparams, "state_dict": module.state_dict(), "extra": extra or {}}
    _atomic_save(blob, path)


def _atomic_save(obj, path) -> None:
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _load_blob(path, kind):
    blob = torch.load(os.fspath(path), map_location="cpu", weights_only=True)
    if blob.get("kind") != kind:
        raise ValueError(f"{path}: holds a {blob.get('kind')!r}, expected {kind!r}")
    return blob


def load_autoencoder(path, device="cpu") -> Autoencoder:
    """Load an autoencoder written by :func:`save_module` (eval mode)."""
    blob = _load_blob(path, "Autoencoder")
    h = blob["hparams"]
    model = Autoencoder(h["input_dim"], h["latent_dim"], h["widths"], h["pca_dim"])
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


def load_integrator(path, device="cpu") -> LatentIntegrator:
    """Load an integrator written by :func:`save_module` (eval mode)."""
    blob = _load_blob(path, "LatentIntegrator")
    h = blob["hparams"]
    model = LatentIntegrator(h["latent_dim"], h["bc_dim"], h["widths"], h["residual"])
    model.load_state_dict(blob["state_dict"])
    return model.to(resolve_device(device)).eval()


# ---------------------------------------------------------------------------
# encode / decode through the autoencoder, losses
# ---------------------------------------------------------------------------
def encode_positions(ae: Autoencoder, coords: RelativeCoordinates, x: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
    """Positions x (..., n, 3), xD (..., m, 3) -> latents (..., r) (float32, no grad)."""
    dev = ae.pca_in.weight.device
    with torch.no_grad():
        u = coords.encode(x.to(dev, torch.float64), xD.to(dev, torch.float64))
        return ae.encode(u.to(torch.float32))


def decode_latents(ae: Autoencoder, coords: RelativeCoordinates, z: torch.Tensor, xD: torch.Tensor) -> torch.Tensor:
    """Latents z (..., r), xD (..., m, 3) -> float64 positions (..., n, 3).

    The network runs in its own dtype; its output is cast to float64 before
    the relative coordinates are undone, so energies are evaluated in float64.
    """
    u = ae.decode(z).to(torch.float64)
    return coords.decode(u, xD.to(u.device, torch.float64))


def balancing_weights(x_prev: torch.Tensor, x_prev2: torch.Tensor, dt: float, eps: float = 1e-2) -> torch.Tensor:
    """Data-balancing weights 1 / max(|v_{t-1}|, eps) of paper Eq. 6.

    v_{t-1} = (1/N) sum_j (x_{t-1}^j - x_{t-2}^j) / dt is the mean full-space
    velocity (a 3-vector) of the previous step.  ``eps`` [m/s] keeps the weight
    finite for samples at rest (v = 0), capping it at 1/eps.

    x_prev, x_prev2 : (B, n, 3) -> (B,)
    """
    v = ((x_prev - x_prev2) / dt).mean(-2)
    return 1.0 / torch.linalg.vector_norm(v, dim=-1).clamp_min(eps)


BATCH_KEYS = ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2", "xD", "xD_prev", "xD_prev2")


def integrator_loss(
    integrator: Callable,
    ae: Autoencoder,
    coords: RelativeCoordinates,
    potential,
    batch: dict,
    mode: str = "self_supervised",
    noise_scale: float = 0.1,
    balancing: bool = True,
    use_penalty: bool | None = None,
    balancing_eps: float = 1e-2,
    generator: torch.Generator | None = None,
    supervised_weight: float = 0.0,
):
    """Loss of one minibatch of triplets.

    Self-supervised (paper Eq. 4): the predicted latent is decoded (with the
    frame-t Dirichlet positions) and the loss is the incremental potential
    ``potential(x_t, x_{t-1}, x_{t-2}, targets=xD_t, penalty=use_penalty)``
    where x_{t-1}, x_{t-2} are the *decoded* input latents.  Supervised: the
    squared L2 distance ``|z_pred - z_t|^2`` to the ground-truth latent.

    Training noise (Eq. 5, ``noise_scale > 0``): the batch is doubled with
    copies whose z_{t-1}, z_{t-2} carry uniform noise in ``[-a, a]``,
    ``a = noise_scale * std`` (per latent dimension, over this batch, separately
    for z_{t-1} and z_{t-2}); BCs, Dirichlet targets (and, in supervised mode,
    the target z_t) unchanged.

    Data balancing (Eq. 6, ``balancing=True``): each sample's loss is
    multiplied by :func:`balancing_weights` of its decoded x_{t-1}, x_{t-2}
    (the perturbed ones for perturbed samples).

    Supervision (``supervised_weight`` w > 0, self-supervised mode only; not in
    the paper): the loss gains ``w * mean_b |(z_pred_b - z_b) / sigma|^2`` over
    the unperturbed samples, sigma the integrator's output scale ``out_std``
    (the spread of the training increments; 1 for a callable without one).
    The incremental potential minimised in a small latent space is not the
    full-space dynamics projected into it; the term pulls the integrator
    towards the latter where the training data show it.

    Parameters
    ----------
    integrator : maps (z_prev, z_prev2, p, p_prev, p_prev2) -> z (B, r).
    ae : autoencoder (frozen, eval mode expected); coords : RelativeCoordinates.
    potential : IncrementalPotential (its ``dt`` is used for balancing).
    batch : dict of tensors, B rows each: ``z_prev, z_prev2`` (B, r),
        ``p, p_prev, p_prev2`` (B, k), ``xD, xD_prev, xD_prev2`` (B, m, 3),
        and ``z`` (B, r) ground truth (needed for ``mode="supervised"``).
    use_penalty : Dirichlet penalty in the potential; ``None`` -> on unless
        ``coords.hard_dirichlet`` (rods: roots re-applied exactly on decode).
    generator : CPU generator for the noise.

    Returns
    -------
    loss : scalar, mean over the (possibly doubled) batch of weight * per-sample loss.
    info : dict with ``per_sample`` (unweighted per-sample losses, (B',)),
        ``weights`` (B',), ``count`` B', ``prediction`` (B', r) (all detached).
    """
    if mode not in ("self_supervised", "supervised"):
        raise ValueError(f"mode must be 'self_supervised' or 'supervised', got {mode!r}")
    if supervised_weight < 0 or (supervised_weight > 0 and mode != "self_supervised"):
        raise ValueError(f"supervised_weight must be >= 0 and is for the self-supervised loss; got {supervised_weight} with mode {mode!r}")
    if use_penalty is None:
        use_penalty = not coords.hard_dirichlet
    clean = batch["z_prev"].shape[0]
    z1, z2 = batch["z_prev"], batch["z_prev2"]
    p, p1, p2 = batch["p"], batch["p_prev"], batch["p_prev2"]
    xD, xD1, xD2 = batch["xD"], batch["xD_prev"], batch["xD_prev2"]
    zt = batch.get("z")
    if noise_scale and noise_scale > 0:
        def noisy(z):
            a = noise_scale * z.std(0, unbiased=False)
            r = torch.rand(z.shape, generator=generator, dtype=z.dtype).to(z.device)
            return z + (2.0 * r - 1.0) * a
        z1n, z2n = noisy(z1), noisy(z2)
        z1, z2 = torch.cat([z1, z1n]), torch.cat([z2, z2n])
        p, p1, p2 = (torch.cat([a, a]) for a in (p, p1, p2))
        xD, xD1, xD2 = (torch.cat([a, a]) for a in (xD, xD1, xD2))
        if zt is not None:
            zt = torch.cat([zt, zt])
    count = z1.shape[0]
    pred = integrator(z1, z2, p, p1, p2)

    need_prev = mode == "self_supervised" or balancing
    if need_prev:
        with torch.no_grad():  # constants w.r.t. the integrator weights
            x1 = decode_latents(ae, coords, z1, xD1)
            x2 = decode_latents(ae, coords, z2, xD2)
    if mode == "self_supervised":
        x = decode_latents(ae, coords, pred, xD)
        per = potential(x, x1, x2, targets=xD.to(torch.float64), penalty=bool(use_penalty))
    else:
        if zt is None:
            raise ValueError("supervised loss needs the ground-truth latents batch['z']")
        per = ((pred - zt.to(pred)) ** 2).sum(-1).to(torch.float64)
    if balancing:
        w = balancing_weights(x1, x2, float(potential.dt), balancing_eps).to(per)
    else:
        w = torch.ones_like(per)
    loss = (w * per).mean()
    if supervised_weight > 0:
        if zt is None:
            raise ValueError("supervised_weight needs the ground-truth latents batch['z']")
        scale = getattr(integrator, "out_std", None)
        scale = torch.ones_like(pred[0]) if scale is None else scale.to(pred)
        sup = (((pred[:clean] - zt[:clean].to(pred)) / scale) ** 2).sum(-1).mean()
        loss = loss + float(supervised_weight) * sup.to(loss)
    info = {"per_sample": per.detach(), "weights": w.detach(), "count": count, "prediction": pred.detach()}
    return loss, info


# ---------------------------------------------------------------------------
# training the integrator
# ---------------------------------------------------------------------------
def training_fingerprint(cfg: dict, seed: int, hparams: dict, data: dict, ae: nn.Module) -> str:
    """sha256 of what determines an integrator's training: its settings (without the checkpoint
    path and interval, and without ``epochs`` at a constant learning rate, where a longer run
    continues a shorter one exactly), the seed, the architecture, the training triplets and the
    autoencoder's weights.  A checkpoint resumes only a training with the same fingerprint."""
    drop = {"checkpoint_path", "checkpoint_every"} | ({"epochs"} if cfg.get("lr_final") is None else set())
    h = hashlib.sha256(json.dumps({"cfg": {k: v for k, v in cfg.items() if k not in drop}, "seed": seed, "hparams": hparams}, sort_keys=True, default=str).encode())
    for name, t in [*sorted(data.items()), *ae.state_dict().items()]:
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


def build_triplets(ae: Autoencoder, coords: RelativeCoordinates, sequences: Sequence[dict]) -> dict:
    """Ground-truth training triplets of all sequences.

    Each sequence dict holds ``positions`` (T, n, 3), ``dirichlet_positions``
    (T, m, 3) and optionally ``bc`` (T, k) (absent -> k = 0).  Latents are the
    frozen autoencoder's encodings.  Returns a dict with the keys of
    :data:`BATCH_KEYS`, N = sum_s (T_s - 2) rows each (latents/BCs float32,
    Dirichlet positions float64, on the autoencoder's device).
    """
    parts: dict[str, list] = {k: [] for k in BATCH_KEYS}
    dev = ae.pca_in.weight.device
    for s in sequences:
        x = torch.as_tensor(s["positions"]).to(torch.float64)
        xD = torch.as_tensor(s["dirichlet_positions"]).to(torch.float64)
        T = x.shape[0]
        bc = s.get("bc")
        bc = torch.zeros(T, 0) if bc is None else torch.as_tensor(bc).reshape(T, -1)
        bc = bc.to(dev, torch.float32)
        if T < 3:
            continue
        z = encode_positions(ae, coords, x, xD)
        xD = xD.to(dev)
        for key, arr in (("z", z), ("p", bc), ("xD", xD)):
            parts[key].append(arr[2:])
            parts[key + "_prev"].append(arr[1:-1])
            parts[key + "_prev2"].append(arr[:-2])
    if not parts["z"]:
        raise ValueError("no training triplets: every sequence needs at least 3 frames")
    return {k: torch.cat(v) for k, v in parts.items()}


def _move_potential(potential, device: torch.device):
    """A copy of the potential with every tensor attribute on ``device``."""
    if potential.masses.device == device:
        return potential
    if hasattr(potential, "to"):
        return potential.to(device)

    def moved(obj):
        new = copy.copy(obj)
        for k, v in vars(obj).items():
            if torch.is_tensor(v):
                setattr(new, k, v.to(device))
        return new

    pot = moved(potential)
    if hasattr(pot, "terms"):
        pot.terms = [moved(t) for t in potential.terms]
    return pot


def fit_integrator(
    ae: Autoencoder,
    coords: RelativeCoordinates,
    potential,
    sequences: Sequence[dict],
    config: dict | None = None,
    seed: int = 0,
    device="cpu",
    progress: bool = False,
    checkpoint_path: str | os.PathLike | None = None,
    compiled: bool = True,
):
    """Train a :class:`LatentIntegrator` on ground-truth triplets.

    Parameters
    ----------
    ae : trained autoencoder (a frozen, eval-mode copy is used).
    coords : RelativeCoordinates of the scene.
    potential : IncrementalPotential of the scene (the self-supervised loss).
    sequences : training sequences (see :func:`build_triplets`).
    config : keys of :data:`INTEGRATOR_DEFAULTS`: widths, epochs, lr,
        lr_final (cosine decay of the learning rate to it; None: constant), batch_size, mode ('self_supervised' | 'supervised'), noise_scale,
        supervised_weight, balancing, balancing_eps, use_penalty, residual, checkpoint_path,
        checkpoint_every.
    seed : seeds weight init, minibatch order and the training noise.
    checkpoint_path : overrides ``config['checkpoint_path']``.  When set, the
        integrator, optimiser, RNG state and history are saved every
        ``checkpoint_every`` epochs (and after the last) via a temp file and
        ``os.replace``; if the file exists at start and belongs to this
        training (:func:`training_fingerprint`: same settings, seed,
        architecture, training triplets and autoencoder; a run with more
        epochs may extend a shorter one at a constant learning rate), training
        resumes from it, else it starts over (logged) and overwrites it.  On
        CPU a resumed run is bitwise identical to an uninterrupted one.
    compiled : on the CPU, the loss's elastic energy runs the simulator's compiled
        kernels (``energy.kernels.with_compiled_elastic``: the same formulas, 5-8x
        faster than the batched PyTorch energy under autograd); False: the terms'
        PyTorch energies.

    Returns
    -------
    integrator : trained, eval mode, on ``device``.
    history : ``loss`` (per-epoch mean weighted training loss), ``latent_mse``
        (per-epoch mean |z_pred - z_t|^2 / r on the clean half of each
        batch), ``start_epoch`` (0, or the epoch resumed from), ``n_triplets``.

    Raises
    ------
    TrainingDiverged : a non-finite loss or gradient; the checkpoint on disk
        (if any) is the last good one.
    """
    cfg = _merge(INTEGRATOR_DEFAULTS, config, "fit_integrator")
    if checkpoint_path is not None:
        cfg["checkpoint_path"] = checkpoint_path
    if cfg["mode"] not in ("self_supervised", "supervised"):
        raise ValueError(f"mode must be 'self_supervised' or 'supervised', got {cfg['mode']!r}")
    device = resolve_device(device)
    ae_f = copy.deepcopy(ae).to(device).eval()
    ae_f.requires_grad_(False)
    pot = _move_potential(potential, device)
    if compiled and device.type == "cpu":
        pot = with_compiled_elastic(pot)
    data = build_triplets(ae_f, coords, sequences)
    N = data["z"].shape[0]
    r, k = data["z"].shape[1], data["p"].shape[1]

    fork = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=fork):
        torch.manual_seed(seed)
        integ = LatentIntegrator(r, k, cfg["widths"], residual=bool(cfg["residual"]))
    integ.fit_normalization(*(data[key].cpu() for key in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")))
    integ = integ.to(device)
    opt = torch.optim.Adam(integ.parameters(), lr=float(cfg["lr"]))
    gen = torch.Generator().manual_seed(seed)
    history: dict[str, Any] = {"loss": [], "latent_mse": [], "start_epoch": 0, "n_triplets": N}
    start = 0

    ckpt = cfg["checkpoint_path"]
    fingerprint = training_fingerprint(cfg, seed, integ.hparams, data, ae_f)
    state = None
    if ckpt is not None and os.path.exists(ckpt):
        state = torch.load(os.fspath(ckpt), map_location="cpu", weights_only=True)
        if state.get("fingerprint") != fingerprint or int(state["epoch"]) > int(cfg["epochs"]):
            log.warning("checkpoint %s belongs to another training (settings, seed, architecture, data or a longer run): starting over", ckpt)
            state = None
    if state is not None:
        integ.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        history["loss"] = list(state["history"]["loss"])
        history["latent_mse"] = list(state["history"]["latent_mse"])
        start = int(state["epoch"])
        history["start_epoch"] = start

    def save(epoch_done: int) -> None:
        _atomic_save(
            {
                "epoch": epoch_done,
                "fingerprint": fingerprint,
                "seed": seed,
                "hparams": integ.hparams,
                "model": integ.state_dict(),
                "optimizer": opt.state_dict(),
                "generator": gen.get_state(),
                "history": {"loss": history["loss"], "latent_mse": history["latent_mse"]},
            },
            ckpt,
        )

    epochs, every = int(cfg["epochs"]), max(1, int(cfg["checkpoint_every"]))
    bar = tqdm(range(start, epochs), desc="integrator", disable=not progress, leave=False)
    for epoch in bar:
        if cfg["lr_final"] is not None:  # cosine decay, a function of the epoch alone (resumes exactly)
            lr0, lr1 = float(cfg["lr"]), float(cfg["lr_final"])
            for group in opt.param_groups:
                group["lr"] = lr1 + 0.5 * (lr0 - lr1) * (1.0 + math.cos(math.pi * epoch / epochs))
        integ.train()
        tot, mse, cnt = 0.0, 0.0, 0
        for b, idx in enumerate(_batches(N, int(cfg["batch_size"]), gen)):
            idx = idx.to(device)
            batch = {key: val[idx] for key, val in data.items()}
            loss, info = integrator_loss(
                integ, ae_f, coords, pot, batch,
                mode=cfg["mode"], noise_scale=float(cfg["noise_scale"]), balancing=bool(cfg["balancing"]),
                use_penalty=cfg["use_penalty"], balancing_eps=float(cfg["balancing_eps"]), generator=gen,
                supervised_weight=float(cfg["supervised_weight"]),
            )
            if not torch.isfinite(loss):
                raise TrainingDiverged(epoch + 1, b)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if any(q.grad is not None and not torch.isfinite(q.grad).all() for q in integ.parameters()):
                raise TrainingDiverged(epoch + 1, b, what="gradient")
            opt.step()
            nb = idx.numel()
            tot += float(loss.detach()) * nb
            mse += float(((info["prediction"][:nb] - batch["z"]) ** 2).mean()) * nb
            cnt += nb
        history["loss"].append(tot / cnt)
        history["latent_mse"].append(mse / cnt)
        bar.set_postfix(loss=f"{history['loss'][-1]:.4e}")
        if ckpt is not None and ((epoch + 1) % every == 0 or epoch + 1 == epochs):
            save(epoch + 1)
    integ.eval()
    return integ, history


# ---------------------------------------------------------------------------
# inference
# ---------------------------------------------------------------------------
@torch.no_grad()
def rollout(
    integrator: Callable,
    ae: Autoencoder,
    coords: RelativeCoordinates,
    z0: torch.Tensor,
    z1: torch.Tensor,
    bc: torch.Tensor,
    dirichlet_positions: torch.Tensor,
    potential=None,
    max_extent: float | None = None,
    rest_positions: torch.Tensor | None = None,
) -> dict:
    """Autoregressive latent rollout from the first two frames' latents.

    Frame t >= 2 is ``integrator(z_{t-1}, z_{t-2}, p_t, p_{t-1}, p_{t-2})``;
    only the boundary-condition history ``bc`` is fed in.  All latents are
    then decoded with the prescribed Dirichlet positions of their frame.

    Divergence: the first frame whose latent is NaN/inf, whose decoded
    positions are non-finite, or (when ``max_extent`` is given) whose decoded
    bounding-box diagonal exceeds ``max_extent`` times the reference diagonal
    (of ``rest_positions`` (n, 3) if given, else of decoded frame 0).  Rolling
    out stops there; that frame keeps its computed values and all later
    frames are NaN.

    Parameters
    ----------
    z0, z1 : (r,) latents of frames 0 and 1.
    bc : (T, k) boundary-condition parameters p_t.
    dirichlet_positions : (T, m, 3) prescribed Dirichlet positions.
    potential : optional IncrementalPotential; if given, per-frame
        ``kinetic_energy`` and ``incremental_potential`` are returned too.

    Returns
    -------
    dict with ``latents`` (T, r) float32, ``positions`` (T, n, 3) float64 (CPU),
    ``diverged_frame`` (int, -1 if stable) and, with ``potential``,
    ``kinetic_energy`` (T,) (NaN at frame 0) and ``incremental_potential``
    (T,) (NaN at frames 0, 1).
    """
    z0, z1 = torch.as_tensor(z0), torch.as_tensor(z1)
    bc, dirichlet_positions = torch.as_tensor(bc), torch.as_tensor(dirichlet_positions)
    T = int(bc.shape[0])
    if dirichlet_positions.shape[0] != T:
        raise ValueError("bc and dirichlet_positions must have the same number of frames")
    mods = [m for m in (integrator, ae) if isinstance(m, nn.Module)]
    was = [m.training for m in mods]
    for m in mods:
        m.eval()
    try:
        dev = ae.pca_in.weight.device
        bcd = bc.reshape(T, -1).to(dev, torch.float32)
        Z = torch.full((T, z0.shape[-1]), float("nan"), dtype=torch.float32, device=dev)
        Z[0], Z[1] = z0.to(dev, torch.float32), z1.to(dev, torch.float32)
        diverged = -1
        last = min(T, 2) - 1
        for t in range(2, T):
            zt = integrator(Z[t - 1 : t], Z[t - 2 : t - 1], bcd[t : t + 1], bcd[t - 1 : t], bcd[t - 2 : t - 1])[0]
            Z[t] = zt
            last = t
            if not torch.isfinite(zt).all():
                diverged = t
                break
        X = torch.full((T, coords.n, 3), float("nan"), dtype=torch.float64)
        X[: last + 1] = decode_latents(ae, coords, Z[: last + 1], dirichlet_positions[: last + 1].to(dev)).cpu()
    finally:
        for m, w in zip(mods, was):
            m.train(w)

    def diag(x):
        return torch.linalg.vector_norm(x.amax(-2) - x.amin(-2), dim=-1)

    bad = ~torch.isfinite(X[: last + 1]).all(-1).all(-1)
    if max_extent is not None:
        ref = diag(torch.as_tensor(rest_positions, dtype=torch.float64)) if rest_positions is not None else diag(X[0])
        bad |= diag(X[: last + 1]) > float(max_extent) * float(ref)
    hits = torch.nonzero(bad).reshape(-1)
    if hits.numel():
        diverged = int(hits[0]) if diverged < 0 else min(diverged, int(hits[0]))
    Z = Z.cpu()
    if diverged >= 0:
        Z[diverged + 1 :] = float("nan")
        X[diverged + 1 :] = float("nan")
    out = {"latents": Z, "positions": X, "diverged_frame": int(diverged)}
    if potential is not None:
        ke = torch.full((T,), float("nan"), dtype=torch.float64)
        ip = torch.full((T,), float("nan"), dtype=torch.float64)
        pot = _move_potential(potential, torch.device("cpu"))
        if T > 1:
            ke[1:] = pot.kinetic_energy(X[1:], X[:-1])
        if T > 2:
            xD = dirichlet_positions.to("cpu", torch.float64)
            ip[2:] = pot(X[2:], X[1:-1], X[:-2], targets=xD[2:], penalty=not coords.hard_dirichlet)
        out["kinetic_energy"] = ke
        out["incremental_potential"] = ip
    return out
