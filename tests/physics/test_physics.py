"""The simulator against analytic beam theory, and stored frames against the equations of motion.

- Static deflection of a clamped cantilever under its own weight, as a rod and
  as a tet beam: Euler-Bernoulli tip deflection q L^4 / (8 EI), within 3%.
- Lowest bending frequencies from the rest-state Hessian (generalised
  eigenproblem with the lumped mass): omega_k = beta_k^2 sqrt(EI / (rho A L^4)),
  beta_1 L = 1.8751, beta_2 L = 4.6941, within 5%.
- Every stored frame of a simulated sequence has an incremental-potential
  gradient (recomputed here by autograd, not by the solver) below tolerance.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch

from latentsim.mesh import beam_tets, rod_stencils
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.modes import lowest_modes, stiffness_matrix

ROOT = Path(__file__).resolve().parents[2]
G = 9.81
BETA = (1.875104068711961, 4.694091132974175)


def rod_cantilever(L=1.0, segments=40, radius=0.01, E=1e10, rho=1000.0, dt=1e6):
    """A horizontal rod along +x clamped at x = 0.

    A discrete rod is clamped by fixing both ends of an edge; its curvature
    lives on vertices, so the clamped section is that edge's midpoint.  The
    clamped edge therefore spans [-ds/2, ds/2] and the tip sits at x = L.
    """
    ds = L / (segments + 0.5)
    x = (np.arange(segments + 2) - 0.5) * ds
    V = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    edges, triples, _ = rod_stencils(1, len(V))
    arrays = dict(rest_positions=V, edges=edges, triples=triples, dirichlet=np.array([0, 1]))
    mat = dict(youngs_modulus=E, poisson_ratio=0.3, density=rho, radius=radius)
    pot = build_potential("rods", arrays, mat, dt, [0.0, -G, 0.0])
    EI = E * np.pi * radius**4 / 4
    q = rho * np.pi * radius**2 * G
    return pot, V, EI, q, rho * np.pi * radius**2


def tet_cantilever(L=1.0, W=0.1, n=(120, 8, 8), E=1e9, rho=1000.0, dt=1e6):
    """A square beam along +x clamped at x = 0; nu = 0 so the clamp adds no Poisson stiffening.

    Linear tets are too stiff in bending (locking): at 8 elements through the
    thickness and L/h = 120 the deflection is 1.5% short of Euler-Bernoulli
    (the 5-tet split locks less than the 6-tet one at the same resolution).
    """
    V, T = beam_tets(n[0], n[1], n[2], L, W, W, tets_per_cell=5)
    D = np.flatnonzero(V[:, 0] < 1e-12)
    arrays = dict(rest_positions=V, tets=T, dirichlet=D)
    mat = dict(youngs_modulus=E, poisson_ratio=0.0, density=rho)
    pot = build_potential("tets", arrays, mat, dt, [0.0, -G, 0.0])
    EI = E * W**4 / 12
    q = rho * W * W * G
    return pot, V, EI, q, rho * W * W


def static_solve(pot, V):
    """One implicit step with a huge time step: inertia vanishes, Newton finds the static equilibrium."""
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-6, max_iterations=30))
    x, info = solver.step(V, V, V[solver.dirichlet])
    return x


def test_rod_cantilever_matches_euler_bernoulli():
    pot, V, EI, q, _ = rod_cantilever()
    x = static_solve(pot, V)
    L = V[-1, 0]
    assert L == pytest.approx(1.0)
    expected = q * L**4 / (8 * EI)
    tip = -(x[-1, 1] - V[-1, 1])
    assert expected / L < 0.01  # small load: linear theory applies
    assert tip == pytest.approx(expected, rel=0.03)


def test_tet_cantilever_matches_euler_bernoulli():
    pot, V, EI, q, _ = tet_cantilever()
    x = static_solve(pot, V)
    L = V[:, 0].max()
    tip = -(x[V[:, 0] > L - 1e-9, 1] - V[V[:, 0] > L - 1e-9, 1]).mean()
    expected = q * L**4 / (8 * EI)
    assert expected / L < 0.01
    assert tip == pytest.approx(expected, rel=0.03)


@pytest.mark.parametrize("build", [rod_cantilever, tet_cantilever], ids=["rod", "tets"])
def test_lowest_bending_frequencies(build):
    pot, V, EI, _, rho_a = build()
    L = V[:, 0].max()
    omega2, modes, free = lowest_modes(pot, 6, V)
    omega = np.sqrt(np.abs(omega2))
    # bending in y and in z have the same frequency: modes come in pairs
    analytic = [b**2 * np.sqrt(EI / (rho_a * L**4)) for b in BETA]
    assert omega[0] == pytest.approx(analytic[0], rel=0.05)
    assert omega[1] == pytest.approx(analytic[0], rel=0.05)
    bending2 = [w for w in omega[2:] if abs(w / analytic[1] - 1) < 0.05]
    assert len(bending2) >= 2, (omega, analytic)


def test_newton_reaches_equilibrium_in_one_iteration_for_a_linear_problem():
    """At rest with no gravity and zero velocity, the rest state is the solution: 0 iterations."""
    pot, V, *_ = rod_cantilever(dt=0.01)
    pot.g = torch.zeros(3, dtype=torch.float64)
    solver = ImplicitEuler(pot)
    x, info = solver.step(V, V, V[solver.dirichlet])
    assert info.iterations == 0 and np.allclose(x, V)


def _eom_scene(model: str, law: str):
    """A small scene of each model: (mesh arrays, material) with a non-trivial response in 20 frames."""
    from latentsim.mesh import cloth_grid, rod_bundle

    if model == "rods":
        V, _, _ = rod_bundle(3, 10, 0.1, 0.02)
        edges, triples, root_of = rod_stencils(3, 10)
        arrays = dict(rest_positions=V, edges=edges, triples=triples, root_of=root_of, dirichlet=np.unique(root_of))
        return arrays, dict(youngs_modulus=1e7, poisson_ratio=0.3, density=1320.0, radius=7e-4)
    if model == "shell":
        V, F = cloth_grid(4, 4, 0.2, 0.2, plane="xz")
        arrays = dict(rest_positions=V, triangles=F, dirichlet=np.flatnonzero(V[:, 0] < V[:, 0].min() + 1e-9))
        return arrays, dict(youngs_modulus=1e5, poisson_ratio=0.3, density=200.0, thickness=1e-3, model=law)
    V, T = beam_tets(3, 1, 1, 0.3, 0.1, 0.1, tets_per_cell=5)
    arrays = dict(rest_positions=V, tets=T, dirichlet=np.flatnonzero(V[:, 0] < 1e-12))
    return arrays, dict(youngs_modulus=5e3, poisson_ratio=0.3, density=1000.0, model=law)


@pytest.mark.parametrize(
    "model,law",
    [("rods", "stvk"), ("shell", "stvk"), ("shell", "stvk_nm"), ("tets", "stvk"), ("tets", "stvk_nm"), ("tets", "neohookean")],
)
def test_stored_frames_satisfy_equations_of_motion(tmp_path, model, law):
    """Every model and material through the simulation stage: at every stored frame the gradient of the
    incremental potential rebuilt from the artefact (its material model included), recomputed by autograd, not
    by the solver, is below the solver's tolerance; tet scenes' recorded det F are the frames' own."""
    import h5py

    import latentsim.io as lio
    from latentsim.stages.simulate import simulate_scene

    arrays, material = _eom_scene(model, law)
    mesh_h5 = tmp_path / "mesh.h5"
    with lio.atomic_h5(mesh_h5) as f:
        f.attrs["model"] = model
        for k, v in arrays.items():
            lio.write_dataset(f, k, v)
    cfg = dict(
        model=model,
        material=material,
        dt=1 / 30,
        gravity=[0, -9.81, 0],
        newton=dict(tolerance=1e-6, max_iterations=50, linear_solver="auto"),
        sequences=[dict(name="s", split="train", frames=20, reverse_every=5, segments=[dict(start=0, velocity=[0.5, 0, 0])])],
    )
    out = tmp_path / "sim" / "eom" / "trajectories.h5"
    out.parent.mkdir(parents=True)
    simulate_scene("eom", mesh_h5, cfg, out)
    # the independent check of a run's frames (benchmarks/check_frames.py): autograd of the rebuilt potential
    spec = importlib.util.spec_from_file_location("check_frames", ROOT / "benchmarks" / "check_frames.py")
    check_frames = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check_frames)
    report = check_frames.check(out)
    assert report["law"] == law and report["frames"] == 19
    assert report["worst"] <= 1.0, f"a frame's residual is {report['worst']:.3g} x the tolerance"
    with h5py.File(out) as f:
        X = torch.as_tensor(f["sequences/s/positions"][()])
        recorded = {k: f[f"sequences/s/{k}"][()] for k in ("min_volume_ratio", "inverted_tets") if f"sequences/s/{k}" in f}
    assert (X[-1] - X[0]).abs().max() > 1e-3  # the motion is not trivial
    if model == "tets":
        T = torch.as_tensor(arrays["tets"])
        vol = lambda x: torch.linalg.det(x[T[:, 1:]] - x[T[:, :1]])  # noqa: E731
        det_f = torch.stack([vol(x) / vol(X[0]) for x in X])
        np.testing.assert_allclose(recorded["min_volume_ratio"], det_f.min(dim=1).values.numpy(), rtol=1e-12)
        np.testing.assert_array_equal(recorded["inverted_tets"], (det_f <= 0).sum(dim=1).numpy())
        assert report["inverted"] == int((det_f[1:] <= 0).any(dim=1).sum())
        assert recorded["min_volume_ratio"].min() < 1.0
    else:
        assert not recorded


def test_free_only_potential_has_the_same_free_gradient_and_hessian():
    """Dropping all-Dirichlet stencils (the solver's potential) changes no free-DoF derivative."""
    V, T = beam_tets(6, 2, 2, 1.0, 0.2, 0.2)
    D = np.flatnonzero(V[:, 0] < 0.55)  # half the beam is prescribed
    arrays = dict(rest_positions=V, tets=T, dirichlet=D)
    mat = dict(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
    full = build_potential("tets", arrays, mat, 0.01, [0, -9.81, 0])
    reduced = build_potential("tets", arrays, mat, 0.01, [0, -9.81, 0], free_only=True)
    assert len(reduced.terms[0].stencils) < len(full.terms[0].stencils)
    assert torch.equal(reduced.masses, full.masses)
    rng = np.random.default_rng(0)
    x = torch.as_tensor(V + 0.01 * rng.standard_normal(V.shape))
    free = np.setdiff1d(np.arange(len(V)), D)
    grads = []
    for pot in (full, reduced):
        xx = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(pot(xx, x, x), xx)
        grads.append(g[free])
    assert torch.allclose(grads[0], grads[1], rtol=1e-12, atol=1e-12)
    fd = np.repeat(np.isin(np.arange(len(V)), free), 3)
    K_full, _ = stiffness_matrix(full, x.numpy(), np.flatnonzero(fd))
    K_red, _ = stiffness_matrix(reduced, x.numpy(), np.flatnonzero(fd))
    assert abs(K_full - K_red).max() < 1e-9 * abs(K_full).max()
