r"""The baselines of the Neural Modes studies (Wang et al. 2024, Sec. 4.1-4.4): supervised and data-free subspaces.

- L2 supervised: the Neural Modes network trained on the grid ground truth with the loss
  mean ||n(z) - x_gt(z)||^2 (the paper's "same architecture, loss of PCA+AE").
- PCA+AE (Fulton et al. 2019) on random / grid ground truth: the project's PCA-initialised MLP
  autoencoder (``latent.fit_autoencoder``) on the displacements x - X, evaluated along its training;
  it is evaluated by reconstructing ground truth (encode then decode), as its latent is not z.
- Sharp et al. 2023 (data-free): x = X + f(z), f an MLP (same widths), loss
  E(X + f(z)) + w_iso mean_pairs (|f(z) - f(z')|_M / (c |z - z'|) - 1)^2, z uniform in the box;
  only for the mode-collapse study (Fig. 4, :func:`mode_collapse`).
"""

from __future__ import annotations

import copy
import logging
import time

import numpy as np
import torch
from torch import nn

from latentsim.latent import fit_autoencoder
from latentsim.neural_modes.directions import direction_correlation, latent_directions
from latentsim.neural_modes.network import NeuralModes
from latentsim.physics.kernels import with_compiled_elastic

log = logging.getLogger(__name__)

__all__ = ["SHARP", "DataFree", "autoencoder_along_training", "mode_collapse", "train_data_free", "train_l2_supervised"]

SHARP = "Sharp et al. 2023"


def train_l2_supervised(model: NeuralModes, z, x_gt, epochs=200, lbfgs_max_iter=20, callback=None):
    """The Neural Modes network trained on ground truth with the L2 loss mean ||n(z) - x_gt||^2.

    One epoch is one L-BFGS step (up to ``lbfgs_max_iter`` iterations) on the whole set, as for
    Neural Modes; ``callback(epoch, model)`` runs after each.  Returns the per-epoch losses.
    """
    z = torch.as_tensor(z, dtype=torch.float64)
    target = torch.as_tensor(x_gt, dtype=torch.float64)
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=lbfgs_max_iter, line_search_fn="strong_wolfe")
    hist = []

    def closure():
        opt.zero_grad()
        loss = ((model(z) - target) ** 2).sum((-1, -2)).mean()
        loss.backward()
        return loss

    for epoch in range(epochs):
        hist.append(float(opt.step(closure).detach()))
        if callback is not None:
            callback(epoch, model)
    return hist


class DataFree(nn.Module):
    """Sharp et al. 2023: x = X + f(z) - f(0), f an MLP with GELU (the subspace passes through the rest state)."""

    def __init__(self, rest_positions, m, widths, fixed_dofs=None):
        super().__init__()
        X = torch.as_tensor(np.asarray(rest_positions), dtype=torch.float64)
        self.n, self.m = X.shape[0], m
        self.register_buffer("X", X.reshape(-1))
        mask = torch.ones(3 * self.n, dtype=torch.float64)
        if fixed_dofs is not None and len(fixed_dofs):
            mask[torch.as_tensor(np.asarray(fixed_dofs), dtype=torch.long)] = 0.0
        self.register_buffer("mask", mask)
        layers, prev = [], m
        for w in widths:
            layers += [nn.Linear(prev, int(w), dtype=torch.float64), nn.GELU()]
            prev = int(w)
        self.mlp = nn.Sequential(*layers, nn.Linear(prev, 3 * self.n, dtype=torch.float64))

    def forward(self, z):
        u = (self.mlp(z) - self.mlp(z.new_zeros(self.m))) * self.mask
        return (self.X + u).reshape(z.shape[:-1] + (self.n, 3))


def train_data_free(model: DataFree, potential, box, scale, w_iso=1.0, epochs=100, batch=512, lbfgs_max_iter=20, seed=0):
    """Energy + isometry regulariser (Sharp et al. 2023); ``scale`` c is the target |dx|_M per |dz|.

    The isometry term is weighted by the energy of a unit-z linear displacement
    scale (``w_iso`` times the mean energy at the start) so that neither term dominates by units.
    The energy runs the compiled kernels (``physics.kernels.with_compiled_elastic``).
    """
    potential = with_compiled_elastic(potential)
    gen = torch.Generator().manual_seed(seed)
    m3 = potential.masses.repeat_interleave(3)
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=lbfgs_max_iter, line_search_fn="strong_wolfe")
    weight = None
    hist = []
    for _ in range(epochs):
        z1 = (torch.rand(batch, model.m, generator=gen, dtype=torch.float64) * 2 - 1) * box
        z2 = (torch.rand(batch, model.m, generator=gen, dtype=torch.float64) * 2 - 1) * box

        def closure(z1=z1, z2=z2):
            nonlocal weight
            opt.zero_grad()
            x1, x2 = model(z1), model(z2)
            energy = 0.5 * (potential.elastic(x1).mean() + potential.elastic(x2).mean())
            d = ((x1 - x2).reshape(batch, -1) ** 2 * m3).sum(-1).sqrt()
            iso = ((d / (scale * (z1 - z2).norm(dim=-1)) - 1.0) ** 2).mean()
            if weight is None:
                weight = w_iso * max(float(energy.detach()), 1e-12) + w_iso
            loss = energy + weight * iso
            loss.backward()
            return loss

        hist.append(float(opt.step(closure).detach()))
    return hist


def autoencoder_along_training(U, config: dict, epochs, seed: int = 0, progress: bool = False):
    """PCA+AE (``latent.fit_autoencoder``) after each of ``epochs``: yields (epoch, model (float64, eval), seconds).

    One run of max(epochs) epochs with ``snapshots``: each model is the one ``fit_autoencoder`` would
    return had it stopped at that epoch (a model above its PCA initialisation's training error is that
    initialisation); ``seconds`` is the training time up to it.
    """
    epochs = [int(k) for k in epochs]
    ae, hist = fit_autoencoder(U, {**config, "epochs": max(epochs)}, seed=seed, progress=progress, snapshots=epochs)
    for k in epochs:
        model = copy.deepcopy(ae)
        model.load_state_dict(hist["snapshots"][k]["state"])
        yield k, model.double().eval(), hist["snapshots"][k]["seconds"]


def mode_collapse(potential, rest_positions, modes, models: dict, widths, box, sharp: dict, fixed_dofs=None, seed: int = 0) -> dict:
    """Correlation matrices (and eigenvalues) of the latent directions at the origin of each of
    ``models`` {label: z -> positions}, and of Sharp et al. 2023 trained here with the same widths,
    latent dimension, box and fixed DoFs (``sharp``: epochs, batch_size, w_iso).

    Returns {label: {"matrix" (m,m), "eigenvalues" (m,), "train_seconds"}}; Sharp et al. under :data:`SHARP`.
    """
    masses = potential.masses.numpy()
    m = np.asarray(modes).shape[1]
    out = {label: dict(zip(("matrix", "eigenvalues"), direction_correlation(latent_directions(f, m).numpy(), masses))) for label, f in models.items()}
    torch.manual_seed(seed)
    model = DataFree(rest_positions, m, widths, fixed_dofs=fixed_dofs)
    scale = float(np.sqrt((np.repeat(masses, 3)[:, None] * np.asarray(modes) ** 2).sum(0)).mean())
    t0 = time.perf_counter()
    train_data_free(model, potential, box, scale, sharp["w_iso"], sharp["epochs"], sharp["batch_size"], seed=seed)
    C, w = direction_correlation(latent_directions(model, m).numpy(), masses)
    out[SHARP] = {"matrix": C, "eigenvalues": w, "train_seconds": time.perf_counter() - t0}
    log.info("%s: %d epochs in %.0f s; correlation eigenvalues %s", SHARP, sharp["epochs"], out[SHARP]["train_seconds"], np.round(w, 3))
    return out
