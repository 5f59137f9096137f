"""Tests of reduced implicit Euler (latentsim.solve.reduced).

A tiny StVK tet beam clamped at one end, under gravity, with its clamp moving:
- a linear subspace spanning every free DoF reproduces the full-space Newton
  step of :class:`latentsim.solve.implicit_euler.ImplicitEuler`;
- the reduced gradient J^T g equals finite differences of the scene's
  IncrementalPotential (with its Dirichlet penalty) along the subspace, for a
  linear and for an autoencoder-decoder (nonlinear) subspace;
- Newton and L-BFGS decrease the energy at every iteration and agree;
- a rollout reports per-step times and the frame where a solve fails;
- with a collider, every iterate stays outside it, as in the full space: a full-rank
  subspace reproduces the full space's frames against a ball the clamp drives the beam onto.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from latentsim.latent import Autoencoder, RelativeCoordinates
from latentsim.mesh import beam_tets
from latentsim.stages.baselines import modes_subspace
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.solve.modes import lowest_modes, stiffness_matrix
from latentsim.solve.reduced import ReducedFailed, ReducedImplicitEuler, ReducedSettings, reduced_rollout
from latentsim.latent.subspaces import DecoderSubspace, LinearSubspace

DT = 1.0 / 30.0


@pytest.fixture(scope="module")
def beam():
    V, T = beam_tets(3, 1, 1, 0.3, 0.1, 0.1, tets_per_cell=5)
    D = np.flatnonzero(V[:, 0] < 1e-12)
    arrays = {"rest_positions": V, "tets": T, "dirichlet": D}
    mat = {"youngs_modulus": 2e4, "poisson_ratio": 0.3, "density": 1000.0}
    pot = build_potential("tets", arrays, mat, DT, [0.0, -9.81, 0.0], w_bc=1e4)
    # the clamp moves up and sideways: 3 frames of prescribed positions
    shift = np.array([[0.0, 0.0, 0.0], [0.0, 0.02, 0.01], [0.0, 0.05, 0.02], [0.0, 0.07, 0.04], [0.0, 0.08, 0.05]])
    xD = V[D][None] + shift[:, None, :]
    return V, D, pot, xD


def _hard_coords(V, D):
    """Every vertex relative to the first clamped vertex; the clamp imposed exactly."""
    return RelativeCoordinates(len(V), D, "roots", root_of=[int(D[0])] * len(V))


def test_full_rank_linear_subspace_reproduces_full_newton(beam):
    V, D, pot, xD = beam
    coords = _hard_coords(V, D)
    u0 = coords.encode(torch.as_tensor(V), torch.as_tensor(V[D])).numpy()
    sub = LinearSubspace(coords, u0, np.eye(coords.dim))
    assert sub.dim == 3 * (len(V) - len(D))
    full = ImplicitEuler(pot, NewtonSettings(tolerance=1e-10))
    xs = [V.copy(), V.copy()]
    for t in range(2, len(xD)):
        xs.append(full.step(xs[-1], xs[-2], xD[t])[0])
    q0 = sub.project(V, xD[0])
    out = reduced_rollout(sub, pot, q0, q0, np.concatenate([V[D][None]] * 2 + [xD[2:]]), ReducedSettings(tolerance=1e-10))
    assert out["diverged_frame"] == -1 and out["failure"] == ""
    X = out["positions"]
    moved = np.abs(xs[-1] - V).max()
    assert moved > 0.02  # the beam really moves and sags
    for t in range(2, len(xD)):
        assert np.abs(X[t] - xs[t]).max() < 1e-9 * moved + 1e-12
    assert np.isfinite(out["step_ms"][2:]).all() and (out["iterations"][2:] >= 1).all()


def _turned_clamp(V, D, xD):
    """The clamp's positions xD (m, 3) turned 0.6 rad about an oblique axis through their centroid."""
    w = 0.6 * np.array([0.3, 1.0, -0.4]) / np.linalg.norm([0.3, 1.0, -0.4])
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    Q = torch.linalg.matrix_exp(torch.as_tensor(K)).numpy()
    c = xD.mean(0)
    return (xD - c) @ Q.T + c


def _decoder_subspace(V, D, r=4, seed=0, rigid=False):
    coords = RelativeCoordinates(len(V), D, "mean", rigid_rest=V[D] if rigid else None)
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    rest = coords.encode(torch.as_tensor(V), torch.as_tensor(V[D]))
    U = rest + 0.02 * torch.randn(64, coords.dim, generator=g, dtype=torch.float64)
    ae = Autoencoder(coords.dim, r, [16, 16], pca_dim=8).double()
    ae.init_pca(U)
    with torch.no_grad():  # a genuinely nonlinear decoder: non-zero branch output, non-trivial BatchNorm
        ae.dec_branch.out.weight.normal_(0.0, 0.05, generator=g)
        for blk in ae.dec_branch.blocks:
            blk[1].running_mean.normal_(0.0, 0.1, generator=g)
            blk[1].running_var.uniform_(0.5, 2.0, generator=g)
    ae.eval()
    return DecoderSubspace(ae, coords), coords, rest.numpy()


def _energy_along(pot, sub, q, x1, x2, xD):
    with torch.no_grad():
        x = torch.from_numpy(sub.map(q, xD))
        return float(pot(x, torch.from_numpy(x1), torch.from_numpy(x2), targets=torch.from_numpy(xD), penalty=True))


@pytest.mark.parametrize("rigid", [False, True])
@pytest.mark.parametrize("kind", ["linear", "decoder"])
def test_reduced_gradient_matches_finite_differences(beam, kind, rigid):
    """The reduced gradient J^T g against central differences of the energy along q; with a rigid frame
    (autoencoder.rigid_frame) at a turned clamp, where J carries the frame's rotation."""
    V, D, pot, xD = beam
    if rigid:
        xD = xD.copy()
        xD[2] = _turned_clamp(V, D, xD[2])
    if kind == "decoder":
        sub, coords, _ = _decoder_subspace(V, D, rigid=rigid)
    else:
        coords = RelativeCoordinates(len(V), D, "mean", rigid_rest=V[D] if rigid else None)
        rng = np.random.default_rng(1)
        u0 = coords.encode(torch.as_tensor(V), torch.as_tensor(V[D])).numpy()
        sub = LinearSubspace(coords, u0, np.linalg.qr(rng.standard_normal((coords.dim, 5)))[0])
    solver = ReducedImplicitEuler(sub, pot)
    assert solver.penalty  # mean coordinates: the Dirichlet vertices are only penalised
    rng = np.random.default_rng(2)
    q = 0.05 * rng.standard_normal(sub.dim)
    x1 = V + 0.01 * rng.standard_normal(V.shape)
    x2 = V + 0.01 * rng.standard_normal(V.shape)
    if kind == "decoder":  # the map is the coordinates' decode of the decoder's output, the frame included
        with torch.no_grad():
            ref = coords.decode(sub.ae.decode(torch.from_numpy(q)[None])[0], torch.from_numpy(xD[2])).numpy()
        assert np.allclose(sub.map(q, xD[2]), ref, rtol=0, atol=1e-12)
    e, gq, _ = solver.reduced_gradient(q, x1, x2, xD[2])
    assert e == pytest.approx(_energy_along(pot, sub, q, x1, x2, xD[2]), rel=1e-12)
    h = 1e-6
    fd = np.array([(_energy_along(pot, sub, q + h * ei, x1, x2, xD[2]) - _energy_along(pot, sub, q - h * ei, x1, x2, xD[2])) / (2 * h) for ei in np.eye(sub.dim)])
    assert np.abs(gq).max() > 1e-3
    assert np.allclose(gq, fd, rtol=1e-5, atol=1e-7 * np.abs(gq).max())


@pytest.mark.parametrize("rigid", [False, True])
def test_decoder_curvature_matches_autograd(beam, rigid):
    """sum_i g_i d^2 x_i / dq^2 of the decoder subspace against torch.func.hessian (with a rigid frame at a
    turned clamp too)."""
    V, D, _, xD = beam
    sub, coords, _ = _decoder_subspace(V, D, seed=4, rigid=rigid)
    target = _turned_clamp(V, D, xD[2]) if rigid else xD[2]
    rng = np.random.default_rng(5)
    q, g = 0.3 * rng.standard_normal(sub.dim), rng.standard_normal(3 * len(V))
    gt, xDt = torch.from_numpy(g), torch.from_numpy(target)

    def weighted(z):
        return (gt * coords.decode(sub.ae.decode(z[None])[0], xDt).reshape(-1)).sum()

    ref = torch.func.hessian(weighted)(torch.from_numpy(q)).detach().numpy()
    C = sub.curvature(q, target, g)
    assert np.abs(ref).max() > 5e-4
    assert np.allclose(C, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


@pytest.mark.parametrize("method,curvature", [("newton", True), ("newton", False), ("lbfgs", False)])
def test_energy_decreases_every_iteration_and_methods_agree(beam, method, curvature):
    V, D, pot, xD = beam
    sub, _, _ = _decoder_subspace(V, D, seed=3)
    q0 = sub.project(V, V[D])
    settings = ReducedSettings(method=method, tolerance=1e-8, max_iterations=200, map_curvature=curvature)
    solver = ReducedImplicitEuler(sub, pot, settings)
    x0 = sub.map(q0, xD[0])
    q, _, info = solver.step(q0, q0, x0, x0, xD[3])
    assert info.converged and info.iterations >= 2
    E = np.asarray(info.energies)
    assert np.all(np.diff(E) <= 1e-12 * np.abs(E).max())
    assert E[-1] < E[0]
    ref = ReducedImplicitEuler(sub, pot, ReducedSettings(method="newton", tolerance=1e-10, max_iterations=200))
    q_ref, _, info_ref = ref.step(q0, q0, x0, x0, xD[3])
    assert np.abs(q - q_ref).max() < 1e-4 * max(np.abs(q_ref - q0).max(), 1e-12)
    if method == "newton" and not curvature:  # Gauss-Newton: linear convergence, more iterations
        assert info.iterations > info_ref.iterations


def test_rollout_records_the_frame_that_does_not_converge(beam):
    V, D, pot, xD = beam
    coords = _hard_coords(V, D)
    sub = LinearSubspace.from_frames(coords, np.stack([V, V + 0.01]), np.stack([V[D], V[D] + 0.01]), 1)
    q0 = sub.project(V, V[D])
    # no iteration allowed and an unreachable tolerance: frame 2 fails, and the rollout stops there
    out = reduced_rollout(sub, pot, q0, q0, xD, ReducedSettings(tolerance=1e-14, max_iterations=0))
    assert out["diverged_frame"] == 2
    assert out["failure"].startswith("ReducedFailed: no convergence in 0 iterations")  # why, for the log
    assert np.isnan(out["positions"][2:]).all() and np.isfinite(out["positions"][:2]).all()
    assert out["positions"].shape == (len(xD), len(V), 3) and out["latents"].shape == (len(xD), 1)


@pytest.mark.parametrize("mode", ["mean", "roots"])
def test_modes_subspace_spans_the_vibration_modes_and_follows_the_clamp(beam, mode):
    """modes_reduced: q = 0 is the rest shape carried by the clamp's translation, and the
    directions are the M-orthonormal lowest modes (zero on the clamp), whose reduced stiffness
    J^T K J is diag(omega^2)."""
    V, D, pot, _ = beam
    coords = RelativeCoordinates(len(V), D, "mean") if mode == "mean" else _hard_coords(V, D)
    sub = modes_subspace(coords, pot, V, 3)
    t = np.array([0.01, -0.02, 0.03])
    assert np.allclose(sub.map(np.zeros(3), V[D] + t), V + t, atol=1e-12)
    _, J = sub.jacobian(np.zeros(3), V[D])
    assert np.abs(J.reshape(len(V), 3, 3)[D]).max() == 0.0
    w, _, free = lowest_modes(pot, 3, V)
    K, _ = stiffness_matrix(pot, V, free)
    m = np.repeat(pot.masses.numpy(), 3)
    Jf = J[free]
    assert np.allclose(Jf.T @ (m[free, None] * Jf), np.eye(3), atol=1e-8)
    assert np.allclose(Jf.T @ (K @ Jf), np.diag(w), rtol=1e-6, atol=1e-8 * w.max())


def test_modes_subspace_is_the_same_on_every_call(beam):
    """The linear-modes basis is reproducible: ARPACK's own start vector is random (and advances
    between calls in one process), so without the fixed start and sign the basis, and every latent
    rolled out in it, differs from run to run."""
    V, _, pot, _ = beam
    (w1, V1, _), (w2, V2, _) = lowest_modes(pot, 4, V), lowest_modes(pot, 4, V)
    assert np.array_equal(w1, w2) and np.array_equal(V1, V2)
    # fix_sign's convention: the first entry within 1e-8 of a column's largest magnitude is positive
    first = np.argmax(np.abs(V1) >= (1 - 1e-8) * np.abs(V1).max(0), axis=0)
    assert (V1[first, np.arange(4)] > 0).all()


def _beam_over_a_ball(beam):
    """The beam with a ball of radius 2 cm 3 cm below its tip's lower corner, its clamp driven down at 1 m/s
    from frame 2: a step moves the tip by more than the ball's diameter, so a step that only tests where it
    lands can jump through the ball.  Returns the potential, the ball's centre and the clamp's positions."""
    V, D, _, _ = beam
    arrays = {"rest_positions": V, "tets": beam_tets(3, 1, 1, 0.3, 0.1, 0.1, tets_per_cell=5)[1], "dirichlet": D}
    tip = int(np.argmin(np.linalg.norm(V - [0.3, -0.05, -0.05], axis=1)))
    centre = V[tip] - [0.0, 0.05, 0.0]
    contact = {"colliders": [{"type": "sphere", "centre": centre.tolist(), "radius": 0.02}]}
    mat = {"youngs_modulus": 2e4, "poisson_ratio": 0.3, "density": 1000.0}
    pot = build_potential("tets", arrays, mat, DT, [0.0, -9.81, 0.0], w_bc=1e4, contact=contact)
    shift = np.zeros((16, 3))
    shift[2:, 1] = -1.0 * DT * np.arange(1, 15)
    return pot, centre, V[D][None] + shift[:, None, :]


def test_with_a_collider_every_reduced_iterate_stays_outside_and_a_full_rank_subspace_is_the_full_space(beam):
    """The reduced line search starts from the collider's first time of impact along the step (exact for a
    linear map) and rejects any trial whose straight path from the iterate crosses a collider; its initial
    guesses are those whose path from x_{t-1} stays outside.  A full-rank subspace then takes the full space's
    steps, frame by frame, as the tip meets the ball and slides off it; testing only where a step lands, it
    jumped into the ball (5.9 mm at frame 4) and off the full space's path."""
    V, D, _, _ = beam
    pot, centre, xD = _beam_over_a_ball(beam)
    full = ImplicitEuler(pot, NewtonSettings(tolerance=1e-9))
    xs = [V.copy(), V.copy()]
    for t in range(2, len(xD)):
        xs.append(full.step(xs[-1], xs[-2], xD[t])[0])
    coords = _hard_coords(V, D)
    u0 = coords.encode(torch.as_tensor(V), torch.as_tensor(V[D])).numpy()
    sub = LinearSubspace(coords, u0, np.eye(coords.dim))
    q0 = sub.project(V, xD[0])
    out = reduced_rollout(sub, pot, q0, q0, xD, ReducedSettings(tolerance=1e-9))
    assert out["diverged_frame"] == -1
    X, xs = out["positions"], np.stack(xs)
    gap = np.linalg.norm(X - centre, axis=-1).min(-1) - 0.02
    assert (gap > 0).all() and gap.min() < 2e-3  # it met the ball, and never entered it
    assert np.linalg.norm(xs - centre, axis=-1).min() - 0.02 < 2e-3
    assert np.abs(X - xs).max() < 1e-7


def test_a_reduced_step_never_starts_inside_a_collider(beam):
    """Every initial guess is inside the ball (the beam already is): the step fails and says why, rather than
    starting from a guess of infinite energy, where no trial is resolvably worse, and returning a state inside."""
    V, D, _, _ = beam
    pot, centre, xD = _beam_over_a_ball(beam)
    inside = V - [0.0, 0.04, 0.0]  # the tip's corner 1 cm into the ball
    coords = _hard_coords(V, D)
    sub = LinearSubspace(coords, coords.encode(torch.as_tensor(V), torch.as_tensor(V[D])).numpy(), np.eye(coords.dim))
    q = sub.project(inside, inside[D])
    with pytest.raises(ReducedFailed, match="every initial guess has a non-finite energy"):
        ReducedImplicitEuler(sub, pot).step(q, q, inside, inside, inside[D])


@pytest.mark.parametrize("linear", [True, False])
def test_a_trial_whose_path_crosses_a_collider_is_rejected_and_the_search_starts_short_of_it(beam, linear, monkeypatch):
    """The line search's two guards, for a step that would carry the beam's tip through the ball to its far side
    (an outside point, of finite energy): ``max_step`` starts the search short of the first impact, and a trial
    whose chord from the iterate crosses the ball costs inf, where the map is not linear (a decoder's chord is
    not its path); a short trial keeps its energy."""
    from latentsim.solve.reduced import ReducedStepInfo, _NewtonProblem

    V, D, _, _ = beam
    pot, centre, _ = _beam_over_a_ball(beam)
    coords = _hard_coords(V, D)
    sub = LinearSubspace(coords, coords.encode(torch.as_tensor(V), torch.as_tensor(V[D])).numpy(), np.eye(coords.dim))
    monkeypatch.setattr(sub, "linear", linear, raising=False)
    solver = ReducedImplicitEuler(sub, pot)
    solver.inner.begin_step(solver.inner.frame(V, V, V[D], V[D]))
    problem = _NewtonProblem(solver, V, V, V[D], ReducedStepInfo())
    q = sub.project(V, V[D])
    problem.stop(q, 0)
    free = np.ones(len(V), dtype=bool)
    free[D] = False
    down = np.where(free[:, None], [0.0, -0.2, 0.0], 0.0)  # the free vertices 20 cm down: the beam's end through the ball
    dq = sub.project(V + down, V[D]) - q
    landed = torch.as_tensor(sub.map(q + dq, V[D]))
    assert float(pot.contact.clearance(landed)) > 0.02  # it lands outside, beyond the ball, every point of its surface
    alpha0 = problem.max_step(q, dq)
    # the corner 3 cm above the ball: impact at 0.15 of the step; the surface's triangles (conservative advancement,
    # to a tenth of the 3 cm gap) stop it at 0.135, within the advancement's 1% of the gap; the search starts at 0.9 of that
    assert 0.9 * 0.135 * (1 - 0.01) <= alpha0 <= 0.9 * 0.135 * (1 + 1e-9)
    e_far, _ = problem.trial(q + dq, 1.0, True)
    e_short, _ = problem.trial(q + alpha0 * dq, alpha0, True)
    assert np.isfinite(e_short)
    assert (e_far == np.inf) != linear  # a linear map's trials stay within max_step: not tested again
