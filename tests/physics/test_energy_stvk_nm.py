"""The Neural Modes authors' energies (``material.model: stvk_nm``, ``physics.stvk_nm``).

The project's terms, built by ``scene.build_elastic`` on the square sheet of
Wang et al. and on a small tet beam, against a direct evaluation of the
authors' formulas written below with plain array arithmetic:

    membrane  h A0 (mu tr(E^2) + lam/2 (J - 1)^2), 3D Lame constants, J the area ratio;
    hinge     3 kB |e0|^2 / (A1 + A2) (theta - theta0)^2, kB = D/2 or given;
    tets      V0 (mu ||E||_F^2 + lam (J - 1)^2), J = det F,

on states that include rigid motion, uniform stretch and bending (energies
and gradients to 1e-10 relative); zero energy and force at rest, rigid
invariance, finite differences, the compiled Hessians (exact and projected)
against autograd, compiled energies against the PyTorch oracle, cubature
subsets, and the sheet's linear modes with an identity mass (as the authors
compute them) against the eigenvalues of the same discrete Hessian.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from latentsim.mesh import read_mesh
from latentsim.mesh.generators import beam_tets
from latentsim.physics.base import autograd_gradient_hessian, project_psd_translation_free
from latentsim.physics.kernels import term_kernel
from latentsim.physics.stvk_nm import ShellMembraneNM, TetsNM
from latentsim.scene import build_elastic
from latentsim.solve.modes import lowest_modes, stiffness_matrix

REPO = Path(__file__).resolve().parents[2]
MESH_DIR = Path(os.environ.get("LATENTSIM_MESH_DIR", REPO / ".." / "shared" / "meshes")).resolve()
_MESHES_MISSING = not (MESH_DIR / "square.obj").is_file()
if _MESHES_MISSING and os.environ.get("CI"):
    raise RuntimeError(f"CI: the shared meshes are not at {MESH_DIR} (set LATENTSIM_MESH_DIR)")
needs_meshes = pytest.mark.skipif(_MESHES_MISSING, reason=f"shared meshes not found at {MESH_DIR}")

# the paper's sheet: E = 4e8 Pa, nu = 0.2, h = 5 mm, rho = 500
Y, NU, H, RHO = 4.0e8, 0.2, 0.005, 500.0
MU = Y / (2 * (1 + NU))
LAM = Y * NU / ((1 + NU) * (1 - 2 * NU))  # 3D
KB = Y * H**3 / (12 * (1 - NU**2)) / 2  # D/2
Y_TET, NU_TET = 1.0e6, 0.45
RTOL = 1e-10


# ---------------------------------------------------------------------------
# the formulas, written plainly (xp: numpy, or torch for their autograd gradient)
# ---------------------------------------------------------------------------
def _cross(a, b, xp):
    return xp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)  # fmt: skip


def _dot(a, b):
    return (a * b).sum(-1)


def _norm(a, xp):
    return xp.sqrt(_dot(a, a))


def plain_hinges(tris):
    """(s0, s1, o1, o2) of every interior edge: s0 -> s1 as it runs in its first triangle, o1 and o2
    the vertices opposite it in that triangle and in the other (where it runs s1 -> s0)."""
    first, rows = {}, []
    for a, b, c in np.asarray(tris):
        for v0, v1, opp in ((a, b, c), (b, c, a), (c, a, b)):
            if (v1, v0) in first:
                rows.append((v1, v0, first.pop((v1, v0)), opp))
            else:
                first[(v0, v1)] = opp
    return np.asarray(rows, dtype=np.int64).T


def sheet_energy_plain(X, tris, x, xp=np, kb=KB):
    """Membrane + hinges of the authors on triangles tris (T, 3) at x (n, 3), rest X (n, 3)."""
    X = np.asarray(X)
    E1, E2 = X[tris[:, 1]] - X[tris[:, 0]], X[tris[:, 2]] - X[tris[:, 0]]
    A0 = 0.5 * np.linalg.norm(np.cross(E1, E2), axis=1)
    Gm = np.stack([np.stack([_dot(E1, E1), _dot(E1, E2)], -1), np.stack([_dot(E2, E1), _dot(E2, E2)], -1)], -2)
    Ginv = np.linalg.inv(Gm)
    e1, e2 = x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]]
    g = xp.stack([xp.stack([_dot(e1, e1), _dot(e1, e2)], -1), xp.stack([_dot(e2, e1), _dot(e2, e2)], -1)], -2)
    # E in the rest frame is similar to (Gm^{-1} g - I)/2, so tr(E^2) = tr(((Gm^{-1} g - I)/2)^2)
    Ginv_t = Ginv if xp is np else torch.as_tensor(Ginv)
    M = 0.5 * (Ginv_t @ g - (np.eye(2) if xp is np else torch.eye(2, dtype=torch.float64)))
    trE2 = M[:, 0, 0] ** 2 + M[:, 1, 1] ** 2 + 2.0 * M[:, 0, 1] * M[:, 1, 0]  # tr(M^2)
    J = _norm(_cross(e1, e2, xp), xp) / (2.0 * A0 if xp is np else torch.as_tensor(2.0 * A0))
    membrane = (H * (A0 if xp is np else torch.as_tensor(A0)) * (MU * trE2 + 0.5 * LAM * (J - 1.0) ** 2)).sum()
    s0, s1, o1, o2 = plain_hinges(tris)
    n1 = _cross(x[s1] - x[s0], x[o1] - x[s0], xp)  # normal of the triangle where the edge runs s0 -> s1
    n2 = _cross(x[s0] - x[s1], x[o2] - x[s1], xp)  # normal of the other (consistent orientation)
    e = x[s1] - x[s0]
    atan2 = np.arctan2 if xp is np else torch.atan2
    theta = atan2(_dot(_cross(n1, n2, xp), e) / _norm(e, xp), _dot(n1, n2))  # theta0 = 0: flat sheet
    e0 = X[s1] - X[s0]
    A1 = 0.5 * np.linalg.norm(np.cross(e0, X[o1] - X[s0]), axis=1)
    A2 = 0.5 * np.linalg.norm(np.cross(X[o2] - X[s0], e0), axis=1)
    w = 3.0 * kb * _dot(e0, e0) / (A1 + A2)
    bending = ((w if xp is np else torch.as_tensor(w)) * theta**2).sum()
    return membrane + bending


def tet_energy_plain(X, tets, x, xp=np):
    """sum V0 (mu ||E||_F^2 + lam (det F - 1)^2), 3D Lame constants of (Y_TET, NU_TET)."""
    mu, lam = Y_TET / (2 * (1 + NU_TET)), Y_TET * NU_TET / ((1 + NU_TET) * (1 - 2 * NU_TET))
    Dm = np.stack([X[tets[:, k]] - X[tets[:, 0]] for k in (1, 2, 3)], -1)
    V0 = np.linalg.det(Dm) / 6.0
    Dinv = np.linalg.inv(Dm)
    Ds = xp.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], -1)
    F = Ds @ (Dinv if xp is np else torch.as_tensor(Dinv))
    C = F.transpose(0, 2, 1) @ F if xp is np else F.transpose(-1, -2) @ F
    E = 0.5 * (C - (np.eye(3) if xp is np else torch.eye(3, dtype=torch.float64)))
    f0, f1, f2 = F[..., 0], F[..., 1], F[..., 2]
    J = _dot(f0, _cross(f1, f2, xp))
    psi = mu * (E * E).sum((-1, -2)) + lam * (J - 1.0) ** 2
    return ((V0 if xp is np else torch.as_tensor(V0)) * psi).sum()


def plain_gradient(fn, X, cells, x):
    """Autograd gradient of the plain formula fn at x (n, 3)."""
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    fn(X, cells, xt, xp=torch).backward()
    return xt.grad.numpy()


# ---------------------------------------------------------------------------
# meshes, potentials, states
# ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sheet():
    m = read_mesh(MESH_DIR / "square.obj")
    X, tris = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64)
    fixed = np.flatnonzero(X[:, 0] <= X[:, 0].min() + 1e-9)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": fixed}
    material = {"model": "stvk_nm", "youngs_modulus": Y, "poisson_ratio": NU, "density": RHO, "thickness": H}
    return X, tris, build_elastic("shell", arrays, material)


@pytest.fixture(scope="module")
def beam():
    X, T = beam_tets(3, 2, 2, 0.3, 0.2, 0.2)
    X, T = np.asarray(X, dtype=np.float64), np.asarray(T, dtype=np.int64)
    arrays = {"rest_positions": X, "tets": T, "dirichlet": np.flatnonzero(X[:, 0] <= 1e-12)}
    material = {"model": "stvk_nm", "youngs_modulus": Y_TET, "poisson_ratio": NU_TET, "density": 1000.0}
    return X, T, build_elastic("tets", arrays, material)


def _rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def states(X, kind):
    """Named states of rest X (n, 3): rest, rigid, stretch, bending, and a random perturbation."""
    c = X.mean(0)
    R = _rotation(1)
    out = {"rest": X.copy(), "rigid": (X - c) @ R.T + np.array([0.3, -0.2, 0.1])}
    out["stretch"] = c + (X - c) * np.array([1.08, 0.97, 0.95]) if kind == "tets" else c + (X - c) * np.array([1.08, 1.0, 0.94])
    # bending about the z axis: the sheet (the y = 0 plane) or the beam rolled onto a cylinder of radius r
    r = 0.25
    u = X[:, 0] - X[:, 0].min()
    out["bending"] = np.stack([(r - X[:, 1]) * np.sin(u / r), r - (r - X[:, 1]) * np.cos(u / r), X[:, 2]], 1)
    scale = np.ptp(X, axis=0).max()
    out["random"] = (X + 0.02 * scale * np.random.default_rng(2).standard_normal(X.shape)) @ R.T
    return out


def total(pot, x):
    return sum(float(t.energy(torch.as_tensor(x))) for t in pot.terms)


def compiled_energy_gradient(pot, x):
    g = np.zeros(x.size)
    e = sum(term_kernel(t).energy_gradient(x, g) for t in pot.terms)
    return e, g.reshape(x.shape)


# ---------------------------------------------------------------------------
# the formulas
# ---------------------------------------------------------------------------
def _check_against_plain(pot, X, cells, plain, kind):
    S = states(X, kind)
    scale_e = plain(X, cells, S["stretch"])
    scale_g = np.abs(plain_gradient(plain, X, cells, S["stretch"])).max()
    assert scale_e > 0 and scale_g > 0
    for name, x in S.items():
        ref = plain(X, cells, x)
        ref_g = plain_gradient(plain, X, cells, x)
        e_torch = total(pot, x)
        e_comp, g_comp = compiled_energy_gradient(pot, x)
        if name in ("rest", "rigid"):  # zero energy and force
            assert abs(ref) <= 1e-12 * scale_e, (name, ref)
            assert abs(e_torch) <= 1e-12 * scale_e and abs(e_comp) <= 1e-12 * scale_e, (name, e_torch, e_comp)
            assert np.abs(g_comp).max() <= 1e-10 * scale_g, name
        else:
            assert ref > 0
            assert abs(e_torch - ref) <= RTOL * ref, (name, e_torch, ref)
            assert abs(e_comp - ref) <= RTOL * ref, (name, e_comp, ref)
            assert np.abs(g_comp - ref_g).max() <= RTOL * np.abs(ref_g).max(), name


@needs_meshes
def test_sheet_matches_the_authors_formulas(sheet):
    X, tris, pot = sheet
    assert [type(t).__name__ for t in pot.terms] == ["ShellMembraneNM", "ShellHinge"]
    _check_against_plain(pot, X, tris, sheet_energy_plain, "shell")
    # the bending state carries most of its energy in the hinges, the stretch none
    S = states(X, "shell")
    assert float(pot.terms[1].energy(torch.as_tensor(S["stretch"]))) < 1e-20 * total(pot, S["stretch"]) + 1e-300
    hinge_share = float(pot.terms[1].energy(torch.as_tensor(S["bending"]))) / total(pot, S["bending"])
    assert hinge_share > 0.5


def test_tets_match_the_authors_formulas(beam):
    X, T, pot = beam
    assert [type(t).__name__ for t in pot.terms] == ["TetsNM"]
    _check_against_plain(pot, X, T, tet_energy_plain, "tets")


def test_inverted_tet_pays_the_volume_term(beam):
    """lam (J - 1)^2 with J = det F: a reflected element (J = -1) costs 4 lam V0, unlike StVK's (tr E)^2."""
    X, T, _ = beam
    term = TetsNM(X, T[:1], Y_TET, NU_TET)
    x = X.copy()
    x[:, 2] *= -1.0  # reflection: E = 0, J = -1
    lam = Y_TET * NU_TET / ((1 + NU_TET) * (1 - 2 * NU_TET))
    assert float(term.energy(torch.as_tensor(x))) == pytest.approx(4 * lam * float(term.rest_volume[0]), rel=1e-12)


@needs_meshes
def test_given_bending_stiffness(sheet):
    X, tris, _ = sheet
    kb = 3.7e-2
    material = {"model": "stvk_nm", "youngs_modulus": Y, "poisson_ratio": NU, "density": RHO, "thickness": H, "bending_stiffness": kb}
    pot = build_elastic("shell", {"rest_positions": X, "triangles": tris, "dirichlet": np.zeros(0, dtype=np.int64)}, material)
    x = states(X, "shell")["bending"]
    ref = sheet_energy_plain(X, tris, x, kb=kb)
    assert total(pot, x) == pytest.approx(ref, rel=RTOL)


def test_material_model_errors():
    X, T = beam_tets(1, 1, 1, 1.0, 1.0, 1.0)
    arrays = {"rest_positions": X, "tets": T, "dirichlet": np.zeros(0, dtype=np.int64)}
    with pytest.raises(ValueError, match="material.model 'neo' is not available for model 'tets'"):
        build_elastic("tets", arrays, {"model": "neo", "youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1.0})
    with pytest.raises(ValueError, match="bending_stiffness"):
        build_elastic("tets", arrays, {"model": "stvk_nm", "youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1.0, "bending_stiffness": 1.0})
    default = build_elastic("tets", arrays, {"youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1.0})
    assert type(default.terms[0]).__name__ == "StVKTets"


# ---------------------------------------------------------------------------
# the contract: derivatives, kernels, subsets
# ---------------------------------------------------------------------------
def _terms(sheet, beam):
    return [(sheet[2].terms[0], sheet[0]), (beam[2].terms[0], beam[0])]


@needs_meshes
def test_finite_differences(sheet, beam):
    for term, X in _terms(sheet, beam):
        x = states(X, "any")["random"]
        k = term_kernel(term)
        g = np.zeros(x.size)
        k.energy_gradient(x, g)
        d = np.random.default_rng(3).standard_normal(x.shape)
        eps = 1e-6 * np.ptp(X, axis=0).max()
        fd = (k.energy(x + eps * d) - k.energy(x - eps * d)) / (2 * eps)
        assert fd == pytest.approx(float(g @ d.ravel()), rel=1e-6), term.name


@needs_meshes
def test_hessians_against_autograd(sheet, beam):
    for term, X in _terms(sheet, beam):
        for x in (states(X, "any")["random"], states(X, "any")["stretch"] * 0.9 + 0.1 * X.mean(0)):
            xe = term.gather(torch.as_tensor(x))
            g0, H0 = autograd_gradient_hessian(term, xe, project=False)
            g, H = term.local_gradient_hessian(xe, project=False)
            scale = H0.abs().amax((-1, -2), keepdim=True)
            assert torch.allclose(g, g0, rtol=0, atol=1e-10 * float(g0.abs().max()))
            assert float(((H - H0).abs() / scale).max()) < 1e-10, term.name
            _, Hp = term.local_gradient_hessian(xe, project=True)
            Hp0 = project_psd_translation_free(H0, xe.shape[1])
            assert float(((Hp - Hp0).abs() / scale).max()) < 1e-9, term.name
            assert float(torch.linalg.eigvalsh(Hp).min()) >= -1e-9 * float(scale.max())


@needs_meshes
def test_compiled_energy_equals_the_oracle_and_subsets(sheet, beam):
    for term, X in _terms(sheet, beam):
        x = states(X, "any")["random"]
        per = term.element_energy(torch.as_tensor(x))
        assert term_kernel(term).energy(x) == pytest.approx(float(per.sum()), rel=1e-12)
        idx = np.array([0, 3, 5])
        w = np.array([0.5, 2.0, 1.5])
        sub = term.weighted_subset(idx, w)
        ref = float((per[idx] * torch.as_tensor(w)).sum())
        assert float(sub.energy(torch.as_tensor(x))) == pytest.approx(ref, rel=1e-12)
        assert term_kernel(sub).energy(x) == pytest.approx(ref, rel=1e-12)


# ---------------------------------------------------------------------------
# linear modes with an identity mass
# ---------------------------------------------------------------------------
@needs_meshes
def test_sheet_modes_with_identity_mass_are_the_hessian_eigenpairs(sheet):
    """The authors' linear modes solve H e = mu e (identity mass): the modes ``lowest_modes`` gives
    with unit masses have Rayleigh quotients (on the dense Hessian of the plain formulas, by
    autograd) equal to its eigenvalues, which are the lowest eigenvalues of that Hessian."""
    X, tris, pot = sheet
    unit = dataclasses.replace(pot, masses=torch.ones(len(X), dtype=torch.float64))
    k = 6
    w, V, free = lowest_modes(unit, k, X)
    xt = torch.as_tensor(X)
    Hd = torch.autograd.functional.hessian(lambda y: sheet_energy_plain(X, tris, y.reshape(-1, 3), xp=torch), xt.reshape(-1))
    Hf = Hd.numpy()[np.ix_(free, free)]
    ref = np.linalg.eigvalsh(Hf)[:k]
    # one edge clamped: the sheet can still turn about it, a rigid motion (eigenvalue 0, to round-off)
    tiny = 1e-10 * ref[-1]
    assert abs(ref[0]) <= tiny and np.all(ref[1:] > 1e-3 * ref[-1])
    assert np.allclose(w, ref, rtol=1e-8, atol=tiny)
    rayleigh = np.einsum("ik,ij,jk->k", V, Hf, V) / np.einsum("ik,ik->k", V, V)
    assert np.allclose(rayleigh, w, rtol=1e-8, atol=tiny)
    assert np.abs(Hf @ V - V * w).max() <= 1e-8 * w.max() * np.abs(V).max()
    # the assembled (compiled) Hessian is the same matrix
    K, _ = stiffness_matrix(unit, X)
    assert np.abs(K.toarray() - Hf).max() <= 1e-10 * np.abs(Hf).max()


def test_the_artefact_keeps_the_material_model():
    """simulate writes ``material.model`` as the attribute material_model (``model`` is the scene's);
    ``potential_from_artefact`` rebuilds the same terms from it."""
    import h5py

    from latentsim.scene import MATERIAL_MODEL_ATTR, potential_from_artefact

    X, T = beam_tets(1, 1, 1, 1.0, 1.0, 1.0)
    with h5py.File("in-memory.h5", "w", driver="core", backing_store=False) as f:
        f["rest_positions"], f["tets"], f["dirichlet"] = X, T, np.array([0])
        f.attrs.update(model="tets", dt=0.01, gravity=np.zeros(3), youngs_modulus=1e6, poisson_ratio=0.3, density=1.0)
        assert type(potential_from_artefact(f).terms[0]).__name__ == "StVKTets"
        f.attrs[MATERIAL_MODEL_ATTR] = "stvk_nm"
        assert type(potential_from_artefact(f).terms[0]).__name__ == "TetsNM"


def test_membrane_stress_is_the_derivative_of_the_density(sheet):
    """Table 4's |S| on stvk_nm: P = 2 mu F E + lam (J - 1) J F C^{-1}, and h Abar P G_a is the vertex force."""
    X, tris, pot = sheet
    mem = next(t for t in pot.terms if isinstance(t, ShellMembraneNM))
    rng = np.random.default_rng(7)
    x = torch.as_tensor(X[None] + 0.02 * rng.standard_normal((4, *X.shape)))
    F = mem.deformation_gradient(mem.gather(x))
    C = F.transpose(-1, -2) @ F
    E = 0.5 * (C - torch.eye(2, dtype=F.dtype))
    J = torch.sqrt(torch.linalg.det(C))
    P = 2.0 * mem.mu[:, None, None] * F @ E + (mem.lam * (J - 1.0) * J)[..., None, None] * F @ torch.linalg.inv(C)
    np.testing.assert_allclose(mem.first_piola(x).numpy(), P.numpy(), rtol=1e-9, atol=1e-9 * float(P.abs().max()))
    np.testing.assert_allclose(mem.stress_norm(x).numpy(), torch.linalg.matrix_norm(P).numpy(), rtol=1e-9)
    assert mem.stress_norm(x[0]).shape == (len(tris),)
