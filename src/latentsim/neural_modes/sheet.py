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

import copy
import logging
import sys
import time

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from latentsim import neural_modes as nm
from latentsim.physics.kernels import with_compiled_elastic

log = logging.getLogger(__name__)

# Paper numbers (Wang et al. 2024), for the adjacent columns.
PAPER_TABLE2 = {  # method: (val dE_avg, dE_max, dE_std, E_avg, test dE_avg, dE_max, dE_std, E_avg)
    "PCA+AE": (1814, 22225, 2005, 18144, 2259, 27991, 2646, 24007),
    "PCA+AE (grid)": (2188, 36168, 3626, 18088, 2649, 72834, 4664, 23217),
    "L2 Supervised": (1630, 10231, 1148, 18210, 2074, 13750, 1697, 24325),
    "Neural Modes (stoch.)": (376, 1197, 170, 17032, 386, 1154, 183, 22891),
    "Neural Modes (grid)": (199, 754, 118, 16831, 245, 3062, 215, 22730),
}
PAPER_TABLE2["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLE2["Neural Modes (grid)"]  # the paper's own formulation
PAPER_TABLE4 = {  # x1e6: weighted dS_avg, dS_max, dS_std, |S|_avg, max-over-elements dS_avg, dS_max, dS_std, |S|_avg
    "PCA+AE": (25, 138, 17, 251, 67, 431, 49, 520),
    "PCA+AE (grid)": (25, 305, 29, 245, 64, 784, 68, 505),
    "L2 Supervised": (25, 100, 14, 255, 87, 350, 57, 550),
    "Neural Modes (stoch.)": (9, 36, 7, 240, 22, 155, 21, 486),
    "Neural Modes (grid)": (6, 24, 5, 236, 16, 124, 16, 479),
}
PAPER_TABLE4["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLE4["Neural Modes (grid)"]
PAPER_TABLEA1 = {  # x1e4: ||dF||_1, ||dF||_2, ||F||_1, ||F||_2
    "PCA+AE": (111, 5.95, 279, 24),
    "PCA+AE (grid)": (83, 4.35, 250, 22),
    "L2 Supervised": (125, 6.59, 293, 24),
    "Neural Modes (stoch.)": (31, 0.93, 199, 19),
    "Neural Modes (grid)": (25, 0.74, 193, 19),
}
PAPER_TABLEA1["Neural Modes (grid, penalty, as the paper)"] = PAPER_TABLEA1["Neural Modes (grid)"]


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


def solve_sets(potential, X, modes, sets: dict, free_dofs=None, rigid=None, metric="euclidean", max_iter=40, progress=False) -> dict:
    """Ground truth (Eq. 9) for every set: {name: {z, x (N,n,3), energy, residual, iterations, seconds}}.

    ``free_dofs`` (Dirichlet modes: the prescribed DoFs stay at rest) and ``rigid`` (free-floating:
    the correction is held M-orthogonal to the rigid modes) as :func:`neural_modes.ground_truth`.
    """
    out = {}
    for name, z in sets.items():
        t0 = time.perf_counter()
        with tqdm(total=len(z), desc=f"ground truth {name}", disable=not progress, file=sys.stderr, leave=False) as bar:
            x, e, infos = nm.ground_truth(
                potential, X, modes, z, free_dofs=free_dofs, rigid=rigid, metric=metric, max_iter=max_iter, progress=lambda i, info: bar.update(1)
            )
        res = np.array([i.residual for i in infos])
        its = np.array([i.iterations for i in infos])
        out[name] = {"z": np.asarray(z), "x": x, "energy": e, "residual": res, "iterations": its, "seconds": time.perf_counter() - t0}
        log.info("ground truth %s: %d samples in %.0f s, median KKT residual %.1e, iterations %.1f", name, len(z), out[name]["seconds"], np.median(res), its.mean())
    return out


# --------------------------------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------------------------------
def train_l2_supervised(model: nm.NeuralModes, z, x_gt, epochs=200, lbfgs_max_iter=20, callback=None):
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
    The energy runs the compiled kernels (``energy.kernels.with_compiled_elastic``).
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
# learning curves and early stopping (Fig. 2, Table 3)
# --------------------------------------------------------------------------------------------------
METRICS = (  # metric_vector's entries: Table 2 (energy), Table 4 (stress, two reductions), Table A1 (forces)
    "dE_avg", "dE_max", "dE_std", "E_avg",
    "dSw_avg", "dSw_max", "dSw_std", "Sw_avg",
    "dSm_avg", "dSm_max", "dSm_std", "Sm_avg",
    "dF_l1", "dF_l2", "F_l1", "F_l2",
    "l2", "E_gt",
)  # fmt: skip
STOPPING = {"val_l2": "l2", "val_energy": "E_avg"}  # early-stopping criterion: the validation metric it minimises


def metric_vector(potential, x, x_gt) -> np.ndarray:
    """:func:`metrics` of states x (N,n,3) against x_gt as one vector, in the order of :data:`METRICS`."""
    m = metrics(potential, x, x_gt)
    return np.array([*m["energy"], *m["stress_weighted"], *m["stress_max"], *m["force"], m["l2"], m["energy_gt"]])


def checkpoints(epochs: int, points: int) -> np.ndarray:
    """Epochs at which a learning curve is evaluated: 0 (before training), then ``points`` epochs spaced
    evenly in log from 1 to ``epochs`` (rounded, repeats dropped; the last is always ``epochs``)."""
    if epochs < 1 or points < 1:
        raise ValueError(f"checkpoints: epochs ({epochs}) and points ({points}) must be at least 1")
    return np.concatenate([[0], np.unique(np.round(np.geomspace(1, epochs, points)).astype(np.int64))])


def stopping_index(epochs, values) -> int:
    """Early stopping: the index of the checkpoint of lowest ``values`` among epochs >= 1 (the first on ties)."""
    epochs, values = np.asarray(epochs), np.asarray(values, dtype=np.float64)
    trained = np.flatnonzero(epochs >= 1)
    if not len(trained) or not np.isfinite(values[trained]).any():
        raise ValueError("stopping_index: no trained checkpoint with a finite criterion")
    return int(trained[np.nanargmin(values[trained])])


def autoencoder_along_training(U, config: dict, epochs, seed: int = 0, progress: bool = False):
    """PCA+AE (``latent.fit_autoencoder``) after each of ``epochs``: yields (epoch, model (float64, eval), seconds).

    One run of max(epochs) epochs with ``snapshots``: each model is the one ``fit_autoencoder`` would
    return had it stopped at that epoch (a model above its PCA initialisation's training error is that
    initialisation); ``seconds`` is the training time up to it.
    """
    from latentsim.latent import fit_autoencoder

    epochs = [int(k) for k in epochs]
    ae, hist = fit_autoencoder(U, {**config, "epochs": max(epochs)}, seed=seed, progress=progress, snapshots=epochs)
    for k in epochs:
        model = copy.deepcopy(ae)
        model.load_state_dict(hist["snapshots"][k]["state"])
        yield k, model.double().eval(), hist["snapshots"][k]["seconds"]


# --------------------------------------------------------------------------------------------------
# latent-space structure (Fig. 3): the origin, a half-turn symmetry, walks along each coordinate
# --------------------------------------------------------------------------------------------------
def half_turn(X, cells, modes, fixed_dofs=None, tol: float = 1e-9):
    """The half turn about the axis of least extent through the centroid, where it is a symmetry.

    It must map the vertices (to ``tol`` times the bounding-box diagonal), the cells (K,k) and the fixed
    DoFs onto themselves, and each mode onto plus or minus itself (a non-degenerate mode's parity).
    Returns ``(perm, R, parity)`` -- vertex i turns into vertex perm[i], R the (3,3) rotation, parity
    (m,) the modes' signs -- or None when any of that fails.
    """
    from scipy.spatial import cKDTree

    X = np.asarray(X, dtype=np.float64)
    c = X.mean(0)
    normal = np.linalg.svd(X - c, full_matrices=False)[2][-1]
    R = 2.0 * np.outer(normal, normal) - np.eye(3)
    dist, perm = cKDTree(X).query((X - c) @ R.T + c)
    if dist.max() > tol * np.linalg.norm(np.ptp(X, axis=0)) or len(np.unique(perm)) != len(X):
        return None
    if {tuple(sorted(e)) for e in np.asarray(cells)} != {tuple(sorted(e)) for e in perm[np.asarray(cells)]}:
        return None
    fixed = np.unique(np.asarray(fixed_dofs if fixed_dofs is not None else [], dtype=np.int64) // 3)
    if not np.array_equal(np.sort(perm[fixed]), fixed):
        return None
    E = np.asarray(modes, dtype=np.float64).T.reshape(-1, len(X), 3)
    turned = turn(E, perm, R)
    parity = np.sign(np.einsum("kij,kij->k", turned, E))
    if np.any(np.linalg.norm((turned - parity[:, None, None] * E).reshape(len(E), -1), axis=1) > 1e-6 * np.linalg.norm(E.reshape(len(E), -1), axis=1)):
        return None  # a degenerate pair: the turn mixes modes
    return perm, R, parity


def turn(u, perm, R) -> np.ndarray:
    """A displacement field u (..., n, 3) carried by the symmetry: out[..., perm[i]] = R u[..., i]."""
    u = np.asarray(u)
    out = np.empty_like(u)
    out[..., perm, :] = u @ R.T
    return out


def symmetry_error(x, z, X, symmetry) -> tuple[float, float]:
    """(mean, max) over samples z != 0 of |turn(u(z)) - u(S z)| / |u(z)|, u = x - X, S = diag(parity).

    A map that keeps the symmetry of the energy, the modes and the mesh (as Eq. 9 does) gives 0.
    ``z`` (N,m) must hold S z with every z; NaNs when ``symmetry`` is None.
    """
    if symmetry is None:
        return float("nan"), float("nan")
    perm, R, parity = symmetry
    z = np.asarray(z, dtype=np.float64)
    u = np.asarray(x, dtype=np.float64) - np.asarray(X, dtype=np.float64)
    from scipy.spatial import cKDTree

    dist, j = cKDTree(z).query(z * parity)
    if dist.max() > 1e-9 * max(np.abs(z).max(), 1e-300):
        raise ValueError("symmetry_error: the sample set does not hold the mirrored coordinates S z of every z")
    size = np.linalg.norm(u.reshape(len(u), -1), axis=1)
    keep = np.any(z != 0, axis=1) & (size > 0)  # z = 0 maps to the rest state (the origin error's business)
    err = np.linalg.norm((turn(u, perm, R) - u[j]).reshape(len(u), -1), axis=1)[keep] / size[keep]
    return float(err.mean()), float(err.max())


def latent_walk(decode, low, high, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Shapes along each latent coordinate i from low[i] to high[i], the others at 0.

    ``decode`` maps (k, m) coordinates to positions (k, n, 3).  Returns coordinates (m, steps) and
    positions (m, steps, n, 3).
    """
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    m = len(low)
    coords = np.linspace(low, high, steps).T
    pos = []
    for i in range(m):
        z = np.zeros((steps, m))
        z[:, i] = coords[i]
        pos.append(decode(z))
    return coords, np.stack(pos)


# --------------------------------------------------------------------------------------------------
# mode collapse (Fig. 4)
# --------------------------------------------------------------------------------------------------
def mode_collapse(potential, rest_positions, modes, models: dict, widths, box, sharp: dict, fixed_dofs=None, seed: int = 0) -> dict:
    """Correlation matrices (and eigenvalues) of the latent directions at the origin of each of
    ``models`` {label: z -> positions}, and of Sharp et al. 2023 trained here with the same widths,
    latent dimension, box and fixed DoFs (``sharp``: epochs, batch_size, w_iso).

    Returns {label: {"matrix" (m,m), "eigenvalues" (m,), "train_seconds"}}; Sharp et al. under :data:`SHARP`.
    """
    masses = potential.masses.numpy()
    m = np.asarray(modes).shape[1]
    out = {label: dict(zip(("matrix", "eigenvalues"), nm.direction_correlation(nm.latent_directions(f, m).numpy(), masses))) for label, f in models.items()}
    torch.manual_seed(seed)
    model = DataFree(rest_positions, m, widths, fixed_dofs=fixed_dofs)
    scale = float(np.sqrt((np.repeat(masses, 3)[:, None] * np.asarray(modes) ** 2).sum(0)).mean())
    t0 = time.perf_counter()
    train_data_free(model, potential, box, scale, sharp["w_iso"], sharp["epochs"], sharp["batch_size"], seed=seed)
    C, w = nm.direction_correlation(nm.latent_directions(model, m).numpy(), masses)
    out[SHARP] = {"matrix": C, "eigenvalues": w, "train_seconds": time.perf_counter() - t0}
    log.info("%s: %d epochs in %.0f s; correlation eigenvalues %s", SHARP, sharp["epochs"], out[SHARP]["train_seconds"], np.round(w, 3))
    return out


# --------------------------------------------------------------------------------------------------
# the whole study
# --------------------------------------------------------------------------------------------------
SHEET_METHODS = {  # slug: the paper's label
    "nm_stochastic": "Neural Modes (stoch.)",
    "nm_grid": "Neural Modes (grid)",
    # with the constraint or the symmetry built into the map (orthogonality 'exact', symmetry 'half_turn'),
    # the paper's map too: the penalty lambda (l^T y)^2, nothing built in but n(0) = X
    "nm_grid_penalty": "Neural Modes (grid, penalty, as the paper)",
    "l2_supervised": "L2 Supervised",
    "pca_ae": "PCA+AE",
    "pca_ae_grid": "PCA+AE (grid)",
}
SUPERVISED = ("l2_supervised", "pca_ae", "pca_ae_grid")  # early-stopped on the validation L2 in Tables 2, 4, A1
TRAIN_SET = {"nm_stochastic": "train_random", "nm_grid": "train_grid", "nm_grid_penalty": "train_grid", "l2_supervised": "train_grid", "pca_ae": "train_random", "pca_ae_grid": "train_grid"}
NM_SAMPLING = {"nm_stochastic": "stochastic", "nm_grid": "grid", "nm_grid_penalty": "grid"}  # the self-supervised runs
WALKS = ("nm_grid", "pca_ae_grid")  # Fig. 3: the two trained on the same grid
SHARP = "Sharp et al. 2023"
PAPER_TABLE3 = {  # E_avg at the epoch chosen by each stopping criterion: val (L2, energy), test (L2, energy)
    "PCA+AE": (18144, 17762, 24007, 23484),
    "PCA+AE (grid)": (18088, 18042, 23217, 23051),
    "L2 Supervised": (18210, 17690, 24325, 23682),
}


def run_sheet_study(potential, basis: dict, gt: dict, nm_settings: dict, study: dict, cells, seed: int = 0, progress: bool = False) -> dict:
    """Every method of Wang et al. Sec. 4.1-4.4 on one shell, evaluated along its training.

    Parameters
    ----------
    potential : the scene's potential (elastic terms; a membrane with ``stress_norm``).
    basis : ``X`` (n,3), ``modes`` (3n,m), ``fixed_dofs``, ``rigid`` (3n,6) or None (linear_modes.h5).
    gt : ground truth (:func:`solve_sets`) of the sets train_grid, train_random, val, test.
    nm_settings : the Neural Modes settings (widths, lam, eta, box, metric, ...; ``NM_DEFAULTS`` keys).
    study : epochs, batch_size (Neural Modes), train_grid, l2_epochs, ae_epochs, ae_lr, ae_batch_size,
        curve_points, sharp_epochs, sharp_batch_size, sharp_w_iso, walk_steps.
    cells : (K,k) the mesh's elements (for the symmetry check).

    Every method is evaluated on the validation and test sets (:data:`METRICS`) and by its L2 error on
    its own training set at :func:`checkpoints` of its training.  Neural Modes (Eq. 13, stochastic or
    on the training grid) are taken at their last epoch; the supervised methods at the epoch of least
    validation L2 (Tables 2, 4, A1; the paper's Table 2 equals its Table 3's L2 column) and, for Table
    3, of least validation energy too.

    Returns a tree of arrays and numbers (:func:`write_tree` stores it): ``methods`` {slug: label,
    train_set, epochs (C,), train_l2 (C,), val and test (C, len(METRICS)), stop_<criterion> (checkpoint
    index), table_stopping, train_seconds, origin_relative_error, symmetry_mean, symmetry_max},
    ``correlation`` {slug: label, matrix, eigenvalues}, ``walk`` {slug: label, coordinates (m,S),
    positions (m,S,n,3)}, ``ground_truth`` (its own symmetry error and the test set's KKT residuals:
    median, 90th percentile; mean Newton iterations), ``metrics``.
    """
    cfg = {**nm.NM_DEFAULTS, **nm_settings}
    X, modes, fixed, rigid = basis["X"], basis["modes"], basis["fixed_dofs"], basis.get("rigid")
    masses = potential.masses.numpy()
    n, m = len(X), modes.shape[1]
    Xf = X.reshape(-1)
    z_of = {s: torch.as_tensor(gt[s]["z"]) for s in gt}
    symmetry = half_turn(X, cells, modes, fixed)

    # the networks' settings: with anything built into the map, a third Neural Modes run with the paper's
    net_cfg = {"nm_stochastic": cfg, "nm_grid": cfg, "l2_supervised": cfg}
    if cfg["orthogonality"] == "exact" or cfg["symmetry"] != "none":
        net_cfg["nm_grid_penalty"] = {**cfg, "orthogonality": "paper", "symmetry": "none"}

    def new_network(slug):
        torch.manual_seed(seed)
        return nm.from_config(basis, net_cfg[slug], masses, symmetry=symmetry)

    def of_network(model):
        @torch.no_grad()
        def predict(s):
            return model(z_of[s]).numpy()

        return predict

    def of_autoencoder(ae):
        @torch.no_grad()
        def predict(s):
            return (ae(torch.as_tensor(gt[s]["x"].reshape(-1, 3 * n) - Xf)).numpy() + Xf).reshape(-1, n, 3)

        return predict

    curves, snapshots = {}, {}

    def record(slug, epoch, predict, snapshot):
        t0 = time.perf_counter()
        c = curves.setdefault(slug, {"label": SHEET_METHODS[slug], "train_set": TRAIN_SET[slug], "epochs": [], "train_l2": [], "val": [], "test": [], "eval_seconds": 0.0})
        c["epochs"].append(int(epoch))
        c["train_l2"].append(float(((predict(c["train_set"]) - gt[c["train_set"]]["x"]) ** 2).sum((-1, -2)).mean()))
        for s in ("val", "test"):
            c[s].append(metric_vector(potential, predict(s), gt[s]["x"]))
        snapshots.setdefault(slug, {})[int(epoch)] = snapshot
        c["eval_seconds"] += time.perf_counter() - t0

    seconds = {}

    def train_network(slug, epochs, train):
        """Train a fresh network with ``train(model, callback)``, recording the checkpoints."""
        want = set(checkpoints(epochs, study["curve_points"]).tolist())
        model = new_network(slug)
        record(slug, 0, of_network(model), copy.deepcopy(model.state_dict()))
        bar = tqdm(total=epochs, desc=SHEET_METHODS[slug], disable=not progress, file=sys.stderr, leave=False)

        def callback(epoch, model):
            bar.update(1)
            if epoch + 1 in want:
                record(slug, epoch + 1, of_network(model), copy.deepcopy(model.state_dict()))

        evaluating, t0 = curves[slug]["eval_seconds"], time.perf_counter()
        train(model, callback)
        bar.close()
        seconds[slug] = time.perf_counter() - t0 - (curves[slug]["eval_seconds"] - evaluating)  # training alone
        log.info("%s: %d epochs in %.0f s", SHEET_METHODS[slug], epochs, seconds[slug])

    for slug in (s for s in net_cfg if s in NM_SAMPLING):
        settings = {**net_cfg[slug], "sampling": NM_SAMPLING[slug], "grid": study["train_grid"], "epochs": study["epochs"], "batch_size": study["batch_size"]}
        train_network(slug, study["epochs"], lambda model, cb, settings=settings: nm.train_neural_modes(model, potential, settings, seed=seed, callback=cb))
    train_network(
        "l2_supervised", study["l2_epochs"],
        lambda model, cb: train_l2_supervised(model, gt["train_grid"]["z"], gt["train_grid"]["x"], study["l2_epochs"], cfg["lbfgs_max_iter"], callback=cb),
    )  # fmt: skip
    ae_cfg = {"latent_dim": m, "widths": list(cfg["widths"]), "lr": study["ae_lr"], "batch_size": study["ae_batch_size"]}
    for slug in ("pca_ae", "pca_ae_grid"):
        U = torch.as_tensor(gt[TRAIN_SET[slug]]["x"].reshape(-1, 3 * n) - Xf)
        for k, ae, fit_seconds in autoencoder_along_training(U, ae_cfg, checkpoints(study["ae_epochs"], study["curve_points"]), seed, progress):
            record(slug, k, of_autoencoder(ae), ae)
            seconds[slug] = fit_seconds  # the last: one run of ae_epochs
        log.info("%s: %d epochs in %.0f s", SHEET_METHODS[slug], study["ae_epochs"], seconds[slug])

    methods, chosen = {}, {}
    for slug, c in curves.items():
        out = {k: c[k] for k in ("label", "train_set")}
        out.update(epochs=np.array(c["epochs"]), train_l2=np.array(c["train_l2"]), val=np.stack(c["val"]), test=np.stack(c["test"]))
        out["stop_final"] = len(c["epochs"]) - 1
        for crit, metric in STOPPING.items():
            out[f"stop_{crit}"] = stopping_index(out["epochs"], out["val"][:, METRICS.index(metric)])
        out["table_stopping"] = "val_l2" if slug in SUPERVISED else "final"
        out["train_seconds"] = float(seconds[slug])
        epoch = int(out["epochs"][out[f"stop_{out['table_stopping']}"]])
        snap = snapshots[slug][epoch]
        if slug.startswith("pca_ae"):
            chosen[slug] = snap
            predict = of_autoencoder(snap)
            with torch.no_grad():
                origin = snap.decode(torch.zeros(m, dtype=torch.float64)).numpy()
        else:
            model = new_network(slug)
            model.load_state_dict(snap)
            chosen[slug] = model.eval()
            predict = of_network(model)
            with torch.no_grad():
                origin = model(torch.zeros(m, dtype=torch.float64)).numpy().reshape(-1) - Xf
        out["origin_relative_error"] = float(np.linalg.norm(origin) / np.linalg.norm(Xf))
        out["symmetry_mean"], out["symmetry_max"] = symmetry_error(predict("test"), gt["test"]["z"], X, symmetry)
        methods[slug] = out

    walk = {}
    for slug in WALKS:
        f = chosen[slug]
        if slug.startswith("pca_ae"):
            with torch.no_grad():
                lat = f.encode(torch.as_tensor(gt[TRAIN_SET[slug]]["x"].reshape(-1, 3 * n) - Xf)).numpy()
            low, high = lat.min(0), lat.max(0)

            @torch.no_grad()
            def decode(z, f=f):
                return (f.decode(torch.as_tensor(z)).numpy() + Xf).reshape(-1, n, 3)
        else:
            low, high = np.full(m, -cfg["box"]), np.full(m, cfg["box"])

            @torch.no_grad()
            def decode(z, f=f):
                return f(torch.as_tensor(z)).numpy()

        coords, pos = latent_walk(decode, low, high, study["walk_steps"])
        walk[slug] = {"label": SHEET_METHODS[slug], "coordinates": coords, "positions": pos}

    collapse = mode_collapse(
        potential, X, modes, {SHEET_METHODS[s]: chosen[s] for s in ("nm_stochastic", "nm_grid")}, cfg["widths"], cfg["box"],
        {"epochs": study["sharp_epochs"], "batch_size": study["sharp_batch_size"], "w_iso": study["sharp_w_iso"]}, fixed, seed,
    )  # fmt: skip
    correlation = {}
    for slug, label in (("nm_stochastic", SHEET_METHODS["nm_stochastic"]), ("nm_grid", SHEET_METHODS["nm_grid"]), ("sharp", SHARP)):
        correlation[slug] = {"label": label, **collapse[label]}
    gt_sym = symmetry_error(gt["test"]["x"], gt["test"]["z"], X, symmetry)
    residual = np.asarray(gt["test"]["residual"])
    return {
        "metrics": list(METRICS),
        "methods": methods,
        "correlation": correlation,
        "walk": walk,
        "ground_truth": {
            "symmetry_mean": gt_sym[0], "symmetry_max": gt_sym[1], "symmetric": symmetry is not None,
            "residual_median": float(np.median(residual)), "residual_p90": float(np.percentile(residual, 90)),
            "iterations_mean": float(np.mean(gt["test"]["iterations"])),
        },
    }  # fmt: skip


STOPPING_LABEL = {"final": "last epoch", "val_l2": "validation L2", "val_energy": "validation energy"}


def _at(method: dict, part: str, criterion: str) -> dict:
    """{metric: value} of a method's ``part`` (val | test) at the checkpoint chosen by ``criterion``."""
    return dict(zip(METRICS, np.asarray(method[part])[int(method[f"stop_{criterion}"])]))


def tables(study: dict) -> dict:
    """pandas DataFrames of Tables 2, 3, 4, A1 (ours beside the paper's), the correlation eigenvalues
    (Fig. 4) and the latent structure (origin, symmetry; Fig. 3) of a :func:`run_sheet_study` result."""
    import pandas as pd

    if list(study["metrics"]) != list(METRICS):
        raise ValueError(f"the study's metrics {list(study['metrics'])} are not this version's {list(METRICS)}; rerun the study")
    t2, t3, t4, ta1, structure = [], [], [], [], []
    for slug, r in study["methods"].items():
        label, crit = r["label"], r["table_stopping"]
        head = {"method": label, "stopping": STOPPING_LABEL[crit], "epoch": int(r["epochs"][int(r[f"stop_{crit}"])])}
        p2, p4, pa = PAPER_TABLE2.get(label), PAPER_TABLE4.get(label), PAPER_TABLEA1.get(label)
        row = dict(head)
        for i, s in enumerate(("val", "test")):
            v = _at(r, s, crit)
            for j, key in enumerate(("dE_avg", "dE_max", "dE_std", "E_avg")):
                row[f"{s}_{key}"] = v[key]
                row[f"{s}_{key}_paper"] = p2[4 * i + j] if p2 else np.nan
        row["test_E_gt"] = _at(r, "test", crit)["E_gt"]
        t2.append(row)
        v = _at(r, "test", crit)
        row = dict(head)
        for i, (red, short) in enumerate((("stress_weighted", "Sw"), ("stress_max", "Sm"))):
            for j, key in enumerate(("dS_avg", "dS_max", "dS_std", "S_avg")):
                row[f"{red}_{key}"] = v[key.replace("S", short, 1)]
                row[f"{red}_{key}_paper_x1e6"] = p4[4 * i + j] if p4 else np.nan
        t4.append(row)
        row = dict(head)
        for j, key in enumerate(("dF_l1", "dF_l2", "F_l1", "F_l2")):
            row[key] = v[key]
            row[f"{key}_paper_x1e4"] = pa[j] if pa else np.nan
        ta1.append(row)
        if slug in SUPERVISED:
            row = {"method": label}
            p3 = PAPER_TABLE3.get(label)
            for i, s in enumerate(("val", "test")):
                for j, c in enumerate(STOPPING):
                    at = _at(r, s, c)
                    row[f"{s}_E_avg_{c}"] = at["E_avg"]
                    row[f"{s}_E_avg_{c}_paper"] = p3[2 * i + j] if p3 else np.nan
                    row[f"{s}_dE_avg_{c}"] = at["dE_avg"]
            for c in STOPPING:
                row[f"epoch_{c}"] = int(r["epochs"][int(r[f"stop_{c}"])])
            row["epoch_last"] = int(r["epochs"][-1])
            row["test_E_avg_last"] = _at(r, "test", "final")["E_avg"]
            t3.append(row)
        structure.append({"method": label, "epoch": head["epoch"], "origin |n(0) - X| / |X|": r["origin_relative_error"],
                          "symmetry error mean": r["symmetry_mean"], "symmetry error max": r["symmetry_max"]})  # fmt: skip
    g = study["ground_truth"]
    structure.append({"method": "ground truth (Eq. 9)", "epoch": np.nan, "origin |n(0) - X| / |X|": 0.0,
                      "symmetry error mean": g["symmetry_mean"], "symmetry error max": g["symmetry_max"]})  # fmt: skip
    corr = [
        {"method": c["label"], "eigenvalues": " ".join(f"{w:.3f}" for w in c["eigenvalues"]), "min": float(np.min(c["eigenvalues"])), "max": float(np.max(c["eigenvalues"]))}
        for c in study["correlation"].values()
    ]
    return {
        "table2": pd.DataFrame(t2), "table3": pd.DataFrame(t3), "table4": pd.DataFrame(t4), "tableA1": pd.DataFrame(ta1),
        "correlation": pd.DataFrame(corr), "structure": pd.DataFrame(structure),
    }  # fmt: skip
