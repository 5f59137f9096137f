r"""The Neural Modes authors' StVK energies (Wang et al. 2024), a material option (``stvk_nm``).

Wang et al. name their energies only as "Discrete Shell" (the sheet) and
"Tetrahedron" (the solids) in their Table 1; the formulas below are those of
their discretisation as the project's issue states them, and differ from the
project's default StVK (``physics.shells``, ``physics.tets``) in three ways:

* membrane (constant-strain triangles), per triangle

      W = h Abar (mu tr(E^2) + lam/2 (J - 1)^2),

  E = (F^T F - I)/2 the 2x2 Green strain (F = Ds Dm^{-1}, 3x2, as in
  ``shells.ShellMembraneStVK``), J = sqrt(det F^T F) = A / Abar the area
  ratio, and mu, lam the *3D* Lame constants (``tets.lame``), where the
  default membrane uses the plane-stress lam with (tr E)^2;
* hinge bending ``3 kB |ebar|^2 / (Abar_1 + Abar_2) (theta - thetabar)^2``:
  ``shells.ShellHinge`` with kB given (``material.bending_stiffness``) or
  kB = D/2, D = Y h^3 / (12 (1 - nu^2)) (:func:`neural_modes_hinge`), where
  the default uses kB = D/6;
* tetrahedra, per tet

      W = V0 (mu ||E||_F^2 + lam (J - 1)^2),   J = det F,

  where the default uses lam/2 (tr E)^2.

Both new terms follow the contract of ``physics.base``: ``local_energy`` in
PyTorch (the autograd oracle), compiled energy, gradient and exact or
PSD-projected Hessian (``kernels.stvk_nm``; formulas there; the projection is
the eigenvalue clamp of each stencil Hessian on its translation-free block),
and ``weighted_subset`` for cubature.  The membrane's J is not differentiable
where a triangle collapses to a segment (J = 0).
"""

from __future__ import annotations

import torch

from latentsim.physics.base import EnergyTerm, subset_weights
from latentsim.physics.kernels import stvk_nm as nm_kernels
from latentsim.physics.kernels.core import translation_free_basis
from latentsim.physics.kernels.dispatch import KernelSpec, float64_array
from latentsim.physics.shells import ShellHinge, ShellMembraneStVK, _as_long, _as_positions, _per_stencil, triangle_kernel_spec, triangle_rest_frames
from latentsim.physics.tets import _edge_matrix, lame

__all__ = ["ShellMembraneNM", "TetsNM", "neural_modes_hinge"]


def neural_modes_hinge(rest_positions, hinges, youngs_modulus, poisson_ratio, thickness, bending_stiffness_kb=None) -> ShellHinge:
    """The authors' hinge term, 3 kB |ebar|^2/(Abar_1 + Abar_2) (theta - thetabar)^2.

    Parameters
    ----------
    rest_positions : (n, 3); hinges : (H, 4) int (``shells.hinges_from_triangles``).
    youngs_modulus, poisson_ratio, thickness : floats, for kB = D/2 = Y h^3 / (24 (1 - nu^2)).
    bending_stiffness_kb : float [N m] or None: kB given directly (the material's
        ``bending_stiffness``); None: D/2.
    """
    if bending_stiffness_kb is None:
        return ShellHinge(rest_positions, hinges, youngs_modulus, poisson_ratio, thickness, stiffness_scale=0.5)
    kb = float(bending_stiffness_kb)
    if not kb > 0.0:
        raise ValueError(f"bending_stiffness must be positive, got {bending_stiffness_kb}")
    return ShellHinge(rest_positions, hinges, 12.0 * kb, 0.0, 1.0)  # D(Y = 12 kB, nu = 0, h = 1) = kB


def _young_poisson(mu: torch.Tensor, lam: torch.Tensor):
    """(Y, nu) of the 3D Lame constants (mu, lam)."""
    return mu * (3.0 * lam + 2.0 * mu) / (lam + mu), lam / (2.0 * (lam + mu))


class ShellMembraneNM(EnergyTerm):
    """The authors' membrane, W = h Abar (mu tr(E^2) + lam/2 (J - 1)^2), 3D Lame constants.

    Parameters
    ----------
    rest_positions : (n, 3); triangles : (T, 3) int;
    youngs_modulus : float or (T,) [Pa]; poisson_ratio : float or (T,) in (-1, 0.5);
    thickness : float or (T,) [m].

    Attributes
    ----------
    stencils : (T, 3) long; rest_area : (T,); Dm_inv : (T, 2, 2) (2D rest frame,
    ``shells.triangle_rest_frames``); mu, lam, thickness : (T,).
    """

    name = "shell_membrane_nm"

    def __init__(self, rest_positions, triangles, youngs_modulus, poisson_ratio, thickness):
        X = _as_positions(rest_positions)
        self.stencils = _as_long(triangles, 3, "triangles")
        self.rest_positions = X
        T = self.stencils.shape[0]
        self.rest_area, Dm = triangle_rest_frames(X, self.stencils)
        self.Dm_inv = torch.linalg.inv(Dm)
        mu, lam = lame(torch.as_tensor(youngs_modulus, dtype=torch.float64), torch.as_tensor(poisson_ratio, dtype=torch.float64))
        self.mu = _per_stencil(mu, T, "youngs_modulus/poisson_ratio")
        self.lam = _per_stencil(lam, T, "youngs_modulus/poisson_ratio")
        self.thickness = _per_stencil(thickness, T, "thickness")

    def weighted_subset(self, index, weights) -> "ShellMembraneNM":
        """sum_{t in index} w_t E_t: thickness w_t h_t (a cubature, see ``base.subset_weights``)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        Y, nu = _young_poisson(self.mu[idx], self.lam[idx])
        return ShellMembraneNM(self.rest_positions, self.stencils[idx], Y, nu, self.thickness[idx] * w)

    deformation_gradient = ShellMembraneStVK.deformation_gradient  # F = Ds Dm^{-1}, (..., T, 3, 3) -> (..., T, 3, 2)

    def energy_density(self, F: torch.Tensor) -> torch.Tensor:
        """psi = mu tr(E^2) + lam/2 (J - 1)^2 [Pa] per triangle; F (..., T, 3, 2) -> (..., T)."""
        C = F.transpose(-1, -2) @ F
        Eg = 0.5 * (C - torch.eye(2, dtype=F.dtype, device=F.device))
        J = torch.sqrt(C[..., 0, 0] * C[..., 1, 1] - C[..., 0, 1] * C[..., 1, 0])
        return self.mu.to(F) * (Eg * Eg).sum((-1, -2)) + 0.5 * self.lam.to(F) * (J - 1.0) ** 2

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """h Abar (mu tr(E^2) + lam/2 (J - 1)^2); xe (..., T, 3, 3) -> (..., T)."""
        return (self.rest_area * self.thickness).to(xe) * self.energy_density(self.deformation_gradient(xe))

    def first_piola(self, x: torch.Tensor) -> torch.Tensor:
        """P = d psi / dF [Pa] per triangle (autograd of :meth:`energy_density`); x (..., n, 3) -> (..., T, 3, 2)."""
        F = self.deformation_gradient(self.gather(x)).detach().requires_grad_(True)
        with torch.enable_grad():
            (P,) = torch.autograd.grad(self.energy_density(F).sum(), F)
        return P

    def stress_norm(self, x: torch.Tensor) -> torch.Tensor:
        """||P||_F per triangle [Pa] (Wang et al. Table 4); x (..., n, 3) -> (..., T)."""
        return torch.linalg.matrix_norm(self.first_piola(x))

    def kernel_spec(self) -> KernelSpec:
        """The compiled kernels (``kernels.stvk_nm``; rest data as ``shells.triangle_kernel_spec``)."""
        return triangle_kernel_spec(self, nm_kernels.membrane_nm_energy, nm_kernels.membrane_nm_energy_gradient, nm_kernels.membrane_nm_run)


class TetsNM(EnergyTerm):
    """The authors' tetrahedra, W = V0 (mu ||E||_F^2 + lam (det F - 1)^2).

    Parameters
    ----------
    rest_positions : (n, 3); tets : (E, 4) int, positively oriented;
    youngs_modulus, poisson_ratio : floats or (E,) tensors (``tets.lame``).

    Attributes
    ----------
    stencils : (E, 4) long; Dm_inv : (E, 3, 3); rest_volume : (E,);
    grad_op : (E, 4, 3) barycentric gradients D (F = sum_a x_a D_a^T); mu, lam : (E,).

    Raises
    ------
    ValueError naming the elements if a rest volume is not positive.
    """

    name = "tets_nm"

    def __init__(self, rest_positions, tets, youngs_modulus, poisson_ratio):
        X = _as_positions(rest_positions)
        self.stencils = _as_long(tets, 4, "tets")
        self.rest_positions = X
        E = self.stencils.shape[0]
        Dm = _edge_matrix(X, self.stencils)
        vol = torch.linalg.det(Dm) / 6.0
        bad = torch.nonzero(~(torch.isfinite(vol) & (vol > 0))).flatten()
        if bad.numel():
            i = int(bad[0])
            raise ValueError(f"tets {bad[:10].tolist()} have non-positive rest volume (element {i}: {float(vol[i]):.3e})")
        self.rest_volume = vol
        self.Dm_inv = torch.linalg.inv(Dm)
        self.grad_op = torch.cat([-self.Dm_inv.sum(1, keepdim=True), self.Dm_inv], dim=1)
        mu, lam = lame(torch.as_tensor(youngs_modulus, dtype=torch.float64), torch.as_tensor(poisson_ratio, dtype=torch.float64))
        self.mu = _per_stencil(mu, E, "youngs_modulus/poisson_ratio")
        self.lam = _per_stencil(lam, E, "youngs_modulus/poisson_ratio")

    def weighted_subset(self, index, weights) -> "TetsNM":
        """sum_{e in index} w_e W_e: Young's modulus w_e Y_e (Psi is linear in (mu, lam) at fixed nu)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        Y, nu = _young_poisson(self.mu[idx], self.lam[idx])
        return TetsNM(self.rest_positions, self.stencils[idx], Y * w, nu)

    def deformation_gradient(self, xe: torch.Tensor) -> torch.Tensor:
        """F = Ds Dm^{-1}; xe (..., E, 4, 3) -> (..., E, 3, 3)."""
        Ds = (xe[..., 1:, :] - xe[..., :1, :]).transpose(-1, -2)
        return Ds @ self.Dm_inv.to(xe)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """V0 (mu ||E||^2 + lam (det F - 1)^2); xe (..., E, 4, 3) -> (..., E)."""
        F = self.deformation_gradient(xe)
        Eg = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(3, dtype=F.dtype, device=F.device))
        J = torch.linalg.det(F)
        psi = self.mu.to(xe) * (Eg * Eg).sum((-1, -2)) + self.lam.to(xe) * (J - 1.0) ** 2
        return self.rest_volume.to(xe) * psi

    def kernel_spec(self) -> KernelSpec:
        """The compiled kernels (``kernels.stvk_nm``)."""
        args = (float64_array(self.grad_op), float64_array(self.rest_volume), float64_array(self.mu), float64_array(self.lam))
        return KernelSpec(nm_kernels.tet_nm_energy, nm_kernels.tet_nm_energy_gradient, nm_kernels.tet_nm_run,
                          args, 4, translation_free_basis(4))
