"""Benchmark the full-space simulator on every paper scene at its paper DoF count.

For each scene: prepare the mesh from the default config, simulate the first
frames of its first sequence, and report ms per frame, Newton iterations per
frame, and the split of one Newton iteration into energy (line search),
local gradient + Hessian + PSD projection, assembly, and linear solve, next to
the floor: the bare sparse factorisation + solve of the same matrix.

    python benchmarks/bench_simulator.py [--frames 20] [--scenes armadillo hair_rotation]
    python benchmarks/bench_simulator.py --markdown results/benchmarks/simulator.md

Run it on an otherwise idle machine; all figures of one run are comparable.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("KMP_BLOCKTIME", "0")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from latentsim.config import load_config  # noqa: E402
from latentsim.prepare import prepare_mesh  # noqa: E402
from latentsim.scene import bc_parameters, build_potential, dirichlet_trajectory  # noqa: E402
from latentsim.simulate import read_mesh_arrays  # noqa: E402
from latentsim.solver import ImplicitEuler, NewtonSettings  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAPER_MS = {"hair_rotation": 268.0, "hair_translation": 208.0, "cloth": 18.83, "armadillo": 136.8, "bunny_ears": 112.6}
TARGET_MS = {"armadillo": 300.0, "hair_rotation": 100.0}


def bench_scene(name, sc, meshes, frames, warmup, hessian):
    with tempfile.TemporaryDirectory() as tmp:
        prepare_mesh(name, sc["model"], sc["mesh"], sc["dirichlet"], meshes, Path(tmp) / "mesh.h5")
        arrays = read_mesh_arrays(Path(tmp) / "mesh.h5")
    pot = build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"], free_only=True)
    solver = ImplicitEuler(pot, NewtonSettings(**dict(sc["newton"], hessian=hessian)))
    seq = sc["sequences"][0]
    T = min(int(seq["frames"]), frames + warmup + 1)
    p = bc_parameters(seq, T)
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    xD = dirichlet_trajectory(rest[solver.dirichlet], p, sc["dt"])
    x2 = x1 = rest.copy()
    frame_ms, iters = [], []
    tm = dict(energy=0.0, local=0.0, assembly=0.0, solve=0.0)
    for t in range(1, T):
        t0 = time.perf_counter()
        x, info = solver.step(x1, x2, xD[t])
        dt = time.perf_counter() - t0
        if t > warmup:
            frame_ms.append(1e3 * dt)
            iters.append(info.iterations)
            for k in tm:
                tm[k] += info.timings[k]
        x2, x1 = x1, x
    n_it = max(sum(iters), 1)
    # floor: factorisation + solve of the same matrix, repeated
    grad, U = solver.gradient_hessian(x1, x2, x2)
    g = grad[solver.free_dofs]
    floor = []
    for _ in range(5):
        t0 = time.perf_counter()
        solver.linear.solve(U, g)
        floor.append(time.perf_counter() - t0)
    per_it = {k: 1e3 * v / n_it for k, v in tm.items()}
    solvers = compare_solvers(solver.pattern, U, g)
    return dict(
        scene=name,
        hessian=hessian,
        dof=int(rest.size),
        solver=solver.linear.method,
        ms_frame=float(np.mean(frame_ms)),
        iterations=float(np.mean(iters)),
        ms_iteration=sum(per_it.values()),
        **{f"{k}_ms": v for k, v in per_it.items()},
        floor_ms=1e3 * float(np.median(floor)),
        solvers=solvers,
    )


def compare_solvers(pattern, U, g, repeats=3):
    """ms of factorisation + solve of the same SPD matrix by each available method."""
    import scipy.sparse.linalg

    from latentsim.sparse import LinearSolver, symmetric_from_upper

    out = {}
    methods = ["pardiso", "splu"] + (["banded"] if pattern.bandwidth <= LinearSolver.BANDED_MAX else [])
    for m in methods:
        ls = LinearSolver(pattern, m)
        ls.solve(U, g)  # symbolic analysis, once per scene
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            ls.solve(U, g)
            ts.append(time.perf_counter() - t0)
        out[m] = 1e3 * float(np.median(ts))
    K = symmetric_from_upper(U).tocsr()
    d = K.diagonal()
    M = scipy.sparse.linalg.LinearOperator(K.shape, matvec=lambda v: v / d)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        scipy.sparse.linalg.cg(K, g, rtol=1e-3, M=M)
        ts.append(time.perf_counter() - t0)
    out["cg_jacobi_1e-3"] = 1e3 * float(np.median(ts))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--frames", type=int, default=30, help="frames timed, after --warmup frames")
    ap.add_argument("--warmup", type=int, default=5, help="frames from rest not timed (the initial drop)")
    ap.add_argument("--hessian", nargs="+", default=["projected", "exact_first"])
    ap.add_argument("--scenes", nargs="*")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--markdown", help="also write the table to this file")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    names = args.scenes or [n for n, s in cfg["scenes"].items() if s["paper"] == "li2025"]
    rows = []
    for name in names:
        for hessian in args.hessian:
            rows.append(bench_scene(name, cfg["scenes"][name], cfg["meshes"], args.frames, args.warmup, hessian))
            print(f"  {name} ({hessian}): done", file=sys.stderr, flush=True)
    head = ["scene", "DoF", "Hessian", "solver", "ms/frame", "paper ms/frame", "target", "Newton it/frame", "ms/iteration",
            "energy", "grad+Hess+proj", "assembly", "solve", "floor (factor+solve)", "iteration/floor"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['dof']:,} | {r['hessian']} | {r['solver']} | {r['ms_frame']:.1f} | {PAPER_MS.get(r['scene'], float('nan')):.1f} | "
            f"{TARGET_MS.get(r['scene'], '')} | {r['iterations']:.2f} | {r['ms_iteration']:.1f} | {r['energy_ms']:.1f} | "
            f"{r['local_ms']:.1f} | {r['assembly_ms']:.1f} | {r['solve_ms']:.1f} | {r['floor_ms']:.1f} | "
            f"{r['ms_iteration'] / max(r['floor_ms'], 1e-9):.2f} |"
        )
    names = sorted({k for r in rows for k in r["solvers"]})
    lines += ["", "Linear solvers, factorisation + solve of the same matrix [ms]:", "",
              "| scene | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]  # fmt: skip
    for r in rows:
        if r["hessian"] == args.hessian[0]:
            lines.append(f"| {r['scene']} | " + " | ".join(f"{r['solvers'].get(k, float('nan')):.1f}" for k in names) + " |")
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
        Path(args.markdown).write_text(table + "\n")


if __name__ == "__main__":
    main()
