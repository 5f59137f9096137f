"""Mode collapse (Wang et al. 2024, Sec. 4.4, Fig. 4): latent directions at the origin, Neural Modes vs Sharp et al. 2023.

    nice python benchmarks/neural_modes_collapse.py nm_giraffe [--epochs 20 --batch 32 --w-iso 1.0]

Loads the scene's trained Neural Modes (results/neural_modes/{scene}/neural_modes.pt), trains the
data-free subspace of Sharp et al. 2023 (energy + isometry regulariser, latentsim.neural_modes.baselines.DataFree)
with the same widths, latent dimension, box and Dirichlet set (``latentsim.neural_modes.baselines.mode_collapse``, as
the sheet study does), and prints the eigenvalues of the normalised mass-weighted correlation matrix of
the latent directions dx/dz at z = 0 for both (Neural Modes target: all in [0.5, 2]; an eigenvalue near
0 is a collapsed direction).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from latentsim import neural_modes as nm
from latentsim.stages import neural_modes as nm_pipeline
from latentsim.neural_modes import baselines as nm_baselines
from latentsim.config import load_config

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--w-iso", type=float, default=1.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sc = load_config(ROOT / "config" / "config.yaml")["scenes"][args.scene]
    settings = sc["neural_modes"]
    pot, arrays = nm_pipeline.scene_potential(ROOT / "results" / "mesh" / args.scene / "mesh.h5", sc["model"], sc["material"])
    model = nm.load_neural_modes(ROOT / "results" / "neural_modes" / args.scene / "neural_modes.pt")
    fixed = np.flatnonzero(model.mask.numpy() == 0)
    t0 = time.perf_counter()
    out = nm_baselines.mode_collapse(
        pot, arrays["rest_positions"], model.E.numpy(), {"Neural Modes": model}, settings["widths"], settings["box"],
        {"epochs": args.epochs, "batch_size": args.batch, "w_iso": args.w_iso}, fixed_dofs=fixed,
    )  # fmt: skip
    print(f"{args.scene}: {model.m} latent dimensions; Sharp et al. trained {args.epochs} L-BFGS epochs in {time.perf_counter() - t0:.0f} s")
    print("| method | correlation eigenvalues | min | max |")
    print("|---|---|---|---|")
    for label, c in out.items():
        w = c["eigenvalues"]
        print(f"| {label} | {' '.join(f'{v:.3f}' for v in w)} | {w.min():.3f} | {w.max():.3f} |")
    np.set_printoptions(precision=3, suppress=True)
    for label, c in out.items():
        print(f"{label} correlation matrix:\n", c["matrix"])


if __name__ == "__main__":
    main()
