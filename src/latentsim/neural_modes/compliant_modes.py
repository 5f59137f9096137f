r"""Ground truth of Neural Modes (Wang et al. 2024, Eq. 9): nonlinear compliant modes per modal sample,

    n(z) = argmin_x E(x)   s.t.   l^T (x - X - l) = 0   (i.e. l^T y = 0),

solved sample after sample by the constrained Newton method of ``latentsim.solve.constrained``
(``ConstrainedNewton``: Newton on the KKT system of the single linear constraint, sparse per-stencil
Hessians, a backtracking line search on E, a tiny Levenberg term for free-floating objects).
"""

from __future__ import annotations

import numpy as np

from latentsim.solve.constrained import ConstrainedNewton

__all__ = ["ground_truth"]


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


def ground_truth(
    potential, rest_positions, modes, z, free_dofs=None, rigid=None, metric="euclidean", rtol=1e-5, etol=1e-7, max_iter=60, progress=None,
    order="given",
):  # fmt: skip
    """Eq. 9 for every row of z (N, m): positions (N, n, 3), energies (N,), infos (in the rows' order).

    The samples are solved one after another, each starting from the lower-energy of X + l and the
    correction of the sample solved just before, made feasible.  ``order``: ``"given"`` (the default, the
    pipeline's) in the rows' order (a grid's rows are neighbours but for the wraps); ``"nearest"`` along
    :func:`nearest_neighbour_order`, so that the sample before is a near neighbour even for random
    samples.  Eq. 9 has more than one minimum where the shape buckles: the start, and so the order,
    decides which one a sample lands in (``benchmarks/nm_ground_truth_order.py`` measures it: on the
    sheet the two orders' solutions lie a median 19% of the displacement apart), so the order is part of
    the ground truth's definition, not only of its cost.
    """
    if order not in ("nearest", "given"):
        raise ValueError(f"ground_truth: order must be 'nearest' or 'given', got {order!r}")
    solver = ConstrainedNewton(potential, rest_positions, free_dofs, rigid, metric)
    E = np.asarray(modes, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    X = solver.X.reshape(-1)
    out, infos = np.empty((len(z), len(X))), [None] * len(z)
    visit = nearest_neighbour_order(z) if order == "nearest" else np.arange(len(z))
    y_prev = None
    for done, i in enumerate(visit):
        l = E @ z[i]
        y0 = None
        if y_prev is not None and solver.energy(X + l + y_prev) < solver.energy(X + l):
            y0 = y_prev  # made feasible by solve()
        x, info = solver.solve(l, y0, rtol=rtol, etol=etol, max_iter=max_iter)
        out[i] = x
        infos[i] = info
        y_prev = x - X - l
        if progress is not None:
            progress(done, info)
    return out.reshape(len(z), -1, 3), np.array([i.energy for i in infos]), infos
