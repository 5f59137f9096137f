"""Discrete shells: StVK membrane triangles and dihedral-angle hinges.

Physics checks: zero energy/force at rest (flat sheet and a curved piece of
cylinder), rigid-motion invariance, finite differences, the compiled
Hessians (``local_gradient_hessian``, ``physics.kernels.shells``) against the autograd oracle (raw and projected), batching, analytic
values (affine membrane strain, a single folded hinge, cylinder bending and
its continuum limit), masses and input validation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from latentsim.physics.base import autograd_gradient_hessian
from latentsim.physics.shells import (
    ShellHinge,
    ShellMembraneStVK,
    bending_stiffness,
    dihedral_angle,
    hinges_from_triangles,
    lumped_masses_shell,
    plane_stress_lame,
)


FLOAT64 = True  # tests/conftest.py: float64 default dtype for this module

Y, NU, H_THICK, RHO = 1.0e6, 0.3, 1.0e-3, 200.0
D = Y * H_THICK**3 / (12 * (1 - NU**2))


def grid(nx, ny, width=1.0, height=None):
    """(nx+1)(ny+1) vertices in the z = 0 plane, every cell cut along one diagonal."""
    height = width * ny / nx if height is None else height
    u, v = np.meshgrid(np.linspace(0, width, nx + 1), np.linspace(0, height, ny + 1))
    V = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    v00 = (j * (nx + 1) + i).ravel()
    v10, v01, v11 = v00 + 1, v00 + nx + 1, v00 + nx + 2
    T = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return torch.as_tensor(V), torch.as_tensor(T)


def equilateral(nx, ny, s):
    """Triangular lattice with edge length s (rows offset by s/2)."""
    V, T = [], []
    idx = {}
    for j in range(ny + 1):
        for i in range(nx + 1):
            idx[i, j] = len(V)
            V.append([i * s + (j % 2) * s / 2, j * s * math.sqrt(3) / 2, 0.0])
    for j in range(ny):
        for i in range(nx):
            if j % 2 == 0:
                T += [[idx[i, j], idx[i + 1, j], idx[i, j + 1]], [idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]]]
            else:
                T += [[idx[i, j], idx[i + 1, j + 1], idx[i, j + 1]], [idx[i, j], idx[i + 1, j], idx[i + 1, j + 1]]]
    return torch.tensor(V), torch.tensor(T)


def to_cylinder(V, R):
    """Isometric map of the z = 0 plane onto a cylinder of radius R, axis along y."""
    u = V[:, 0]
    return torch.stack([R * torch.sin(u / R), V[:, 1], R * (1 - torch.cos(u / R))], -1)


def random_rotation(gen):
    Q, R = torch.linalg.qr(torch.randn(3, 3, generator=gen))
    Q = Q * torch.sign(torch.diagonal(R))
    if torch.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def deformed(X, seed, scale):
    gen = torch.Generator().manual_seed(seed)
    return X + scale * torch.randn(X.shape, generator=gen)


@pytest.fixture(scope="module", params=["flat", "cylinder"])
def sheet(request):
    V, T = grid(4, 3, width=0.4)
    if request.param == "cylinder":
        V = to_cylinder(V, 0.3)
    hinges = hinges_from_triangles(T)
    return V, T, ShellMembraneStVK(V, T, Y, NU, H_THICK), ShellHinge(V, hinges, Y, NU, H_THICK)


# --------------------------------------------------------------------------
# topology, masses, parameters, validation
# --------------------------------------------------------------------------
def test_hinges_of_a_grid():
    nx, ny = 4, 3
    V, T = grid(nx, ny)
    hinges = hinges_from_triangles(T)
    assert hinges.dtype == torch.long
    # interior edges: all edges minus the boundary ones
    n_edges = nx * (ny + 1) + ny * (nx + 1) + nx * ny
    assert hinges.shape == (n_edges - 2 * (nx + ny), 4)
    tris = {tuple(t) for t in T.tolist()}

    def has_triangle(i, j, k):  # cyclic orientation as listed
        return (i, j, k) in tris or (j, k, i) in tris or (k, i, j) in tris

    for v0, v1, a, b in hinges.tolist():
        assert has_triangle(v0, v1, a)  # first triangle in its own orientation
        assert has_triangle(v1, v0, b)  # consistently oriented neighbour
    # flat rest shape: all rest angles zero
    assert ShellHinge(V, hinges, Y, NU, H_THICK).rest_angle.abs().max().item() < 1e-14


def test_non_manifold_edge_is_named():
    T = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(ValueError, match=r"edge \(0, 1\).*3 triangles"):
        hinges_from_triangles(T)
    assert hinges_from_triangles(torch.zeros((0, 3), dtype=torch.long)).shape == (0, 4)
    assert hinges_from_triangles(torch.tensor([[0, 1, 2]])).shape == (0, 4)  # boundary only


def test_degenerate_triangle_is_named():
    V = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0], [2.0, 0, 0], [1.0, 1, 0]])
    T = torch.tensor([[0, 1, 2], [1, 4, 2], [0, 1, 3]])  # triangle 2 is collinear
    with pytest.raises(ValueError, match="triangle 2"):
        ShellMembraneStVK(V, T, Y, NU, H_THICK)
    with pytest.raises(ValueError, match="hinge 0"):
        ShellHinge(V, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK)


def test_lumped_masses():
    V, T = grid(5, 4, width=0.5)
    V = to_cylinder(V, 0.4)
    m = lumped_masses_shell(V, T, RHO, H_THICK)
    x = V[T]
    areas = 0.5 * torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]).norm(dim=-1)
    assert m.sum().item() == pytest.approx(RHO * H_THICK * areas.sum().item(), rel=1e-13)
    # a corner vertex of the (v00, v10, v11) diagonal touches one triangle
    assert m[5].item() == pytest.approx(RHO * H_THICK * areas[4].item() / 3, rel=1e-12)
    # single triangle: each vertex a third
    m1 = lumped_masses_shell(torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [0.0, 3, 0]]), torch.tensor([[0, 1, 2]]), RHO, H_THICK)
    assert torch.allclose(m1, torch.full((3,), RHO * H_THICK * 3.0 / 3.0))


def test_material_constants():
    mu, lam = plane_stress_lame(Y, NU)
    assert mu == pytest.approx(Y / (2 * (1 + NU)))
    assert lam == pytest.approx(Y * NU / (1 - NU**2))
    assert bending_stiffness(Y, NU, H_THICK) == pytest.approx(D)
    with pytest.raises(ValueError):
        plane_stress_lame(Y, 0.6)


# --------------------------------------------------------------------------
# rest state and invariances (flat and curved rest shapes)
# --------------------------------------------------------------------------
def test_zero_energy_and_force_at_rest(sheet):
    V, _, membrane, hinge = sheet
    for term in (membrane, hinge):
        xe = term.gather(V)
        assert term.element_energy(V).abs().max().item() < 1e-20
        g, Hm = term.local_gradient_hessian(xe)
        g_ad, _ = autograd_gradient_hessian(term, xe, project=False)
        assert g.abs().max().item() < 1e-12 * Y * H_THICK
        assert g_ad.abs().max().item() < 1e-12 * Y * H_THICK
        assert torch.isfinite(Hm).all()


def test_rigid_motion_invariance(sheet):
    V, _, membrane, hinge = sheet
    gen = torch.Generator().manual_seed(4)
    x = deformed(V, 1, 0.02)
    xr = x @ random_rotation(gen).T + torch.randn(3, generator=gen)
    for term in (membrane, hinge):
        e0 = term.energy(x).item()
        assert e0 > 0
        assert term.energy(xr).item() == pytest.approx(e0, rel=1e-10)


# --------------------------------------------------------------------------
# derivatives
# --------------------------------------------------------------------------
def assemble_gradient(term, x, g_local):
    k = term.stencils.shape[1]
    g = torch.zeros_like(x)
    g.index_add_(0, term.stencils.reshape(-1), g_local.reshape(-1, k, 3).reshape(-1, 3))
    return g


@pytest.mark.parametrize("which", ["membrane", "hinge"])
def test_gradient_finite_differences(sheet, which):
    V, _, membrane, hinge = sheet
    term = membrane if which == "membrane" else hinge
    x = deformed(V, 7, 0.02)
    flat = x.reshape(-1)
    h = 1e-6
    g_fd = torch.zeros_like(flat)
    for i in range(flat.numel()):
        d = torch.zeros_like(flat)
        d[i] = h
        g_fd[i] = (term.energy((flat + d).reshape(x.shape)) - term.energy((flat - d).reshape(x.shape))) / (2 * h)
    g = assemble_gradient(term, x, term.local_gradient_hessian(term.gather(x))[0])
    assert (g.reshape(-1) - g_fd).abs().max().item() < 1e-6 * g_fd.abs().max().item()


@pytest.mark.parametrize("which", ["membrane", "hinge"])
@pytest.mark.parametrize("seed", [31, 32])
def test_hessian_matches_autograd_oracle(sheet, which, seed):
    V, _, membrane, hinge = sheet
    term = membrane if which == "membrane" else hinge
    # shrink the sheet so that some membrane triangles are compressed
    c = V.mean(0)
    x = deformed(c + 0.95 * (V - c), seed, 0.01 if seed == 31 else 0.03)
    xe = term.gather(x)
    raw = None
    for project in (False, True):
        g, Hm = term.local_gradient_hessian(xe, project=project)
        g0, H0 = autograd_gradient_hessian(term, xe, project=project)
        if raw is None:
            raw = H0
        scale = raw.abs().amax((1, 2), keepdim=True)  # per stencil, of the raw Hessian
        assert (g - g0).abs().max().item() < 1e-12 * g0.abs().max().item()
        assert ((Hm - H0).abs() / scale).max().item() < 1e-10
    w_raw = torch.linalg.eigvalsh(term.local_gradient_hessian(xe, project=False)[1])
    w_psd = torch.linalg.eigvalsh(term.local_gradient_hessian(xe, project=True)[1])
    top = w_raw.abs().max(-1).values
    assert (w_raw.min(-1).values < -1e-6 * top).any()  # indefinite before projection
    assert (w_psd.min(-1).values >= -1e-10 * top).all()


def test_hinge_smooth_at_flat_state():
    """atan2 form: finite, exact derivatives at theta = 0 (flat rest and flat state)."""
    V, T = grid(3, 3, width=0.3)
    hinge = ShellHinge(V, hinges_from_triangles(T), Y, NU, H_THICK)
    xe = hinge.gather(V).clone().requires_grad_(True)
    theta = dihedral_angle(xe)
    (gth,) = torch.autograd.grad(theta.sum(), xe)
    assert torch.isfinite(gth).all() and gth.abs().max().item() > 0
    g0, H0 = autograd_gradient_hessian(hinge, hinge.gather(V), project=False)
    g, Hm = hinge.local_gradient_hessian(hinge.gather(V), project=False)
    assert torch.isfinite(H0).all() and torch.isfinite(Hm).all()
    assert g0.abs().max().item() == 0.0 and g.abs().max().item() < 1e-14
    # at the flat state the Hessian is 2 k grad(theta) grad(theta)^T, rank one, PSD
    assert torch.allclose(Hm, H0, atol=1e-12 * H0.abs().max().item())
    assert torch.linalg.matrix_rank(H0[0]).item() == 1
    # flat state of a curved rest shape: finite, non-zero force
    Vc = to_cylinder(V, 0.2)
    hc = ShellHinge(Vc, hinges_from_triangles(T), Y, NU, H_THICK)
    gc, Hc = autograd_gradient_hessian(hc, hc.gather(V), project=False)
    assert torch.isfinite(gc).all() and torch.isfinite(Hc).all() and gc.abs().max().item() > 0


# --------------------------------------------------------------------------
# batching, dtype
# --------------------------------------------------------------------------
def test_batched_energy_equals_separate_calls(sheet):
    V, _, membrane, hinge = sheet
    xs = torch.stack([deformed(V, s, 0.02) for s in range(3)])
    for term in (membrane, hinge):
        separate = torch.stack([term.energy(x) for x in xs])
        assert torch.allclose(term.energy(xs), separate, rtol=1e-13, atol=0)
        assert torch.allclose(term.energy(xs[None]).reshape(3), separate, rtol=1e-13, atol=0)
    P = membrane.first_piola(xs)
    assert P.shape == (3, membrane.stencils.shape[0], 3, 2)
    assert torch.allclose(P[1], membrane.first_piola(xs[1]))


def test_float32_states(sheet):
    V, _, membrane, hinge = sheet
    x = deformed(V, 2, 0.02)
    for term in (membrane, hinge):
        e32 = term.energy(x.float())
        assert e32.dtype == torch.float32
        assert e32.item() == pytest.approx(term.energy(x).item(), rel=1e-3)


# --------------------------------------------------------------------------
# analytic values: membrane
# --------------------------------------------------------------------------
def stvk_density(F2):
    """Psi of a 2x2 in-plane deformation gradient, by hand."""
    mu, lam = Y / (2 * (1 + NU)), Y * NU / (1 - NU**2)
    E = 0.5 * (F2.T @ F2 - torch.eye(2))
    return mu * (E * E).sum() + 0.5 * lam * torch.trace(E) ** 2


def test_affine_in_plane_stretch():
    V, T = grid(4, 4, width=0.5)
    membrane = ShellMembraneStVK(V, T, Y, NU, H_THICK)
    area = 0.25
    A = torch.tensor([[1.1, 0.07], [-0.03, 0.92]])
    x = V.clone()
    x[:, :2] = V[:, :2] @ A.T
    assert membrane.energy(x).item() == pytest.approx(area * H_THICK * stvk_density(A).item(), rel=1e-12)
    # the same strain embedded in 3D: rotate the deformed sheet out of plane
    gen = torch.Generator().manual_seed(0)
    xr = x @ random_rotation(gen).T
    assert membrane.energy(xr).item() == pytest.approx(area * H_THICK * stvk_density(A).item(), rel=1e-12)


def test_uniaxial_stress():
    V, T = grid(2, 2, width=0.2)
    membrane = ShellMembraneStVK(V, T, Y, NU, H_THICK)
    s = 1.2
    x = V.clone()
    x[:, 0] *= s
    mu, lam = Y / (2 * (1 + NU)), Y * NU / (1 - NU**2)
    e11 = 0.5 * (s * s - 1)
    P_expected = torch.tensor([[s * (2 * mu + lam) * e11, 0.0], [0.0, lam * e11], [0.0, 0.0]])
    P = membrane.first_piola(x)
    # the rest frames of the triangles differ, but F = diag(s, 1) in world axes
    F = membrane.deformation_gradient(membrane.gather(x))
    Fw = membrane.deformation_gradient(membrane.gather(V))  # maps rest frame -> world (isometry)
    P_world = P @ Fw.transpose(-1, -2)  # (T, 3, 3) = P R^T, rotate the material axis to world
    assert torch.allclose(P_world[..., :2], P_expected.expand(P.shape[0], 3, 2), rtol=1e-12, atol=1e-6)
    assert torch.allclose(membrane.stress_norm(x), torch.linalg.matrix_norm(P_expected).expand(P.shape[0]))
    assert F.shape == (8, 3, 2)


def test_first_piola_is_energy_derivative():
    V, T = grid(2, 2, width=0.2)
    membrane = ShellMembraneStVK(V, T, Y, NU, H_THICK)
    x = deformed(V, 3, 0.02)
    F = membrane.deformation_gradient(membrane.gather(x)).clone().requires_grad_(True)
    Eg = 0.5 * (F.transpose(-1, -2) @ F - torch.eye(2))
    psi = membrane.mu * (Eg * Eg).sum((-1, -2)) + 0.5 * membrane.lam * (Eg[..., 0, 0] + Eg[..., 1, 1]) ** 2
    (dpsi,) = torch.autograd.grad(psi.sum(), F)
    assert torch.allclose(membrane.first_piola(x), dpsi, rtol=1e-12, atol=1e-9)


# --------------------------------------------------------------------------
# analytic values: hinges
# --------------------------------------------------------------------------
def single_hinge(phi, L=0.3, h1=0.2, h2=0.1, p=0.1, q=0.25):
    """Edge along x; wing a at +y, wing b rotated about the edge by phi (theta = phi)."""
    x = torch.tensor(
        [[0.0, 0, 0], [L, 0, 0], [p, h1, 0], [q, -h2 * math.cos(phi), -h2 * math.sin(phi)]]
    )
    w = 3 * L**2 / (0.5 * L * h1 + 0.5 * L * h2)
    return x, w


def test_folded_hinge_energy():
    X, w = single_hinge(0.0)
    hinge = ShellHinge(X, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK)
    assert hinge.weight.item() == pytest.approx(w, rel=1e-13)
    for phi in (-2.0, -0.3, 0.4, 1.5, 3.0):
        x, _ = single_hinge(phi)
        assert hinge.angle(x[None]).item() == pytest.approx(phi, rel=1e-12)
        assert hinge.energy(x).item() == pytest.approx(D * w * phi**2, rel=1e-12)


def test_curved_rest_hinge():
    X, w = single_hinge(0.8)
    hinge = ShellHinge(X, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK)
    assert hinge.rest_angle.item() == pytest.approx(0.8, rel=1e-12)
    assert hinge.energy(X).item() < 1e-25
    for phi in (0.0, 0.5, 1.7):
        x, _ = single_hinge(phi)
        assert hinge.energy(x).item() == pytest.approx(D * w * (phi - 0.8) ** 2, rel=1e-12)
    # near-complete fold: theta - thetabar wraps around +-pi continuously
    Xf, _ = single_hinge(math.pi - 0.05)
    hf = ShellHinge(Xf, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK)
    x, _ = single_hinge(-math.pi + 0.05)  # 0.1 rad further, across the branch cut
    assert hf.energy(x).item() == pytest.approx(D * w * 0.1**2, rel=1e-10)


def test_stiffness_scale():
    X, w = single_hinge(0.0)
    x, _ = single_hinge(0.5)
    a = ShellHinge(X, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK).energy(x)
    b = ShellHinge(X, torch.tensor([[0, 1, 2, 3]]), Y, NU, H_THICK, stiffness_scale=1 / 6).energy(x)
    assert b.item() == pytest.approx(a.item() / 6, rel=1e-14)


def test_cylinder_bending_grid():
    """Bending a grid sheet (one diagonal per cell) around the y axis.

    Each strip of cells stays planar, so only the edges parallel to the axis
    bend, each by exactly s / R: E = 3 D (nx - 1) ny s^2 / R^2.  The plate
    energy is D/2 (1/R^2) W H = D/2 nx ny s^2 / R^2, so the ratio is
    6 (nx - 1) / nx -> 6: ``stiffness_scale = 1/6`` recovers the plate.
    """
    R = 0.4
    errors = []
    for n in (10, 20, 40):
        V, T = grid(n, n, width=1.0)
        s = 1.0 / n
        hinge = ShellHinge(V, hinges_from_triangles(T), Y, NU, H_THICK)
        e = hinge.energy(to_cylinder(V, R)).item()
        assert e == pytest.approx(3 * D * (n - 1) * n * s * s / R**2, rel=1e-10)
        plate = D / 2 / R**2 * 1.0
        calibrated = ShellHinge(V, hinges_from_triangles(T), Y, NU, H_THICK, stiffness_scale=1 / 6)
        errors.append(abs(calibrated.energy(to_cylinder(V, R)).item() / plate - 1))
    assert errors[-1] < 0.03
    assert errors[0] > errors[1] > errors[2]


def test_cylinder_bending_equilateral_and_diagonal():
    """The factor 6 also holds for an equilateral mesh and for a grid bent along its diagonal."""
    R = 0.5
    V, T = equilateral(48, 56, 1 / 48)
    ratios = []
    for angle in (0.0, math.pi / 4):
        c, s = math.cos(angle), math.sin(angle)
        Vr = V.clone()
        Vr[:, 0], Vr[:, 1] = c * V[:, 0] - s * V[:, 1], s * V[:, 0] + c * V[:, 1]
        hinge = ShellHinge(Vr, hinges_from_triangles(T), Y, NU, H_THICK)
        area = ShellMembraneStVK(Vr, T, Y, NU, H_THICK).rest_area.sum().item()
        ratios.append(hinge.energy(to_cylinder(Vr, R)).item() / (D / 2 / R**2 * area))
    Vg, Tg = grid(48, 48)
    c = math.cos(math.pi / 4)
    Vd = Vg.clone()
    Vd[:, 0], Vd[:, 1] = c * (Vg[:, 0] - Vg[:, 1]), c * (Vg[:, 0] + Vg[:, 1])
    hinge = ShellHinge(Vd, hinges_from_triangles(Tg), Y, NU, H_THICK)
    ratios.append(hinge.energy(to_cylinder(Vd, R)).item() / (D / 2 / R**2))
    for r in ratios:
        assert r == pytest.approx(6.0, rel=0.04)
