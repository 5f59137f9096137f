r"""Ground truth of Neural Modes (Wang et al. 2024, Eq. 9): nonlinear compliant modes per modal sample,

    n(z) = argmin_x E(x)   s.t.   l^T (x - X - l) = 0   (i.e. l^T y = 0),

solved sample after sample by the constrained Newton method of ``latentsim.solve.constrained``
(``ConstrainedNewton``: Newton on the KKT system of the single linear constraint, sparse per-stencil
Hessians, a backtracking line search on E, a tiny Levenberg term for free-floating objects).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from latentsim.solve.constrained import ConstrainedNewton

__all__ = ["ground_truth"]


def ground_truth(
    potential, rest_positions, modes, z, free_dofs=None, rigid=None, metric="euclidean", rtol=1e-5, etol=1e-7, max_iter=60, progress=None,
    order=None, resume=None, solved=None,
):  # fmt: skip
    """Eq. 9 for every row of z (N, m): positions (N, n, 3), energies (N,), infos (in the rows' order).

    The samples are solved one after another, each starting from the lower-energy of X + l and the
    correction of the sample solved just before, made feasible.  A lower energy at the start is no nearer
    the solution: where a solve from that correction ends unconverged with steps shortened to keep
    tetrahedra from inverting (``CompliantInfo.blocked``: on the armadillo such a start can lie next to
    collapsed elements, and its energy-study samples are not neighbours), the sample is solved again from X + l and
    the converged solve (else the one with the smaller residual) is kept; its ``iterations`` count both.
    Where the solve from that correction fails on the way (a non-finite gradient, a singular system: on the
    sheet a grid's wrap, from one corner of the box to the opposite, starts next to a collapsed element), the
    sample is solved from X + l alone.
    ``order``: the row indices in the order to
    solve them (a permutation); None, the pipeline's: the rows' order (a grid's rows are neighbours but for
    the wraps).  Eq. 9 has more than one minimum where the shape buckles: the start, and so the order,
    decides which one a sample lands in (``benchmarks/nm_ground_truth_order.py`` measures it: on the
    sheet a nearest-neighbour order's solutions lie a median 19% of the displacement from the rows'
    order's), so the order is part of the ground truth's definition, not only of its cost.

    ``resume``: (x, infos) of the first k samples of the order, solved before (a killed job's
    checkpoint): they are taken as they are and the solve goes on at the (k+1)-th, from the correction
    of the k-th, so that a resumed set equals one solved in one go.  ``solved(done, x, info)`` is called
    after each sample (x flat) with the number of samples done, for a checkpoint.
    """
    solver = ConstrainedNewton(potential, rest_positions, free_dofs, rigid, metric)
    E = np.asarray(modes, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    X = solver.X.reshape(-1)
    out, infos = np.empty((len(z), len(X))), [None] * len(z)
    visit = np.arange(len(z)) if order is None else np.asarray(order, dtype=np.int64)
    if sorted(visit.tolist()) != list(range(len(z))):
        raise ValueError(f"ground_truth: order must be a permutation of the {len(z)} rows of z")
    y_prev, start = None, 0
    if resume is not None:
        x_done, infos_done = resume
        start = len(infos_done)
        if start > len(z) or len(x_done) != start:
            raise ValueError(f"ground_truth: resume holds {len(x_done)} positions and {start} infos for {len(z)} samples")
        for k in range(start):
            out[visit[k]], infos[visit[k]] = np.asarray(x_done[k], dtype=np.float64).reshape(-1), infos_done[k]
        if start:
            last = visit[start - 1]
            y_prev = out[last] - X - E @ z[last]
    for done in range(start, len(visit)):
        i = visit[done]
        l = E @ z[i]
        y0 = None
        if y_prev is not None and solver.energy(X + l + y_prev) < solver.energy(X + l):
            y0 = y_prev  # made feasible by solve()
        try:
            x, info = solver.solve(l, y0, rtol=rtol, etol=etol, max_iter=max_iter)
        except (ArithmeticError, RuntimeError, np.linalg.LinAlgError):
            if y0 is None:
                raise
            y0 = None
            x, info = solver.solve(l, None, rtol=rtol, etol=etol, max_iter=max_iter)
        if y0 is not None and not info.converged and info.blocked:
            x_rest, info_rest = solver.solve(l, None, rtol=rtol, etol=etol, max_iter=max_iter)
            if info_rest.converged or info_rest.residual < info.residual:
                x, info = x_rest, info_rest
            info = dataclasses.replace(info, iterations=info.iterations + info_rest.iterations)
        out[i] = x
        infos[i] = info
        y_prev = x - X - l
        if solved is not None:
            solved(done + 1, x, info)
        if progress is not None:
            progress(done, info)
    return out.reshape(len(z), -1, 3), np.array([i.energy for i in infos]), infos
