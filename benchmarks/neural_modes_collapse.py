"""Mode collapse (Wang et al. 2024, Sec. 4.4, Fig. 4): latent directions at the origin, Neural Modes vs Sharp et al. 2023.

    nice python benchmarks/neural_modes_collapse.py nm_giraffe [--epochs 20 --batch 32 --w-iso 1.0]

Loads the scene's trained Neural Modes (results/neural_modes/{scene}/neural_modes.pt), trains the
data-free subspace of Sharp et al. 2023 (energy + isometry regulariser, latentsim.nm_sheet.DataFree)
with the same widths, latent dimension, box and Dirichlet set, and prints the eigenvalues of the
normalised mass-weighted correlation matrix of the latent directions dx/dz at z = 0 for both
(Neural Modes target: all in [0.5, 2]; an eigenvalue near 0 is a collapsed direction).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from latentsim import neural_modes as nm
from latentsim import nm_pipeline, nm_sheet

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--w-iso", type=float, default=1.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    import yaml

    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    params = nm_pipeline.scene_params({"scenes": {args.scene: {"neural_modes": {}, **cfg["scenes"][args.scene]}}}, args.scene)
    settings = {**nm.NM_DEFAULTS, **params["neural_modes"]}
    pot, arrays = nm_pipeline.scene_potential(ROOT / "results" / "mesh" / args.scene / "mesh.h5", params["model"], params["material"])
    masses = pot.masses.numpy()
    model = nm.load_neural_modes(ROOT / "results" / "neural_modes" / args.scene / "neural_modes.pt")
    C_nm, w_nm = nm.direction_correlation(nm.latent_directions(model, model.m).numpy(), masses)
    fixed = np.flatnonzero(model.mask.numpy() == 0)
    torch.manual_seed(0)
    sharp = nm_sheet.DataFree(arrays["rest_positions"], model.m, settings["widths"], fixed_dofs=fixed)
    scale = float(np.sqrt((np.repeat(masses, 3)[:, None] * model.E.numpy() ** 2).sum(0)).mean())
    t0 = time.perf_counter()
    nm_sheet.train_data_free(sharp, pot, settings["box"], scale, args.w_iso, args.epochs, args.batch)
    C_sh, w_sh = nm.direction_correlation(nm.latent_directions(sharp, model.m).numpy(), masses)
    print(f"{args.scene}: {model.m} latent dimensions; Sharp et al. trained {args.epochs} L-BFGS epochs in {time.perf_counter() - t0:.0f} s")
    print("| method | correlation eigenvalues | min | max |")
    print("|---|---|---|---|")
    for label, w in (("Neural Modes", w_nm), ("Sharp et al. 2023", w_sh)):
        print(f"| {label} | {' '.join(f'{v:.3f}' for v in w)} | {w.min():.3f} | {w.max():.3f} |")
    np.set_printoptions(precision=3, suppress=True)
    print("Neural Modes correlation matrix:\n", C_nm, "\nSharp et al. correlation matrix:\n", C_sh)


if __name__ == "__main__":
    main()
