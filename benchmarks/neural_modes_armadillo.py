"""Neural Modes on the armadillo against PCA+AE: Wang et al. 2024, Table 5, outside the pipeline.

    snakemake --cores 1 results/neural_modes/nm_armadillo/neural_modes.pt
    nice python benchmarks/neural_modes_armadillo.py                       # the paper's 1,300 samples
    nice python benchmarks/neural_modes_armadillo.py --samples 260         # 180 / 20 / 60, the same split ratios

The pipeline's rules nm_ground_truth and nm_energy_table do this for every scene whose
``nm_study.energy`` is enabled; this script calls the same functions (``latentsim.neural_modes.energy_study``) with the
sample count from the command line.  Samples modal coordinates uniformly in the scene's modal box,
solves the ground truth of each (Eq. 9: minimum elastic energy with l^T y = 0, the held feet fixed;
constrained Newton) and splits them in order 900 / 100 / 300 (train / validation / test; scaled with
``--samples``).  PCA+AE (Fulton et al. 2019, the pipeline's autoencoder) is trained on the training
states for ``--ae-epochs`` and kept at its least validation L2; the trained Neural Modes (rule
nm_train; they never see a ground-truth state) are evaluated at the test coordinates.  Prints the mean
elastic energy of each over every 20% interval of the test set and over all of it, with the paper's row
alongside (its material is not ours: compare ratios), and the mean L2 position error; writes CSV and
Markdown to results/neural_modes/nm_armadillo/benchmark_table5.{csv,md}.  The ground truth is cached in
results/neural_modes/nm_armadillo/table5_gt_<samples>_<iterations>.npz.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from latentsim import neural_modes as nm
from latentsim.neural_modes import energy_study as nm_energy
from latentsim.neural_modes import sheet as nm_sheet
from latentsim.config import load_config
from latentsim.stages.neural_modes import read_linear_modes, scene_potential

ROOT = Path(__file__).resolve().parents[1]
SCENE = "nm_armadillo"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=1300)
    ap.add_argument("--gt-max-iter", type=int, default=40)
    ap.add_argument("--ae-epochs", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sc = load_config(ROOT / "config" / "config.yaml")["scenes"][SCENE]
    nmc, st = sc["neural_modes"], dict(sc["nm_study"]["energy"], ae_epochs=args.ae_epochs, widths=sc["neural_modes"]["widths"])
    out_dir = ROOT / "results" / "neural_modes" / SCENE
    pot, _ = scene_potential(ROOT / "results" / "mesh" / SCENE / "mesh.h5", sc["model"], sc["material"])
    basis = read_linear_modes(out_dir / "linear_modes.h5")
    model = nm.load_neural_modes(out_dir / "neural_modes.pt")
    n_train, n_val = round(args.samples * 900 / 1300), round(args.samples * 100 / 1300)
    sets = nm_energy.energy_sets(basis["modes"].shape[1], float(nmc["box"]), args.samples, n_train, n_val, args.seed)

    cache = out_dir / f"table5_gt_{args.samples}_{args.gt_max_iter}.npz"
    if cache.exists():
        flat = dict(np.load(cache))
        gt = {s: {k: flat[f"{s}/{k}"] for k in ("z", "x", "energy", "residual", "iterations")} for s in sets}
    else:
        t0 = time.perf_counter()
        gt = nm_sheet.solve_sets(pot, basis["X"], basis["modes"], sets, free_dofs=basis["free_dofs"], metric=nmc["metric"], max_iter=args.gt_max_iter, progress=True)
        print(f"ground truth: {time.perf_counter() - t0:.0f} s")
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, **{f"{s}/{k}": v for s, d in gt.items() for k, v in d.items() if k != "seconds"})
        tmp.replace(cache)
    res = np.concatenate([gt[s]["residual"] for s in gt])
    its = np.concatenate([gt[s]["iterations"] for s in gt])
    print(f"{SCENE}: {basis['X'].size:,} DoF, {model.m} modes, box {nmc['box']}; {args.samples} samples ({n_train} / {n_val} / "
          f"{args.samples - n_train - n_val}); {its.mean():.1f} iterations, median KKT residual {np.median(res):.1e}")  # fmt: skip
    t0 = time.perf_counter()
    table, hist = nm_energy.energy_table(pot, basis["X"], gt, model, st, args.seed, progress=True)
    print(f"PCA+AE: {args.ae_epochs} epochs ({time.perf_counter() - t0:.0f} s with its checkpoints), kept epoch "
          f"{hist['epochs'][hist['stop']]} (validation L2 {hist['val_l2'][hist['stop']]:.4g})\n")  # fmt: skip
    table.to_csv(out_dir / "benchmark_table5.csv", index=False)
    md = table.to_markdown(index=False, floatfmt=".4g")
    (out_dir / "benchmark_table5.md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    main()
