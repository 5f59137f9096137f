"""Benchmark the full-space simulator on every paper scene at its paper DoF count.

For each scene: prepare the mesh from the default config, simulate the first
frames of its first sequence, and report ms per frame, Newton iterations per
frame, and the split of one Newton iteration into energy (line search),
local gradient + Hessian + PSD projection, assembly, and linear solve, next to
the floor: the bare sparse factorisation + solve of the same matrix (for the
banded solver, of the banded storage: no CSR -> band conversion counted).

The split and ms/iteration are medians over the timed frames of (the frame's
time in each part / its Newton iterations): energy (the line search's
energy + gradient evaluations), grad+Hess+proj, assembly and solve.  The
frame's initial guess (the energies of three candidate states and the
gradient of the best, once per frame, before any iteration) is reported per
frame beside them, not in the iteration.  Each row runs with the compiled
per-stencil kernels (``energy.kernels``, the solver's default; they add
straight into the matrix, so their scatter counts as grad+Hess+proj and
assembly is what remains: inertia, gravity, the matrix wrapper), on one and
on two threads (``--kernel-threads``: two vertex-disjoint halves of each
term's stencils at once), fused or not (``--paths``); the last column is how
far each row's final state lies from the first row's (fused, first thread
count) after the same frames.  The untimed warm-up frames also absorb the
kernels' JIT compile (or cache load).

    python benchmarks/bench_simulator.py [--frames 20] [--scenes armadillo hair_rotation] [--repeats 3]
    python benchmarks/bench_simulator.py --markdown results/benchmarks/simulator.md
    python benchmarks/bench_simulator.py --against cloth armadillo --frames 300

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

import numpy as np
import torch

from latentsim.config import load_config
from latentsim.stages.mesh import prepare_mesh
from latentsim.scene import bc_parameters, build_potential, dirichlet_trajectory
from latentsim.io import read_mesh_arrays
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.sparse import BandedUpper

ROOT = Path(__file__).resolve().parents[1]
PAPER_MS = {"hair_rotation": 268.0, "hair_translation": 208.0, "cloth": 18.83, "armadillo": 136.8, "bunny_ears": 112.6}
TARGET_MS = {"armadillo": 300.0, "hair_rotation": 100.0}
PARTS = ("energy", "local", "assembly", "solve")  # of one Newton iteration (the initial guess is per frame)


def prepare_scene(name, sc, meshes):
    """Mesh arrays and the solver's potential of one scene (stencils of prescribed vertices dropped)."""
    with tempfile.TemporaryDirectory() as tmp:
        prepare_mesh(name, sc["model"], sc["mesh"], sc["dirichlet"], meshes, Path(tmp) / "mesh.h5")
        arrays = read_mesh_arrays(Path(tmp) / "mesh.h5")
    pot = build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"], free_only=True)
    return arrays, pot


def bench_scene(name, sc, arrays, pot, frames, warmup, hessian, path="kernels", threads=1):
    """Simulate the first frames of the scene's first sequence; time them and the floor.

    ``path``: 'kernels' (compiled per-stencil kernels, on ``threads`` threads; the line search's
    full-step trial builds the next Hessian in the same pass), 'unfused' (the same kernels, the
    trial an energy + gradient pass and the Hessian a pass of its own).
    """
    settings = NewtonSettings(**dict(sc["newton"], hessian=hessian, fused_trial=path == "kernels"))
    solver = ImplicitEuler(pot, settings, threads=threads)
    seq = sc["sequences"][0]
    T = min(int(seq["frames"]), frames + warmup + 1)
    p = bc_parameters(seq, T)
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    xD = dirichlet_trajectory(rest[solver.dirichlet], p, sc["dt"])
    x2 = x1 = rest.copy()
    frame_ms, iters, fallbacks, per_it, guess, hessians = [], [], [], [], [], []
    for t in range(1, T):
        t0 = time.perf_counter()
        x, info = solver.step(x1, x2, xD[t])
        dt = time.perf_counter() - t0
        if t > warmup:
            frame_ms.append(1e3 * dt)
            iters.append(info.iterations)
            fallbacks.append(info.projected)
            hessians.append(info.hessians)
            guess.append(1e3 * info.timings["guess"])
            if info.iterations:  # this frame's split of one Newton iteration [ms]
                per_it.append({k: 1e3 * v / info.iterations for k, v in info.timings.items() if k != "guess"})
        x2, x1 = x1, x
    # floor: the bare factorisation + solve of the same matrix (for 'banded', of the banded
    # storage, so a CSR -> band conversion is not counted), repeated
    grad, U = solver.gradient_hessian(x1, x2, x2)
    U_csr = U.tocsr() if isinstance(U, BandedUpper) else U
    if solver.linear.method == "banded" and not isinstance(U, BandedUpper):
        U = BandedUpper.from_csr(U, solver.pattern)
    g = grad[solver.free_dofs]
    floor = []
    for _ in range(7):
        t0 = time.perf_counter()
        solver.linear.solve(U, g)
        floor.append(time.perf_counter() - t0)
    # medians over frames: a busy shared machine pre-empts some iterations for whole scheduler
    # ticks, and the floor is a median too
    split = {f"{k}_ms": float(np.median([f[k] for f in per_it])) if per_it else float("nan") for k in PARTS}
    ms_iteration = float(np.median([sum(f.values()) for f in per_it])) if per_it else float("nan")
    solvers = compare_solvers(solver.pattern, U_csr, g)
    return dict(
        scene=name,
        hessian=hessian,
        path=f"{'kernels' if path == 'kernels' else 'kernels unfused'}, {threads} thread{'s' if threads > 1 else ''}",
        dof=int(rest.size),
        solver=solver.linear.method,
        ms_frame=float(np.mean(frame_ms)),
        iterations=float(np.mean(iters)),
        guess_ms=float(np.median(guess)),
        fallbacks=float(np.mean(fallbacks)),
        hessians=float(np.mean(hessians)),
        ms_iteration=ms_iteration,
        **split,
        floor_ms=1e3 * float(np.median(floor)),
        solvers=solvers,
        final=x1,
        size=float(np.ptp(rest, axis=0).max()),
    )


def compare_solvers(pattern, U, g, repeats=3):
    """ms of factorisation + solve of the same SPD matrix by each available method."""
    import scipy.sparse.linalg

    from latentsim.solve.sparse import LinearSolver, symmetric_from_upper

    out = {}
    methods = ["pardiso", "splu"] + (["banded"] if pattern.bandwidth <= LinearSolver.BANDED_MAX else [])
    for m in methods:
        ls = LinearSolver(pattern, m)
        A = BandedUpper.from_csr(U, pattern) if m == "banded" else U
        ls.solve(A, g)  # symbolic analysis, once per scene
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            ls.solve(A, g)
            ts.append(time.perf_counter() - t0)
        out[m] = 1e3 * float(np.median(ts))
    K = symmetric_from_upper(U).tocsr()
    d = K.diagonal()
    M = scipy.sparse.linalg.LinearOperator(K.shape, matvec=lambda v: v / d)
    t0 = time.perf_counter()  # once: slow, and its 10k-entry dot products wake OpenBLAS's threads
    _, info = scipy.sparse.linalg.cg(K, g, rtol=1e-3, M=M, maxiter=1000)
    out["cg_jacobi_1e-3"] = 1e3 * (time.perf_counter() - t0) if info == 0 else float("nan")
    return out


def against_artefact(path, frames):
    """Re-simulate the first ``frames`` frames of every sequence stored in a trajectories.h5
    (written by an earlier version of the solver) from its stored Dirichlet positions, with
    the current solver and its default path; the largest deviation from the stored positions.

    Returns dict(frames, max_dev, motion, kernels): max_dev is max |x - x_stored| over frames,
    vertices and axes [m], motion the largest stored displacement from rest, max |x_stored - X|.
    """
    import h5py

    from latentsim.io import read_config_attr
    from latentsim.stages.simulate import simulate_sequence

    with h5py.File(path, "r") as f:
        cfg = read_config_attr(f)
        arrays = {k: f[k][()] for k in ("rest_positions", "dirichlet", "edges", "triples", "triangles", "tets") if k in f}
        stored = {name: f["sequences"][name]["positions"][:frames] for name in f["sequences"]}
    pot = build_potential(cfg["model"], arrays, cfg["material"], cfg["dt"], cfg["gravity"], free_only=True)
    solver = ImplicitEuler(pot, NewtonSettings(**cfg["newton"]))
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    dev, motion = 0.0, 0.0
    for seq in cfg["sequences"]:
        pos = stored[seq["name"]]
        data, _ = simulate_sequence(solver, rest, dict(seq, frames=len(pos)), cfg["dt"], seq["name"])
        dev = max(dev, float(np.abs(data["positions"] - pos).max()))
        motion = max(motion, float(np.abs(pos - rest).max()))
    return {"frames": len(pos), "max_dev": dev, "motion": motion}


def median_row(runs):
    """Median over repeated runs of every figure of one (scene, Hessian, path)."""
    r = dict(runs[0])
    for k in ("ms_frame", "iterations", "guess_ms", "fallbacks", "hessians", "ms_iteration", "energy_ms", "local_ms", "assembly_ms",
              "solve_ms", "floor_ms", "ratio"):  # fmt: skip
        r[k] = float(np.median([u[k] for u in runs]))
    r["solvers"] = {k: float(np.median([u["solvers"][k] for u in runs])) for k in runs[0]["solvers"]}
    return r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--frames", type=int, default=30, help="frames timed, after --warmup frames")
    ap.add_argument("--warmup", type=int, default=5, help="frames from rest not timed (the initial drop)")
    ap.add_argument("--hessian", nargs="+", default=["projected", "exact_first"])
    ap.add_argument("--paths", nargs="+", default=["kernels", "unfused"], choices=["kernels", "unfused"],
                    help="kernels: compiled (numba), the line search's full-step trial fused with the next Hessian; "
                         "unfused: the same kernels, not fused")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each row, interleaved; medians are reported")
    ap.add_argument("--scenes", nargs="*")
    ap.add_argument("--threads", type=int, default=2, help="torch and linear-solver threads")
    ap.add_argument("--kernel-threads", type=int, nargs="+", default=[1, 2], help="threads of the compiled kernels, a row each")
    ap.add_argument("--markdown", help="also write the table to this file")
    ap.add_argument("--against", nargs="*", metavar="SCENE",
                    help="only re-simulate the first --frames frames of these scenes' stored sequences "
                         "(results/sim/SCENE/trajectories.h5) and compare")  # fmt: skip
    args = ap.parse_args(argv)
    if args.against is not None:
        print("| scene | frames | path | max abs(x - x_stored) [m] | / max abs(x_stored - rest) |")
        print("|---|---|---|---|---|")
        for name in args.against:
            r = against_artefact(ROOT / "results" / "sim" / name / "trajectories.h5", args.frames)
            print(f"| {name} | {r['frames']} | kernels | {r['max_dev']:.2e} | {r['max_dev'] / r['motion']:.1e} |")
        return
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config)
    names = args.scenes or [n for n, s in cfg["scenes"].items() if s["paper"] == "li2025"]
    rows = []
    for name in names:
        sc = cfg["scenes"][name]
        arrays, pot = prepare_scene(name, sc, cfg["meshes"])
        for hessian in args.hessian:
            variants = [(p, t) for p in args.paths for t in args.kernel_threads]
            runs = {v: [] for v in variants}
            for _ in range(args.repeats):
                for path, threads in variants:
                    r = bench_scene(name, sc, arrays, pot, args.frames, args.warmup, hessian, path, threads)
                    r["ratio"] = r["ms_iteration"] / max(r["floor_ms"], 1e-9)
                    runs[path, threads].append(r)
            ref = runs[variants[0]][0]["final"]
            for v in variants:
                row = median_row(runs[v])
                # same frames from the same start: how far the two paths' final states are apart
                row["deviation"] = float(np.abs(row["final"] - ref).max() / row["size"])
                rows.append(row)
            print(f"  {name} ({hessian}): done", file=sys.stderr, flush=True)
    head = ["scene", "DoF", "Hessian", "path", "solver", "ms/frame", "paper ms/frame", "target", "Newton it/frame",
            "initial guess ms/frame", "fallbacks/frame", "Hessian passes/frame", "ms/iteration", "energy", "grad+Hess+proj", "assembly", "solve", "floor (factor+solve)",
            "iteration/floor", "max abs(x - x_ref)/size"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['dof']:,} | {r['hessian']} | {r['path']} | {r['solver']} | {r['ms_frame']:.1f} | "
            f"{PAPER_MS.get(r['scene'], float('nan')):.1f} | {TARGET_MS.get(r['scene'], '')} | {r['iterations']:.2f} | "
            f"{r['guess_ms']:.2f} | {r['fallbacks']:.2f} | {r['hessians']:.2f} | {r['ms_iteration']:.2f} | {r['energy_ms']:.2f} | {r['local_ms']:.2f} | "
            f"{r['assembly_ms']:.2f} | {r['solve_ms']:.2f} | {r['floor_ms']:.2f} | {r['ratio']:.2f} | {r['deviation']:.1e} |"
        )
    names = sorted({k for r in rows for k in r["solvers"]})
    lines += ["", "Linear solvers, factorisation + solve of the same matrix [ms]:", "",
              "| scene | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]  # fmt: skip
    for r in rows:
        if r is next(u for u in rows if u["scene"] == r["scene"]):
            lines.append(f"| {r['scene']} | " + " | ".join(f"{r['solvers'].get(k, float('nan')):.1f}" for k in names) + " |")
    load = os.getloadavg()
    loads = ", ".join(f"{v:.1f}" for v in load)
    lines += ["", f"Load average (1, 5, 15 min) at the end of the run: {loads} on {os.cpu_count()} cores."]
    table = "\n".join(lines)
    print(table)
    if args.markdown:
        Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
        Path(args.markdown).write_text(table + "\n")


if __name__ == "__main__":
    main()
