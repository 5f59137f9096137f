"""The contact projection of a latent rollout's frames (latentsim.latent.projection): a frame inside a collider
comes out to the surface, no further than the barrier's reach, by the least motion its subspace allows."""

import numpy as np
import pytest
import torch

from latentsim.config import with_defaults
from latentsim.latent.projection import ContactProjection
from latentsim.physics.colliders import Sphere
from latentsim.physics.contact import ContactBarrier


class _Lift:
    """x = X0 + q0 e_z + q1 (0, 0, |X0_xy|^2): a sheet lifted and cupped (linear in q, no curvature)."""

    def __init__(self, X0):
        self.X0 = X0
        self.J = np.zeros((len(X0), 3, 2))
        self.J[:, 2, 0] = 1.0
        self.J[:, 2, 1] = (X0[:, :2] ** 2).sum(-1)
        self.J = self.J.reshape(-1, 2)

    def map(self, q, xD):
        return self.X0 + (self.J @ np.asarray(q, dtype=np.float64)).reshape(-1, 3)

    def jacobian(self, q, xD):
        return self.map(q, xD), self.J


def _sheet():
    g = np.linspace(-0.1, 0.1, 9)
    return np.array([(a, b, 0.0) for a in g for b in g])


def _projection(settings=None):
    X0 = _sheet()
    ball = ContactBarrier(len(X0), [Sphere((0.0, 0.0, -0.5), 0.52)], d_hat=1e-3, kappa=1.0)  # the sheet's middle 2 cm inside
    cfg = with_defaults("rollout", {"contact_projection": {"enabled": True, **(settings or {})}}, "test")["contact_projection"]
    return ContactProjection(_Lift(X0), ball, np.full(len(X0), 1e-3), 0.01, cfg), X0, ball


def test_a_frame_inside_the_ball_comes_out_to_its_surface_and_no_further_than_the_barriers_reach():
    proj, X0, ball = _projection()
    xD = np.zeros((0, 3))
    assert float(ball.distances(torch.as_tensor(X0)).min()) == pytest.approx(-0.02, abs=1e-9)
    q, x, iterations = proj.project(np.zeros(2), X0, xD)
    d = ball.distances(torch.as_tensor(x)).numpy()
    assert d.min() >= 0 and d.min() <= proj.barrier.d_hat  # outside, within the reach of the barrier (1 cm)
    assert iterations > 0 and np.allclose(x, proj.subspace.map(q, xD))
    # a minimum of the projection's objective (the mass-weighted distance plus the barrier it ended with)
    barrier = proj.barrier.extended(proj.barrier.extend_below / proj.barrier.d_hat, 1.0, 10.0 ** _level(proj, q, ball))
    f = lambda v: 0.5 * float((proj.weights * ((proj.subspace.map(v, xD) - X0) ** 2).sum(-1)).sum()) + float(barrier.energy(torch.as_tensor(proj.subspace.map(v, xD))))
    for dv in np.vstack([np.eye(2), -np.eye(2)]) * 1e-4:
        assert f(q) <= f(q + dv)
    assert q[1] < 0  # it cups over the ball (the least motion) rather than lifting the whole sheet


def _level(proj, q, ball):
    """The stiffening level the projection stopped at: the first whose barrier's minimum is where q is."""
    x, J = proj.subspace.jacobian(q, None)
    pull = J.T @ (proj.weights[:, None] * (x - proj.subspace.X0)).reshape(-1)  # the mass term's part of the gradient
    for level in range(proj.stiffening + 1):
        b = proj.barrier.extended(proj.barrier.extend_below / proj.barrier.d_hat, 1.0, 10.0**level)
        if np.abs(pull + J.T @ _grad(b, x).reshape(-1)).max() < 1e-3 * np.abs(pull).max():
            return level
    raise AssertionError("no level's gradient vanishes at the projection")


def _grad(barrier, x):
    xt = torch.as_tensor(x).requires_grad_(True)
    return torch.autograd.grad(barrier.energy(xt), xt)[0].numpy()

def test_a_soft_barrier_alone_stops_inside_and_stiffening_brings_the_frame_out():
    soft, X0, ball = _projection({"barrier_kappa": 1e-4, "stiffening": 0})
    _, x, _ = soft.project(np.zeros(2), X0, np.zeros((0, 3)))
    assert float(ball.distances(torch.as_tensor(x)).min()) < 0  # the mass term outweighs the barrier
    stiff, _, _ = _projection({"barrier_kappa": 1e-4, "stiffening": 5})
    _, x, _ = stiff.project(np.zeros(2), X0, np.zeros((0, 3)))
    assert float(ball.distances(torch.as_tensor(x)).min()) >= 0


def test_a_rollouts_frames_are_projected_only_where_they_come_near_a_collider():
    proj, X0, ball = _projection()
    frames = np.stack([X0 + [0.0, 0.0, 0.1], X0, X0 + [0.0, 0.0, 0.05], X0 + [0.0, 0.0, np.nan]])
    out = proj.frames(np.zeros((4, 2)), frames, np.zeros((4, 0, 3)))
    assert out["projected"].tolist() == [False, True, False, False] and out["iterations"][1] > 0
    assert np.array_equal(out["positions"][[0, 2]], frames[[0, 2]]) and np.array_equal(out["positions"][3], frames[3], equal_nan=True)
    assert float(ball.distances(torch.as_tensor(out["positions"][1])).min()) >= 0
