"""Where a plateau rule would have ended each supervised training of a run, read from its loss histories.

    python benchmarks/plateau_rule.py RESULTS [--window 100] [--tolerance 0.02] [--methods supervised_5x256 ...]

For every ``RESULTS/integrator/<scene>/<method>/seed<k>/history.h5`` of a supervised method (by default the
variants named ``supervised*``), the epoch at which ``integrator.plateau_stop`` {window, tolerance}
(:class:`latentsim.latent.base.PlateauStop`) would have stopped it, the share of its epochs saved, and its
loss there against its last epoch's and against the spread of its last ``window`` epochs (how far the stop
lies from where the training ended, in the training's own late noise).  The trainings are deterministic, so a
training stopped by the rule is the first epochs of the one recorded: this tells what a rule would save and
where it would leave the loss without training again.  What it does to the test errors and divergences
takes a run with the rule (``benchmarks/before_after.py``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from latentsim.latent.base import PlateauStop  # noqa: E402 (the rule itself, not a copy)


def stop_epoch(losses, rule: PlateauStop) -> int:
    """The number of epochs a training with these epoch losses runs under ``rule`` (all of them if it never stops)."""
    for n in range(1, len(losses) + 1):
        if rule.reached(losses[:n]):
            return n
    return len(losses)


def plateau_table(results, window: int, tolerance: float, methods=None) -> pd.DataFrame:
    """One row per supervised training: scene, method, seed, epochs, stop, saved, loss at the stop, last loss,
    and the last window's spread (its largest over its least loss)."""
    rule, rows = PlateauStop(window, tolerance), []
    for path in sorted(Path(results, "integrator").glob("*/*/seed*/history.h5")):
        scene, method, seed = path.parts[-4], path.parts[-3], path.parts[-2]
        if (methods and method not in methods) or (not methods and not method.startswith("supervised")):
            continue
        with h5py.File(path, "r") as f:
            losses = [float(v) for v in f["loss"][()]]
        n = stop_epoch(losses, rule)
        tail = np.asarray(losses[-window:])
        rows.append({"scene": scene, "method": method, "seed": int(seed[4:]), "epochs": len(losses), "stop": n,
                     "saved": round(1 - n / len(losses), 3), "loss at stop": losses[n - 1], "last loss": losses[-1],
                     "stop / last": losses[n - 1] / losses[-1], "last window max / min": float(tail.max() / tail.min())})  # fmt: skip
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", help="a run's results folder")
    ap.add_argument("--window", type=int, default=100)
    ap.add_argument("--tolerance", type=float, default=0.02)
    ap.add_argument("--methods", nargs="*", help="these methods (default: the variants named supervised*)")
    args = ap.parse_args(argv)
    table = plateau_table(args.results, args.window, args.tolerance, args.methods)
    if table.empty:
        print(f"{args.results}: no supervised training history")
        return 1
    print(table.to_markdown(index=False, floatfmt=".4g"))
    print(f"\nwindow {args.window}, tolerance {args.tolerance}: {table['saved'].mean():.0%} of the epochs saved on average; "
          f"loss at the stop / last loss: median {table['stop / last'].median():.3g}, largest {table['stop / last'].max():.3g}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
