"""Step a trained latent model outside the pipeline: encode two frames, then step with the boundary conditions.

The rollout stage leaves the trained model of each scene, method and seed, folded into plain arrays, in
``results/rollout/{scene}/{method}/seed{k}/runtime.npz`` (and the same step as a ``torch.export`` program,
``runtime.pt``).  This script loads it with ``latentsim.runtime.load`` (NumPy only: no training
code), encodes the first two full-space frames of a test sequence of the scene's
``trajectories.h5``, steps the remaining frames with that sequence's boundary-condition parameters
and Dirichlet positions, and prints the error against the simulated frames and the time per step;
then it steps the same frames with the ``torch.export`` program.

    python examples/step_trained_model.py                      # the tiny run's tiny_rods, from the workflow directory
    python examples/step_trained_model.py results/rollout/cantilever/self_supervised/seed0 \\
        --trajectories results/sim/cantilever/trajectories.h5 --frames 50
"""

from __future__ import annotations

import argparse
import os
import time

import h5py
import numpy as np
import torch

from latentsim import runtime


def read_sequence(trajectories, name=None) -> tuple[str, dict, np.ndarray]:
    """A test sequence of ``trajectories.h5`` (the first one, or ``name``): its name, its ``positions``
    (T, n, 3), ``dirichlet_positions`` (T, m, 3), ``bc`` (T, k), and the rest positions (n, 3)."""
    with h5py.File(trajectories, "r") as f:
        tests = [k for k, g in f["sequences"].items() if g.attrs["split"] == "test"]
        if name is None:
            if not tests:
                raise SystemExit(f"{trajectories}: no test sequence; name one with --sequence")
            name = tests[0]
        if name not in f["sequences"]:
            raise SystemExit(f"{trajectories}: no sequence {name!r} (sequences: {', '.join(f['sequences'])})")
        g = f["sequences"][name]
        return name, {k: g[k][()] for k in ("positions", "dirichlet_positions", "bc")}, f["rest_positions"][()]


def step_numpy(model: runtime.TrainedModel, seq: dict, frames: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Frames 0..frames-1 (frames 0 and 1 as simulated, the rest stepped), the latents (2, r) that frames 0
    and 1 encode to, and the seconds per step."""
    x, xD, bc = seq["positions"], seq["dirichlet_positions"], seq["bc"]
    out = np.empty((frames,) + x.shape[1:])
    out[:2] = x[:2]
    z01 = model.encode(x[0], x[1], xD[:2], bc[:2])
    t0 = time.perf_counter()
    for t in range(2, frames):
        out[t] = model.step(bc[t], xD[t])
    return out, z01, (time.perf_counter() - t0) / (frames - 2)


def step_torch_export(program_path, z01: np.ndarray, seq: dict, frames: int) -> tuple[np.ndarray, float]:
    """The same frames with the ``torch.export`` program of the step, ``module(z_{t-1}, z_{t-2}, p_t, p_{t-1},
    p_{t-2}, xD_t) -> (z_t, x_t)``, started from the latents z01 (2, r) that the NumPy encoder gave."""
    step = runtime.load_program(program_path)  # checked against its checksum; takes inputs of any float dtype
    bc = torch.as_tensor(seq["bc"], dtype=torch.float32)
    xD = torch.as_tensor(seq["dirichlet_positions"], dtype=torch.float64)
    z = [torch.as_tensor(z01[0]), torch.as_tensor(z01[1])]
    out = np.empty((frames,) + seq["positions"].shape[1:])
    out[:2] = seq["positions"][:2]
    t0 = time.perf_counter()
    with torch.inference_mode():
        for t in range(2, frames):
            zt, xt = step(z[-1], z[-2], bc[t], bc[t - 1], bc[t - 2], xD[t])
            z = [z[-1], zt]
            out[t] = xt.numpy()
    return out, (time.perf_counter() - t0) / (frames - 2)


def vertex_error(x: np.ndarray, reference: np.ndarray, diagonal: float) -> tuple[float, float]:
    """Mean and max vertex distance between frames (T, n, 3), relative to the bounding-box diagonal."""
    d = np.linalg.norm(x - reference, axis=-1) / diagonal
    return float(d.mean()), float(d.max())


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    parser.add_argument("rollout", nargs="?", default="results/rollout/tiny_rods/self_supervised/seed0",
                        help="a rollout folder holding runtime.npz (and runtime.pt), or the runtime.npz (default: %(default)s)")  # fmt: skip
    parser.add_argument("--trajectories", default="results/sim/tiny_rods/trajectories.h5", help="the scene's simulated sequences (default: %(default)s)")
    parser.add_argument("--sequence", help="the sequence to step (default: the first test sequence)")
    parser.add_argument("--frames", type=int, help="frames to compare, the two encoded ones included (default: the whole sequence)")
    parser.add_argument("--no-torch-export", action="store_true", help="skip stepping runtime.pt with torch.export")
    args = parser.parse_args(argv)

    model = runtime.load(args.rollout)
    name, seq, rest = read_sequence(args.trajectories, args.sequence)
    T = len(seq["positions"]) if args.frames is None else min(args.frames, len(seq["positions"]))
    if T < 3:
        raise SystemExit(f"--frames {T}: need at least 3 (two encoded, one stepped)")
    if seq["positions"].shape[1] != model.n:
        raise SystemExit(f"{args.trajectories}: {seq['positions'].shape[1]} vertices, the model {model.n}: another scene's model?")
    diagonal = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    x, z01, seconds = step_numpy(model, seq, T)
    mean_e, max_e = vertex_error(x[2:], seq["positions"][2:T], diagonal)
    print(f"{name}: frames 0, 1 encoded, {T - 2} stepped (r = {model.r} latents, {model.n} vertices)")
    print(f"NumPy runtime:        {1e3 * seconds:8.3f} ms per step; vertex error against the simulation: mean {mean_e:.2e}, max {max_e:.2e} of the bounding-box diagonal")
    result = {"sequence": name, "positions": x, "latents": z01, "numpy_ms": 1e3 * seconds, "mean_error": mean_e, "max_error": max_e}
    program = os.path.join(os.path.dirname(os.path.abspath(args.rollout)) if args.rollout.endswith(".npz") else args.rollout, "runtime.pt")
    if not args.no_torch_export and os.path.isfile(program):
        xt, seconds_t = step_torch_export(program, z01, seq, T)
        gap = float(np.abs(xt - x).max()) / diagonal
        print(f"torch.export program: {1e3 * seconds_t:8.3f} ms per step; its frames differ from the NumPy runtime's by at most {gap:.1e} of the diagonal")
        result.update(torch_export_positions=xt, torch_export_ms=1e3 * seconds_t)
    return result


if __name__ == "__main__":
    main()
