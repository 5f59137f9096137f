r"""St. Venant-Kirchhoff elasticity on linear tetrahedra.

Kinematics (Sifakis & Barbic 2012, "FEM simulation of 3D deformable solids",
SIGGRAPH course notes, sections 3-4).  A tet with rest vertices X_0..X_3 and
deformed vertices x_0..x_3 has the constant deformation gradient

    F = Ds Dm^{-1},   Ds = [x1-x0, x2-x0, x3-x0],   Dm = [X1-X0, X2-X0, X3-X0],

rest volume W = det(Dm)/6 > 0, and elastic energy W * Psi(F) with the StVK
energy density

    E   = (F^T F - I) / 2                          (Green strain)
    Psi = mu ||E||_F^2 + lam/2 tr(E)^2
    P   = dPsi/dF = F S,   S = 2 mu E + lam tr(E) I  (first / second Piola).

F is linear in the 12 stencil coordinates: F_ij = sum_a x_{a,i} D_{a,j} with
D (4, 3) the gradients of the barycentric coordinates (rows of Dm^{-1} and
minus their sum), so vec(F) = B x_e with B (9, 12) and

    g_e = W B^T vec(P)  (= W D P^T as a (4, 3) array),
    H_e = W B^T (dP/dF) B,
    dP  = dF S + F dS,  dS = 2 mu dE + lam tr(dE) I,  dE = (dF^T F + F^T dF)/2.

PSD projection for Newton (Teran et al. 2005, "Robust quasistatic finite
elements and flesh simulation"; Smith et al. 2019, "Analytic eigensystems for
isotropic distortion energies").  With the rotation-variant SVD
F = U diag(sigma) V^T (det U = det V = +1, the smallest sigma carries the sign
of det F) the 9x9 Hessian dP/dF has the closed-form eigensystem

    scaling (3): eigenpairs (alpha_k, w_k) of the 3x3 matrix
                 A_ii = mu (3 sigma_i^2 - 1) + lam T + lam sigma_i^2,
                 A_ij = lam sigma_i sigma_j,     T = sum_j (sigma_j^2 - 1)/2,
                 eigenmatrix U diag(w_k) V^T;
    flip  (ij):  mu (sigma_i^2 + sigma_j^2 - 1) + lam T + mu sigma_i sigma_j,
                 eigenmatrix U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2;
    twist (ij):  mu (sigma_i^2 + sigma_j^2 - 1) + lam T - mu sigma_i sigma_j,
                 eigenmatrix U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2.

(These are the Hessian of Psi(diag sigma), which is block diagonal by the
reflection symmetries of Psi; the flip/twist values equal Teran's
(psi_i -/+ psi_j)/(sigma_i -/+ sigma_j) with the division carried out, so they
stay exact at repeated singular values.)  Clamping the eigenvalues at zero
gives the projected element Hessian

    H_e^+ = W sum_k max(lambda_k, 0) g_k g_k^T,   g_k = B^T vec(Q_k).

Note that this projects dP/dF in F-space, which differs from the eigenvalue
clamp of the 12x12 element Hessian unless D^T D is a multiple of the identity
(e.g. for regular tets); both are PSD and both are exact where dP/dF is PSD.

The gradient and both Hessians are compiled per element (``kernels.tets``,
with the Jacobi SVD of ``kernels.core``; ``kernel_spec``) and serve
``local_gradient_hessian``; ``local_energy`` is pure torch and
autograd-differentiable, the oracle the tests compare the kernels with.
"""

from __future__ import annotations

import torch

from latentsim.physics.base import EnergyTerm, subset_weights
from latentsim.physics.kernels import tets as tet_kernels
from latentsim.physics.kernels.dispatch import KernelSpec, float64_array


# --------------------------------------------------------------------------
# material parameters and rest geometry
# --------------------------------------------------------------------------
def lame(youngs_modulus, poisson_ratio):
    """Lame parameters from Young's modulus Y and Poisson's ratio nu.

    mu = Y / (2 (1 + nu)),  lam = Y nu / ((1 + nu)(1 - 2 nu)).

    Parameters
    ----------
    youngs_modulus, poisson_ratio : float or tensor (broadcastable), with
        -1 < nu < 1/2.

    Returns
    -------
    (mu, lam) : same type/shape as the broadcast inputs.
    """
    nu = torch.as_tensor(poisson_ratio, dtype=torch.float64)
    if bool(torch.any((nu <= -1.0) | (nu >= 0.5))):
        raise ValueError(f"Poisson ratio must lie in (-1, 0.5), got {poisson_ratio}")
    mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))
    return mu, lam


def _edge_matrix(positions: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Dm (E, 3, 3) with columns X1-X0, X2-X0, X3-X0."""
    X = positions[tets]  # (E, 4, 3)
    return (X[:, 1:, :] - X[:, :1, :]).transpose(1, 2)


def tet_volumes(positions: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed tet volumes det([x1-x0, x2-x0, x3-x0]) / 6.

    positions : (n, 3); tets : (E, 4) long.  Returns (E,).
    """
    return torch.linalg.det(_edge_matrix(positions, tets)) / 6.0


def lumped_masses(rest_positions: torch.Tensor, tets: torch.Tensor, density) -> torch.Tensor:
    """Lumped vertex masses: each vertex gets density * |W_e| / 4 from each incident tet.

    Parameters
    ----------
    rest_positions : (n, 3); tets : (E, 4) long;
    density : float or (E,) tensor [kg/m^3].

    Returns
    -------
    (n,) tensor of masses; they sum to sum_e density_e |W_e|.
    """
    tets = torch.as_tensor(tets, dtype=torch.long)
    vol = tet_volumes(rest_positions, tets).abs()
    m_e = torch.as_tensor(density, dtype=vol.dtype) * vol / 4.0
    m_e = m_e.expand(vol.shape[0])
    masses = torch.zeros(rest_positions.shape[0], dtype=vol.dtype, device=vol.device)
    return masses.index_add_(0, tets.reshape(-1), m_e.repeat_interleave(4))


def stvk_density(F: torch.Tensor, mu, lam) -> torch.Tensor:
    """StVK energy density Psi(F) = mu ||E||_F^2 + lam/2 tr(E)^2, E = (F^T F - I)/2.

    F : (..., 3, 3); mu, lam broadcastable to (...).  Returns (...).
    """
    C = F.transpose(-1, -2) @ F
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    Eg = 0.5 * (C - eye)
    trE = Eg.diagonal(dim1=-2, dim2=-1).sum(-1)
    return mu * (Eg * Eg).sum((-1, -2)) + 0.5 * lam * trE * trE


# --------------------------------------------------------------------------
# the energy term
# --------------------------------------------------------------------------
class StVKTets(EnergyTerm):
    """St. Venant-Kirchhoff energy of linear tetrahedra, sum_e W_e Psi(F_e).

    Parameters
    ----------
    rest_positions : (n, 3) tensor of rest vertex positions (its dtype is kept).
    tets : (E, 4) long tensor of vertex indices, positively oriented
        (det [X1-X0, X2-X0, X3-X0] > 0).
    youngs_modulus, poisson_ratio : floats or (E,) tensors.

    Attributes
    ----------
    stencils : (E, 4) vertex indices.
    Dm_inv : (E, 3, 3) inverse rest edge matrices.
    rest_volume : (E,) rest volumes W_e.
    grad_op : (E, 4, 3) D with F = sum_a x_a D_a^T, i.e. the (9, 12) map
        vec(F) = B x_e in factored form (see ``deformation_map``).
    mu, lam : Lame parameters, scalars or (E,) tensors.

    Raises
    ------
    ValueError if a rest volume is <= 0 or non-finite (the message names the
    element indices).
    """

    name = "stvk_tets"

    def __init__(self, rest_positions, tets, youngs_modulus, poisson_ratio):
        rest = torch.as_tensor(rest_positions)
        if not rest.is_floating_point():
            rest = rest.to(torch.float64)
        tets = torch.as_tensor(tets, dtype=torch.long, device=rest.device)
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets must have shape (E, 4), got {tuple(tets.shape)}")
        self.stencils = tets
        self.rest_positions = rest
        Dm = _edge_matrix(rest, tets)
        vol = torch.linalg.det(Dm) / 6.0
        bad = torch.nonzero(~(torch.isfinite(vol) & (vol > 0)), as_tuple=False).flatten()
        if bad.numel():
            idx = bad[:10].tolist()
            more = f" (and {bad.numel() - 10} more)" if bad.numel() > 10 else ""
            raise ValueError(
                f"tets {idx}{more} have non-positive or non-finite rest volume "
                f"(first: element {idx[0]}, volume {vol[idx[0]].item():.3e}); "
                "inverted or degenerate rest tetrahedra"
            )
        self.rest_volume = vol
        self.Dm_inv = torch.linalg.inv(Dm)
        self.grad_op = torch.cat([-self.Dm_inv.sum(1, keepdim=True), self.Dm_inv], dim=1)
        mu, lam = lame(youngs_modulus, poisson_ratio)
        self.mu = torch.as_tensor(mu, dtype=rest.dtype, device=rest.device)
        self.lam = torch.as_tensor(lam, dtype=rest.dtype, device=rest.device)

    def weighted_subset(self, index, weights) -> "StVKTets":
        """sum_{e in index} w_e W_e Psi(F_e) (a cubature, see ``base.subset_weights``).

        StVK is linear in (mu, lam) at a fixed Poisson ratio, so w_e W_e Psi is
        W_e Psi with Young's modulus w_e Y.
        """
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))

        def per_element(t):
            t = torch.as_tensor(t, dtype=torch.float64)
            return t[idx] if t.ndim else t

        mu, lam = per_element(self.mu), per_element(self.lam)
        youngs = mu * (3.0 * lam + 2.0 * mu) / (lam + mu)
        nu = lam / (2.0 * (lam + mu))
        return StVKTets(self.rest_positions, self.stencils[idx], youngs * w, nu)

    # -- kinematics -------------------------------------------------------
    def _rest(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        return t if (t.dtype == like.dtype and t.device == like.device) else t.to(like)

    def deformation_gradient(self, xe: torch.Tensor) -> torch.Tensor:
        """F = Ds Dm^{-1}; xe (..., E, 4, 3) -> (..., E, 3, 3)."""
        Ds = (xe[..., 1:, :] - xe[..., :1, :]).transpose(-1, -2)
        return Ds @ self._rest(self.Dm_inv, xe)

    def deformation_map(self) -> torch.Tensor:
        """Dense B (E, 9, 12) with vec(F) = B x_e (row-major vec, x_e = xe.reshape(E, 12)).

        B[e, 3i+j, 3a+c] = delta_ic D[e, a, j].
        """
        D = self.grad_op
        eye = torch.eye(3, dtype=D.dtype, device=D.device)
        B = eye[None, :, None, None, :] * D.transpose(1, 2)[:, None, :, :, None]  # (E, i, j, a, c)
        return B.reshape(D.shape[0], 9, 12)

    # -- energy and stress ------------------------------------------------
    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """W_e Psi(F_e), Psi = mu ||E||_F^2 + lam/2 tr(E)^2, E = (F^T F - I)/2.

        xe : (..., E, 4, 3) -> (..., E); differentiable, batched.
        """
        F = self.deformation_gradient(xe)
        psi = stvk_density(F, self._rest(self.mu, xe), self._rest(self.lam, xe))
        return self._rest(self.rest_volume, xe) * psi

    def first_piola(self, x: torch.Tensor) -> torch.Tensor:
        """First Piola-Kirchhoff stress P = F (2 mu E + lam tr(E) I).

        x : (..., n, 3) -> (..., E, 3, 3).
        """
        F = self.deformation_gradient(self.gather(x))
        eye = torch.eye(3, dtype=F.dtype, device=F.device)
        Eg = 0.5 * (F.transpose(-1, -2) @ F - eye)
        trE = Eg.diagonal(dim1=-2, dim2=-1).sum(-1)
        mu = self._rest(self.mu, F)[..., None, None]
        lam = self._rest(self.lam, F)[..., None, None]
        S = 2.0 * mu * Eg + lam * trE[..., None, None] * eye
        return F @ S

    def stress_norm(self, x: torch.Tensor) -> torch.Tensor:
        """||P||_F per element; x (..., n, 3) -> (..., E)."""
        return torch.linalg.matrix_norm(self.first_piola(x))

    # -- compiled derivatives ----------------------------------------------
    def kernel_spec(self) -> KernelSpec:
        """The compiled StVK kernels (``kernels.tets``): gradient W B^T vec(P), the exact Hessian
        W B^T (dP/dF) B, or the projected one with dP/dF clamped in its analytic eigensystem."""
        E = int(self.stencils.shape[0])
        args = (float64_array(self.grad_op), float64_array(self.rest_volume, E), float64_array(self.mu, E), float64_array(self.lam, E))
        return KernelSpec(tet_kernels.tet_energy, tet_kernels.tet_energy_gradient, tet_kernels.tet_run, args, 4)


__all__ = [
    "StVKTets",
    "lame",
    "lumped_masses",
    "stvk_density",
    "tet_volumes",
]
