r"""Self-supervised training of Neural Modes (Wang et al. 2024, Eq. 12-13): the loss, the samples, the optimiser.

Trained by minimising, over samples z drawn uniformly in a box (stochastic) or on a regular grid,

    L = mean_z [ E(X + l + y) + lambda (l^T y)^2 ] + eta ||y(0)||^2,

E the scene's elastic energy only (``IncrementalPotential.elastic``: no inertia, gravity or
Dirichlet penalty).  ``orthogonality='unit'`` uses (l^T y / |l|)^2 instead of the paper's
(l^T y)^2; ``orthogonality='exact'`` builds the constraint into the map instead (see
``network.NeuralModes``), so l^T y = 0 holds to round-off and the loss is the energy alone: the
constrained problem of Eq. 9 itself rather than its penalty, which on the sheet trains to a tenth of
the energy error in the same epochs (the penalty's large lambda makes the loss stiff).
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import torch

from latentsim.config import with_defaults
from latentsim.neural_modes.network import NeuralModes
from latentsim.physics.incremental_potential import IncrementalPotential
from latentsim.physics.kernels import with_compiled_elastic

__all__ = ["make_optimizer", "modal_samples", "neural_modes_loss", "train_neural_modes"]


def neural_modes_loss(model: NeuralModes, potential: IncrementalPotential, z, aux=None, lam=1e8, eta=1e7, orthogonality="paper", metric="euclidean"):
    """Paper Eq. 12-13; returns (loss, parts) with parts = mean energy, mean constraint, origin term.

    ``metric='mass'`` uses l^T M y in place of l^T y (see ``ConstrainedNewton``).
    """
    l = model.linear(z)
    y = model.correction(z, aux)
    x = (model.X + l + y).reshape(z.shape[:-1] + (model.n, 3))
    energy = potential.elastic(x)
    if metric == "mass":
        c = (l * potential.masses.repeat_interleave(3).to(l) * y).sum(-1)
    elif metric == "euclidean":
        c = (l * y).sum(-1)
    else:
        raise ValueError(f"metric '{metric}': use 'euclidean' or 'mass'")
    if orthogonality == "unit":
        c = c / l.norm(dim=-1).clamp_min(1e-12)
    elif orthogonality == "exact":
        if model.exact_orthogonality != metric:
            raise ValueError(f"orthogonality 'exact' needs a NeuralModes built with exact_orthogonality='{metric}' (see from_config)")
    elif orthogonality != "paper":
        raise ValueError(f"orthogonality '{orthogonality}': use 'paper', 'unit' or 'exact'")
    z0 = torch.zeros((1, model.m), dtype=z.dtype)
    a0 = None if aux is None else aux[:1]
    y0 = model.correction(z0, a0)
    origin = (y0 * y0).sum()
    loss = energy.mean() + lam * (c * c).mean() + eta * origin
    return loss, {"energy": energy.mean().detach(), "constraint": (c * c).mean().detach(), "origin": origin.detach()}


def modal_samples(kind: str, m: int, box: float, count: int = 0, resolution: int = 9, generator=None) -> torch.Tensor:
    """Modal coordinates: a regular ``resolution``^m grid over [-box, box]^m, or ``count`` uniform samples."""
    if kind == "grid":
        axis = np.linspace(-box, box, resolution)
        return torch.as_tensor(np.array(list(itertools.product(axis, repeat=m))), dtype=torch.float64)
    if kind in ("stochastic", "uniform"):
        return (torch.rand(count, m, generator=generator, dtype=torch.float64) * 2 - 1) * box
    raise ValueError(f"sampling '{kind}': use 'grid' or 'stochastic'")


def make_optimizer(params, cfg: dict):
    """``cfg['optimizer']``: 'lbfgs' (strong-Wolfe line search, up to ``lbfgs_max_iter`` iterations a step, as the
    paper) or 'adam'; learning rate ``lr``."""
    if cfg["optimizer"] == "lbfgs":
        return torch.optim.LBFGS(params, lr=float(cfg["lr"]), max_iter=int(cfg["lbfgs_max_iter"]), line_search_fn="strong_wolfe")
    if cfg["optimizer"] == "adam":
        return torch.optim.Adam(params, lr=float(cfg["lr"]))  # its step(closure) evaluates the closure once
    raise ValueError(f"optimizer '{cfg['optimizer']}': use 'lbfgs' or 'adam'")


def train_neural_modes(model: NeuralModes, potential: IncrementalPotential, config: dict | None = None, seed: int = 0, callback=None, compiled: bool = True):
    """Train Neural Modes self-supervised (Eq. 13).

    config keys (the config schema's ``neural_modes``; missing ones take its
    defaults): sampling ('grid' | 'stochastic'), grid, batch_size, box, epochs,
    optimizer ('lbfgs' with strong-Wolfe line search, as the paper, or 'adam'),
    lr, lbfgs_max_iter, lam, eta, orthogonality, metric.
    One epoch = one optimiser step (L-BFGS: up to ``lbfgs_max_iter``
    iterations) on one batch; stochastic sampling draws a new batch each epoch.
    ``callback(epoch, model)`` runs after every epoch.  ``compiled``: the loss's
    elastic energy runs the simulator's compiled kernels on the CPU
    (``physics.kernels.with_compiled_elastic``: the same formulas, several times
    faster than the batched PyTorch energy under autograd).

    Returns history: dict of per-epoch lists (loss, energy, constraint, origin) and seconds.
    """
    cfg = with_defaults("neural_modes", config, "train_neural_modes")
    if compiled:
        potential = with_compiled_elastic(potential)
    gen = torch.Generator().manual_seed(seed)
    opt = make_optimizer([p for p in model.parameters() if p.requires_grad], cfg)
    grid = modal_samples("grid", model.m, cfg["box"], resolution=int(cfg["grid"])) if cfg["sampling"] == "grid" else None
    hist = {"loss": [], "energy": [], "constraint": [], "origin": []}
    t0 = time.perf_counter()
    for epoch in range(int(cfg["epochs"])):
        z = grid if grid is not None else modal_samples("stochastic", model.m, cfg["box"], int(cfg["batch_size"]), generator=gen)
        parts = {}

        def closure(z=z, parts=parts):
            opt.zero_grad()
            loss, p = neural_modes_loss(model, potential, z, None, cfg["lam"], cfg["eta"], cfg["orthogonality"], cfg["metric"])
            loss.backward()
            parts.update(p, loss=loss.detach())
            return loss

        opt.step(closure)  # L-BFGS evaluates the closure itself (several times); Adam once before its step
        for key, values in hist.items():
            values.append(float(parts[key]))
        if not np.isfinite(hist["loss"][-1]):
            raise FloatingPointError(f"Neural Modes training diverged at epoch {epoch + 1}")
        if callback is not None:
            callback(epoch, model)
    hist["seconds"] = time.perf_counter() - t0
    return hist
