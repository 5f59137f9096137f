r"""Stable neo-Hookean elasticity on linear tetrahedra (Smith, de Goes, Kim 2018).

"Stable Neo-Hookean Flesh Simulation", ACM TOG 37(2).  With the kinematics of
``physics.tets`` (F = Ds Dm^{-1}, rest volume W), I_C = tr(F^T F) and J = det F,
the energy density is (the paper's eq. 14, with the rest-stability shift of
section 3.3)

    Psi(F) = mu/2 (I_C - 3) + lam/2 (J - alpha)^2 - mu/2 log(I_C + 1) - Psi(I),
    alpha  = 1 + 3 mu / (4 lam)            (= 1 + mu/lam - mu/(4 lam)),

where the constant Psi(I) = lam/2 (1 - alpha)^2 - mu/2 log 4 is subtracted so
that the rest state has zero energy (it changes no force).  alpha makes
P(I) = 0.  Psi is finite for every F, inverted (J <= 0) and collapsed ones
included, and its J term pushes J towards alpha > 0: an inverted element is
pushed back.  StVK, whose energy depends on F^T F only, is zero at every
reflection of the rest state (F = diag(1, 1, -1)) and has no such force.

Lame reparametrisation (the paper's section 3.4).  Expanding Psi to second order
in the displacement gradient G = F - I, with eps = (G + G^T)/2,

    Psi = 3 mu/4 ||eps||^2 + (lam/2 - 5 mu/16) tr(eps)^2 + O(|G|^3),

so with the Lame parameters (mu_L, lam_L) of Young's modulus E and Poisson's
ratio nu (``tets.lame``) the energy's own parameters

    mu = 4/3 mu_L,   lam = lam_L + 5/6 mu_L

make small strains equal linear elasticity mu_L ||eps||^2 + lam_L/2 tr(eps)^2
(the small-strain limit of StVK with the same E, nu; tested).

Derivatives, closed form: P = mu I_C/(I_C + 1) F + lam (J - alpha) cof F, and
dP/dF with its analytic eigensystem in the principal-stretch frame (the paper's
section 4), clamped for Newton; formulas in ``kernels.neohookean``, which
compiles them per element (``kernel_spec``).  ``local_energy`` is pure torch
and autograd-differentiable, the oracle the tests compare the kernels with.
"""

from __future__ import annotations

import math

import torch

from latentsim.physics.base import subset_weights
from latentsim.physics.kernels import neohookean as snh_kernels
from latentsim.physics.kernels.dispatch import KernelSpec, float64_array
from latentsim.physics.tets import StVKTets, lame


def snh_parameters(youngs_modulus, poisson_ratio):
    """The stable neo-Hookean (mu, lam) whose small-strain limit is linear elasticity with E, nu.

    mu = 4/3 mu_L, lam = lam_L + 5/6 mu_L with (mu_L, lam_L) = ``tets.lame(E, nu)``.
    """
    mu_l, lam_l = lame(youngs_modulus, poisson_ratio)
    return 4.0 / 3.0 * mu_l, lam_l + 5.0 / 6.0 * mu_l


def snh_density(F: torch.Tensor, mu, lam) -> torch.Tensor:
    """Psi(F) - Psi(I) of the module docstring; F (..., 3, 3), mu, lam broadcastable to (...) -> (...).

    mu and lam given as Python numbers (``snh_density(F, *snh_parameters(E, nu))``) are taken in float64:
    alpha and Psi(I) cancel the rest energy only to the precision they are computed in (float32's would leave
    about 1e-8 mu at F = I)."""
    mu, lam = (m if isinstance(m, torch.Tensor) else torch.as_tensor(m, dtype=torch.float64, device=F.device) for m in (mu, lam))
    Ic = (F * F).sum((-1, -2))
    J = torch.linalg.det(F)
    ratio = torch.where(lam != 0, mu / lam, 0.0)  # a zero-weight element: 0
    alpha = 1.0 + 0.75 * ratio
    rest = 0.28125 * mu * ratio - 0.5 * mu * math.log(4.0)  # lam/2 (1 - alpha)^2 - mu/2 log 4
    return 0.5 * mu * (Ic - 3.0) + 0.5 * lam * (J - alpha) ** 2 - 0.5 * mu * torch.log(Ic + 1.0) - rest


class StableNeoHookeanTets(StVKTets):
    """Stable neo-Hookean energy of linear tetrahedra, sum_e W_e Psi(F_e).

    The rest geometry, its checks and the kinematics are those of ``StVKTets``
    (same parameters); ``mu``, ``lam`` hold the energy's own (reparametrised)
    Lame parameters, ``snh_parameters(E, nu)``.
    """

    name = "snh_tets"

    def __init__(self, rest_positions, tets, youngs_modulus, poisson_ratio):
        super().__init__(rest_positions, tets, youngs_modulus, poisson_ratio)
        mu, lam = snh_parameters(youngs_modulus, poisson_ratio)
        self.mu = torch.as_tensor(mu, dtype=self.rest_positions.dtype, device=self.rest_positions.device)
        self.lam = torch.as_tensor(lam, dtype=self.rest_positions.dtype, device=self.rest_positions.device)

    def youngs_poisson(self):
        """(E, nu) of this term's (reparametrised) mu, lam: the inverse of ``snh_parameters``."""
        mu_l = 0.75 * self.mu
        lam_l = self.lam - 5.0 / 6.0 * mu_l
        return mu_l * (3.0 * lam_l + 2.0 * mu_l) / (lam_l + mu_l), lam_l / (2.0 * (lam_l + mu_l))

    def weighted_subset(self, index, weights) -> "StableNeoHookeanTets":
        """sum_{e in index} w_e W_e Psi(F_e) (a cubature, see ``base.subset_weights``).

        Psi is linear in (mu, lam) at a fixed ratio (alpha depends on mu/lam only),
        so w_e W_e Psi is W_e Psi with Young's modulus w_e E.
        """
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        youngs, nu = self.youngs_poisson()

        def per_element(t):
            t = torch.as_tensor(t, dtype=torch.float64)
            return t[idx] if t.ndim else t

        sub = StableNeoHookeanTets(self.rest_positions, self.stencils[idx], per_element(youngs), per_element(nu))
        sub.mu, sub.lam = per_element(self.mu) * w, per_element(self.lam) * w  # a zero weight: mu = lam = 0
        return sub

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """W_e (Psi(F_e) - Psi(I)); xe (..., E, 4, 3) -> (..., E); differentiable, batched."""
        F = self.deformation_gradient(xe)
        psi = snh_density(F, self._rest(self.mu, xe), self._rest(self.lam, xe))
        return self._rest(self.rest_volume, xe) * psi

    def first_piola(self, x: torch.Tensor) -> torch.Tensor:
        """P = mu I_C/(I_C + 1) F + lam (J - alpha) cof F; x (..., n, 3) -> (..., E, 3, 3)."""
        F = self.deformation_gradient(self.gather(x))
        mu = self._rest(self.mu, F)[..., None, None]
        lam = self._rest(self.lam, F)[..., None, None]
        Ic = (F * F).sum((-1, -2))[..., None, None]
        J = torch.linalg.det(F)[..., None, None]
        c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
        cof = torch.stack([torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0), torch.linalg.cross(c0, c1)], -1)
        ratio = torch.where(lam != 0, mu / lam, 0.0)
        return mu * Ic / (Ic + 1.0) * F + lam * (J - (1.0 + 0.75 * ratio)) * cof

    def kernel_spec(self) -> KernelSpec:
        """The compiled kernels (``kernels.neohookean``): gradient W B^T vec(P), the exact Hessian
        W B^T (dP/dF) B, or the projected one with dP/dF clamped in its analytic eigensystem."""
        E = int(self.stencils.shape[0])
        args = (float64_array(self.grad_op), float64_array(self.rest_volume, E), float64_array(self.mu, E), float64_array(self.lam, E))
        return KernelSpec(snh_kernels.snh_energy, snh_kernels.snh_energy_gradient, snh_kernels.snh_run, args, 4)


__all__ = ["StableNeoHookeanTets", "snh_density", "snh_parameters"]
