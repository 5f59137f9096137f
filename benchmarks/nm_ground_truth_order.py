"""Neural Modes ground truth (Eq. 9): the order the samples are solved in, given against nearest-neighbour.

    python benchmarks/nm_ground_truth_order.py nm_armadillo [--study energy] [--set train] [--samples 200]

Needs the scene's mesh and linear modes (``snakemake --cores 2 results/neural_modes/<scene>/linear_modes.h5``).
Takes the first ``--samples`` samples of one set of the study's ground truth (as rule ``nm_ground_truth``
draws them), solves them in the rows' order and along :func:`nearest_neighbour_order` (each sample
starts from the one solved before it), one thread, and prints per order the Newton iterations (total,
median, largest), the seconds, and how far the two solutions lie apart: the largest vertex distance over
the largest displacement of the sample, and the largest relative difference of the energies.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from latentsim.config import load_config  # noqa: E402
from latentsim.neural_modes.compliant_modes import ground_truth  # noqa: E402
from latentsim.rule_params import nm_ground_truth_params  # noqa: E402
from latentsim.stages import neural_modes as nm_pipeline  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def nearest_neighbour_order(z: np.ndarray) -> np.ndarray:
    """A visiting order of the rows of z (N, m): start at the row nearest the origin, then always the nearest row
    not yet visited (a greedy chain; O(N^2) distances, a second for the studies' few thousand samples).
    Consecutive samples of the chain are close, so each starts from a near neighbour's solution."""
    z = np.asarray(z, dtype=np.float64)
    n = len(z)
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.empty(n, np.int64)
    free = np.ones(n, bool)
    d = np.einsum("ij,ij->i", z, z)  # distances to the origin first
    for k in range(n):
        i = int(np.argmin(np.where(free, d, np.inf)))
        order[k], free[i] = i, False
        diff = z - z[i]
        d = np.einsum("ij,ij->i", diff, diff)
    return order


def subset_arguments(ap: argparse.ArgumentParser, samples: int) -> None:
    """The command line of a ground-truth subset: scene, --study, --set, --samples, --config, --results."""
    ap.add_argument("scene")
    ap.add_argument("--study", default="energy")
    ap.add_argument("--set", default="train")
    ap.add_argument("--samples", type=int, default=samples)
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--results", default=str(ROOT / "results"))


def study_subset(args) -> dict:
    """The first ``args.samples`` samples of one set of a study's ground truth, as rule ``nm_ground_truth``
    draws them: {params (the rule's), potential, arrays (the mesh's), basis (linear modes), z (N, m)}."""
    p = nm_ground_truth_params(load_config(args.config), args.scene, args.study)
    results = Path(args.results)
    pot, arrays = nm_pipeline.scene_potential(results / "mesh" / args.scene / "mesh.h5", p["model"], p["material"])
    basis = nm_pipeline.read_linear_modes(results / "neural_modes" / args.scene / "linear_modes.h5")
    sets = nm_pipeline.study_sets(args.study, basis["modes"].shape[1], float(p["neural_modes"]["box"]), p["sets"], p["seed"])
    return {"params": p, "potential": pot, "arrays": arrays, "basis": basis, "z": sets[args.set][: args.samples]}


def solution_gap(xa: np.ndarray, xb: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Per sample, the largest vertex distance between two solutions (N, n, 3) over the largest displacement of the first from X."""
    X = np.asarray(X).reshape(1, -1, 3)
    return np.linalg.norm(xa - xb, axis=-1).max(axis=1) / np.linalg.norm(xa - X, axis=-1).max(axis=1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    subset_arguments(ap, 200)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sub = study_subset(args)
    p, pot, basis, z = sub["params"], sub["potential"], sub["basis"], sub["z"]
    nmc = p["neural_modes"]
    solved = {}
    for order, visit in (("given", None), ("nearest", nearest_neighbour_order(z))):
        t0 = time.perf_counter()
        x, e, infos = ground_truth(pot, basis["X"], basis["modes"], z, free_dofs=basis["free_dofs"], rigid=basis["rigid"], metric=nmc["metric"],
                                   max_iter=int(p["max_iterations"]), order=visit)  # fmt: skip
        seconds = time.perf_counter() - t0
        its = np.array([i.iterations for i in infos])
        res = np.array([i.residual for i in infos])
        solved[order] = (x, e)
        print(f"{order:8s} {len(z)} samples: {seconds:.1f} s, iterations total {its.sum()}, median {np.median(its):g}, largest {its.max()}, "
              f"largest KKT residual {res.max():.2e}")  # fmt: skip
    (xa, ea), (xb, eb) = solved["given"], solved["nearest"]
    gap = solution_gap(xa, xb, basis["X"])
    print(f"solutions apart: largest vertex distance / largest displacement: median {np.median(gap):.2e}, largest {gap.max():.2e}; "
          f"energies: largest relative difference {np.max(np.abs(ea - eb) / np.abs(ea)):.2e}")  # fmt: skip


if __name__ == "__main__":
    main()
