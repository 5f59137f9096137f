r"""Elastic energy of learned subspaces on a solid: Wang et al. 2024, Sec. 4.1 "Deformable Solids", Table 5.

Modal coordinates are drawn uniformly in the scene's modal box ([-b, b]^m) and each is solved for
its ground truth (Eq. 9, ``neural_modes.ground_truth``); the samples are split in order into
training, validation and test sets (the paper: 1,300 = 900 / 100 / 300).  PCA+AE (Fulton et al.
2019, ``latent.fit_autoencoder``) is trained on the training states and early-stopped on the
validation L2 (evaluated along its training, ``baselines.autoencoder_along_training``); the trained
Neural Modes, which never see a ground-truth state, are evaluated at the test coordinates (PCA+AE
reconstructs the test states: encode, then decode).  The table gives the mean elastic energy of
each over every 20% interval of the test set (in sample order) and over all of it; a subspace that
captures the equilibrium manifold comes close to the ground truth's (Eq. 9 is the constrained
minimum).
"""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import torch

from latentsim.neural_modes.baselines import autoencoder_along_training
from latentsim.neural_modes.metrics import checkpoints, stopping_index
from latentsim.neural_modes.network import NeuralModes
from latentsim.neural_modes.training import modal_samples

log = logging.getLogger(__name__)

__all__ = ["PAPER_TABLE5", "energy_sets", "energy_table", "interval_slices"]

PAPER_TABLE5 = {  # x 1e4: intervals 0-20% ... 80-100%, all
    "Ground truth": (12.3, 9.7, 12.5, 10.9, 10.8, 11.3),
    "PCA+AE": (106.7, 4329.9, 216.5, 179.5, 104.8, 987.5),
    "Neural Modes": (57.1, 58.0, 58.9, 52.3, 51.9, 55.8),
}


def energy_sets(m: int, box: float, samples: int, train: int, validation: int, seed: int = 0) -> dict:
    """``samples`` uniform coordinates in [-box, box]^m split in order: train, val, test (the rest)."""
    if train < 1 or validation < 1 or train + validation >= samples:
        raise ValueError(f"energy_sets: {samples} samples cannot be split into {train} training, {validation} validation and at least one test sample")
    z = modal_samples("stochastic", m, box, samples, generator=torch.Generator().manual_seed(seed)).numpy()
    return {"train": z[:train], "val": z[train : train + validation], "test": z[train + validation :]}


def interval_slices(count: int, intervals: int) -> list[slice]:
    """``intervals`` consecutive slices covering range(count) once, sizes differing by at most one
    (``np.array_split``'s; the paper's 20% intervals of its 300 test samples)."""
    if not 1 <= intervals <= count:
        raise ValueError(f"interval_slices: cannot split {count} samples into {intervals} intervals")
    edges = np.cumsum([0] + [len(p) for p in np.array_split(np.arange(count), intervals)])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def _energies(potential, x, chunk: int = 50) -> np.ndarray:
    with torch.no_grad():
        return np.concatenate([potential.elastic(torch.as_tensor(x[i : i + chunk])).numpy() for i in range(0, len(x), chunk)])


def energy_table(potential, X, gt: dict, model: NeuralModes, settings: dict, seed: int = 0, progress: bool = False):
    """Table 5 for one scene.

    Parameters
    ----------
    potential : the scene's potential (its elastic energy).
    X : (n,3) rest positions.
    gt : ground truth (``sheet.solve_sets``) of the sets train, val, test.
    model : the trained Neural Modes.
    settings : ``widths`` (PCA+AE's, the Neural Modes'), ``ae_epochs``, ``ae_lr``, ``ae_batch_size``,
        ``curve_points`` (checkpoints along the PCA+AE training), ``intervals``.

    Returns (table, history): a DataFrame with one row per method (Ground truth, PCA+AE, Neural Modes):
    the mean energy of each test interval and of all, the mean L2 error ||x - x_gt||^2 and the
    paper's row beside; history: PCA+AE's ``epochs``, ``val_l2``, ``test_l2``, ``test_E_avg`` along its
    training, ``stop`` (the checkpoint index kept), ``train_seconds``.
    """
    n = len(X)
    Xf = np.asarray(X, dtype=np.float64).reshape(-1)
    U = {s: torch.as_tensor(gt[s]["x"].reshape(len(gt[s]["x"]), -1) - Xf) for s in ("train", "val", "test")}
    ae_cfg = {"latent_dim": model.m, "widths": list(settings["widths"]), "lr": settings["ae_lr"], "batch_size": settings["ae_batch_size"]}
    hist = {"epochs": [], "val_l2": [], "test_l2": [], "test_E_avg": []}
    kept = {}
    for k, ae, fit_seconds in autoencoder_along_training(U["train"], ae_cfg, checkpoints(settings["ae_epochs"], settings["curve_points"]), seed, progress):
        with torch.no_grad():
            rec = {s: (ae(U[s]).numpy() + Xf).reshape(-1, n, 3) for s in ("val", "test")}
        hist["epochs"].append(k)
        for s in ("val", "test"):
            hist[f"{s}_l2"].append(float(((rec[s] - gt[s]["x"]) ** 2).sum((-1, -2)).mean()))
        hist["test_E_avg"].append(float(_energies(potential, rec["test"]).mean()))
        kept[k] = rec["test"]
        hist["train_seconds"] = fit_seconds  # the last fit: one run of ae_epochs
    hist = {k: np.asarray(v) for k, v in hist.items()}
    hist["stop"] = stopping_index(hist["epochs"], hist["val_l2"])
    epoch = int(hist["epochs"][hist["stop"]])
    log.info("PCA+AE: validation L2 least at epoch %d of %d (%.4g)", epoch, settings["ae_epochs"], hist["val_l2"][hist["stop"]])
    with torch.no_grad():
        pred_nm = model(torch.as_tensor(gt["test"]["z"])).numpy().reshape(-1, n, 3)
    x_gt = gt["test"]["x"]
    parts = interval_slices(len(x_gt), int(settings["intervals"]))
    names = [f"{round(100 * p.start / len(x_gt))}-{round(100 * p.stop / len(x_gt))}%" for p in parts]
    rows = []
    for label, x in (("Ground truth", x_gt), ("PCA+AE", kept[epoch]), ("Neural Modes", pred_nm)):
        e = _energies(potential, x)
        row = {"method": label, **{name: float(e[p].mean()) for name, p in zip(names, parts)}, "all": float(e.mean())}
        row["l2"] = float(((x - x_gt) ** 2).sum((-1, -2)).mean())
        row["epoch"] = epoch if label == "PCA+AE" else np.nan
        paper = PAPER_TABLE5[label]
        if len(parts) == 5:  # the paper's row beside, x 1e4
            row.update({f"paper {name} (x1e4)": v for name, v in zip(names + ["all"], paper)})
        else:
            row["paper all (x1e4)"] = paper[-1]
        rows.append(row)
    return pd.DataFrame(rows), hist
