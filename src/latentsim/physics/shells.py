r"""Discrete shells: StVK membrane triangles and dihedral-angle bending hinges.

Membrane (constant-strain triangles, plane stress).  A triangle with rest
vertices X_0, X_1, X_2 gets a 2D orthonormal rest frame (u along X_1 - X_0, v
in the plane), the 2x2 rest edge matrix Dm = [X1-X0, X2-X0] in that frame, and

    F   = Ds Dm^{-1}  (3x2),     Ds = [x1-x0, x2-x0],
    E   = (F^T F - I) / 2        (2x2 Green strain),
    Psi = mu ||E||_F^2 + lam/2 tr(E)^2,
    W   = Abar h Psi             (energy of the triangle),
    P   = dPsi/dF = F S,  S = 2 mu E + lam tr(E) I,

with the plane-stress Lame constants mu = Y / (2 (1 + nu)),
lam = Y nu / (1 - nu^2) (the 3D StVK energy with the transverse strain
eliminated under sigma_33 = 0, linearised).

Bending (Grinspun, Hirani, Desbrun & Schroeder 2003, "Discrete shells",
SCA).  A hinge (v0, v1, a, b) is an interior edge e = x_{v1} - x_{v0} with the
opposite vertices a, b of its two triangles:

    W_B = kb * 3 |ebar|^2 / (Abar_1 + Abar_2) * (theta - thetabar)^2,
    kb  = D = Y h^3 / (12 (1 - nu^2)),

|ebar| / hbar_e = 3 |ebar|^2 / (Abar_1 + Abar_2) being Grinspun's weight
(hbar_e a third of the mean height of the two triangles).  theta is the
signed dihedral angle (0 for a flat hinge), the right-handed rotation angle
about e/|e| taking n_1 = e x (x_a - x_0) to n_2 = (x_b - x_0) x e,

    theta = atan2((n_1 x n_2) . e/|e|, n_1 . n_2),

which is smooth through the flat state (no square root of |n_1 x n_2|); the
difference theta - thetabar is wrapped to (-pi, pi].  Rest shapes may be
curved (thetabar != 0).

Continuum limit (calibration).  Bent to a cylinder of radius R (curvature
kappa = 1/R, no Gaussian curvature), a plate has the energy
D/2 kappa^2 * area.  On regular meshes the hinge energy above converges
instead to c D/2 kappa^2 * area with the constant c = 6:

* square grid, every cell cut along the same diagonal (``mesh.cloth_grid``),
  axis along a grid line: each strip of cells stays planar, the edges along
  the axis bend by exactly theta = s/R and carry the weight 3 s^2/s^2 = 3,
  so each cell holds 3 D s^2/R^2 = 6 x D/2 kappa^2 s^2 (and (n-1)/n of that
  on an n-cell-wide sheet, the boundary lines do not bend);
* equilateral triangles (edge s): the piecewise-linear interpolant of the
  cylinder gives theta = kappa s/sqrt(3) on both slanted edge families and
  kappa s/(2 sqrt(3)) on the edges along the curvature direction, so
  sum theta^2 = 3/4 kappa^2 s^2 per rhombus of area sqrt(3)/2 s^2 and weight
  2 sqrt(3): again 6 x D/2 kappa^2 (the tests measure 6 for 0 and 45 degree
  axes, and for the grid bent along its diagonal).

``tests/physics/test_energy_shells.py`` checks these values.  The default keeps the
energy as specified (kb = D, i.e. 6x the plate's bending stiffness on these
meshes); ``ShellHinge(..., stiffness_scale=1/6)`` calibrates it to the plate,
within a few % on fine meshes.

Newton derivatives.  Both terms have compiled per-stencil gradients and
exact Hessians (``kernels.shells``; formulas in the ``kernel_spec``
docstrings), which the tests compare with the ``torch.func`` oracle of
``base``.  The eigenvalue clamp is done on the (3k-3)-dimensional
translation-free block of each stencil (``kernels.core.project_psd``; exact,
as both energies are translation invariant) with a cyclic Jacobi solver.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from latentsim.physics.base import EnergyTerm, subset_weights
from latentsim.physics.kernels import shells as shell_kernels
from latentsim.physics.kernels.core import translation_free_basis
from latentsim.physics.kernels.dispatch import KernelSpec, float64_array

__all__ = [
    "plane_stress_lame",
    "bending_stiffness",
    "hinges_from_triangles",
    "lumped_masses_shell",
    "triangle_rest_frames",
    "triangle_kernel_spec",
    "dihedral_angle",
    "ShellMembraneStVK",
    "ShellHinge",
]


# --------------------------------------------------------------------------
# material, topology, masses
# --------------------------------------------------------------------------
def _check_poisson(poisson_ratio):
    nu = torch.as_tensor(poisson_ratio, dtype=torch.float64)
    if bool(torch.any((nu <= -1.0) | (nu > 0.5))):
        raise ValueError(f"Poisson ratio must lie in (-1, 0.5], got {poisson_ratio}")


def plane_stress_lame(youngs_modulus, poisson_ratio):
    """Plane-stress Lame constants mu = Y / (2 (1 + nu)), lam = Y nu / (1 - nu^2)."""
    _check_poisson(poisson_ratio)
    mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / (1.0 - poisson_ratio**2)
    return mu, lam


def bending_stiffness(youngs_modulus, poisson_ratio, thickness):
    """Flexural rigidity D = Y h^3 / (12 (1 - nu^2)) [N m]."""
    _check_poisson(poisson_ratio)
    return youngs_modulus * thickness**3 / (12.0 * (1.0 - poisson_ratio**2))


def _as_long(cells, k: int, name: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(cells), dtype=torch.long)
    if t.ndim != 2 or t.shape[1] != k:
        raise ValueError(f"{name} must have shape (E, {k}), got {tuple(t.shape)}")
    return t


def _as_positions(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x, dtype=torch.float64)


def hinges_from_triangles(triangles) -> torch.Tensor:
    """Bending hinges of a triangle mesh.

    Every edge shared by exactly two triangles gives a hinge (v0, v1, a, b):
    v0 -> v1 is the edge in the cyclic order of the first triangle (v0, v1, a),
    b the vertex opposite the edge in the second.  Boundary edges (one
    triangle) give none.

    Parameters
    ----------
    triangles : (T, 3) int.

    Returns
    -------
    (H, 4) long, ordered by (min, max) edge vertex.

    Raises
    ------
    ValueError
        naming the edge and its triangles if an edge has more than two
        triangles (non-manifold).
    """
    tri = _as_long(triangles, 3, "triangles").numpy()
    T = tri.shape[0]
    if T == 0:
        return torch.zeros((0, 4), dtype=torch.long)
    # directed edges (t[k], t[k+1]) with opposite vertex t[k+2]
    v0 = tri.reshape(-1)
    v1 = np.roll(tri, -1, axis=1).reshape(-1)
    opp = np.roll(tri, -2, axis=1).reshape(-1)
    owner = np.repeat(np.arange(T), 3)
    lo, hi = np.minimum(v0, v1), np.maximum(v0, v1)
    key = lo.astype(np.int64) * (int(tri.max()) + 1) + hi
    order = np.argsort(key, kind="stable")
    _, start, count = np.unique(key[order], return_index=True, return_counts=True)
    bad = np.nonzero(count > 2)[0]
    if bad.size:
        idx = order[start[bad[0]] : start[bad[0]] + count[bad[0]]]
        raise ValueError(
            f"non-manifold edge ({lo[idx[0]]}, {hi[idx[0]]}) is shared by {count[bad[0]]} "
            f"triangles {sorted(owner[idx].tolist())}"
        )
    pair = start[count == 2]
    first, second = order[pair], order[pair + 1]
    hinges = np.stack([v0[first], v1[first], opp[first], opp[second]], axis=1)
    return torch.as_tensor(hinges, dtype=torch.long)


def lumped_masses_shell(rest_positions, triangles, density, thickness) -> torch.Tensor:
    """Lumped vertex masses: density h Abar / 3 from every incident triangle.

    Parameters
    ----------
    rest_positions : (n, 3); triangles : (T, 3) int;
    density : float or (T,) [kg/m^3]; thickness : float or (T,) [m].

    Returns
    -------
    (n,) float64, summing to sum_t density h Abar_t.
    """
    X = _as_positions(rest_positions)
    tri = _as_long(triangles, 3, "triangles")
    x = X[tri]
    area = 0.5 * torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]).norm(dim=-1)
    m_t = torch.as_tensor(density, dtype=torch.float64) * torch.as_tensor(thickness, dtype=torch.float64) * area
    m = torch.zeros(X.shape[0], dtype=torch.float64)
    for k in range(3):
        m.index_add_(0, tri[:, k], m_t / 3.0)
    return m


def triangle_rest_frames(rest_positions, triangles, eps: float = 1e-12):
    """Rest areas and 2D rest edge matrices of triangles.

    Parameters
    ----------
    rest_positions : (n, 3); triangles : (T, 3) int.
    eps : a triangle is degenerate if 2 Abar <= eps * (longest edge)^2.

    Returns
    -------
    area : (T,) Abar.
    Dm : (T, 2, 2) = [[|X1-X0|, (X2-X0).u], [0, (X2-X0).v]] (columns are the
        rest edges in the orthonormal frame u = (X1-X0)/|X1-X0|, v).

    Raises
    ------
    ValueError naming the first degenerate (zero-area) triangle.
    """
    X = _as_positions(rest_positions)
    tri = _as_long(triangles, 3, "triangles")
    x = X[tri]
    e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    nrm = torch.linalg.cross(e1, e2)
    two_area = nrm.norm(dim=-1)
    longest = torch.stack([e1.norm(dim=-1), e2.norm(dim=-1), (e2 - e1).norm(dim=-1)], -1).amax(-1)
    bad = torch.nonzero(~(two_area > eps * longest**2)).flatten()
    if bad.numel():
        i = int(bad[0])
        raise ValueError(
            f"triangle {i} {tri[i].tolist()} is degenerate (rest area {0.5 * float(two_area[i]):.3e}); "
            f"{bad.numel()} degenerate triangle(s) in total"
        )
    l1 = e1.norm(dim=-1)
    u = e1 / l1[:, None]
    v = torch.linalg.cross(nrm, e1)
    v = v / v.norm(dim=-1, keepdim=True)
    Dm = torch.zeros(tri.shape[0], 2, 2, dtype=X.dtype)
    Dm[:, 0, 0] = l1
    Dm[:, 0, 1] = (e2 * u).sum(-1)
    Dm[:, 1, 1] = (e2 * v).sum(-1)
    return 0.5 * two_area, Dm


def dihedral_angle(xe: torch.Tensor) -> torch.Tensor:
    """Signed dihedral angle of hinges, xe (..., E, 4, 3) -> (..., E).

    theta = atan2((n1 x n2) . e/|e|, n1 . n2) with e = x1 - x0,
    n1 = e x (xa - x0), n2 = (xb - x0) x e: zero when flat, positive for a
    right-handed rotation about e taking n1 to n2; smooth (also at theta = 0)
    away from theta = +-pi and degenerate triangles.
    """
    x0, x1, xa, xb = xe.unbind(-2)
    e = x1 - x0
    n1 = torch.linalg.cross(e, xa - x0)
    n2 = torch.linalg.cross(xb - x0, e)
    s = (torch.linalg.cross(n1, n2) * e).sum(-1) / e.norm(dim=-1)
    c = (n1 * n2).sum(-1)
    return torch.atan2(s, c)


def _per_stencil(value, count: int, name: str) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.ndim > 1 or (t.ndim == 1 and t.shape[0] not in (1, count)):
        raise ValueError(f"{name} must be a scalar or have shape ({count},), got {tuple(t.shape)}")
    return t.expand(count).clone()


# --------------------------------------------------------------------------
# membrane
# --------------------------------------------------------------------------
class ShellMembraneStVK(EnergyTerm):
    """StVK membrane of constant-strain triangles, W = Abar h Psi(E).

    Parameters
    ----------
    rest_positions : (n, 3) rest vertex positions.
    triangles : (T, 3) int vertex indices.
    youngs_modulus : float or (T,) Y [Pa].
    poisson_ratio : float or (T,) nu in (-1, 0.5].
    thickness : float or (T,) h [m].

    Attributes
    ----------
    stencils : (T, 3) long.
    rest_area : (T,) Abar.
    Dm_inv : (T, 2, 2) inverse rest edge matrices (2D rest frame).
    mu, lam : (T,) plane-stress Lame constants.
    thickness : (T,).

    Raises
    ------
    ValueError naming the triangle if a rest triangle has zero area.
    """

    name = "shell_membrane_stvk"

    def __init__(self, rest_positions, triangles, youngs_modulus, poisson_ratio, thickness):
        X = _as_positions(rest_positions)
        self.stencils = _as_long(triangles, 3, "triangles")
        self.rest_positions = X
        T = self.stencils.shape[0]
        self.rest_area, Dm = triangle_rest_frames(X, self.stencils)
        self.Dm_inv = torch.linalg.inv(Dm)
        mu, lam = plane_stress_lame(
            torch.as_tensor(youngs_modulus, dtype=torch.float64), torch.as_tensor(poisson_ratio, dtype=torch.float64)
        )
        self.mu = _per_stencil(mu, T, "youngs_modulus/poisson_ratio")
        self.lam = _per_stencil(lam, T, "youngs_modulus/poisson_ratio")
        self.thickness = _per_stencil(thickness, T, "thickness")

    def weighted_subset(self, index, weights) -> "ShellMembraneStVK":
        """sum_{t in index} w_t E_t: thickness w_t h_t in the energy Abar h Psi (a cubature, see
        ``base.subset_weights``; only the energy's factor, masses come from the scene)."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        mu, lam = self.mu[idx], self.lam[idx]
        nu = lam / (2.0 * mu + lam)  # plane stress: lam / (2 mu) = nu / (1 - nu)
        return ShellMembraneStVK(self.rest_positions, self.stencils[idx], 2.0 * mu * (1.0 + nu), nu, self.thickness[idx] * w)

    def deformation_gradient(self, xe: torch.Tensor) -> torch.Tensor:
        """F = Ds Dm^{-1}; xe (..., T, 3, 3) -> (..., T, 3, 2)."""
        Ds = torch.stack([xe[..., 1, :] - xe[..., 0, :], xe[..., 2, :] - xe[..., 0, :]], dim=-1)
        return Ds @ self.Dm_inv.to(xe)

    def _green_strain(self, F: torch.Tensor) -> torch.Tensor:
        eye = torch.eye(2, dtype=F.dtype, device=F.device)
        return 0.5 * (F.transpose(-1, -2) @ F - eye)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """Abar h (mu ||E||^2 + lam/2 tr(E)^2); xe (..., T, 3, 3) -> (..., T)."""
        Eg = self._green_strain(self.deformation_gradient(xe))
        trE = Eg[..., 0, 0] + Eg[..., 1, 1]
        psi = self.mu.to(xe) * (Eg * Eg).sum((-1, -2)) + 0.5 * self.lam.to(xe) * trE * trE
        return (self.rest_area * self.thickness).to(xe) * psi

    def first_piola(self, x: torch.Tensor) -> torch.Tensor:
        """P = F (2 mu E + lam tr(E) I) [Pa]; x (..., n, 3) -> (..., T, 3, 2)."""
        F = self.deformation_gradient(self.gather(x))
        Eg = self._green_strain(F)
        trE = Eg[..., 0, 0] + Eg[..., 1, 1]
        eye = torch.eye(2, dtype=F.dtype, device=F.device)
        S = 2.0 * self.mu.to(F)[..., None, None] * Eg + (self.lam.to(F) * trE)[..., None, None] * eye
        return F @ S

    def stress_norm(self, x: torch.Tensor) -> torch.Tensor:
        """||P||_F per triangle [Pa]; x (..., n, 3) -> (..., T)."""
        return torch.linalg.matrix_norm(self.first_piola(x))

    def kernel_spec(self) -> KernelSpec:
        """The compiled membrane kernels (``kernels.shells``).

        With G (3, 2) = [[-1, -1], [1, 0], [0, 1]] Dm^{-1} the gradients of the
        barycentric coordinates in the rest frame (F = sum_a x_a G_a^T),
        Psi_ia = (F G^T)_ia and K = Abar h:

            g_a = K P G_a,
            H_(a i)(b j) = K [ (G S G^T)_ab delta_ij + mu Psi_ib Psi_ja
                               + mu (F F^T)_ij (G G^T)_ab + lam Psi_ia Psi_jb ].

        The projection clamps the eigenvalues on the 6x6 translation-free
        block (exact eigenvalue clamp of the 9x9 Hessian).
        """
        return triangle_kernel_spec(self, shell_kernels.membrane_energy, shell_kernels.membrane_energy_gradient, shell_kernels.membrane_run)


def triangle_kernel_spec(term, energy, energy_gradient, run) -> KernelSpec:
    """The ``KernelSpec`` of a constant-strain triangle term (``ShellMembraneStVK``,
    ``stvk_nm.ShellMembraneNM``: ``Dm_inv``, ``rest_area``, ``thickness``, ``mu``, ``lam``) with
    the kernels ``energy``, ``energy_gradient``, ``run``: their rest data G (T, 3, 2) =
    [[-1, -1], [1, 0], [0, 1]] Dm^{-1} (the barycentric gradients, F = sum_a x_a G_a^T),
    K = Abar h, mu, lam, and the projection's translation-free basis."""
    sel = torch.tensor([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    args = (float64_array(sel @ term.Dm_inv), float64_array(term.rest_area * term.thickness), float64_array(term.mu), float64_array(term.lam))
    return KernelSpec(energy, energy_gradient, run, args, 3, translation_free_basis(3))


# --------------------------------------------------------------------------
# bending
# --------------------------------------------------------------------------
class ShellHinge(EnergyTerm):
    """Discrete-shells hinge bending, W = kb 3|ebar|^2/(Abar_1+Abar_2) (theta - thetabar)^2.

    Parameters
    ----------
    rest_positions : (n, 3) rest vertex positions (flat or curved).
    hinges : (H, 4) int (v0, v1, a, b), e.g. from ``hinges_from_triangles``.
    youngs_modulus, poisson_ratio, thickness : floats or (H,) tensors;
        kb = Y h^3 / (12 (1 - nu^2)).
    stiffness_scale : float, multiplies kb (1 / c calibrates a mesh whose
        continuum factor is c, see the module docstring).

    Attributes
    ----------
    stencils : (H, 4) long.
    rest_angle : (H,) thetabar.
    weight : (H,) 3 |ebar|^2 / (Abar_1 + Abar_2).
    kb : (H,) stiffness_scale * D.

    Raises
    ------
    ValueError naming the hinge if one of its rest triangles is degenerate.
    """

    name = "shell_hinge"

    def __init__(self, rest_positions, hinges, youngs_modulus, poisson_ratio, thickness, stiffness_scale: float = 1.0):
        X = _as_positions(rest_positions)
        self.stencils = _as_long(hinges, 4, "hinges")
        self.rest_positions = X
        Hn = self.stencils.shape[0]
        x = X[self.stencils]
        e = x[:, 1] - x[:, 0]
        A1 = 0.5 * torch.linalg.cross(e, x[:, 2] - x[:, 0]).norm(dim=-1)
        A2 = 0.5 * torch.linalg.cross(x[:, 3] - x[:, 0], e).norm(dim=-1)
        le2 = (e * e).sum(-1)
        bad = torch.nonzero(~((A1 > 0.5e-12 * le2) & (A2 > 0.5e-12 * le2))).flatten()
        if bad.numel():
            i = int(bad[0])
            raise ValueError(f"hinge {i} {self.stencils[i].tolist()} has a degenerate rest triangle")
        self.weight = 3.0 * le2 / (A1 + A2)
        self.rest_angle = dihedral_angle(x)
        kb = bending_stiffness(
            torch.as_tensor(youngs_modulus, dtype=torch.float64),
            torch.as_tensor(poisson_ratio, dtype=torch.float64),
            torch.as_tensor(thickness, dtype=torch.float64),
        )
        self.kb = float(stiffness_scale) * _per_stencil(kb, Hn, "youngs_modulus/poisson_ratio/thickness")

    def weighted_subset(self, index, weights) -> "ShellHinge":
        """sum_{h in index} w_h E_h: stiffness w_h kb_h (a cubature, see ``base.subset_weights``).

        Built with Y = 12 w kb, nu = 0, h = 1, for which D = Y h^3 / (12 (1 - nu^2)) = w kb."""
        idx, w = subset_weights(index, weights, int(self.stencils.shape[0]))
        return ShellHinge(self.rest_positions, self.stencils[idx], 12.0 * self.kb[idx] * w, 0.0, 1.0)

    def angle(self, xe: torch.Tensor) -> torch.Tensor:
        """Dihedral angles theta, xe (..., H, 4, 3) -> (..., H)."""
        return dihedral_angle(xe)

    def local_energy(self, xe: torch.Tensor) -> torch.Tensor:
        """kb w (theta - thetabar)^2 with the difference wrapped to (-pi, pi]; (..., H, 4, 3) -> (..., H)."""
        d = dihedral_angle(xe) - self.rest_angle.to(xe)
        d = d - 2.0 * math.pi * torch.round(d / (2.0 * math.pi))
        return (self.kb * self.weight).to(xe) * d * d

    def kernel_spec(self) -> KernelSpec:
        """The compiled hinge kernels (``kernels.shells``).

        With e = x1 - x0, L = |e|, d_a = x_a - x0, d_b = x_b - x0,
        N1 = e x d_a, N2 = d_b x e, t_a = d_a.e / L^2, t_b = d_b.e / L^2:

            grad_a theta = g_a = -L N1 / |N1|^2,   grad_b theta = g_b = -L N2 / |N2|^2,
            grad_1 theta = -t_a g_a - t_b g_b,    grad_0 theta = -(grad_1 + g_a + g_b),

        and the Hessian of theta is the Jacobian of these expressions, using
        d(N / |N|^2) = (I - 2 n n^T) / |N|^2 dN.  The energy k (theta -
        thetabar)^2, k = kb w, has g = 2 k d grad theta and
        H = 2 k (grad theta grad theta^T + d Hess theta), d = theta - thetabar
        (wrapped).  The projection clamps the eigenvalues on the 9x9
        translation-free block (exact eigenvalue clamp).
        """
        args = (float64_array(self.kb * self.weight), float64_array(self.rest_angle))
        return KernelSpec(shell_kernels.hinge_energy, shell_kernels.hinge_energy_gradient, shell_kernels.hinge_run,
                          args, 4, translation_free_basis(4))
