"""Time the compiled StVK tet kernels (``physics.kernels.tets``) against the autograd oracle.

Usage: PYTHONPATH=src python3 benchmarks/bench_tet_hessian.py [mesh.vtu] [--repeats N]

Uses the given tet mesh (e.g. the armadillo, 7,179 vertices, 26,211 tets) when
meshio reads it, else a randomly perturbed structured grid of ~15k tets.  The state
is a random smooth deformation (stretch, shear, some compression) of the rest
shape, so a fair fraction of elements need the PSD projection.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from latentsim.physics import kernels
from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.kernels import rotation_variant_svd
from latentsim.physics.tets import StVKTets


def load_mesh(path):
    if path is None:
        return grid_mesh(14), None
    try:
        import meshio

        m = meshio.read(path)
        tets = np.concatenate([c.data for c in m.cells if c.type == "tetra"])
        return torch.tensor(m.points, dtype=torch.float64), torch.tensor(tets, dtype=torch.long), path
    except Exception as exc:  # noqa: BLE001 - fall back to a synthetic mesh
        print(f"could not read {path} ({exc}); using a perturbed grid")
        return grid_mesh(14), None


def grid_mesh(m):
    g = torch.arange(m + 1, dtype=torch.float64) / m
    X = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    idx = torch.arange((m + 1) ** 3).reshape(m + 1, m + 1, m + 1)
    tets = []
    for perm in ([0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]):
        steps = [torch.eye(3, dtype=torch.long)[p] for p in perm]
        c = torch.stack(torch.meshgrid(*[torch.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3)
        vs = [c, c + steps[0], c + steps[0] + steps[1], c + 1]
        tets.append(torch.stack([idx[v[:, 0], v[:, 1], v[:, 2]] for v in vs], 1))
    tets = torch.cat(tets)
    X = X + 0.1 / m * torch.randn_like(X)
    D = X[tets[:, 1:]] - X[tets[:, :1]]
    neg = torch.linalg.det(D) < 0
    tets[neg, 1], tets[neg, 2] = tets[neg, 2].clone(), tets[neg, 1].clone()
    return (X, tets), f"perturbed grid {m}^3"


def timeit(fn, repeats):
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * min(ts), 1e3 * float(np.median(ts))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("mesh", nargs="?", default=None, help="a .vtu tet mesh (default: a perturbed grid)")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    loaded = load_mesh(args.mesh)
    if loaded[1] is None:
        (X, tets), name = loaded[0]
    else:
        X, tets, name = loaded
    term = StVKTets(X, tets, youngs_modulus=1e5, poisson_ratio=0.45)
    ext = X.max(0).values - X.min(0).values
    # large smooth deformation (bend + squash + shear) plus noise: many inverted elements
    Y = (X - X.mean(0)) / ext.max()
    x = X.clone()
    x[:, 0] += 0.2 * ext.max() * torch.sin(2.0 * Y[:, 1])
    x[:, 1] *= 1.0 - 0.3 * torch.cos(3.0 * Y[:, 0])
    x[:, 2] += 0.15 * ext.max() * Y[:, 1] * Y[:, 0]
    x = x + 0.002 * ext.max() * torch.randn_like(x)
    xe = term.gather(x)
    E = tets.shape[0]
    F = term.deformation_gradient(xe)
    print(f"mesh: {name}: {X.shape[0]} vertices, {E} tets; torch threads = {torch.get_num_threads()}")
    print(f"inverted elements: {(torch.linalg.det(F) < 0).sum().item()}")

    kern, xn, Fn = kernels.term_kernel(term), x.numpy(), F.numpy()
    rows = [
        ("compiled kernel (numba), projected", lambda: kern.local(xn, project=True)),
        ("compiled kernel (numba), exact", lambda: kern.local(xn, project=False)),
        ("  rotation-variant SVD (compiled Jacobi)", lambda: rotation_variant_svd(Fn)),
        ("  LAPACK SVD, numpy (reference)", lambda: np.linalg.svd(Fn)),
        ("  LAPACK SVD, torch (reference)", lambda: torch.linalg.svd(F)),
    ]
    for label, fn in rows:
        tmin, tmed = timeit(fn, args.repeats)
        print(f"{label:40s} min {tmin:8.1f} ms   median {tmed:8.1f} ms")
    xn_near = (X + 0.001 * ext.max() * torch.randn_like(X)).numpy()
    for project in (True, False):
        tmin, tmed = timeit(lambda: kern.local(xn_near, project=project), args.repeats)
        label = f"compiled kernel, near rest, project={project}"
        print(f"{label:40s} min {tmin:8.1f} ms   median {tmed:8.1f} ms")
    for project in (True, False):
        tmin, tmed = timeit(lambda: autograd_gradient_hessian(term, xe, project=project), 2)
        label = f"autograd oracle, project={project}"
        print(f"{label:40s} min {tmin:8.1f} ms   median {tmed:8.1f} ms")

    g, He = (torch.from_numpy(a) for a in kern.local(xn, project=False))
    Hp = torch.from_numpy(kern.local(xn, project=True)[1])
    g0, He0 = autograd_gradient_hessian(term, xe, project=False)
    print(f"rel. error vs autograd: gradient {((g - g0).norm() / g0.norm()).item():.2e}, "
          f"exact Hessian {((He - He0).norm() / He0.norm()).item():.2e}")
    ev = torch.linalg.eigvalsh(Hp)
    print(f"projected Hessian: min eigenvalue / max = {(ev.min() / ev.max()).item():.2e}; "
          f"elements with indefinite exact Hessian: "
          f"{(torch.linalg.eigvalsh(He).min(1).values < -1e-9 * ev.max()).sum().item()}")


if __name__ == "__main__":
    main()
