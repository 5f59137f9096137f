"""Non-finite input to the full-space solver fails clearly, by name and value, never deep inside
the compiled kernels: a NaN material constant, time step or gravity when the potential is built
(a ValueError naming the quantity); a non-finite state or Dirichlet target, or a step whose every
initial guess has a non-finite energy (a ``NewtonFailed`` that the simulation stage turns into a
``SimulationError`` naming scene, sequence, frame and the value)."""

from __future__ import annotations

import numpy as np
import pytest

from latentsim.mesh import cloth_grid, rod_bundle
from latentsim.physics.rods import rod_topology
from latentsim.scene import build_potential
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonFailed, NewtonSettings
from latentsim.stages.simulate import SimulationError, simulate_sequence

MATERIAL = {"youngs_modulus": 1e5, "poisson_ratio": 0.35, "density": 1000.0, "radius": 1e-3, "thickness": 2e-3}
DT, GRAVITY = 0.01, [0.0, -9.81, 0.0]


def arrays_of(model):
    if model == "rods":
        X, edges, roots = rod_bundle(2, 6, 0.2, 0.05)
        return {"rest_positions": X, "edges": edges, "triples": rod_topology(2, 6)[1].numpy(), "dirichlet": roots}
    X, tris = cloth_grid(3, 3, 0.3, 0.3)
    return {"rest_positions": X, "triangles": tris, "dirichlet": np.array([0, 3])}


def solver_of(model, material=MATERIAL, dt=DT, gravity=GRAVITY):
    pot = build_potential(model, arrays_of(model), material, dt, gravity, free_only=True)
    return ImplicitEuler(pot, NewtonSettings(tolerance=1e-6, max_iterations=30))


@pytest.mark.parametrize("model", ["rods", "shell"])
@pytest.mark.parametrize(
    "change, named",
    [
        ({"material": {**MATERIAL, "youngs_modulus": float("nan")}}, "term"),
        ({"material": {**MATERIAL, "density": float("inf")}}, "the masses"),
        ({"dt": float("nan")}, "the time step dt"),
        ({"gravity": [0.0, float("nan"), 0.0]}, "gravity g"),
    ],
)
def test_a_non_finite_potential_is_refused_when_the_solver_is_built(model, change, named):
    with pytest.raises(ValueError, match="not finite") as exc:
        solver_of(model, **change)
    message = str(exc.value)
    assert named in message and ("nan" in message or "inf" in message), message


@pytest.mark.parametrize("model", ["rods", "shell"])
def test_a_healthy_step_is_unchanged(model):
    """The checks only raise: a sane step still converges, from the lowest-energy initial guess."""
    solver = solver_of(model)
    X = solver.potential.masses.new_tensor(arrays_of(model)["rest_positions"]).numpy()
    x, info = solver.step(X, X, X[solver.dirichlet])
    assert np.isfinite(x).all() and info.gradient_norm <= 1e-6 * solver.f_ref


@pytest.mark.parametrize("model", ["rods", "shell"])
@pytest.mark.parametrize("which", ["x_{t-1}", "x_{t-2}", "the Dirichlet targets"])
def test_a_non_finite_state_fails_the_step_by_name(model, which):
    solver = solver_of(model)
    X = np.asarray(arrays_of(model)["rest_positions"], dtype=np.float64)
    x1, x2, xD = X.copy(), X.copy(), X[solver.dirichlet].copy()
    {"x_{t-1}": x1, "x_{t-2}": x2, "the Dirichlet targets": xD}[which][1, 2] = np.nan
    with pytest.raises(NewtonFailed, match="non-finite input") as exc:
        solver.step(x1, x2, xD)
    assert f"{which} has 1 non-finite" in str(exc.value) and "(1, 2): nan" in str(exc.value)


def test_a_nan_constant_after_construction_is_caught_by_the_initial_guess():
    """Every initial guess then has a NaN energy: the step raises NewtonFailed naming the energies
    (it used to pass None on to the compiled kernels, a numba TypingError)."""
    solver = solver_of("rods")
    solver.assembly = _NaNEnergy(solver.assembly)
    X = np.asarray(arrays_of("rods")["rest_positions"], dtype=np.float64)
    with pytest.raises(NewtonFailed, match=r"every initial guess has a non-finite energy \(constant velocity: nan, x_\{t-1\}: nan"):
        solver.step(X, X, X[solver.dirichlet])


class _NaNEnergy:
    """A compiled assembly whose elastic energy is NaN (a NaN stiffness inside the kernels)."""

    def __init__(self, assembly):
        self.assembly = assembly

    def energy(self, x):
        return float("nan")

    def __getattr__(self, name):
        return getattr(self.assembly, name)


@pytest.mark.parametrize("model", ["rods", "shell"])
@pytest.mark.parametrize(
    "velocity, expected",
    [
        # a NaN velocity makes the Dirichlet targets NaN (it used to end in 'SVD did not converge')
        ([float("nan"), 0.0, 0.0], r"non-finite input to the step: the Dirichlet targets has \d+ non-finite"),
        # a finite but absurd velocity: every initial guess's energy overflows
        ([1e200, 0.0, 0.0], r"every initial guess has a non-finite energy \(constant velocity: (inf|nan)"),
    ],
)
def test_the_simulation_stage_names_scene_sequence_frame_and_value(model, velocity, expected):
    solver = solver_of(model)
    X = np.asarray(arrays_of(model)["rest_positions"], dtype=np.float64)
    seq = {"name": "shake", "frames": 4, "segments": [{"start": 2, "velocity": velocity}]}
    with pytest.raises(SimulationError, match=r"^scene tiny, sequence shake, frame 2: " + expected):
        simulate_sequence(solver, X, seq, DT, "scene tiny, sequence shake")
