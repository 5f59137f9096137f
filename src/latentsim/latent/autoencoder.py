"""The autoencoder of Li et al. 2025 (sec. 3.2, Eq. 2): a symmetric MLP ResNet whose outer
linear layers are initialised from PCA (Fulton et al. 2019).

The PCA path *is* the skip path: an untrained, PCA-initialised autoencoder is exactly PCA with
``latent_dim`` components; the residual MLP branches (zero-initialised output layers) learn the
nonlinear correction.  Holds :func:`pca_basis`, :class:`Autoencoder`, its training
:func:`fit_autoencoder` (reconstruction MSE, Eq. 2) and :func:`encode_positions` /
:func:`decode_latents` (positions <-> latents through the relative coordinates).  The network
runs in float32; decoded positions are cast to float64.
"""

from __future__ import annotations

import copy
import time
from typing import Sequence

import torch
from torch import nn
from tqdm import tqdm

from latentsim.config import with_defaults
from latentsim.latent.base import LossHealth, TrainingDiverged, minibatches, resolve_device
from latentsim.latent.coordinates import RelativeCoordinates


# a PCA direction counts when its std exceeds this fraction of the first's (eigenvalue 1e-12)
RANK_TOL = 1e-6


class LatentRankError(ValueError):
    """The training data have fewer independent directions than the latent dimension."""


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

    def __init__(self, input_dim: int, latent_dim: int, widths: Sequence[int], pca_dim: int | None = None):
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
        """Initialise the outer layers from PCA of U (N, d); returns PCA stats: ``scale`` s,
        ``explained_std`` (pca_dim,), ``rank`` (directions whose std exceeds ``RANK_TOL`` of the
        first's, the cut of :func:`pca_basis`) and ``frames`` (the rows the PCA saw)."""
        mean, V, std = pca_basis(U, self.pca_dim, max_samples=max_samples, seed=seed)
        rank = int((std > RANK_TOL * std[0]).sum()) if float(std[0]) > 0 else 0
        frames = U.shape[0] if max_samples is None else min(U.shape[0], max_samples)
        s = float(std[0]) if float(std[0]) > 0 else 1.0
        W = V / s
        dev, dt = self.pca_in.weight.device, self.pca_in.weight.dtype
        self.pca_in.weight.copy_(W.to(dev, dt))
        self.pca_in.bias.copy_((-(W @ mean)).to(dev, dt))
        self.pca_out.weight.copy_((V.T * s).to(dev, dt))
        self.pca_out.bias.copy_(mean.to(dev, dt))
        return {"scale": s, "explained_std": std.tolist(), "rank": rank, "frames": frames}

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


def fit_autoencoder(U: torch.Tensor, config: dict | None = None, seed: int = 0, device="cpu", progress: bool = False, snapshots=(), label: str = ""):
    """Train an :class:`Autoencoder` on encoded frames (paper Eq. 2).

    Parameters
    ----------
    U : (N, d) encoded training frames (output of :meth:`RelativeCoordinates.encode`).
    config : settings of the config schema's ``autoencoder`` (latent_dim, widths, pca_dim (0: the
        first width), epochs, lr, batch_size, train_pca, pca_samples, and the health rule's
        divergence_factor and max_loss); those absent take the
        schema's defaults (:func:`latentsim.config.with_defaults`); ``coordinates`` is not read here.
    seed : seeds weight init and minibatch order (bitwise reproducible on CPU).
    device : anything :func:`resolve_device` accepts.
    progress : show a tqdm bar over epochs.
    snapshots : epochs (0 = the PCA initialisation) after which to keep the weights this call
        would have returned had it stopped there (learning curves, early stopping).
    label : what trains, for messages (e.g. "scene tiny_rods").

    Returns
    -------
    model : the trained autoencoder in eval mode, on ``device``.
    history : dict with ``loss`` (per-epoch mean of the normalised training
        MSE, i.e. MSE of u / s), ``mse_initial`` (MSE per coordinate of the
        PCA-initialised model, in data units^2), ``mse_final`` (of the model
        returned), ``kept`` ('trained', or 'pca' when training ended worse than
        the PCA initialisation, whose weights are then returned), ``pca_scale``
        s, ``pca_dim``, ``epochs``; with ``snapshots``, ``snapshots`` {epoch: {"state"
        (state dict, on the CPU), "mse", "kept", "seconds" (training time so far)}};
        ``loss_start``, ``loss_scale`` (:class:`~latentsim.latent.base.LossHealth`).

    Raises
    ------
    LatentRankError
        U has fewer independent directions (PCA std above ``RANK_TOL`` of the first) than
        ``latent_dim``: the message gives the frames, the rank and the PCA spectrum.
    TrainingDiverged
        Naming ``label``, the epoch and the loss, when a loss is not finite or an epoch's mean
        loss is far above the PCA start's (:class:`~latentsim.latent.base.LossHealth` with a least
        scale of 0.01, the normalised loss being dimensionless) or above ``max_loss``. A milder
        worsening is no divergence: the PCA start is then returned (``kept``).
    """
    cfg = with_defaults("autoencoder", config, "fit_autoencoder")
    device = resolve_device(device)
    U = torch.as_tensor(U).detach()
    if U.ndim != 2:
        raise ValueError(f"U must be (N, d), got shape {tuple(U.shape)}")
    epochs = int(cfg["epochs"])
    wanted = {int(k) for k in snapshots}
    model, s = _pca_initialised(U, cfg, seed, device)
    Ud = U.to(device=device, dtype=torch.float32)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], lr=float(cfg["lr"]))
    history = {"loss": [], "mse_initial": reconstruction_mse(model, Ud), "pca_scale": s, "pca_dim": model.pca_dim, "epochs": epochs}
    pca_state = copy.deepcopy(model.state_dict())
    if any(k < 0 or k > epochs for k in wanted):
        raise ValueError(f"snapshots {sorted(wanted)} outside epochs 0..{cfg['epochs']}")
    t_start = time.perf_counter()
    if 0 in wanted:
        _snapshot(model, Ud, history, pca_state, 0, t_start)
    health = LossHealth(cfg["divergence_factor"], cfg["max_loss"], floor=0.01, key="autoencoder")
    bar = tqdm(range(epochs), desc="autoencoder", disable=not progress, leave=False)
    for epoch in bar:
        try:
            loss = _autoencoder_epoch(model, opt, Ud, s, int(cfg["batch_size"]), gen, epoch, health)
            health.check(epoch, loss)
        except TrainingDiverged as e:
            e.label = e.label or label
            raise
        history["loss"].append(loss)
        bar.set_postfix(loss=f"{history['loss'][-1]:.3e}")
        if epoch + 1 in wanted:
            _snapshot(model, Ud, history, pca_state, epoch + 1, t_start)
    history.update(health.state())
    history["mse_final"] = reconstruction_mse(model, Ud)
    # Never return a model worse than its own PCA initialisation (small data sets whose PCA is
    # already near exact can get worse under SGD noise): keep the PCA start instead, and say so.
    history["kept"] = "trained"
    if not history["mse_final"] <= history["mse_initial"]:
        model.load_state_dict(pca_state)
        history["kept"] = "pca"
        history["mse_final"] = reconstruction_mse(model, Ud)
    model.eval()
    return model, history


def _pca_initialised(U: torch.Tensor, cfg: dict, seed: int, device: torch.device) -> tuple[Autoencoder, float]:
    """The untrained autoencoder of settings ``cfg`` (weights seeded by ``seed``), its outer layers
    set from PCA of U (N, d) and trainable iff ``train_pca``; and the PCA scale s.  Raises
    :class:`LatentRankError` when U has fewer independent directions than ``latent_dim``."""
    fork = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=fork):
        torch.manual_seed(seed)
        model = Autoencoder(U.shape[1], int(cfg["latent_dim"]), cfg["widths"], cfg["pca_dim"] or None)
        stats = model.init_pca(U, max_samples=cfg["pca_samples"], seed=seed)
    if stats["rank"] < model.latent_dim:
        # the latent coordinates beyond the data's directions would carry nothing, and an
        # integrator trained on them nothing to learn
        n, r = stats["frames"], model.latent_dim
        seen = f"{n} training frames" + (f" (a random {n} of {U.shape[0]}, pca_samples)" if n < U.shape[0] else "")
        ratios = [float(f"{x / stats['explained_std'][0]:.2g}") if stats["explained_std"][0] > 0 else 0.0 for x in stats["explained_std"][:r]]
        raise LatentRankError(
            f"latent_dim {r} is above the rank of the training data: its {seen} have {stats['rank']} independent "
            f"directions (PCA std / the first: {ratios}); use latent_dim <= {stats['rank']}, or train on more frames or more varied motion"
        )
    model = model.to(device)
    for prm in list(model.pca_in.parameters()) + list(model.pca_out.parameters()):
        prm.requires_grad_(bool(cfg["train_pca"]))
    return model, stats["scale"]


@torch.no_grad()
def reconstruction_mse(model: Autoencoder, U: torch.Tensor, chunk: int = 4096) -> float:
    """Mean squared reconstruction error per coordinate of U (N, d), in data units^2 (eval mode,
    float64 sums over chunks of rows)."""
    model.eval()
    N, d = U.shape
    err = 0.0
    for i in range(0, N, chunk):
        r = model(U[i : i + chunk]) - U[i : i + chunk]
        err += float((r.double() ** 2).sum())
    return err / (N * d)


def _autoencoder_epoch(model: Autoencoder, opt, U: torch.Tensor, s: float, batch_size: int, gen: torch.Generator, epoch: int, health: LossHealth | None = None) -> float:
    """One epoch of Adam on the normalised MSE ``|(AE(u) - u) / s|^2`` (Eq. 2); its mean loss.  The
    first minibatch of a training sets ``health``'s start and scale."""
    model.train()
    tot, cnt = 0.0, 0
    for idx in minibatches(U.shape[0], batch_size, gen, min_size=2):
        idx = idx.to(U.device)
        ub = U[idx]
        r2 = ((model(ub) - ub) / s) ** 2
        loss = r2.mean()
        if not torch.isfinite(loss):
            raise TrainingDiverged(epoch + 1)
        if health is not None:
            health.first_batch(float(loss.detach()), r2.detach().mean(-1))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        tot += float(loss.detach()) * idx.numel()
        cnt += idx.numel()
    return tot / max(cnt, 1)


def _snapshot(model: Autoencoder, U: torch.Tensor, history: dict, pca_state: dict, epoch: int, t_start: float) -> None:
    """Keep in ``history["snapshots"][epoch]`` what :func:`fit_autoencoder` returns had it stopped
    here: the PCA start when training made it worse."""
    mse = reconstruction_mse(model, U)
    kept = "trained" if mse <= history["mse_initial"] else "pca"
    state = model.state_dict() if kept == "trained" else pca_state
    history.setdefault("snapshots", {})[epoch] = {
        "state": {k: v.detach().cpu().clone() for k, v in state.items()},
        "mse": mse if kept == "trained" else history["mse_initial"],
        "kept": kept,
        "seconds": time.perf_counter() - t_start,
    }


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

