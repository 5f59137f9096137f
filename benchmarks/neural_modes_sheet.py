"""Neural Modes on the square sheet: Tables 2, 3, 4, A1, Figs. 2-4 numbers (Wang et al. 2024), outside the pipeline.

    nice python benchmarks/neural_modes_sheet.py                      # paper sizes (9^3 / 7^3 / 11^3 grids)
    nice python benchmarks/neural_modes_sheet.py --train-grid 7 --val-grid 5 --test-grid 9 --random 343 \
        --batch-size 343 --epochs 40 --sharp-epochs 20     # the run in the README: ~40 min on 2 shared cores

The pipeline's stages (rules nm_ground_truth, nm_sheet_study, nm_sheet_tables; the nm_sheet scene's
``nm_study.sheet`` block) do the same with the scene's mesh and settings; this script calls the same
functions (``latentsim.neural_modes.sheet``) on the shared square.obj with sizes from the command line.  The sheet
is the Neural Modes square (121 vertices, 200 triangles, free-floating as in the paper's released sheet
setup), with the material of the ``nm_sheet`` scene in config/config.yaml and its ``neural_modes`` block
(modes, box, widths, lambda, eta).  Ground truth (Eq. 9) is solved once per set of sizes and cached in
results/neural_modes/nm_sheet/benchmark_gt_*.pkl.  Prints the tables in Markdown and writes CSV +
Markdown beside the cache.  The paper's columns are the paper's own numbers (its sheet material is not
published, so absolute energies differ; compare the ratios).
"""

from __future__ import annotations

import argparse
import logging
import pickle
from pathlib import Path

import numpy as np
import torch

from latentsim import neural_modes as nm
from latentsim.neural_modes import sheet as nm_sheet
from latentsim.neural_modes import sheet_tables as nm_tables
from latentsim.config import load_config
from latentsim.mesh import read_mesh
from latentsim.scene import build_elastic

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--train-grid", type=int, default=9)
    ap.add_argument("--val-grid", type=int, default=7)
    ap.add_argument("--test-grid", type=int, default=11)
    ap.add_argument("--random", type=int, default=729)
    ap.add_argument("--epochs", type=int, default=None, help="Neural Modes epochs (default: the config's nm_study.sheet)")
    ap.add_argument("--batch-size", type=int, default=None, help="stochastic Neural Modes batch (default: the config's)")
    ap.add_argument("--l2-epochs", type=int, default=100)
    ap.add_argument("--ae-epochs", type=int, default=1000)
    ap.add_argument("--curve-points", type=int, default=20, help="checkpoints along each training (learning curves, early stopping)")
    ap.add_argument("--sharp-epochs", type=int, default=50)
    ap.add_argument("--gt-max-iter", type=int, default=40)
    ap.add_argument("--mesh", default=str(ROOT.parent / "shared" / "meshes" / "square.obj"))
    ap.add_argument("--out", default=str(ROOT / "results" / "neural_modes" / "nm_sheet"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)

    scene = load_config(ROOT / "config" / "config.yaml")["scenes"]["nm_sheet"]
    nmc, st = scene["neural_modes"], dict(scene["nm_study"]["sheet"])
    st.update(
        train_grid=args.train_grid, val_grid=args.val_grid, test_grid=args.test_grid, random_samples=args.random, l2_epochs=args.l2_epochs,
        ae_epochs=args.ae_epochs, curve_points=args.curve_points, sharp_epochs=args.sharp_epochs, gt_max_iterations=args.gt_max_iter,
        epochs=args.epochs or st["epochs"], batch_size=args.batch_size or st["batch_size"],
    )  # fmt: skip
    mesh = read_mesh(args.mesh)
    X = mesh.vertices * float(scene["mesh"].get("scale", 1.0))
    arrays = {"rest_positions": X, "triangles": mesh.triangles, "dirichlet": np.zeros(0, dtype=np.int64)}
    pot = build_elastic("shell", arrays, scene["material"])
    m = nmc["modes"]
    lm = nm.linear_modes(pot, m, X, boundary="free", normalization="euclidean")
    basis = {"X": X, "modes": lm.modes, "fixed_dofs": np.zeros(0, dtype=np.int64), "rigid": nm.rigid_modes(X, pot.masses.numpy())}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    key = f"{m}m_{nmc['box']}_{args.train_grid}-{args.random}-{args.val_grid}-{args.test_grid}_{nmc['metric']}_{args.gt_max_iter}"
    cache = out / f"benchmark_gt_{key}.pkl"
    if cache.exists():
        gt = pickle.loads(cache.read_bytes())
    else:
        sets = nm_sheet.sample_sets(m, nmc["box"], args.train_grid, args.val_grid, args.test_grid, args.random)
        gt = nm_sheet.solve_sets(pot, X, lm.modes, sets, rigid=basis["rigid"], metric=nmc["metric"], max_iter=args.gt_max_iter, progress=True)
        tmp = cache.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps(gt))
        tmp.rename(cache)
    study = nm_sheet.run_sheet_study(pot, basis, gt, nmc, st, mesh.triangles, progress=True)
    tabs = nm_tables.tables(study)
    print(f"\nSquare sheet, {m} modes, box {nmc['box']}, grids train {args.train_grid}^{m} (random {args.random}), "
          f"validation {args.val_grid}^{m}, test {args.test_grid}^{m}; Neural Modes {st['epochs']} L-BFGS epochs")  # fmt: skip
    for name, s in gt.items():
        print(f"ground truth {name}: {len(s['z'])} samples, E_avg {s['energy'].mean():.3f} J, median KKT residual "
              f"{np.median(s['residual']):.1e}, 90th pct {np.percentile(s['residual'], 90):.1e}")  # fmt: skip
    print("training seconds:", {r["label"]: round(r["train_seconds"]) for r in study["methods"].values()})
    for name, df in tabs.items():
        df.to_csv(out / f"benchmark_{name}.csv", index=False)
        md = df.to_markdown(index=False, floatfmt=".4g")
        (out / f"benchmark_{name}.md").write_text(md + "\n")
        print(f"\n{name}\n{md}")


if __name__ == "__main__":
    main()
