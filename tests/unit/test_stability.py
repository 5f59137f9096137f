"""Stress conditions and the survival measurement of latent rollouts."""

import numpy as np
import pytest
import torch

from latentsim import latent
from latentsim.latent import stability
from latentsim.scene import bc_parameters


@pytest.fixture
def program():
    seq = {"segments": [{"start": 0, "velocity": [0.2, 0, 0]}, {"start": 10, "velocity": [-0.1, 0, 0.05]}]}
    return bc_parameters(seq, 30)


def test_programs_scale_stop_reverse_and_repeat(program):
    out = stability.stress_programs(program, train_frames=20, factors=(0.5, 5.0), long_factor=10)
    assert set(out) == {"long_x10", "speed_x0p5", "speed_x5", "sudden_stop", "sudden_reversal", "perturbed_start"}
    long = out["long_x10"]
    assert long.shape == (200, 6)
    assert np.allclose(long[0], 0.0)
    assert np.allclose(long[1:30], program[1:30]) and np.allclose(long[30:59], program[1:30])  # the motion repeats
    assert np.allclose(out["speed_x5"], 5.0 * program)
    cut = 30 // 3
    assert np.allclose(out["sudden_stop"][:cut], program[:cut]) and np.allclose(out["sudden_stop"][cut:], 0.0)
    assert np.allclose(out["sudden_reversal"][cut:], -program[cut:])


def test_a_program_without_motion_keeps_only_the_conditions_that_change_it():
    """A free body (no prescribed set) has p_t = 0 throughout: scaling, stopping or reversing it would give the
    test sequence back, so only the long rollout and the perturbed start are stress conditions; with no
    Dirichlet vertex their prescribed trajectories are empty."""
    still = np.zeros((30, 6))
    out = stability.stress_programs(still, train_frames=20, factors=(0.5, 5.0), long_factor=10)
    assert set(out) == {"long_x10", "perturbed_start"} and out["long_x10"].shape == (200, 6) and not out["long_x10"].any()
    conds = stability.stress_conditions(still, np.zeros((0, 3)), 0.1, train_frames=20, factors=(2.0,), long_factor=10, perturbation=0.5)
    assert [(c.name, c.dirichlet_positions.shape) for c in conds] == [("long_x10", (200, 0, 3)), ("perturbed_start", (30, 0, 3))]


def test_conditions_prescribe_the_rigid_motion_of_their_program(program):
    rest_D = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    conds = {c.name: c for c in stability.stress_conditions(program, rest_D, 0.1, train_frames=20, factors=(2.0,), long_factor=10, perturbation=0.5)}
    c = conds["speed_x2"]
    # first segment: both vertices translate at 2 * 0.2 m/s along x
    assert np.allclose(c.dirichlet_positions[5] - rest_D, [[0.4 * 0.1 * 5, 0, 0]] * 2)
    assert conds["perturbed_start"].perturbation > 0 and c.perturbation == 0


def _tiny_autoencoder(n=6):
    rest = torch.tensor(np.random.default_rng(0).normal(size=(n, 3)))
    coords = latent.RelativeCoordinates(n, [0], mode="mean")
    X = rest[None] + 0.01 * torch.randn(40, n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    xD = X[:, :1]
    ae = latent.Autoencoder(coords.dim, 2, [], pca_dim=2)
    ae.init_pca(coords.encode(X, xD).float())
    return ae.eval(), coords, rest


class _Linear(torch.nn.Module):
    """z_t = a z_{t-1} + b: a stable (a < 1) or an exploding (a > 1) integrator."""

    def __init__(self, a, b=0.0):
        super().__init__()
        self.a, self.b = a, b

    def forward(self, z1, z2, p, p1, p2):
        return self.a * z1 + self.b


def test_a_contracting_integrator_survives_and_an_exploding_one_fails_where_its_extent_crosses_the_bound():
    ae, coords, rest = _tiny_autoencoder()
    T = 60
    bc = np.zeros((T, 6))
    cond = stability.Condition("still", bc, np.repeat(rest[None, :1].numpy(), T, 0))
    diag = float(np.linalg.norm(rest.numpy().max(0) - rest.numpy().min(0)))
    z = torch.zeros(2)
    ok = stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0)
    assert ok["survived"] == T and ok["frames"] == T and len(ok["dirichlet_error"]) == T
    bad = stability.survive_latent(_Linear(1.5, 1.0), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0)
    assert 2 < bad["survived"] < T
    # the reported frame is the first whose decoded extent exceeds the bound
    Z = [torch.zeros(2), torch.zeros(2)]
    for _ in range(2, T):
        Z.append(1.5 * Z[-1] + 1.0)
    with torch.no_grad():
        x = latent.decode_latents(ae, coords, torch.stack(Z), torch.as_tensor(cond.dirichlet_positions)).numpy()
    ext = np.linalg.norm(x.max(-2) - x.min(-2), axis=-1)
    assert bad["survived"] == int(np.argmax(ext > 3.0 * diag))


def _still_shape(T):
    """The tiny autoencoder, a condition of T frames holding it still, its rest diagonal and its decode at z = 0."""
    ae, coords, rest = _tiny_autoencoder()
    cond = stability.Condition("still", np.zeros((T, 6)), np.repeat(rest[None, :1].numpy(), T, 0))
    diag = float(np.linalg.norm(rest.numpy().max(0) - rest.numpy().min(0)))
    with torch.no_grad():
        x = latent.decode_latents(ae, coords, torch.zeros(1, 2), torch.as_tensor(cond.dirichlet_positions[:1]))[0].numpy()
    return ae, coords, rest, cond, diag, x


def test_with_colliders_a_stress_rollout_reports_how_deep_it_entered_one_before_it_failed():
    """The deepest entry of any surviving frame, over the diagonal: a half-space cutting through the decoded
    states gives their deepest vertex; one below every frame gives 0; frames after the failure do not count."""
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    T = 40
    ae, coords, rest, cond, diag, x = _still_shape(T)
    z = torch.zeros(2)
    level = float(np.median(x[:, 1]))  # a plane through the middle of the (still) decoded shape
    cut = ContactBarrier(len(rest), [HalfSpace((0.0, level, 0.0), (0.0, 1.0, 0.0))], 1e-3, 1.0)
    r = stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=cut)
    assert r["max_penetration"] == pytest.approx((level - x[:, 1].min()) / diag, rel=1e-6)
    below = ContactBarrier(len(rest), [HalfSpace((0.0, float(x[:, 1].min()) - 1.0, 0.0), (0.0, 1.0, 0.0))], 1e-3, 1.0)
    assert stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=below)["max_penetration"] == 0
    assert "max_penetration" not in stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0)
    # an exploding rollout: only the frames before its failure are measured (finite, however far it flew)
    bad = stability.survive_latent(_Linear(1.5, 1.0), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=cut)
    assert bad["survived"] < T and np.isfinite(bad["max_penetration"]) and bad["max_penetration"] < 3.0


def test_where_the_rollout_projects_its_frames_the_stress_rollouts_are_projected_too():
    """With the rollout's contact projection the surviving frames near a collider are projected as a test
    rollout's are: the reported depth is the projected frames' (out of the half-space), the network's own
    is kept beside it, and survival is the network's."""
    from latentsim.config import with_defaults
    from latentsim.latent.projection import ContactProjection
    from latentsim.latent.subspaces import DecoderSubspace
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    T = 30
    ae, coords, rest, cond, diag, x = _still_shape(T)
    z = torch.zeros(2)
    level = float(x[:, 1].min()) + 0.002  # the lowest vertex 2 mm below the floor
    floor = ContactBarrier(len(rest), [HalfSpace((0.0, level, 0.0), (0.0, 1.0, 0.0))], 1e-3, 1.0)
    settings = with_defaults("rollout", {"contact_projection": {"enabled": True}}, "test")["contact_projection"]
    proj = ContactProjection(DecoderSubspace(ae, coords), floor, np.full(len(rest), 1e-3), 0.01, settings)
    r = stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=floor, projection=proj)
    assert r["survived"] == T and r["projected_frames"] == T
    assert r["max_penetration_own"] == pytest.approx(0.002 / diag, rel=1e-6) and r["max_penetration"] == 0
    plain = stability.survive_latent(_Linear(0.5), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=floor)
    assert plain["max_penetration"] == r["max_penetration_own"] and "projected_frames" not in plain
    bad = stability.survive_latent(_Linear(1.5, 1.0), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=floor, projection=proj)
    assert bad["survived"] == stability.survive_latent(_Linear(1.5, 1.0), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0)["survived"]


class _Recording(torch.nn.Module):
    """z_t = z_{t-1} (a shape held still), keeping every z_{t-1} it is given."""

    def __init__(self):
        super().__init__()
        self.inputs = []

    def forward(self, z1, z2, p, p1, p2):
        self.inputs.append(z1.detach().clone())
        return z1.clone()


def test_a_projection_fed_back_is_the_state_the_next_step_starts_from():
    """With ``feedback`` the projected latent is the next step's input: an integrator that holds its state
    still, started 2 mm inside a floor, is given the projected start (outside the floor) at every step and
    is never projected again (the state it holds stays out); the depth before projection is the start's,
    2 mm.  Without feedback it is given its own latent, 2 mm inside, at every step, and every frame is
    projected."""
    from latentsim.config import with_defaults
    from latentsim.latent.projection import ContactProjection
    from latentsim.latent.subspaces import DecoderSubspace
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    T = 12
    ae, coords, rest, cond, diag, x = _still_shape(T)
    z = torch.zeros(2)
    level = float(x[:, 1].min()) + 0.002
    floor = ContactBarrier(len(rest), [HalfSpace((0.0, level, 0.0), (0.0, 1.0, 0.0))], 1e-3, 1.0)
    runs = {}
    for feedback in (False, True):
        settings = with_defaults("rollout", {"contact_projection": {"enabled": True, "feedback": feedback}}, "test")["contact_projection"]
        proj = ContactProjection(DecoderSubspace(ae, coords), floor, np.full(len(rest), 1e-3), 0.01, settings)
        integ = _Recording()
        r = stability.survive_latent(integ, ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=floor, projection=proj)
        runs[feedback] = (r, torch.cat(integ.inputs))
    (plain, plain_in), (fed, fed_in) = runs[False], runs[True]
    assert plain["projected_frames"] == T and torch.equal(plain_in, torch.zeros_like(plain_in))
    assert fed["projected_frames"] == 2 and fed["max_penetration"] == 0 and plain["max_penetration"] == 0
    assert fed["max_penetration_own"] == pytest.approx(0.002 / diag, rel=1e-6) == plain["max_penetration_own"]
    assert fed["survived"] == plain["survived"] == T
    assert (fed_in - fed_in[0]).abs().max() == 0 and fed_in[0].abs().max() > 0
    with torch.no_grad():
        held = latent.decode_latents(ae, coords, fed_in[:1], torch.as_tensor(cond.dirichlet_positions[:1]))[0]
    assert float(floor.distances(held).min()) >= 0

class _Counted:
    """A fed-back projection (``ContactProjection.step``) that records the frames it is asked to correct."""

    def __init__(self, fed):
        self.fed, self.calls = fed, []

    def __call__(self, t, z):
        self.calls.append(t)
        return self.fed(t, z)

    def __getattr__(self, name):
        return getattr(self.fed, name)


def test_a_projection_fed_back_stops_at_the_first_failure_with_the_same_results(monkeypatch):
    """An exploding integrator with the projection fed back: the stress rollout and the test rollout project no frame
    past the first whose extent crosses the bound (each projection a Newton solve, slow on a diverged state), and
    report what they reported when every frame was projected (survival, depths, positions, the diverged frame)."""
    from latentsim.config import with_defaults
    import importlib

    rollout_module = importlib.import_module("latentsim.latent.rollout")  # (the package's ``rollout`` is the function)
    from latentsim.latent.projection import ContactProjection
    from latentsim.latent.subspaces import DecoderSubspace
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    T = 40
    ae, coords, rest, cond, diag, x = _still_shape(T)
    z = torch.zeros(2)
    floor = ContactBarrier(len(rest), [HalfSpace((0.0, float(x[:, 1].min()) + 0.002, 0.0), (0.0, 1.0, 0.0))], 1e-3, 1.0)
    settings = with_defaults("rollout", {"contact_projection": {"enabled": True, "feedback": True}}, "test")["contact_projection"]
    xD = torch.as_tensor(cond.dirichlet_positions)

    def both():
        proj = ContactProjection(DecoderSubspace(ae, coords), floor, np.full(len(rest), 1e-3), 0.01, settings)
        counted = [_Counted(proj.step(cond.dirichlet_positions)), _Counted(proj.step(cond.dirichlet_positions))]
        proj.step = lambda xD_: counted[0]
        r = stability.survive_latent(_Linear(1.5, 1.0), ae, coords, z, z, cond, np.array([0]), diag, max_extent=3.0, contact=floor, projection=proj)
        res = rollout_module.rollout(_Linear(1.5, 1.0), ae, coords, z, z, torch.zeros(T, 6), xD, max_extent=3.0, rest_positions=rest, correct=counted[1])
        return r, res, len(counted[0].calls), len(counted[1].calls)

    r, res, n_stress, n_test = both()
    monkeypatch.setattr(stability, "past_extent", lambda *a: False)
    monkeypatch.setattr(rollout_module, "past_extent", lambda *a: False)
    r_all, res_all, n_stress_all, n_test_all = both()
    assert 2 < r["survived"] < T - 5 and n_stress == r["survived"] + 1 and n_stress_all == T  # frames 0 ... the failure
    assert {k: v for k, v in r.items() if k != "dirichlet_error"} == {k: v for k, v in r_all.items() if k != "dirichlet_error"}
    assert np.array_equal(r["dirichlet_error"], r_all["dirichlet_error"])
    assert res["diverged_frame"] == res_all["diverged_frame"] == r["survived"] and n_test == res["diverged_frame"] + 1 and n_test_all == T
    assert torch.equal(res["positions"].nan_to_num(-1.0), res_all["positions"].nan_to_num(-1.0))
    assert torch.equal(res["latents"].nan_to_num(-1.0), res_all["latents"].nan_to_num(-1.0))


class _SpeedSensitive(torch.nn.Module):
    """Contracting while the boundary moves slowly; exploding above ``limit`` (|p_t| max-norm), and
    for good once its latent has run away (|z| > 10)."""

    def __init__(self, limit):
        super().__init__()
        self.limit = limit

    def forward(self, z1, z2, p, p1, p2):
        fast = (p.abs().amax(-1, keepdim=True) > self.limit) | (z1.abs().amax(-1, keepdim=True) > 10.0)
        return torch.where(fast, 1.5 * z1 + 1.0, 0.5 * z1)


def test_stress_test_runs_every_condition_of_the_settings_and_finds_the_one_that_breaks_a_method(program):
    """The shared stress test (rollout stage and sizing sweep): every condition of the settings runs on the
    sequence's program, and an integrator that explodes only beyond 3x the program's speed fails
    speed_x5 alone."""
    ae, coords, rest = _tiny_autoencoder()
    dt = 0.1
    xD = stability.dirichlet_trajectory(rest.numpy()[[0]], program, dt)
    x = rest.numpy()[None] + (xD - rest.numpy()[[0]])  # the shape carried rigidly by its Dirichlet vertex
    seq = {"positions": x, "dirichlet_positions": xD, "bc": program}
    settings = {"speed_factors": [0.5, 2.0, 5.0], "long_factor": 3, "perturbation": 0.1}
    limit = 3.0 * np.abs(program).max()
    out = {c.name: r for c, r in stability.stress_test(_SpeedSensitive(limit), ae, coords, seq, rest.numpy(), np.array([0]),
                                                       dt, train_frames=20, settings=settings, max_extent=3.0)}  # fmt: skip
    assert set(out) == {"long_x3", "speed_x0p5", "speed_x2", "speed_x5", "sudden_stop", "sudden_reversal", "perturbed_start"}
    assert out["long_x3"]["frames"] == 60
    failed = {name for name, r in out.items() if r["survived"] < r["frames"]}
    assert failed == {"speed_x5"}
    calm = {c.name: r for c, r in stability.stress_test(_Linear(0.5), ae, coords, seq, rest.numpy(), np.array([0]), dt,
                                                        train_frames=20, settings=settings, max_extent=3.0)}  # fmt: skip
    assert all(r["survived"] == r["frames"] for r in calm.values())
