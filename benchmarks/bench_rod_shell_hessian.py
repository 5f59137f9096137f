"""Per-stencil gradient + Hessian timings of the rod and shell terms: compiled kernels against autograd.

Scenes: a hair scene of 100 rods x 36 vertices (3,600 vertices, 10,800 DoFs,
3,500 stretch edges, 3,400 bending stencils), a 12 x 16 cloth (192 vertices)
and an 11 x 11 sheet (121 vertices), in random deformed states.  For every
term it times the compiled kernels of ``physics.kernels`` (numba, one thread;
``TermKernel.local``, the per-stencil g and H of ``local_gradient_hessian``,
projected and exact) and the autograd oracle ``base.autograd_gradient_hessian``
(torch.func Hessian + batched ``eigh`` clamp of the full stencil Hessian) with
1 and 2 torch threads.  Reports the minimum and the median over repeats (the
machine is shared; the minimum is the better estimate of the cost).

Run:  PYTHONPATH=src python3 benchmarks/bench_rod_shell_hessian.py [--repeats 20]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from latentsim.physics import kernels
from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.rods import RodBend, RodStretch, rod_stiffness, rod_topology
from latentsim.physics.shells import ShellHinge, ShellMembraneStVK, hinges_from_triangles


def grid(nx, ny, size=1.0):
    """(nx+1)(ny+1) vertices in the xz plane, cells cut along one diagonal."""
    u, w = np.meshgrid(np.linspace(0, size, nx + 1), np.linspace(0, size * ny / nx, ny + 1))
    V = np.stack([u.ravel(), np.zeros(u.size), w.ravel()], 1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    v00 = (j * (nx + 1) + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    T = np.concatenate([np.stack([v00, v11, v10], 1), np.stack([v00, v01, v11], 1)])
    return torch.as_tensor(V), torch.as_tensor(T)


def scenes(seed=0):
    gen = torch.Generator().manual_seed(seed)
    n_rods, m = 100, 36
    X = torch.zeros(n_rods * m, 3, dtype=torch.float64)
    X[:, 1] = -0.01 * torch.arange(m, dtype=torch.float64).repeat(n_rods)
    X[:, 0] = 0.005 * torch.arange(n_rods, dtype=torch.float64).repeat_interleave(m)
    edges, triples = rod_topology(n_rods, m)
    ks, kb = rod_stiffness(2e9, 5e-5)
    x = X + 0.003 * torch.randn(X.shape, generator=gen, dtype=torch.float64)
    out = {"hair 3600 v": (x, [RodStretch(X, edges, ks), RodBend(X, triples, kb)])}
    for name, (nx, ny) in (("cloth 192 v", (11, 15)), ("sheet 121 v", (10, 10))):
        V, T = grid(nx, ny)
        terms = [ShellMembraneStVK(V, T, 1e6, 0.3, 1e-3), ShellHinge(V, hinges_from_triangles(T), 1e6, 0.3, 1e-3)]
        out[name] = (V + 0.02 * torch.randn(V.shape, generator=gen, dtype=torch.float64), terms)
    return out


def timeit(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1e3 * min(ts), 1e3 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-oracle", action="store_true")
    args = ap.parse_args()
    sc = scenes()
    for name, (x, terms) in sc.items():
        xn = x.numpy()
        for term in terms:
            k = kernels.term_kernel(term)
            kp = timeit(lambda: k.local(xn, project=True), args.repeats)
            ke = timeit(lambda: k.local(xn, project=False), args.repeats)
            line = f"{name:12s} {term.name:20s} E={len(k.stencils):5d}  compiled {kp[0]:7.2f} ms (median {kp[1]:7.2f}), exact {ke[0]:7.2f} ms"
            if not args.no_oracle:
                xe = term.gather(x)
                for threads in (1, 2):
                    torch.set_num_threads(threads)
                    orc = timeit(lambda: autograd_gradient_hessian(term, xe, project=True), max(3, args.repeats // 4))
                    line += f" | autograd oracle, {threads} thread(s) {orc[0]:7.2f} ms (median {orc[1]:7.2f})"
            print(line)


if __name__ == "__main__":
    main()
