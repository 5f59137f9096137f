"""Subspace dynamics in Neural Modes (Eq. 15) against linear modes and the full simulation.

    nice python benchmarks/neural_modes_dynamics.py nm_giraffe nm_bunny [--frames 120] [--cubature-tolerance 0.01]

Needs, per scene, the full simulation (results/sim/{scene}/trajectories.h5) and the trained Neural
Modes (results/neural_modes/{scene}/neural_modes.pt, rule nm_train).  Replays the first sequence's
prescribed Dirichlet motion in the subspace with the reduced implicit-Euler solver
(latentsim.reduced): Neural Modes with L-BFGS (as the paper) and with Gauss-Newton on the reduced
Hessian J^T H J (the paper's future work), and the linear modes alone with Gauss-Newton.  Prints
ms/step (median and mean over the steps) and the position error against the full simulation
(mean and max over frames of the RMS vertex error, relative to the rest bounding-box diagonal),
and the median split of a step (map + Jacobian, full-space gradient + Hessian, reduction + solve,
line search; L-BFGS reports none).  The full-space Newton frame of the same sequence is timed in the
same run (the mean over 20 frames spread over it, as the rollout stage does).

Every method runs twice: with every element, and with a cubature (latentsim.cubature) fitted to
each subspace's reduced elastic forces at poses drawn in the scene's Neural Modes training box
(data-free, like the modes; no frame of the simulation is used).  The fit's element count, its
relative force error on held-out poses and its wall time are printed first.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core per step, as the timings are meant (set before numpy loads)

import argparse
from pathlib import Path

import h5py
import numpy as np
import torch

from latentsim.config import load_config
from latentsim.cubature import box_samples, cubature_potential, fit_cubature
from latentsim.neural_modes import load_neural_modes
from latentsim.nm_dynamics import NeuralModesSubspace
from latentsim.reduced import ReducedSettings, reduced_rollout
from latentsim.scene import potential_from_artefact
from latentsim.train import time_full_space

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenes", nargs="+")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"), help="where the scenes' modal box is read")
    ap.add_argument("--cubature-tolerance", type=float, default=0.01, help="relative reduced-force error of the fit")
    ap.add_argument("--cubature-samples", type=int, default=300, help="training poses (and half as many held out)")
    ap.add_argument("--cubature-max", type=int, default=1000, help="most elements")
    args = ap.parse_args()
    torch.set_num_threads(1)
    scenes_cfg = load_config(args.config)["scenes"]
    fits = []
    print(
        "| scene | DoF | method | steps | ms/step median | ms/step mean | iterations/step | error mean | error max | diverged "
        "| map ms | derivatives ms | reduce ms | line search ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        with h5py.File(ROOT / "results" / "sim" / scene / "trajectories.h5", "r") as f:
            pot = potential_from_artefact(f)
            name = next(iter(f["sequences"]))
            ref = f["sequences"][name]["positions"][: args.frames]
            xD = f["sequences"][name]["dirichlet_positions"][: args.frames]
            X = f["rest_positions"][()]
            full = time_full_space(f, name)
        model = load_neural_modes(ROOT / "results" / "neural_modes" / scene / "neural_modes.pt")
        diag = float(np.linalg.norm(X.max(0) - X.min(0)))
        D = pot.dirichlet.numpy()
        box = float(scenes_cfg[scene]["neural_modes"]["box"])
        neural, linear = NeuralModesSubspace(model, D), NeuralModesSubspace(model, D, linear_only=True)
        cub = {}
        for what, sub in (("Neural Modes", neural), ("linear modes", linear)):
            c = fit_cubature(
                pot.terms, sub, box_samples(sub.dim, box, args.cubature_samples, seed=0),
                args.cubature_tolerance, args.cubature_max, validation=box_samples(sub.dim, box, args.cubature_samples // 2, seed=1),
            )
            cub[what] = cubature_potential(pot, c)
            fits.append(
                f"| {scene} | {what} | {len(c.index)} of {c.n_elements} | {c.train_error:.4f} | {c.validation_error:.4f} | {c.fit_seconds:.1f} |"
            )
        runs = (
            ("Neural Modes, L-BFGS", neural, "lbfgs", pot),
            ("Neural Modes, Gauss-Newton", neural, "newton", pot),
            ("linear modes, Newton", linear, "newton", pot),
            ("Neural Modes, L-BFGS, cubature", neural, "lbfgs", cub["Neural Modes"]),
            ("Neural Modes, Gauss-Newton, cubature", neural, "newton", cub["Neural Modes"]),
            ("linear modes, Newton, cubature", linear, "newton", cub["linear modes"]),
        )
        print(f"| {scene} | {X.size:,} | full space, Newton ({full['full_frames_timed']} frames) | | {full['full_ms']:.1f} | | "
              f"{full['full_iterations']:.1f} | 0 | 0 | | | | | |", flush=True)  # fmt: skip
        for label, sub, method, potential in runs:
            q0 = np.zeros(sub.dim)
            out = reduced_rollout(sub, potential, q0, q0, xD, ReducedSettings(method=method, max_iterations=100))
            ok = np.isfinite(out["positions"]).all(axis=(1, 2))
            err = np.sqrt(((out["positions"][ok] - ref[ok]) ** 2).sum(-1).mean(-1)) / diag
            ms = out["step_ms"][2:][np.isfinite(out["step_ms"][2:])]
            print(
                f"| {scene} | {X.size:,} | {label} | {len(ms)} | {np.median(ms):.1f} | {ms.mean():.1f} | "
                f"{out['iterations'][2:].mean():.1f} | {err.mean():.4f} | {err.max():.4f} | {out['diverged_frame']} | "
                + " | ".join(f"{np.nanmedian(out[k + '_ms'][2:]):.1f}" for k in ("map", "derivatives", "reduce", "line_search"))
                + " |",
                flush=True,
            )
    print("\n| scene | subspace | cubature elements | force error (training poses) | force error (held out) | fit s |")
    print("|---|---|---|---|---|---|")
    print("\n".join(fits))


if __name__ == "__main__":
    main()
