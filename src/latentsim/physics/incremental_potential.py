"""The elastic potential of a scene, the per-vertex terms of the incremental potential, and the latter.

``ElasticPotential`` is the elastic energy alone, E_elastic(x) = sum of the
scene's EnergyTerms, with its lumped masses and Dirichlet set and no time
step: the potential energy that Neural Modes (Wang et al. 2024, Eq. 5-8)
minimise and the stiffness their linear modes come from.

Variational implicit Euler (Martin et al. 2011): the end-of-step positions
``x_t`` minimise

    E_total(x) = 1/(2 h^2) ||x - 2 x_{t-1} + x_{t-2}||_M^2      (inertia)
               - sum_i m_i g . x_i                               (gravity)
               + w_bc ||x_D - x*_D||^2                           (Dirichlet penalty)
               + E_elastic(x)                                    (sum of EnergyTerms)
               + E_contact(x)                                    (barrier of the colliders, if any)
               + any further term that depends on the step       (``extra_terms``)

with a lumped (diagonal) mass ``M``.  The same object serves the full-space
Newton solver (which removes Dirichlet DoFs instead of penalising them), the
self-supervised losses (batched over decoded states), the metrics, and the
reduced solvers.  All functions broadcast over leading batch axes.

The barrier and the further terms depend on the step (:class:`~latentsim.physics.frame.Frame`:
the targets, the previous positions, the time step): ``frame_terms`` lists them, each evaluated as
``energy(x, frame)``; a solver sees them as terms like any other (``EnergyTerm.at``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from latentsim.physics.base import EnergyTerm
from latentsim.physics.frame import Frame
from latentsim.physics.kernels.dispatch import compiled_energy


def inertia(x, x_prev, x_prev2, masses, dt):
    """1/(2 h^2) sum_i m_i |x_i - 2 x_{t-1,i} + x_{t-2,i}|^2.

    x, x_prev, x_prev2 : (..., n, 3); masses : (n,); returns (...).
    """
    a = x - 2.0 * x_prev + x_prev2
    return 0.5 / dt**2 * (masses * (a * a).sum(-1)).sum(-1)


def gravity(x, masses, g):
    """External potential of uniform gravity, -sum_i m_i g . x_i; g : (3,)."""
    return -(masses * (x * g).sum(-1)).sum(-1)


def dirichlet_penalty(x, indices, targets, weight):
    """w_bc sum_{i in D} |x_i - x*_i|^2; indices (m,), targets (..., m, 3)."""
    d = x[..., indices, :] - targets
    return weight * (d * d).sum(-1).sum(-1)


@dataclass
class ElasticPotential:
    """E_elastic of one scene: the sum of its elastic terms, with its lumped masses and Dirichlet set.

    Attributes
    ----------
    terms : elastic EnergyTerms (rod stretch/bend, shell membrane/hinge, tets)
    masses : (n,) lumped vertex masses [kg]
    dirichlet : (m,) indices of prescribed vertices
    kernels : None, or one compiled ``kernels.TermKernel`` per term
        (``kernels.with_compiled_elastic``): ``elastic`` then runs them on
        float64 CPU states (first derivatives only)
    """

    terms: list[EnergyTerm]
    masses: torch.Tensor
    dirichlet: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    kernels: list | None = None

    @property
    def n_vertices(self) -> int:
        return int(self.masses.shape[0])

    def elastic(self, x: torch.Tensor) -> torch.Tensor:
        """Elastic energy, x (..., n, 3) -> (...)."""
        if self.kernels is not None and x.device.type == "cpu" and x.dtype == torch.float64:
            return compiled_energy(self.kernels, x)
        total = torch.zeros(x.shape[:-2], dtype=x.dtype, device=x.device)
        for term in self.terms:
            total = total + term.energy(x)
        return total


@dataclass
class IncrementalPotential(ElasticPotential):
    """E_total of one scene: the elastic potential + inertia + gravity (+ Dirichlet penalty).

    Attributes
    ----------
    terms, masses, dirichlet, kernels : as in ``ElasticPotential``
    dt : time step [s]
    g : (3,) gravitational acceleration [m/s^2]
    w_bc : penalty weight used where constraints are soft (learning, reduced solvers)
    contact : None, or the barrier of the scene's colliders (``physics.contact.ContactBarrier``), a
        term of E_total beside the elastic ones (it does not scale with the modulus)
    extra_terms : further terms of E_total that take the step's frame (``energy(x, frame)``; a damping
        term), after the barrier; like it, not scaled with the modulus
    """

    dt: float = field(kw_only=True)
    g: torch.Tensor = field(kw_only=True)
    w_bc: float = 1e5
    contact: object | None = field(default=None, kw_only=True)
    extra_terms: list = field(default_factory=list, kw_only=True)

    @property
    def frame_terms(self) -> list:
        """The terms of E_total that take the step's frame: the contact's (the vertex barrier and, with a surface's
        primitives, their barrier: ``ContactBarrier.terms``), then ``extra_terms``."""
        return ([] if self.contact is None else self.contact.terms()) + list(self.extra_terms)

    def __call__(self, x, x_prev, x_prev2, targets=None, penalty=True, dt=None, stiffness=None):
        """E_total(x); ``targets`` (..., m, 3) are x*_D, penalised when ``penalty``.

        ``dt`` (a float, or a tensor of the batch shape ``(...)``): the time step of each state in
        place of ``self.dt``.  ``stiffness`` (likewise): a factor on the elastic energy, the ratio
        of each state's Young's modulus to the one the terms were built with (every elastic term
        is linear in the modulus at a fixed Poisson ratio; ``tests/physics`` checks it).
        """
        e = inertia(x, x_prev, x_prev2, self.masses, self.dt if dt is None else dt)
        elastic = self.elastic(x)
        e = e + gravity(x, self.masses, self.g) + (elastic if stiffness is None else stiffness * elastic)
        terms = self.frame_terms
        if terms:  # (an attached collider stands where the targets put it; friction is lagged from x_prev)
            frame = Frame(targets, x_prev, x_prev2, x_prev[..., self.dirichlet, :], self.dt if dt is None else dt, stiffness)
            for term in terms:
                e = e + term.energy(x, frame)
        if penalty and targets is not None and self.dirichlet.numel():
            e = e + dirichlet_penalty(x, self.dirichlet, targets, self.w_bc)
        return e

    def kinetic_energy(self, x, x_prev):
        """1/2 sum_i m_i |(x_i - x_prev_i)/dt|^2 (backward-difference velocity)."""
        v = (x - x_prev) / self.dt
        return 0.5 * (self.masses * (v * v).sum(-1)).sum(-1)
