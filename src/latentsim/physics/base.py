"""The contract every energy term follows.

An energy term is a sum over *stencils*: small tuples of vertices (an edge, a
triangle, a tetrahedron, a hinge, three consecutive rod vertices).  Each term
stores

- ``stencils`` : (E, k) int64 tensor of vertex indices,
- per-stencil rest quantities as tensors whose leading axis is E,

and implements

- ``local_energy(xe)`` : xe (..., E, k, 3) -> (..., E), differentiable and
  batched over any leading axes (decoded latents, samples, time),
- ``kernel_spec()`` : the term's compiled kernels (``kernels.KernelSpec``:
  energy, gradient and Hessian per stencil, ``physics.kernels``), or None;

and so offers ``local_gradient_hessian(xe)`` : xe (E, k, 3) -> (g (E, 3k),
H (E, 3k, 3k)), the per-stencil gradient and Hessian, exact or positive
semi-definite (projected, Teran et al. 2005), by the compiled kernels, or by
autograd (``torch.func``) plus an eigenvalue clamp for a term without.  The
autograd version, ``autograd_gradient_hessian``, is the oracle the tests
compare the kernels against, and the path by which every solver runs a term
without kernels (``solve.assembly.AutogradKernel``): ``local_energy`` is all a
new term needs, the kernels are an optimisation.

A term of the incremental potential is ``energy(x, frame)``, with ``frame`` what
the time step knows (:class:`~latentsim.physics.frame.Frame`: the prescribed
targets, the previous positions, the time step); a term that depends on it (the
contact barrier with its moving colliders and lagged friction, a damping term)
overrides ``at(frame)``, the term as it stands over one step, whose energy and
per-stencil derivatives are functions of x alone: what a solver evaluates.  A
term whose energy is infinite somewhere (a barrier) also offers
``first_impact(x, dx, frame=None)``: the first fraction t >= 0 of the straight
step x -> x + dx at which it turns infinite (inf: never), where a line search
must stop short; a term without it imposes no limit.

Everything here is float64 unless the caller passes float32 states.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.func import vmap

from latentsim.physics.kernels.core import translation_free_basis
from latentsim.physics.kernels.dispatch import KernelSpec, TermKernel


class EnergyTerm:
    """Base class: a sum of per-stencil energies over ``stencils``."""

    name = "term"
    stencils: torch.Tensor  # (E, k)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- derived quantities -------------------------------------------------
    def gather(self, x: torch.Tensor) -> torch.Tensor:
        """x (..., n, 3) -> xe (..., E, k, 3)."""
        return x[..., self.stencils, :]

    def element_energy(self, x: torch.Tensor) -> torch.Tensor:
        """Energy per stencil, x (..., n, 3) -> (..., E)."""
        return self.local_energy(self.gather(x))

    def energy(self, x: torch.Tensor, frame=None) -> torch.Tensor:
        """Total energy, x (..., n, 3) -> (...); ``frame`` (:class:`~latentsim.physics.frame.Frame`) that of
        :meth:`at` the step's, ignored by a term that does not depend on it."""
        return self.element_energy(x).sum(-1)

    def at(self, frame) -> "EnergyTerm":
        """The term as it stands over the step of ``frame``: its energy and derivatives then depend on x
        alone (this term itself, unless it depends on the frame)."""
        return self

    def kernel_spec(self) -> KernelSpec | None:
        """The term's compiled kernels (``physics.kernels``); None: the term has none."""
        return None

    def local_gradient_hessian(self, xe: torch.Tensor, project: bool = True, hessian: bool = True):
        """Per-stencil gradient (E, 3k) and Hessian (E, 3k, 3k), PSD-projected when ``project``
        (the Hessian None without ``hessian``: a line search's trial needs the gradient alone).

        xe : (E, k, 3), the positions of all E stencils (in ``stencils`` order).
        Computed by the compiled kernels (float64, returned in xe's dtype and
        device), or by ``autograd_gradient_hessian`` for a term without.
        """
        spec = self.kernel_spec()
        if spec is None:
            g, H = autograd_gradient_hessian(self, xe, project=project)
            return g, (H if hessian else None)
        E, k, _ = xe.shape
        if E != len(self.stencils):
            raise ValueError(f"{self.name}: xe holds {E} stencils, the term has {len(self.stencils)} (their rest data)")
        own = TermKernel(self.name, np.arange(E * k).reshape(E, k), spec)  # stencil e = its own k vertices
        g, H = own.local(xe.detach().cpu().numpy().reshape(E * k, 3), project)
        return torch.from_numpy(g).to(xe), (torch.from_numpy(H).to(xe) if hessian else None)


def autograd_gradient_hessian(term: EnergyTerm, xe: torch.Tensor, project: bool = True):
    """Oracle: per-stencil gradient and Hessian by autograd, optionally PSD-projected.

    Differentiates ``term.local_energy`` of a batch of single stencils.  Each
    stencil's rest data are selected by broadcasting: we evaluate the energy of
    all stencils at once with a perturbation applied only to stencil e, which
    ``vmap`` over the flattened coordinates achieves without loops.

    Parameters
    ----------
    xe : (E, k, 3) stencil positions.

    Returns
    -------
    g : (E, 3k), H : (E, 3k, 3k)
    """
    E, k, _ = xe.shape
    flat = xe.reshape(E, 3 * k)

    def total(flat_all: torch.Tensor) -> torch.Tensor:
        return term.local_energy(flat_all.reshape(E, k, 3)).sum()

    # Stencils are independent, so the gradient of the sum is the per-stencil
    # gradient, and the Hessian of the sum is block diagonal: recover each
    # block by a Hessian-vector product with the j-th unit vector replicated
    # on every stencil.
    g = torch.func.grad(total)(flat)
    eye = torch.eye(3 * k, dtype=xe.dtype, device=xe.device)

    def hvp(v_local: torch.Tensor) -> torch.Tensor:
        v = v_local.expand(E, 3 * k)
        return torch.func.jvp(torch.func.grad(total), (flat,), (v,))[1]

    H = vmap(hvp)(eye)  # (3k, E, 3k): column j of every block
    H = H.permute(1, 2, 0).contiguous()
    H = 0.5 * (H + H.transpose(1, 2))
    if project:
        H = project_psd(H)
    return g.detach(), H.detach()


def subset_weights(index, weights, count: int):
    """Validated (index (k,) long, weights (k,) float64) of a cubature subset of ``count`` stencils.

    Every term's ``weighted_subset(index, weights)`` returns the term over the
    stencils ``index`` with each stencil's energy scaled by its weight,
    sum_{e in index} w_e E_e (``latentsim.solve.cubature``); all our energies are
    linear in a per-stencil stiffness, so the subset is a term of the same
    class and every solver path, compiled kernels included, serves it.
    """
    idx = torch.as_tensor(np.asarray(index, dtype=np.int64))
    w = torch.as_tensor(np.asarray(weights, dtype=np.float64))
    if idx.ndim != 1 or w.shape != idx.shape:
        raise ValueError(f"index and weights must be two (k,) arrays, got shapes {tuple(idx.shape)} and {tuple(w.shape)}")
    if not bool(torch.all(torch.isfinite(w))) or bool(torch.any(w < 0)):
        raise ValueError("cubature weights must be finite and non-negative")
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= count):
        raise ValueError(f"stencil index out of range [0, {count})")
    return idx, w


def project_psd(H: torch.Tensor, floor: float = 0.0) -> torch.Tensor:
    """Clamp the eigenvalues of a batch of symmetric matrices at ``floor``."""
    w, Q = torch.linalg.eigh(H)
    w = torch.clamp(w, min=floor)
    return (Q * w.unsqueeze(-2)) @ Q.transpose(-1, -2)


def project_psd_translation_free(H: torch.Tensor, k: int) -> torch.Tensor:
    """Eigenvalue clamp of translation-invariant stencil Hessians H (E, 3k, 3k).

    An energy invariant under translations of all k stencil vertices has
    H = B M B^T with B = Q (x) I3 (3k, 3k-3), Q (k, k-1) an orthonormal basis
    of the vectors orthogonal to (1, .., 1) (``kernels.translation_free_basis``),
    and M = B^T H B; clamping the eigenvalues of M (``project_psd``) is the
    exact eigenvalue clamp of H, as the compiled kernels do it.
    """
    B = torch.from_numpy(translation_free_basis(k)).to(H)
    M = B.T @ H @ B
    return B @ project_psd(0.5 * (M + M.transpose(-1, -2))) @ B.T


__all__ = ["EnergyTerm", "autograd_gradient_hessian", "project_psd", "project_psd_translation_free", "subset_weights"]
