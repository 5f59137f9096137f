"""A term that depends on the step's frame (latentsim.physics.frame) reaches every solver as a term: a viscous
damping term written against the Frame alone, with no solver edit, gives a falling cloth the velocity that
linear drag gives it under implicit Euler, in the full space and in a reduced space."""

import dataclasses

import numpy as np
import pytest
import torch

from latentsim.physics.base import EnergyTerm
from latentsim.physics.frame import Frame

F64 = torch.float64


class Damping(EnergyTerm):
    """Linear viscous damping as a potential of the step, sum_i c_i / (2 dt) |x_i - x_{t-1,i}|^2: its force
    -c_i (x_i - x_{t-1,i}) / dt is the drag of the step's velocity (one vertex per stencil; derivatives by the
    base class's autograd)."""

    name = "damping"

    def __init__(self, c, x_prev=None, dt=None):
        self.c = torch.as_tensor(np.asarray(c, dtype=np.float64))
        self.stencils = torch.arange(len(self.c)).reshape(-1, 1)
        self.x_prev, self.dt = x_prev, dt

    def at(self, frame: Frame) -> "Damping":
        return Damping(self.c, torch.as_tensor(frame.x_prev, dtype=F64), frame.dt)

    def energy(self, x, frame=None):
        return (self if frame is None else self.at(frame)).element_energy(x).sum(-1)

    def local_energy(self, xe):
        d = xe[..., 0, :] - self.x_prev
        return 0.5 * self.c / self.dt * (d * d).sum(-1)


def _falling_cloth(beta):
    """A free cloth under gravity with mass-proportional damping c_i = beta m_i (every vertex the same terminal
    velocity g / beta: the cloth falls rigidly, its elastic energy zero)."""
    from latentsim.mesh import cloth_grid
    from latentsim.scene import build_potential

    X, tris = cloth_grid(3, 3, 0.2, 0.2, plane="xz")
    X = np.asarray(X, dtype=np.float64)
    arrays = {"rest_positions": X, "triangles": tris, "dirichlet": np.zeros(0, dtype=np.int64)}
    material = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}
    pot = build_potential("shell", arrays, material, 1 / 60, [0, -9.81, 0], free_only=True)
    return X, dataclasses.replace(pot, extra_terms=[Damping(beta * pot.masses.numpy())])


def _drag_velocity(beta, dt, steps, g=-9.81):
    """Implicit Euler's vertical velocity of a body under gravity and linear drag from rest:
    v_t = (v_{t-1} + dt g) / (1 + beta dt)."""
    v = [0.0]
    for _ in range(steps):
        v.append((v[-1] + dt * g) / (1 + beta * dt))
    return np.array(v[1:])


def test_a_damping_term_of_the_frame_gives_a_falling_cloth_implicit_eulers_drag_in_the_full_space():
    from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings

    beta, steps = 5.0, 30
    X, pot = _falling_cloth(beta)
    solver = ImplicitEuler(pot, NewtonSettings(tolerance=1e-10))
    assert not solver.limits_steps  # no term bounds the line search
    dt = float(pot.dt)
    x2 = x1 = X.copy()
    velocities = []
    for _ in range(steps):
        x, _ = solver.step(x1, x2, np.zeros((0, 3)))
        # the potential's own path (energy(x, frame), autograd) has its minimum there too
        xt = torch.as_tensor(x).requires_grad_(True)
        (g,) = torch.autograd.grad(pot(xt, torch.as_tensor(x1), torch.as_tensor(x2)), xt)
        assert float(g.norm()) <= 1.5e-10 * solver.f_ref
        velocities.append((x - x1) / dt)
        x2, x1 = x1, x
    v = np.stack(velocities)  # (steps, n, 3)
    want = _drag_velocity(beta, dt, steps)
    assert np.allclose(v[..., 1], want[:, None], rtol=1e-7, atol=1e-12) and np.abs(v[..., [0, 2]]).max() < 1e-9
    # towards the terminal velocity g / beta, well short of free fall's g t
    assert 0.85 * 9.81 / beta < -v[-1, 0, 1] < 9.81 / beta < 9.81 * steps * dt


def test_the_same_damping_term_in_a_reduced_space():
    """A reduced solver over the cloth's rigid translations: the same velocities as the full space's."""
    from latentsim.solve.reduced import ReducedSettings, reduced_rollout

    beta, steps = 5.0, 12
    X, pot = _falling_cloth(beta)

    class Translations:
        dim, hard_dirichlet, dirichlet, linear = 3, True, np.zeros(0, dtype=np.int64), True
        n_vertices = len(X)
        J = np.tile(np.eye(3), (len(X), 1))

        def map(self, q, xD):
            return X + np.asarray(q)[None, :]

        def jacobian(self, q, xD):
            return self.map(q, xD), self.J

    out = reduced_rollout(Translations(), pot, np.zeros(3), np.zeros(3), np.zeros((steps + 2, 0, 3)), ReducedSettings(tolerance=1e-10))
    assert out["diverged_frame"] == -1
    v = np.diff(out["latents"][:, 1]) / float(pot.dt)
    assert v[1:] == pytest.approx(_drag_velocity(beta, float(pot.dt), steps), rel=1e-7)
