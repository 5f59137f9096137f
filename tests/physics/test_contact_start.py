"""What the simulation stage refuses before its first frame, naming the key: a rest mesh that starts inside a
collider (the barrier is infinite there; it said "every initial guess has a non-finite energy"), and a
``contact.d_hat`` that is a large part of a mesh's size, which only the built mesh shows for a file's."""

import re

import numpy as np
import pytest
import torch

from latentsim.config import with_defaults
from latentsim.physics.colliders import HalfSpace, Sphere
from latentsim.physics.contact import ContactBarrier
from latentsim.stages.mesh import prepare_mesh
from latentsim.stages.simulate import SimulationError, simulate_scene

FLOOR = {"type": "half_space", "point": [0.0, -0.5, 0.0], "normal": [0.0, 1.0, 0.0]}


def _cloth(tmp_path, held):
    """A 0.2 m square cloth of 5 x 5 cells in the xy plane about the origin (36 vertices, 4 cm apart) as the mesh
    stage writes it, ``held`` its prescribed vertices; and the simulation stage's settings for it, without colliders."""
    mesh_h5 = tmp_path / "mesh.h5"
    mesh = with_defaults("mesh", {"generator": "cloth_grid", "nx": 5, "ny": 5, "width": 0.2, "height": 0.2, "plane": "xy"}, "test")
    prepare_mesh("cloth", "shell", mesh, with_defaults("dirichlet", {"type": "indices", "indices": held}, "test"), {}, mesh_h5)
    cfg = dict(model="shell", material={"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 200.0, "thickness": 0.001}, dt=1 / 30,
               gravity=[0, -9.81, 0], newton=dict(tolerance=1e-6), sequences=[dict(name="s", split="train", frames=3)])  # fmt: skip
    return mesh_h5, cfg


def test_penetrations_count_the_vertices_inside_or_on_each_collider():
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, -0.5, 0.0]])
    barrier = ContactBarrier(4, [HalfSpace((0, 0, 0), (0, 1, 0)), Sphere((0, 0.5, 0), 0.25)], d_hat=0.01, kappa=1.0)
    (on_floor, floor_min), (in_ball, ball_min) = barrier.penetrations(x)
    assert (on_floor, floor_min, in_ball, ball_min) == (2, -0.5, 1, -0.25)  # one on the plane, one below; the ball's centre
    assert float(barrier.energy(torch.as_tensor(x))) == float("inf")
    x[[0, 1, 3], 1] = 1.0  # all outside: none counted, a finite energy
    assert barrier.penetrations(x) == [(0, 1.0), (0, 0.25)] and np.isfinite(float(barrier.energy(torch.as_tensor(x))))


@pytest.mark.parametrize("attached", [False, True])
def test_a_collider_the_rest_mesh_starts_inside_is_named_before_any_frame(tmp_path, attached):
    """A ball about the cloth's centre holds its four middle vertices (2.8 cm from the centre, inside 5 cm) and the
    16 triangles about them (the deepest, through the centre, 5 cm + the cloth's half thickness 0.5 mm inside); the
    error names it by its index and type and counts them, static or attached to the held corner."""
    mesh_h5, cfg = _cloth(tmp_path, [29, 34, 35])
    ball = {"type": "sphere", "centre": [0.0, 0.0, 0.0], "radius": 0.05, "attached": attached}
    cfg["contact"] = {"colliders": [FLOOR, ball]}
    with pytest.raises(SimulationError, match=r"scene 'cloth': initial penetration: 20 of the rest mesh's vertices, edges or triangles lie inside or "
                                              r"on collider 1 \(sphere\) of contact\.colliders \(config key 'scenes\.cloth\.contact\.colliders\.1'; "
                                              r"deepest 0\.0505 m inside\)"):  # fmt: skip
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    assert not (tmp_path / "trajectories.h5").exists()
    # between the middle vertices: no vertex is in it, the middle cell's two triangles are, and the four that share their edges
    ball["radius"] = 0.02  # (2 cm from the centre, within 2 cm + the half thickness)
    with pytest.raises(SimulationError, match=r"initial penetration: 6 of the rest mesh's .* deepest 0\.0205 m inside"):
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    ball["centre"] = [0.0, 0.0, -0.0203]  # 0.3 mm under the mid-surface, within the half thickness: still inside
    with pytest.raises(SimulationError, match=r"deepest 0\.0002 m inside"):
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    cfg["contact"]["thickness"] = 0.0  # the mid-surface alone: outside, and it runs
    simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    assert (tmp_path / "trajectories.h5").exists()


def test_a_rest_mesh_within_its_own_self_contact_thickness_is_named_before_any_frame(tmp_path):
    """With self-contact the cloth's parts keep twice contact.thickness apart: at 2 cm (4 cm) the rest grid's nearest
    primitives sharing no vertex, 2.83 cm apart (a vertex and the cell diagonal beside it), are within it; at 5 mm it runs."""
    mesh_h5, cfg = _cloth(tmp_path, [30, 35])
    cfg["contact"] = {"colliders": [FLOOR], "self_contact": True, "thickness": 0.02}
    _refused_then_run(tmp_path, mesh_h5, cfg, r"scene 'cloth': initial self-contact: two parts of the rest mesh lie 0\.0283 m apart, within the "
                                              r"thickness 0\.04 m they keep \(config key 'scenes\.cloth\.contact\.self_contact'", "thickness", 0.005)  # fmt: skip


def _refused_then_run(tmp_path, mesh_h5, cfg, match: str, key: str, value) -> None:
    """The simulation stage refuses ``cfg`` with an error matching ``match``, writing nothing; with contact.``key`` set to
    ``value`` it runs."""
    with pytest.raises(SimulationError, match=match):
        simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    assert not (tmp_path / "trajectories.h5").exists()
    cfg["contact"][key] = value
    simulate_scene("cloth", mesh_h5, cfg, tmp_path / "trajectories.h5")
    assert (tmp_path / "trajectories.h5").exists()


def test_a_d_hat_too_large_for_the_built_mesh_stops_the_simulation(tmp_path):
    """The issue's case, 1.0 m on a 0.2 m cloth (thrown 1.75 diagonals in frame 1): above 0.05 of the rest diagonal."""
    mesh_h5, cfg = _cloth(tmp_path, [30, 35])
    cfg["contact"] = {"colliders": [FLOOR], "d_hat": 1.0}
    _refused_then_run(tmp_path, mesh_h5, cfg, rf"scene 'cloth' \({re.escape(str(mesh_h5))}\): config key 'scenes\.cloth\.contact\.d_hat': 1\.0 m is 3\.54 times the "
                                              r"rest bounding-box diagonal \(0\.283 m\).*at most 0\.05 of the diagonal \(0\.0141 m\)", "d_hat", 0.01)  # fmt: skip
