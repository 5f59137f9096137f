"""Subspace dynamics in Neural Modes (Eq. 15) against linear modes and the full simulation, outside the pipeline.

    nice python benchmarks/neural_modes_dynamics.py nm_giraffe nm_bunny [--frames 120] [--cubature-tolerance 0.01]

The pipeline's rule nm_dynamics does this for every scene whose ``nm_study.dynamics`` is enabled (and
writes the rolled-out positions and ParaView series); this script calls the same function
(``latentsim.neural_modes.dynamics.subspace_dynamics``) and prints its rows.  Needs, per scene, the full simulation
(results/sim/{scene}/trajectories.h5) and the trained Neural Modes (results/neural_modes/{scene}/
neural_modes.pt, rule nm_train).  Replays the first test sequence's prescribed Dirichlet motion in the
subspace with the reduced implicit-Euler solver (latentsim.solve.reduced): Neural Modes with L-BFGS (as the
paper) and with Gauss-Newton on the reduced Hessian J^T H J (the paper's future work), and the linear
modes alone with Gauss-Newton, each with every element and with a cubature (latentsim.solve.cubature) fitted
to each subspace's reduced elastic forces at poses drawn in the scene's Neural Modes training box
(data-free, like the modes).  Prints ms/step (median and mean), iterations per step, the position error
against the full simulation (mean and max over frames of the RMS vertex error, relative to the rest
bounding-box diagonal) and the median split of a Gauss-Newton step; the full-space Newton frame of the
same sequence is timed in the same run (the mean over 20 frames spread over it, as the rollout stage does).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core per step, as the timings are meant (set before numpy loads)

import argparse
from pathlib import Path

import h5py
import torch

from latentsim.config import load_config
from latentsim.neural_modes import load_neural_modes
from latentsim.neural_modes.dynamics import first_test_sequence, subspace_dynamics
from latentsim.latent.timing import time_full_space

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
    settings = {"frames": args.frames, "max_iterations": 100, "cubature_tolerance": args.cubature_tolerance,
                "cubature_samples": args.cubature_samples, "cubature_max_elements": args.cubature_max, "full_frames_timed": 20}  # fmt: skip
    fits = []
    for scene in args.scenes:
        model = load_neural_modes(ROOT / "results" / "neural_modes" / scene / "neural_modes.pt")
        with h5py.File(ROOT / "results" / "sim" / scene / "trajectories.h5", "r") as f:
            full = time_full_space(f, first_test_sequence(f), settings["full_frames_timed"])
            res = subspace_dynamics(f, model, float(scenes_cfg[scene]["neural_modes"]["box"]), settings, full, progress=True)
            dof = f["rest_positions"].size
        print(f"\n{scene} ({dof:,} DoF), sequence {res['sequence']}\n" + res["rows"].to_markdown(index=False, floatfmt=".4g"), flush=True)
        for kind, c in res["cubatures"].items():
            fits.append(f"| {scene} | {kind} modes | {len(c.index)} of {c.n_elements} | {c.train_error:.4f} | {c.validation_error:.4f} | {c.fit_seconds:.1f} |")
    print("\n| scene | subspace | cubature elements | force error (training poses) | force error (held out) | fit s |")
    print("|---|---|---|---|---|---|")
    print("\n".join(fits))


if __name__ == "__main__":
    main()
