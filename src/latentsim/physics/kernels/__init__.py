"""Compiled per-stencil kernels for the full-space Newton solver and the energy losses (numba).

The energies of ``physics.rods``, ``physics.shells`` and ``physics.tets`` are
written once in PyTorch (batched, differentiable); with autograd
(``base.autograd_gradient_hessian``) they are the test oracles.  For the
full-space solver (one state, many Newton iterations) and for the energy
losses of many states, the per-call overhead of those array programs
dominates the small per-stencil work, so the same formulas are compiled
stencil by stencil (an optimisation: a term without kernels runs through
autograd, ``solve.assembly.AutogradKernel``):

- ``core``: the loops of the energy + gradient and of the run kernels
  (``energy_gradient_lanes``, ``run_stencils``), scatter into the gradient
  and the sparse Hessian, the Jacobi eigensolver, the 3x3 SVD, the PSD
  projection, the lanes (the energy kernels take one state or many, the
  state index innermost);
- ``tets``, ``rods``, ``shells``: the kernels of each term (formulas in their
  docstrings); each term names its own (``EnergyTerm.kernel_spec``);
- ``inertia``: inertia and gravity of the incremental potential;
- ``distances``: contact pairs' distances without gradients, which of a broad
  phase's candidates lie within reach (self-contact, a mesh collider);
- ``dispatch``: ``TermKernel`` (one term's kernels over its stencils, on one or
  two threads), ``batch_energy_gradient`` and ``compiled_energy`` (many
  states, the losses).
"""

from latentsim.physics.kernels.core import add_at, rotation_variant_svd, translation_free_basis
from latentsim.physics.kernels.dispatch import (
    KernelSpec,
    TermKernel,
    available,
    batch_energy_gradient,
    compiled_energy,
    float64_array,
    split_stencils,
    term_kernel,
    with_compiled_elastic,
)
from latentsim.physics.kernels.inertia import inertia_gravity

__all__ = [
    "KernelSpec",
    "TermKernel",
    "add_at",
    "available",
    "batch_energy_gradient",
    "compiled_energy",
    "float64_array",
    "inertia_gravity",
    "rotation_variant_svd",
    "split_stencils",
    "term_kernel",
    "translation_free_basis",
    "with_compiled_elastic",
]
