"""Neural Modes ground truth (Eq. 9): convergence of the constrained Newton with and without the inversion guard.

    python benchmarks/nm_ground_truth_convergence.py nm_armadillo [--study energy] [--set train] [--samples 20]
    python benchmarks/nm_ground_truth_convergence.py nm_sheet --study sheet --set test --samples 150

Needs the scene's mesh and linear modes (``snakemake --cores 2 results/neural_modes/<scene>/linear_modes.h5``).
Takes the first ``--samples`` samples of one set of the study's ground truth (as rule ``nm_ground_truth``
draws them) and solves them in the rows' order, one thread, twice: ``unguarded``, the iteration as it
was before the guard (every step length allowed, no restart: ``ConstrainedNewton.inversion_free_step``
answers 1), and ``guarded``, the pipeline's (``latentsim.solve.constrained``: on tetrahedra no step
inverts an element, a warm start that ends blocked against a collapse is solved again from X + l).
Prints per variant the seconds, the Newton iterations (total, median, largest), how many samples reach
the tolerance (KKT residual <= rtol of the force at X + l) and the largest residual, the samples that end
with inverted tetrahedra and the least det F, and the mean energy; then how far the two variants' solutions
lie apart (the largest vertex distance over the largest displacement, per sample).  ``--variants guarded``
runs the pipeline's alone.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from unittest import mock

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from latentsim.neural_modes.compliant_modes import ground_truth  # noqa: E402
from latentsim.solve.constrained import ConstrainedNewton, volume_signs  # noqa: E402
from nm_ground_truth_order import solution_gap, study_subset, subset_arguments  # noqa: E402  (this folder: first on the path)

RTOL = 1e-5  # ground_truth's default, the pipeline's


def volume_ratios(x: np.ndarray, X: np.ndarray, tets) -> np.ndarray:
    """det F of every tetrahedron (E,) at positions x, rest X (n, 3)."""
    return volume_signs(x, tets) / volume_signs(X, tets)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    subset_arguments(ap, 20)
    ap.add_argument("--variants", default="unguarded,guarded")
    args = ap.parse_args()
    torch.set_num_threads(1)
    sub = study_subset(args)
    p, pot, arrays, basis, z = sub["params"], sub["potential"], sub["arrays"], sub["basis"], sub["z"]
    nmc = p["neural_modes"]
    tets = np.asarray(arrays["tets"], dtype=np.int64) if "tets" in arrays else None
    X = np.asarray(basis["X"], dtype=np.float64)
    print(f"{args.scene} {args.study}/{args.set}: {len(z)} samples, {len(X)} vertices, at most {p['max_iterations']} iterations, rtol {RTOL:g}")
    solved = {}
    for variant in args.variants.split(","):
        unguarded = mock.patch.object(ConstrainedNewton, "inversion_free_step", lambda self, x, dxf: 1.0)
        with unguarded if variant == "unguarded" else contextlib.nullcontext():
            t0 = time.perf_counter()
            x, e, infos = ground_truth(pot, X, basis["modes"], z, free_dofs=basis["free_dofs"], rigid=basis["rigid"], metric=nmc["metric"],
                                       rtol=RTOL, max_iter=int(p["max_iterations"]))  # fmt: skip
            seconds = time.perf_counter() - t0
        its = np.array([i.iterations for i in infos])
        res = np.array([i.residual for i in infos])
        solved[variant] = x
        line = (f"{variant:9s} {seconds:7.1f} s ({seconds / len(z):.2f} s a sample), iterations total {its.sum()}, median {np.median(its):g}, "
                f"largest {its.max()}; converged {int((res <= RTOL).sum())} of {len(z)}, largest residual {res.max():.2e}, "
                f"median {np.median(res):.1e}; mean energy {e.mean():.4g}")  # fmt: skip
        if tets is not None:
            ratios = np.stack([volume_ratios(xi, X, tets) for xi in x])
            inverted = (ratios <= 0).any(axis=1)
            line += f"; {int(inverted.sum())} samples end with inverted tets (least det F {ratios.min():.3g})"
        print(line, flush=True)
        for i in np.flatnonzero(res > RTOL)[:10]:
            print(f"    not converged: sample {i}, {its[i]} iterations, residual {res[i]:.2e}, energy {e[i]:.4g}, "
                  f"{infos[i].blocked} steps shortened by the inversion guard")  # fmt: skip
    if len(solved) == 2:
        (na, xa), (nb, xb) = solved.items()
        gap = solution_gap(xa, xb, X)
        print(f"{na} against {nb}: largest vertex distance / largest displacement: median {np.median(gap):.2e}, largest {gap.max():.2e}; "
              f"{int((gap == 0).sum())} samples identical")  # fmt: skip


if __name__ == "__main__":
    main()
