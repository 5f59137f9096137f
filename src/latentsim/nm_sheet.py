r"""Neural Modes on the square sheet: baselines, metrics and tables (Wang et al. 2024, Sec. 4.1, 4.4).

Methods (all map 3 modal/latent coordinates to the 121-vertex sheet):

- Neural Modes (stoch.) / (grid): self-supervised (``neural_modes.train_neural_modes``),
  z uniform in [-b, b]^3 redrawn every epoch, or the fixed 9^3 grid.
- L2 supervised: the same network, trained on the 9^3 grid ground truth with
  the loss mean ||n(z) - x_gt(z)||^2 (the paper's "same architecture, loss
  of PCA+AE").
- PCA+AE (Fulton et al. 2019) on random / grid ground truth: the project's
  PCA-initialised MLP autoencoder (``latent.fit_autoencoder``) on the
  displacements x - X; evaluated by reconstructing the validation/test
  ground truth (encode then decode), as its latent is not z.
- Sharp et al. 2023 (data-free): x = X + f(z), f an MLP (same widths), loss
  E(X + f(z)) + w_iso mean_pairs (|f(z) - f(z')|_M / (c |z - z'|) - 1)^2,
  z uniform in the box; only for the mode-collapse study (Fig. 4).

Metrics per method on a set of samples (validation 7^3, test 11^3 grids):
elastic energy E and dE = |E - E_gt| (avg, max, std over samples; Table 2);
membrane stress |P|_F per triangle (``ShellMembraneStVK.stress_norm``, the
first Piola-Kirchhoff stress of the StVK membrane; bending moments are not
included), reduced per sample by the area-weighted mean and by the max over
elements, and its error against ground truth (Table 4); nodal forces
F = -dE/dx and ||dF||_1, ||dF||_2 (batch means; Table A1).
"""

from __future__ import annotations

import logging
import time

import numpy as np
import torch
from torch import nn

from . import neural_modes as nm

log = logging.getLogger(__name__)

# Paper numbers (Wang et al. 2024), for the adjacent columns.
PAPER_TABLE2 = {  # method: (val dE_avg, dE_max, dE_std, E_avg, test dE_avg, dE_max, dE_std, E_avg)
    "PCA+AE": (1814, 22225, 2005, 18144, 2259, 27991, 2646, 24007),
    "PCA+AE (grid)": (2188, 36168, 3626, 18088, 2649, 72834, 4664, 23217),
    "L2 Supervised": (1630, 10231, 1148, 18210, 2074, 13750, 1697, 24325),
    "Neural Modes (stoch.)": (376, 1197, 170, 17032, 386, 1154, 183, 22891),
    "Neural Modes (grid)": (199, 754, 118, 16831, 245, 3062, 215, 22730),
}
PAPER_TABLE4 = {  # x1e6: weighted dS_avg, dS_max, dS_std, |S|_avg, max-over-elements dS_avg, dS_max, dS_std, |S|_avg
    "PCA+AE": (25, 138, 17, 251, 67, 431, 49, 520),
    "PCA+AE (grid)": (25, 305, 29, 245, 64, 784, 68, 505),
    "L2 Supervised": (25, 100, 14, 255, 87, 350, 57, 550),
    "Neural Modes (stoch.)": (9, 36, 7, 240, 22, 155, 21, 486),
    "Neural Modes (grid)": (6, 24, 5, 236, 16, 124, 16, 479),
}
PAPER_TABLEA1 = {  # x1e4: ||dF||_1, ||dF||_2, ||F||_1, ||F||_2
    "PCA+AE": (111, 5.95, 279, 24),
    "PCA+AE (grid)": (83, 4.35, 250, 22),
    "L2 Supervised": (125, 6.59, 293, 24),
    "Neural Modes (stoch.)": (31, 0.93, 199, 19),
    "Neural Modes (grid)": (25, 0.74, 193, 19),
}


# --------------------------------------------------------------------------------------------------
# ground truth sets
# --------------------------------------------------------------------------------------------------
def sample_sets(m: int, box: float, train_grid=9, val_grid=7, test_grid=11, random_count=729, seed=0) -> dict:
    """The modal coordinates of every set: train grid, train random, validation and test grids."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "train_grid": nm.modal_samples("grid", m, box, resolution=train_grid).numpy(),
        "train_random": nm.modal_samples("stochastic", m, box, random_count, generator=gen).numpy(),
        "val": nm.modal_samples("grid", m, box, resolution=val_grid).numpy(),
        "test": nm.modal_samples("grid", m, box, resolution=test_grid).numpy(),
    }


def solve_sets(potential, X, modes, rigid, sets: dict, metric="euclidean", max_iter=40) -> dict:
    """Ground truth (Eq. 9) for every set: {name: {z, x (N,n,3), energy, residual, iterations}}."""
    out = {}
    for name, z in sets.items():
        t0 = time.perf_counter()
        x, e, infos = nm.ground_truth(potential, X, modes, z, rigid=rigid, metric=metric, max_iter=max_iter)
        res = np.array([i.residual for i in infos])
        its = np.array([i.iterations for i in infos])
        out[name] = {"z": z, "x": x, "energy": e, "residual": res, "iterations": its}
        log.info("ground truth %s: %d samples in %.0f s, median KKT residual %.1e, iterations %.1f", name, len(z), time.perf_counter() - t0, np.median(res), its.mean())
    return out


# --------------------------------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------------------------------
def train_l2_supervised(model: nm.NeuralModes, z, x_gt, epochs=200, lbfgs_max_iter=20):
    """The Neural Modes network trained on ground truth with the L2 loss mean ||n(z) - x_gt||^2."""
    z = torch.as_tensor(z, dtype=torch.float64)
    target = torch.as_tensor(x_gt, dtype=torch.float64)
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=lbfgs_max_iter, line_search_fn="strong_wolfe")
    hist = []

    def closure():
        opt.zero_grad()
        loss = ((model(z) - target) ** 2).sum((-1, -2)).mean()
        loss.backward()
        return loss

    for _ in range(epochs):
        hist.append(float(opt.step(closure).detach()))
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
    """
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


# --------------------------------------------------------------------------------------------------
# metrics
# --------------------------------------------------------------------------------------------------
def membrane_term(potential):
    for t in potential.terms:
        if hasattr(t, "stress_norm") and hasattr(t, "rest_area"):
            return t
    raise ValueError("no membrane term with stress_norm in this potential")


def metrics(potential, x, x_gt) -> dict:
    """Energy, stress and nodal-force statistics of states x (N,n,3) against ground truth x_gt."""
    x = torch.as_tensor(x, dtype=torch.float64).requires_grad_(True)
    xg = torch.as_tensor(x_gt, dtype=torch.float64).requires_grad_(True)
    E = potential.elastic(x)
    Eg = potential.elastic(xg)
    F = -torch.autograd.grad(E.sum(), x)[0].reshape(len(x), -1)
    Fg = -torch.autograd.grad(Eg.sum(), xg)[0].reshape(len(x), -1)
    mem = membrane_term(potential)
    with torch.no_grad():
        A = mem.rest_area
        S, Sg = mem.stress_norm(x), mem.stress_norm(xg)
        Sw, Sgw = (S * A).sum(-1) / A.sum(), (Sg * A).sum(-1) / A.sum()
        Smax, Sgmax = S.max(-1).values, Sg.max(-1).values
    E, Eg = E.detach().numpy(), Eg.detach().numpy()

    def stats(err, value):
        err = np.asarray(err)
        return float(err.mean()), float(err.max()), float(err.std()), float(np.mean(value))

    dF = (F - Fg).detach()
    return {
        "energy": stats(np.abs(E - Eg), E),
        "energy_gt": float(Eg.mean()),
        "stress_weighted": stats(np.abs((Sw - Sgw).numpy()), Sw.numpy()),
        "stress_max": stats(np.abs((Smax - Sgmax).numpy()), Smax.numpy()),
        "force": (float(dF.abs().sum(-1).mean()), float(dF.norm(dim=-1).mean()), float(F.abs().sum(-1).mean()), float(F.norm(dim=-1).mean())),
        "l2": float(((x - xg).detach() ** 2).sum((-1, -2)).mean()),
    }


# --------------------------------------------------------------------------------------------------
# the whole study
# --------------------------------------------------------------------------------------------------
def run_sheet_study(potential, X, cfg: dict, seed=0, gt=None, log_every=10) -> dict:
    """Everything of Tables 2, 4, A1 and the mode-collapse study on one sheet.

    cfg keys: modes, box, widths, lam, eta, metric, epochs (Neural Modes), l2_epochs,
    ae_epochs, ae_lr, batch_size, grids {train, val, test}, random_count, gt_max_iter,
    sharp_epochs, sharp_w_iso.  ``gt`` may pass precomputed ground truth (``solve_sets``).
    Returns {"gt", "rows": {method: {set: metrics}}, "correlation": {...}, "linear": LinearModes, "seconds"}.
    """
    from .latent import fit_autoencoder

    torch.manual_seed(seed)
    masses = potential.masses.numpy()
    m = int(cfg["modes"])
    lm = nm.linear_modes(potential, m, X, boundary="free", normalization="euclidean")
    R = nm.rigid_modes(X, masses)
    g = cfg["grids"]
    if gt is None:
        sets = sample_sets(m, cfg["box"], g["train"], g["val"], g["test"], cfg["random_count"], seed)
        gt = solve_sets(potential, X, lm.modes, R, sets, cfg["metric"], cfg["gt_max_iter"])
    n = len(X)
    Xf = X.reshape(-1)
    preds, seconds, models = {}, {}, {}

    def nm_model():
        torch.manual_seed(seed)
        return nm.NeuralModes(X, lm.modes, cfg["widths"], rigid=R, masses=masses)

    def at(model, name):
        with torch.no_grad():
            return model(torch.as_tensor(gt[name]["z"])).numpy()

    base = {k: cfg[k] for k in ("box", "lam", "eta", "metric", "epochs", "batch_size")}
    for label, sampling in (("Neural Modes (stoch.)", "stochastic"), ("Neural Modes (grid)", "grid")):
        model = nm_model()
        t0 = time.perf_counter()
        nm.train_neural_modes(model, potential, {**base, "sampling": sampling, "grid": g["train"]}, seed=seed)
        seconds[label] = time.perf_counter() - t0
        preds[label] = {s: at(model, s) for s in ("val", "test")}
        models[label] = model
        log.info("%s trained in %.0f s", label, seconds[label])

    model = nm_model()
    t0 = time.perf_counter()
    train_l2_supervised(model, gt["train_grid"]["z"], gt["train_grid"]["x"], cfg["l2_epochs"])
    seconds["L2 Supervised"] = time.perf_counter() - t0
    preds["L2 Supervised"] = {s: at(model, s) for s in ("val", "test")}

    ae_cfg = {"latent_dim": m, "widths": list(cfg["widths"]), "epochs": cfg["ae_epochs"], "lr": cfg["ae_lr"], "batch_size": 64}
    for label, train_set in (("PCA+AE", "train_random"), ("PCA+AE (grid)", "train_grid")):
        U = torch.as_tensor(gt[train_set]["x"].reshape(-1, 3 * n) - Xf)
        t0 = time.perf_counter()
        ae, hist = fit_autoencoder(U, ae_cfg, seed=seed)
        seconds[label] = time.perf_counter() - t0
        ae = ae.double()
        with torch.no_grad():
            preds[label] = {s: (ae(torch.as_tensor(gt[s]["x"].reshape(-1, 3 * n) - Xf)).numpy() + Xf).reshape(-1, n, 3) for s in ("val", "test")}
        log.info("%s trained in %.0f s (kept %s)", label, seconds[label], hist["kept"])

    rows = {label: {s: metrics(potential, p[s], gt[s]["x"]) for s in ("val", "test")} for label, p in preds.items()}

    # mode collapse (Fig. 4): latent directions at the origin
    corr = {}
    scale = float(np.sqrt((np.repeat(masses, 3)[:, None] * lm.modes**2).sum(0)).mean())
    for label in ("Neural Modes (stoch.)", "Neural Modes (grid)"):
        J = nm.latent_directions(models[label], m)
        corr[label] = nm.direction_correlation(J.numpy(), masses)
    torch.manual_seed(seed)
    sharp = DataFree(X, m, cfg["widths"])
    t0 = time.perf_counter()
    train_data_free(sharp, potential, cfg["box"], scale, cfg["sharp_w_iso"], cfg["sharp_epochs"], seed=seed)
    seconds["Sharp et al."] = time.perf_counter() - t0
    corr["Sharp et al."] = nm.direction_correlation(nm.latent_directions(sharp, m).numpy(), masses)
    return {"gt": gt, "rows": rows, "correlation": corr, "linear": lm, "seconds": seconds}


def tables(study: dict) -> dict:
    """pandas DataFrames of Tables 2, 4, A1 (ours next to the paper's) and the correlation eigenvalues."""
    import pandas as pd

    t2, t4, ta1 = [], [], []
    for label, r in study["rows"].items():
        p2, p4, pa = PAPER_TABLE2.get(label), PAPER_TABLE4.get(label), PAPER_TABLEA1.get(label)
        row = {"method": label}
        for i, s in enumerate(("val", "test")):
            for j, key in enumerate(("dE_avg", "dE_max", "dE_std", "E_avg")):
                row[f"{s}_{key}"] = r[s]["energy"][j]
                row[f"{s}_{key}_paper"] = p2[4 * i + j] if p2 else np.nan
        row["test_E_gt"] = r["test"]["energy_gt"]
        t2.append(row)
        row = {"method": label}
        for i, red in enumerate(("stress_weighted", "stress_max")):
            for j, key in enumerate(("dS_avg", "dS_max", "dS_std", "S_avg")):
                row[f"{red}_{key}"] = r["test"][red][j]
                row[f"{red}_{key}_paper_x1e6"] = p4[4 * i + j] if p4 else np.nan
        t4.append(row)
        row = {"method": label}
        for j, key in enumerate(("dF_l1", "dF_l2", "F_l1", "F_l2")):
            row[key] = r["test"]["force"][j]
            row[f"{key}_paper_x1e4"] = pa[j] if pa else np.nan
        ta1.append(row)
    corr = [{"method": k, "eigenvalues": " ".join(f"{w:.3f}" for w in v[1]), "min": float(v[1].min()), "max": float(v[1].max())} for k, v in study["correlation"].items()]
    return {"table2": pd.DataFrame(t2), "table4": pd.DataFrame(t4), "tableA1": pd.DataFrame(ta1), "correlation": pd.DataFrame(corr)}
