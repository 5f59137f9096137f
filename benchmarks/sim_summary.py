"""Summarise the simulations a run produced: frames, Newton iterations and ms per frame per scene.

    python benchmarks/sim_summary.py [results/sim]

Reads every results/sim/<scene>/trajectories.h5 (sequences stored twice as <name>_train are counted
once) and prints a Markdown table.  Timings are those of the run itself (jobs may have shared cores).
"""

import sys
from pathlib import Path

import h5py
import numpy as np


def main(root="results/sim"):
    print("| scene | DoF | sequences | frames | Newton it/frame (mean, max) | ms/frame (mean) | max residual / tolerance |")
    print("|---|---|---|---|---|---|---|")
    for path in sorted(Path(root).glob("*/trajectories.h5")):
        with h5py.File(path) as f:
            tol = f.attrs["newton_tolerance"] * f.attrs["force_scale"]
            names = [n for n in f["sequences"] if not (n.endswith("_train") and n[: -len("_train")] in f["sequences"])]
            its = np.concatenate([f["sequences"][n]["newton_iterations"][1:] for n in names])
            ms = np.concatenate([f["sequences"][n]["frame_ms"][1:] for n in names])
            res = max(np.nanmax(f["sequences"][n]["gradient_norm"][1:]) for n in names)
            print(f"| {path.parent.name} | {f['rest_positions'].size:,} | {len(names)} | {len(its) + len(names):,} | "
                  f"{its.mean():.2f}, {its.max()} | {ms.mean():.1f} | {res / tol:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main(*sys.argv[1:])
