"""Neural Modes on the armadillo against PCA+AE: Wang et al. 2024, Table 5.

    snakemake --cores 1 --configfile <config with nm_armadillo> results/neural_modes/nm_armadillo/neural_modes.pt
    nice python benchmarks/neural_modes_armadillo.py                       # the paper's 1,300 samples
    nice python benchmarks/neural_modes_armadillo.py --samples 260         # 180 / 20 / 60, the same split ratios

Samples modal coordinates uniformly in the scene's modal box (``neural_modes.box`` of ``nm_armadillo``
in config/config.yaml), solves the ground truth of each (Eq. 9: minimum elastic energy with l^T y = 0,
the held feet fixed; constrained Newton) and splits them in order 900 / 100 / 300 (train / validation
/ test; scaled with ``--samples``).  PCA+AE (Fulton et al. 2019, the pipeline's autoencoder) is trained
on the training states for ``--ae-epochs`` (its validation L2 is printed); the trained Neural Modes
(rule nm_train; they never see a ground-truth state) are evaluated at the test coordinates.  Prints the mean
elastic energy of each over every 20% interval of the test set and over all of it, with the paper's
row alongside (its material is not ours: compare ratios), and the mean L2 position error; writes CSV
and Markdown to results/neural_modes/nm_armadillo/table5.{csv,md}.  The ground truth is cached in
results/neural_modes/nm_armadillo/table5_gt_<samples>_<iterations>.npz.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from latentsim import neural_modes as nm
from latentsim.config import load_config
from latentsim.latent import fit_autoencoder
from latentsim.nm_pipeline import scene_potential

ROOT = Path(__file__).resolve().parents[1]
SCENE = "nm_armadillo"
PAPER = {  # Table 5, x 1e4: intervals 0-20% ... 80-100%, all
    "Ground truth": [12.3, 9.7, 12.5, 10.9, 10.8, 11.3],
    "PCA+AE": [106.7, 4329.9, 216.5, 179.5, 104.8, 987.5],
    "Neural Modes": [57.1, 58.0, 58.9, 52.3, 51.9, 55.8],
}


def energies(pot, x, chunk=50) -> np.ndarray:
    with torch.no_grad():
        return np.concatenate([pot.elastic(torch.as_tensor(x[i : i + chunk])).numpy() for i in range(0, len(x), chunk)])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=1300)
    ap.add_argument("--gt-max-iter", type=int, default=40)
    ap.add_argument("--ae-epochs", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sc = load_config(ROOT / "config" / "config.yaml")["scenes"][SCENE]
    cfg = {**nm.NM_DEFAULTS, **sc["neural_modes"]}
    out_dir = ROOT / "results" / "neural_modes" / SCENE
    pot, _ = scene_potential(ROOT / "results" / "mesh" / SCENE / "mesh.h5", sc["model"], sc["material"])
    with h5py.File(out_dir / "linear_modes.h5", "r") as f:
        X, modes, free = f["rest_positions"][()], f["modes"][()], f["free_dofs"][()]
    model = nm.load_neural_modes(out_dir / "neural_modes.pt")
    m, n = modes.shape[1], len(X)
    gen = torch.Generator().manual_seed(args.seed)
    z = nm.modal_samples("stochastic", m, float(cfg["box"]), args.samples, generator=gen).numpy()
    n_train, n_val = round(args.samples * 900 / 1300), round(args.samples * 100 / 1300)

    cache = out_dir / f"table5_gt_{args.samples}_{args.gt_max_iter}.npz"
    if cache.exists():
        gt = dict(np.load(cache))
    else:
        t0 = time.perf_counter()
        bar = tqdm(total=len(z), desc="ground truth")
        x, e, infos = nm.ground_truth(
            pot, X, modes, z, free_dofs=free, metric=cfg["metric"], max_iter=args.gt_max_iter, progress=lambda i, info: bar.update(1)
        )
        bar.close()
        gt = {"z": z, "x": x, "energy": e, "residual": np.array([i.residual for i in infos]), "iterations": np.array([i.iterations for i in infos])}
        gt["seconds"] = np.array(time.perf_counter() - t0)
        tmp = cache.with_suffix(".tmp.npz")
        np.savez(tmp, **gt)
        tmp.replace(cache)
    print(f"{SCENE}: {X.size:,} DoF, {m} modes, box {cfg['box']}; {args.samples} samples ({n_train} / {n_val} / "
          f"{args.samples - n_train - n_val}); ground truth {float(gt['seconds']):.0f} s, {gt['iterations'].mean():.1f} iterations, "
          f"median KKT residual {np.median(gt['residual']):.1e}")  # fmt: skip

    Xf = X.reshape(-1)
    U = torch.as_tensor(gt["x"].reshape(len(z), -1) - Xf)
    tr, va, te = slice(0, n_train), slice(n_train, n_train + n_val), slice(n_train + n_val, None)
    t0 = time.perf_counter()
    ae_cfg = {"latent_dim": m, "widths": list(cfg["widths"]), "epochs": args.ae_epochs, "lr": 1e-3, "batch_size": 64}
    ae, hist = fit_autoencoder(U[tr], ae_cfg, seed=args.seed)
    ae = ae.double()
    with torch.no_grad():
        rec = lambda s: (ae(U[s]).numpy() + Xf).reshape(-1, n, 3)  # noqa: E731
        val_l2 = float(((rec(va) - gt["x"][va]) ** 2).sum((-1, -2)).mean())
        pred_ae = rec(te)
        pred_nm = model(torch.as_tensor(z[te])).numpy().reshape(-1, n, 3)
    ae_seconds = time.perf_counter() - t0

    x_gt = gt["x"][te]
    rows = []
    for label, x in (("Ground truth", x_gt), ("PCA+AE", pred_ae), ("Neural Modes", pred_nm)):
        e = energies(pot, x)
        parts = np.array_split(e, 5)
        l2 = float(((x - x_gt) ** 2).sum((-1, -2)).mean())
        rows.append({"method": label, **{f"{20 * i}-{20 * (i + 1)}%": float(p.mean()) for i, p in enumerate(parts)}, "all": float(e.mean()), "l2": l2,
                     **{f"paper {k}": v for k, v in zip(["0-20%", "20-40%", "40-60%", "60-80%", "80-100%", "all"], PAPER[label])}})  # fmt: skip
    table = pd.DataFrame(rows)
    table.to_csv(out_dir / "table5.csv", index=False)
    md = table.to_markdown(index=False, floatfmt=".4g")
    (out_dir / "table5.md").write_text(md + "\n")
    print(f"PCA+AE: {args.ae_epochs} epochs in {ae_seconds:.0f} s (kept {hist['kept']}), validation L2 {val_l2:.4g}\n")
    print(md)


if __name__ == "__main__":
    main()
