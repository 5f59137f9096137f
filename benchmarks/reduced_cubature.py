"""Reduced implicit Euler with every element against cubatures of several tolerances.

    nice python benchmarks/reduced_cubature.py cantilever [--tolerances 0 0.1 0.03 0.01 0.003] [--seed 0]

Needs the scene's full simulation and its autoencoder of seed ``--seed`` (default 0,
``results/autoencoder/{scene}/seed{k}/autoencoder.pt``; rules simulate, train_autoencoder).  For the PCA
subspace and the autoencoder's decoder (Fulton et al. 2019), fits a cubature of the elastic forces
(latentsim.solve.cubature) at the projections of the training frames, as the pipeline's baselines do with
``reduced.cubature_tolerance``, and rolls the first test sequence out from its first two frames.
Tolerance 0 evaluates every element.  Prints, per run: cubature elements, its force error on the
training poses, fit seconds, ms/step (median), iterations/step, the RMS vertex error / bbox diagonal
against the full simulation (mean and max over frames), and the frame where the rollout failed (-1:
none); and the full-space Newton frame timed in the same run.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
from pathlib import Path

import h5py
import numpy as np
import torch

from latentsim import latent
from latentsim.config import seed_dir
from latentsim.solve import reduced
from latentsim.stages.baselines import fit_subspace_cubature, make_subspace
from latentsim.solve.cubature import cubature_potential
from latentsim.report.metrics import bbox_diagonal
from latentsim.scene import potential_from_artefact
from latentsim.latent import coordinates_for, load_sequences
from latentsim.latent.timing import time_full_space

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--tolerances", type=float, nargs="+", default=[0.0, 0.1, 0.03, 0.01, 0.003])
    ap.add_argument("--methods", nargs="+", default=["pca_reduced", "fulton_reduced"])
    ap.add_argument("--frames", type=int, default=0, help="first frames of the test sequence (0: all)")
    ap.add_argument("--seed", type=int, default=0, help="the seed of the autoencoder (default: %(default)s)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    with h5py.File(ROOT / "results" / "sim" / args.scene / "trajectories.h5", "r") as f:
        coords = coordinates_for(f)
        train, tests = load_sequences(f, "train"), load_sequences(f, "test")
        pot = potential_from_artefact(f)
        name = next(iter(tests))
        full = time_full_space(f, name)
        X = f["rest_positions"][()]
    ae = latent.load_autoencoder(ROOT / "results" / "autoencoder" / args.scene / seed_dir(args.seed) / "autoencoder.pt")
    seq = tests[name]
    T = args.frames or len(seq["positions"])
    ref, xD = seq["positions"][:T], seq["dirichlet_positions"][:T]
    diag = bbox_diagonal(X)
    n_el = sum(len(t.stencils) for t in pot.terms)
    print(f"{args.scene}: {X.size:,} DoF, {n_el:,} elements; test '{name}', {T} frames; "
          f"full-space Newton {full.get('full_ms', float('nan')):.2f} ms/frame (same run)\n")  # fmt: skip
    print("| method | cubature tolerance | elements | force error (training poses) | fit s | ms/step median | iterations/step | error mean | error max | failed at |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for method in args.methods:
        sub = make_subspace(method, ae, coords, train, {})
        for tol in args.tolerances:
            p, label = pot, (f"{n_el} (all)", "-", "-")
            if tol > 0:
                cub = fit_subspace_cubature(pot, sub, train, {"cubature_tolerance": tol})
                p, label = cubature_potential(pot, cub), (str(len(cub.index)), f"{cub.train_error:.4f}", f"{cub.fit_seconds:.1f}")
            q0, q1 = sub.project(ref[0], xD[0]), sub.project(ref[1], xD[1])
            out = reduced.reduced_rollout(sub, p, q0, q1, xD, reduced.ReducedSettings())
            ok = np.isfinite(out["positions"]).all(axis=(1, 2))
            err = np.sqrt(((out["positions"][ok] - ref[ok]) ** 2).sum(-1).mean(-1)) / diag
            ms = out["step_ms"][np.isfinite(out["step_ms"])]
            print(
                f"| {method} | {tol:g} | {label[0]} | {label[1]} | {label[2]} | {np.median(ms):.2f} | {out['iterations'][2:].mean():.1f} | "
                f"{err.mean():.2e} | {err.max():.2e} | {out['diverged_frame']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
