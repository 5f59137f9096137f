"""The compiled assembly of the elastic energy, its gradient and its sparse Hessian.

Every solver (:mod:`latentsim.solve.implicit_euler`, :mod:`latentsim.solve.constrained`,
:mod:`latentsim.solve.modes`) evaluates the elastic terms of a potential through their
per-stencil derivatives: E = sum_e E_e(x_e), its gradient sum_e P_e^T g_e and Hessian
sum_e P_e^T H_e P_e (P_e the stencil's gather), with H_e exact or projected to positive
semi-definite per stencil (Teran et al. 2005), added straight into the upper-triangular CSR
data (or the banded storage) of a :class:`~latentsim.solve.sparse.HessianPattern`.  A term with
compiled kernels (``EnergyTerm.kernel_spec``, :mod:`latentsim.physics.kernels`) runs them; a
term without runs its PyTorch ``local_energy`` through autograd (:class:`AutogradKernel`,
``EnergyTerm.local_gradient_hessian``), scattered into the same gradient and pattern: the
kernels are an optimisation, not a requirement.
The terms that depend on the step's frame (:meth:`CompiledAssembly.with_frame_terms`) add their own
per-stencil gradient and Hessian (torch) into the same arrays.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import torch

from latentsim.physics.kernels import add_at, split_stencils, term_kernel
from latentsim.solve.sparse import BandedUpper, HessianPattern

__all__ = ["AutogradKernel", "CompiledAssembly"]


def stencil_dofs(stencils) -> np.ndarray:
    """The degrees of freedom of each stencil, (E, 3k), vertex-major as the per-stencil gradients."""
    return (3 * stencils[:, :, None] + np.arange(3)).reshape(len(stencils), 3 * stencils.shape[1])


def add_stencil_blocks(grad, data, dofs, slots, g, H=None):
    """grad (3n,) += the per-stencil gradients g (E, 3k) at ``dofs``; with ``data`` and H (E, 3k, 3k), data[slots]
    += the upper triangles of the Hessians (``slots`` (E, 3k(3k+1)/2) as ``HessianPattern.stencil_slots``, -1 for
    entries of fixed DoFs, which are dropped)."""
    np.add.at(grad, dofs, g)
    if data is not None:
        iu, ju = np.triu_indices(dofs.shape[1])
        values, ok = H[:, iu, ju], slots >= 0
        np.add.at(data, slots[ok], values[ok])


class AutogradKernel:
    """A term without compiled kernels, behind the interface of ``kernels.TermKernel`` that
    :class:`CompiledAssembly` calls: its energy and gradient by PyTorch autograd of
    ``local_energy``, its per-stencil gradient and (exact or projected) Hessian by
    ``EnergyTerm.local_gradient_hessian`` (``base.autograd_gradient_hessian``), scattered
    into the gradient and the Hessian data at the pattern's slots.  float64 on the CPU.
    """

    def __init__(self, term):
        self.term, self.name = term, term.name
        self.stencils = np.ascontiguousarray(term.stencils.cpu().numpy(), dtype=np.int64)
        self.k = int(self.stencils.shape[1])
        self.groups, self.threads = (np.arange(len(self.stencils)),), 1  # set by split_stencils, unused

    def energy(self, x) -> float:
        """The term's energy at x (n, 3)."""
        with torch.no_grad():
            return float(self.term.energy(torch.as_tensor(np.asarray(x, dtype=np.float64))))

    def energy_gradient(self, x, grad) -> float:
        """grad (3n,) += the gradient at x (n, 3); returns the energy."""
        xt = torch.tensor(np.asarray(x, dtype=np.float64), requires_grad=True)
        with torch.enable_grad():
            e = self.term.energy(xt)
            (g,) = torch.autograd.grad(e, xt)
        grad += g.numpy().reshape(-1)
        return float(e.detach())

    def accumulate(self, x, grad, data, slots, project: bool) -> float:
        """grad (3n,) += gradient; data[slots] += the upper triangles of the stencil Hessians
        (slots as ``TermKernel.accumulate``'s, -1 for dropped entries); returns the energy."""
        xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
        xe = self.term.gather(xt)
        with torch.no_grad():
            e = float(self.term.local_energy(xe).sum())
        g, H = self.term.local_gradient_hessian(xe, project=bool(project))
        add_stencil_blocks(grad, data, stencil_dofs(self.stencils), slots, g.cpu().numpy(), H.cpu().numpy())
        return e


class CompiledAssembly:
    """The kernels of a potential's elastic terms (compiled, :mod:`latentsim.physics.kernels`, or
    :class:`AutogradKernel`), scattering each stencil's gradient and Hessian straight into the
    gradient and into the data of a ``HessianPattern``'s upper-triangular CSR (or, for ``banded=True``, the banded storage of
    ``sparse.BandedUpper``): no per-stencil blocks, no COO->CSR conversion.

    Parameters
    ----------
    kernels : one ``TermKernel`` (``term_kernel``) or ``AutogradKernel`` per term; their stencils are split for
        ``threads`` (``latentsim.physics.kernels.split_stencils``).
    pattern : the free-DoF Hessian pattern of those stencils.
    """

    def __init__(self, kernels, pattern: HessianPattern, n_vertices: int, banded: bool = False, threads: int = 1):
        self.kernels, self.pattern, self.n, self.banded = kernels, pattern, int(n_vertices), bool(banded)
        split_stencils(kernels, self.n, threads)
        self.slots = [pattern.stencil_slots(k.stencils) for k in kernels]
        self._diag_slots = pattern.diagonal_slots
        self._target_size = pattern.nnz
        if banded:
            pos = pattern.band_positions()
            self.slots = [np.where(s >= 0, pos[s], -1).astype(np.int32) for s in self.slots]
            self._diag_slots = pos[self._diag_slots]
            self._target_size = (pattern.bandwidth + 1) * pattern.shape[0]

        self.step_terms, self._step_slots, self._step_dofs = [], [], []
        self._extra = []  # the dynamic terms' Hessians of the last evaluation (upper CSR over the free DoFs)

    def with_frame_terms(self, terms) -> "CompiledAssembly":
        """Add terms that depend on the step's frame (``EnergyTerm.at``; their stencils among the pattern's) to
        every evaluation, by their own per-stencil gradient and (projected or exact) Hessian.  ``step_terms``
        holds them as they stand over the current step (a solver sets it per step, in the same order).  A
        ``dynamic`` term (its pairs change with x: self-contact) gives its gradient and its Hessian as a sparse
        matrix of its own (``energy_gradient_hessian(x, free_dofs, project, hessian)``), added to the pattern's:
        the matrix's pattern then changes between evaluations, so the banded storage cannot hold it."""
        self.step_terms = list(terms)
        self._step_slots, self._step_dofs = [], []
        if self.banded and any(getattr(t, "dynamic", False) for t in self.step_terms):
            raise ValueError("a dynamic term (self-contact) needs a general sparse Hessian, not the banded storage")
        for term in self.step_terms:
            st = term.stencils.cpu().numpy()
            slots = self.pattern.stencil_slots(st)
            if self.banded:
                slots = np.where(slots >= 0, self.pattern.band_positions()[slots], -1)
            self._step_slots.append(slots)
            self._step_dofs.append(stencil_dofs(st))
        return self

    def _frame_terms(self, x, grad, data=None, project=True) -> float:
        """The step terms' energy at x (n,3); with ``grad``, their gradients added into it and, with ``data``,
        their Hessians' upper triangles into the matrix data."""
        xt = torch.as_tensor(np.asarray(x, dtype=np.float64))
        total = 0.0
        for term, slots, dofs in zip(self.step_terms, self._step_slots, self._step_dofs):
            if getattr(term, "dynamic", False) and grad is not None:
                e, g, U = term.energy_gradient_hessian(x, self.pattern.free_dofs, project, hessian=data is not None)
                total += e
                grad += g
                if data is not None:
                    self._extra.append(U)
                continue
            e = float(term.energy(xt))
            total += e
            if grad is None or not np.isfinite(e):
                continue
            g, H = term.local_gradient_hessian(term.gather(xt), project=project, hessian=data is not None)
            add_stencil_blocks(grad, data, dofs, slots, g.numpy(), None if data is None else H.numpy())
        return total

    @classmethod
    def of(cls, terms, pattern: HessianPattern, n_vertices: int, banded: bool = False, threads: int = 1):
        """For the terms' compiled kernels (``term_kernel``), an ``AutogradKernel`` for a term without."""
        ks = [term_kernel(t) or AutogradKernel(t) for t in terms]
        return cls(ks, pattern, n_vertices, banded, threads)

    def energy(self, x) -> float:
        """Elastic energy at x (n,3) (and the step terms')."""
        e = sum(k.energy(x) for k in self.kernels)
        if self.step_terms:
            e += self._frame_terms(x, None)
        return e

    def energy_gradient(self, x):
        """Elastic energy and its full gradient (3n,) in one pass (with the step terms')."""
        grad = np.zeros(3 * self.n)
        e = sum(k.energy_gradient(x, grad) for k in self.kernels)
        if self.step_terms:
            e += self._frame_terms(x, grad)
        return e, grad

    def gradient_hessian(self, x, diagonal, project: bool):
        """Elastic gradient (3n,) and the free-DoF Hessian plus ``diagonal`` (3n,) on its diagonal,
        as upper-triangular CSR or ``BandedUpper``; per-stencil PSD-projected or exact."""
        _, grad, U = self.energy_gradient_hessian(x, diagonal, project)
        return grad, U

    def energy_gradient_hessian(self, x, diagonal, project: bool):
        """``gradient_hessian`` with the elastic energy of the same pass in front: (E, grad, U)."""
        grad = np.zeros(3 * self.n)
        data = np.zeros(self._target_size)
        e = 0.0
        self._extra = []
        for k, slots in zip(self.kernels, self.slots):
            e += k.accumulate(x, grad, data, slots, project)
        if self.step_terms:
            e += self._frame_terms(x, grad, data, project)
        add_at(data, self._diag_slots, np.ascontiguousarray(diagonal, dtype=np.float64)[self.pattern.free_dofs])
        p = self.pattern
        if self.banded:
            return e, grad, BandedUpper(data, p)
        U = scipy.sparse.csr_matrix((data, p.indices, p.indptr), shape=p.shape)
        for extra in self._extra:
            U = U + extra
        return e, grad, U
