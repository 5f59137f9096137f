"""Pipeline stages of Neural Modes (``workflow/rules/neural_modes.smk``): linear modes, training, summary.

Each stage reads its inputs, calls ``latentsim.neural_modes`` and writes one artefact atomically
with provenance (``docs/artefacts.md``, section Neural Modes).
"""

from __future__ import annotations

import json
import logging
import time

import h5py
import numpy as np
import torch

from . import neural_modes as nm
from .io import atomic_h5
from .latent import save_module
from .scene import build_potential
from .simulate import read_mesh_arrays

log = logging.getLogger(__name__)


def scene_params(config: dict, scene: str) -> dict:
    """The params of the Neural Modes rules: the scene's model, material and neural_modes slice (sorted keys)."""
    sc = config["scenes"][scene]
    return json.loads(json.dumps({"model": sc["model"], "material": sc["material"], "neural_modes": sc["neural_modes"]}, sort_keys=True))


def targets(scenes) -> list:
    """Every Neural Modes artefact of the given (wang2024) scenes; none when there are none."""
    if not scenes:
        return []
    return [f"results/neural_modes/{s}/neural_modes.pt" for s in scenes] + ["results/neural_modes/summary.csv", "results/neural_modes/summary.md"]


def scene_potential(mesh_h5, model: str, material: dict):
    """(potential with every elastic stencil, arrays) of a scene's mesh; no inertia or gravity needed here."""
    arrays = read_mesh_arrays(mesh_h5)
    return build_potential(model, arrays, material, 1.0, [0.0, 0.0, 0.0]), arrays


def _fixed_dofs(arrays, boundary):
    if boundary == "free":
        return np.zeros(0, dtype=np.int64)
    D = np.asarray(arrays["dirichlet"], dtype=np.int64)
    return (3 * D[:, None] + np.arange(3)).reshape(-1)


def linear_modes_stage(mesh_h5, params: dict, out_h5):
    """Stage ``nm_linear_modes``: the scene's lowest m modes (sparse shift-invert) to ``linear_modes.h5``."""
    cfg = {**nm.NM_DEFAULTS, **params["neural_modes"]}
    pot, arrays = scene_potential(mesh_h5, params["model"], params["material"])
    X = np.asarray(arrays["rest_positions"], dtype=np.float64)
    t0 = time.perf_counter()
    lm = nm.linear_modes(pot, int(cfg["modes"]), X, boundary=cfg["boundary"], normalization=cfg["normalization"])
    seconds = time.perf_counter() - t0
    log.info("%d modes of %d DoF in %.2f s; omega [rad/s] %s", lm.modes.shape[1], lm.modes.shape[0], seconds, np.sqrt(lm.omega2))
    with atomic_h5(out_h5, config=params) as f:
        f["rest_positions"] = X
        f["masses"] = pot.masses.numpy()
        f["omega2"] = lm.omega2
        f["modes"] = lm.modes
        f["free_dofs"] = lm.free_dofs
        f["fixed_dofs"] = _fixed_dofs(arrays, cfg["boundary"])
        if cfg["boundary"] == "free":
            f["rigid_modes"] = nm.rigid_modes(X, pot.masses.numpy())
        f.attrs.update(rigid_removed=lm.rigid_removed, normalization=lm.normalization, boundary=cfg["boundary"], seconds=seconds)


def train_stage(mesh_h5, modes_h5, params: dict, seed: int, out_pt, out_h5):
    """Stage ``nm_train``: self-supervised Neural Modes (Eq. 13), its history and latent-direction correlation."""
    cfg = {**nm.NM_DEFAULTS, **params["neural_modes"]}
    pot, _ = scene_potential(mesh_h5, params["model"], params["material"])
    with h5py.File(modes_h5, "r") as f:
        X = f["rest_positions"][()]
        modes = f["modes"][()]
        fixed = f["fixed_dofs"][()]
        rigid = f["rigid_modes"][()] if "rigid_modes" in f else None
    masses = pot.masses.numpy()
    torch.manual_seed(seed)
    model = nm.NeuralModes(X, modes, cfg["widths"], fixed_dofs=fixed, rigid=rigid, masses=masses, exact_origin=cfg["exact_origin"])
    hist = nm.train_neural_modes(model, pot, cfg, seed=seed)
    log.info("trained %d epochs in %.0f s; final energy %.4g, constraint %.3g", cfg["epochs"], hist["seconds"], hist["energy"][-1], hist["constraint"][-1])
    # evaluation on a fixed set of uniform samples: energy of Neural Modes vs linear modes at the same z
    gen = torch.Generator().manual_seed(seed + 1)
    z = nm.modal_samples("stochastic", model.m, cfg["box"], 256, generator=gen)
    with torch.no_grad():
        e_nm = pot.elastic(model(z)).numpy()
        e_lin = pot.elastic((model.X + model.linear(z)).reshape(-1, model.n, 3)).numpy()
        l, y = model.linear(z), model.correction(z)
        cos = ((l * y).sum(-1).abs() / (l.norm(dim=-1) * y.norm(dim=-1)).clamp_min(1e-300)).numpy()
        origin = float((model(torch.zeros(1, model.m, dtype=torch.float64))[0].reshape(-1) - model.X).norm() / model.X.norm())
    C, w = nm.direction_correlation(nm.latent_directions(model, model.m).numpy(), masses)
    save_module(out_pt, model, extra={"config": cfg, "seed": seed})
    with atomic_h5(out_h5, config=params, seed=seed) as f:
        for key in ("loss", "energy", "constraint", "origin"):
            f[key] = np.asarray(hist[key])
        f["eval_z"] = z.numpy()
        f["eval_energy"] = e_nm
        f["eval_energy_linear"] = e_lin
        f["eval_cosine_ly"] = cos
        f["correlation"] = C
        f["correlation_eigenvalues"] = w
        f.attrs.update(train_seconds=hist["seconds"], origin_relative_error=origin)


def summary_stage(history_files: dict, out_csv, out_md):
    """Stage ``nm_summary``: one row per scene (energy vs linear modes, constraint, origin, correlation eigenvalues)."""
    import pandas as pd

    rows = []
    for scene, path in sorted(history_files.items()):
        with h5py.File(path, "r") as f:
            cfg = json.loads(f.attrs["config"])["neural_modes"]
            e, el = f["eval_energy"][()], f["eval_energy_linear"][()]
            w = f["correlation_eigenvalues"][()]
            rows.append(
                {
                    "scene": scene,
                    "modes": cfg.get("modes"),
                    "boundary": cfg.get("boundary"),
                    "E_avg neural": float(e.mean()),
                    "E_avg linear": float(el.mean()),
                    "E ratio": float(e.mean() / max(el.mean(), 1e-300)),
                    "max |cos(l, y)|": float(f["eval_cosine_ly"][()].max()),
                    "|n(0) - X| / |X|": float(f.attrs["origin_relative_error"]),
                    "correlation eigenvalues": " ".join(f"{v:.3f}" for v in w),
                    "train s": float(f.attrs["train_seconds"]),
                }
            )
    df = pd.DataFrame(rows)
    df.to_csv(out_csv, index=False)
    with open(out_md, "w") as fh:
        fh.write(df.to_markdown(index=False, floatfmt=".4g") + "\n")
