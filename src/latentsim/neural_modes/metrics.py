r"""Metrics of the Neural Modes studies (Wang et al. 2024, Tables 2, 3, 4, A1), learning curves and early stopping.

Per method on a set of samples (validation 7^3, test 11^3 grids on the sheet): elastic energy E and
dE = |E - E_gt| (avg, max, std over samples; Table 2); membrane stress |P|_F per triangle
(``ShellMembraneStVK.stress_norm``, the first Piola-Kirchhoff stress of the StVK membrane; bending
moments are not included), reduced per sample by the area-weighted mean and by the max over
elements, and its error against ground truth (Table 4); nodal forces F = -dE/dx and ||dF||_1,
||dF||_2 (batch means; Table A1).  A learning curve evaluates them at :func:`checkpoints` of a
training; early stopping picks the checkpoint of least validation L2 or energy (Table 3).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["METRICS", "STOPPING", "checkpoints", "membrane_term", "metric_vector", "metrics", "stopping_index"]


def membrane_term(potential):
    """The potential's membrane term (the one with ``stress_norm`` and ``rest_area``)."""
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
