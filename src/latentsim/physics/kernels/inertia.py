"""Compiled inertia and gravity: the full-space solver's share of the incremental potential.

``inertia_gravity`` evaluates, in one pass over the vertices, the inertia
1/(2h^2) ||x - 2x_{t-1} + x_{t-2}||_M^2 and the gravity potential
-sum_i m_i x_i . g of ``physics.incremental_potential`` (Martin et al. 2011)
with lumped masses, and adds their gradient.
"""

from __future__ import annotations

from numba import njit

from latentsim.physics.kernels.core import JIT


@njit(**JIT)
def inertia_gravity(x, x_prev, x_prev2, masses, g, inv_h2, grad):
    """Inertia ``1/(2h^2) ||x - 2x_{t-1} + x_{t-2}||_M^2`` plus gravity ``-sum_i m_i x_i . g``.

    The same terms as ``physics.incremental_potential.IncrementalPotential`` (lumped masses), in one pass
    over the vertices; adds their gradient into ``grad`` (3n,) unless it is empty, and
    returns the energy.
    """
    e_in = 0.0
    e_g = 0.0
    with_grad = grad.shape[0] > 0
    for v in range(x.shape[0]):
        m = masses[v]
        for i in range(3):
            a = x[v, i] - 2.0 * x_prev[v, i] + x_prev2[v, i]
            e_in += m * a * a
            e_g += m * x[v, i] * g[i]
            if with_grad:
                grad[3 * v + i] += m * (inv_h2 * a - g[i])
    return 0.5 * inv_h2 * e_in - e_g

