"""Time the compiled elastic energy + gradient of a batch of states (the integrator's loss).

The self-supervised losses evaluate the elastic energy of S states of one mesh at once
(``kernels.compiled_energy`` -> ``kernels.batch_energy_gradient``).  For the cloth (shell
membrane + hinges), the cantilever (StVK tets) and a finer beam of about 3,000 vertices (StVK and
stable neo-Hookean tets), this prints ms per call of each term's kernel on S random states, with
and without the gradient, and of the whole ``compiled_energy`` forward + backward.

    python benchmarks/bench_energy_batch.py [--states 256] [--repeats 20] [--threads 1]

The figures are the minimum over the repeats (the least disturbed by other load).  To compare two
versions of the kernels, run the script once per source tree (``PYTHONPATH=<tree>/src``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from latentsim.mesh import beam_tets, cloth_grid
from latentsim.physics import kernels
from latentsim.scene import build_potential

MATERIAL = {"youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1000.0, "thickness": 3e-3}


def scenes():
    """(name, model, material overrides, arrays): the paper's cloth and cantilever meshes and a ~3,000-vertex beam."""
    X, tris = cloth_grid(15, 11, 0.45, 0.33, plane="xy")
    yield "cloth", "shell", {}, {"rest_positions": X, "triangles": tris, "dirichlet": np.array([0])}
    X, T = beam_tets(20, 4, 4, 0.5, 0.1, 0.1)
    yield "cantilever", "tets", {}, {"rest_positions": X, "tets": T, "dirichlet": np.array([0])}
    X, T = beam_tets(36, 8, 8, 0.9, 0.2, 0.2)
    yield "beam_3k", "tets", {}, {"rest_positions": X, "tets": T, "dirichlet": np.array([0])}
    yield "beam_3k", "tets", {"model": "neohookean"}, {"rest_positions": X, "tets": T, "dirichlet": np.array([0])}


def random_states(X, count, seed=0):
    """Rest shape, rigidly moved and smoothly plus randomly deformed, per state."""
    rng = np.random.default_rng(seed)
    size = np.ptp(X, axis=0).max()
    out = np.empty((count, *X.shape))
    for s in range(count):
        R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        bend = 0.1 * np.sin(X[:, :1] / size * np.pi) * rng.normal(size=3)
        out[s] = (X + bend) @ R.T + rng.normal(size=3) + 0.01 * size * rng.normal(size=X.shape)
    return out


def best_ms(fn, repeats):
    fn()  # compile or load the cache
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--states", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"S = {args.states} states, {args.threads} thread(s), min of {args.repeats} calls, ms per call")
    print(f"{'scene':<11} {'term':<20} {'vertices':>8} {'stencils':>8} {'energy+grad':>12} {'energy':>8}")
    for name, model, material, arrays in scenes():
        pot = build_potential(model, arrays, {**MATERIAL, **material}, 0.01, [0.0, -9.81, 0.0])
        pot = kernels.with_compiled_elastic(pot)
        X = np.asarray(arrays["rest_positions"], dtype=np.float64)
        x = random_states(X, args.states)
        for k in pot.kernels:
            eg = best_ms(lambda: kernels.batch_energy_gradient([k], x, threads=args.threads), args.repeats)
            e = best_ms(lambda: kernels.batch_energy_gradient([k], x, gradient=False, threads=args.threads), args.repeats)
            print(f"{name:<11} {k.name:<20} {len(X):>8} {len(k.stencils):>8} {eg:>12.2f} {e:>8.2f}")
        xt = torch.from_numpy(x)

        def forward_backward():
            xg = xt.clone().requires_grad_(True)
            pot.elastic(xg).sum().backward()

        print(f"{name:<11} {'compiled (f+b)':<20} {len(X):>8} {'':>8} {best_ms(forward_backward, args.repeats):>12.2f}")


if __name__ == "__main__":
    main()
