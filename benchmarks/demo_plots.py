"""Render the looking-at-results figures from whatever results/ holds now.

    python benchmarks/demo_plots.py [--scene cloth] [--seed 0] [--out results/demo_plots]

For one scene (default cloth) with ``results/sim/{scene}/trajectories.h5``: ground
truth against the rollouts of seed ``--seed`` (default 0; the methods no seed changes
have one) side by side at a few frames, a GIF clip, the
kinetic energy over time and an XDMF series of the rollout with its per-vertex
error (open ``paraview/<scene>_<sequence>_<method>.xdmf`` in ParaView, then *Warp By Vector* on
``displacement``).  Across scenes, where the files exist: the speed-accuracy
chart and a stability map from ``results/evaluation/summary.csv`` (every
method against the full-space solver; the stability map of seed ``--seed``), and the
training histories of ``results/integrator/*/*/seed{k}/history.h5``.
Nothing here is part of the workflow; it shows what the functions draw.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pandas as pd

from latentsim.config import seed_dir
from latentsim.report import paraview, plots, render
from latentsim.report.tables import speed_accuracy_points, stability_table


def _frames_to_show(T: int, diverged: int, k=4) -> list[int]:
    """k frames spread over the sequence, one of them just before divergence."""
    frames = set(np.linspace(0, T - 1, k).astype(int).tolist())
    if diverged > 0:
        frames.add(max(diverged - 1, 0))
    return sorted(frames)


def _rollouts(scene: str, seed: int = 0) -> dict:
    """Method name -> rollout file of ``seed``: ``results/rollout/{scene}/{method}/seed{k}/rollout.h5`` of a
    method trained (or reducing with a model trained) per seed, ``results/rollout/{scene}/{method}/rollout.h5``
    of one no seed changes."""
    base = Path(f"results/rollout/{scene}")
    found = {p.parent.name: p for p in sorted(base.glob("*/rollout.h5"))}
    found.update({p.parents[1].name: p for p in sorted(base.glob(f"*/{seed_dir(seed)}/rollout.h5"))})
    return found


def scene_figures(scene: str, out: Path, seed: int = 0) -> None:
    truth = Path(f"results/sim/{scene}/trajectories.h5")
    if not truth.exists():
        print(f"skip {scene}: {truth} missing")
        return
    methods = _rollouts(scene, seed)
    with h5py.File(truth, "r") as f:
        common = [n for n, g in f["sequences"].items() if g.attrs.get("split") == "test"]
    for p in methods.values():
        with h5py.File(p, "r") as f:
            common = [n for n in common if n in f["sequences"]]
    if not common:
        print(f"skip {scene}: no test sequence common to the ground truth and {sorted(methods)}")
        return
    seq = common[0]
    with h5py.File(truth, "r") as f:
        T = f[f"sequences/{seq}/positions"].shape[0]
    div = -1
    for p in methods.values():
        with h5py.File(p, "r") as f:
            d = int(f[f"sequences/{seq}"].attrs.get("diverged_frame", -1))
        div = d if d >= 0 and (div < 0 or d < div) else div
    t0 = time.perf_counter()
    frames = _frames_to_show(T, div)
    r = render.render_frames(truth, methods, seq, frames, out / f"{scene}_{seq}_frames.png", bounds="row", color_by_error=True)
    print(f"{scene}/{seq}: frames {frames} -> {r['status'].tolist()} ({time.perf_counter() - t0:.1f} s)")
    t0 = time.perf_counter()
    stride = max(1, T // 60)
    r = render.render_clip(truth, methods, seq, out / f"{scene}_{seq}.gif", stride=stride, max_frames=60, color_by_error=True)
    print(f"{scene}/{seq}: clip of {len(r['frames'])} frames, {r['bytes'] / 1e6:.2f} MB ({time.perf_counter() - t0:.1f} s)")
    if methods:
        plots.energy_curves_from_files(truth, methods, seq, out / f"{scene}_{seq}_energy.png")
    for name, p in methods.items():
        r = paraview.write_xdmf_series(p, seq, out / "paraview" / f"{scene}_{seq}_{name}.xdmf", reference=truth)
        print(f"{scene}/{seq}/{name}: XDMF series, {r['frames']} steps, fields {r['fields']}")


def summary_figures(out: Path, seed: int = 0) -> None:
    table = Path("results/evaluation/summary.csv")
    if table.exists():
        df = pd.read_csv(table)
        pts = speed_accuracy_points(df)  # every method over its seeds, and the full-space solver at error 0
        plots.speed_accuracy_chart(pts, out / "speed_accuracy.png")
        print("speed-accuracy: on the front ->", pts.loc[pts["on_front"], ["scene", "method"]].values.tolist())
        for scene in sorted(df["scene"].unique())[:1]:
            plots.speed_accuracy_chart(pts, out / f"speed_accuracy_{scene}.png", scene=scene)
        st = stability_table(df)
        st = st[st["seed"].isin([seed, -1])]  # one row per method and sequence: the seed's, or the method's only run
        stab = pd.DataFrame(
            {
                "method": st["scene"] + " / " + st["method"],
                "condition": st["sequence"],
                "frames_survived": st["survived"],
                "frames": st["frames"],
                "bc_error": st["dirichlet_error"],
                "diverged_frame": st["diverged_frame"],
            }
        )
        plots.stability_heatmap(stab, out / "stability.png", title=f"test sequences, seed {seed}: frames survived (BC: mean Dirichlet error)")
    root = Path("results/integrator")
    files = sorted(root.glob(f"*/*/{seed_dir(seed)}/history.h5"))
    histories = {str(p.parents[1].relative_to(root)): p for p in files}
    if histories:
        r = plots.training_curves(histories, out / "training_integrator.png", title="latent integrator training")
        print(f"training curves: {len(histories)} runs, y axis {r['yscale']}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cloth")
    ap.add_argument("--seed", type=int, default=0, help="whose trained models to show (default: %(default)s)")
    ap.add_argument("--out", default="results/demo_plots", type=Path)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    scene_figures(args.scene, args.out, args.seed)
    summary_figures(args.out, args.seed)
    print(f"written to {args.out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
