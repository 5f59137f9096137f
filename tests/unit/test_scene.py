"""The boundary-condition program: piecewise-constant rigid motion of the Dirichlet set."""

import numpy as np
import pytest
import torch

from latentsim.mesh import beam_tets, cloth_grid, rod_bundle
from latentsim.physics.incremental_potential import ElasticPotential, IncrementalPotential
from latentsim.physics.rods import rod_topology
from latentsim.scene import bc_parameters, build_elastic, build_potential, dirichlet_trajectory


def test_constant_translation_moves_by_v_dt_per_frame():
    seq = {"segments": [{"start": 0, "velocity": [0.3, 0.0, 0.0]}]}
    p = bc_parameters(seq, 11)
    assert np.all(p[0] == 0)
    assert np.allclose(p[1:, :3], [0.3, 0, 0]) and np.all(p[:, 3:] == 0)
    rest = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    xD = dirichlet_trajectory(rest, p, 0.1)
    assert np.allclose(xD[10] - rest, [0.3 * 0.1 * 10, 0, 0])


def test_reverse_every_flips_sign_and_returns_to_start():
    seq = {"reverse_every": 5, "segments": [{"velocity": [1.0, 0, 0]}]}
    p = bc_parameters(seq, 11)
    assert np.allclose(p[1:6, 0], 1.0) and np.allclose(p[6:11, 0], -1.0)
    xD = dirichlet_trajectory(np.zeros((1, 3)), p, 0.1)
    assert np.allclose(xD[5, 0, 0], 0.5) and np.allclose(xD[10], 0.0)


def test_segments_switch_at_their_start_frame():
    seq = {"segments": [{"start": 0, "velocity": [1.0, 0, 0]}, {"start": 4, "velocity": [0, 2.0, 0]}]}
    p = bc_parameters(seq, 6)
    assert np.allclose(p[3, :3], [1, 0, 0]) and np.allclose(p[4, :3], [0, 2, 0])


def test_rotation_is_rigid_and_about_the_centroid():
    rest = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    w = np.pi / 2  # a quarter turn per second about +y
    p = bc_parameters({"segments": [{"angular_velocity": [0, w, 0]}]}, 11)
    xD = dirichlet_trajectory(rest, p, 0.1)
    # after 1 s a quarter turn: (1,0,0) -> (0,0,-1) for a rotation about +y
    assert np.allclose(xD[10][0], [0, 0, -1.0], atol=1e-12)
    for t in range(11):
        d = np.linalg.norm(xD[t][:, None] - xD[t][None], axis=-1)
        assert np.allclose(d, np.linalg.norm(rest[:, None] - rest[None], axis=-1))
        assert np.allclose(xD[t].mean(0), 0.0)


MATERIAL = {"youngs_modulus": 1e5, "poisson_ratio": 0.35, "density": 1000.0, "radius": 1e-3, "thickness": 2e-3}


def scene_arrays(model):
    if model == "tets":
        X, T = beam_tets(3, 2, 2, 0.3, 0.1, 0.1, tets_per_cell=6)
        return {"rest_positions": X, "tets": T, "dirichlet": np.flatnonzero(X[:, 0] < 1e-9)}
    if model == "rods":
        X, edges, roots = rod_bundle(2, 6, 0.2, 0.05)
        return {"rest_positions": X, "edges": edges, "triples": rod_topology(2, 6)[1].numpy(), "dirichlet": roots}
    X, tris = cloth_grid(3, 3, 0.3, 0.3)
    return {"rest_positions": X, "triangles": tris, "dirichlet": np.array([0, 3])}


@pytest.mark.parametrize("model", ["tets", "rods", "shell"])
@pytest.mark.parametrize("free_only", [False, True])
def test_elastic_potential_is_the_incremental_potentials_elastic_part(model, free_only):
    """build_elastic: the terms, masses and Dirichlet set of build_potential, no time step; the
    same elastic energy, and the incremental potential adds inertia and gravity to it."""
    arrays = scene_arrays(model)
    el = build_elastic(model, arrays, MATERIAL, free_only=free_only)
    pot = build_potential(model, arrays, MATERIAL, 0.01, [0.0, -9.81, 0.0], free_only=free_only)
    assert type(el) is ElasticPotential and isinstance(pot, IncrementalPotential) and not hasattr(el, "dt")
    assert [t.name for t in el.terms] == [t.name for t in pot.terms]
    assert all(torch.equal(a.stencils, b.stencils) for a, b in zip(el.terms, pot.terms))
    assert torch.equal(el.masses, pot.masses) and torch.equal(el.dirichlet, pot.dirichlet)
    assert el.n_vertices == len(arrays["rest_positions"])
    X = torch.as_tensor(np.asarray(arrays["rest_positions"], dtype=np.float64))
    x = X + 0.01 * torch.randn(X.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    e = el.elastic(x)
    assert e > 0 and torch.equal(e, pot.elastic(x))
    assert torch.allclose(pot(x, X, X, penalty=False), e + 0.5 / 0.01**2 * (pot.masses * ((x - X) ** 2).sum(-1)).sum()
                          + 9.81 * (pot.masses * x[:, 1]).sum(), rtol=1e-12)  # fmt: skip


def test_every_material_is_one_entry_of_the_registry():
    """The materials each model offers, their energies in words and their optional keys come from
    physics.materials alone."""
    from latentsim.physics.materials import MATERIALS, materials_of
    from latentsim.physics.materials import energy_description, material_model

    assert {m: materials_of(m) for m in ("rods", "shell", "tets")} == {
        "rods": ("stvk",), "shell": ("stvk", "stvk_nm"), "tets": ("stvk", "stvk_nm", "neohookean")}  # fmt: skip
    mat = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "thickness": 1e-3, "radius": 1e-3}
    for name, kinds in MATERIALS.items():
        for model, entry in kinds.items():
            assert energy_description(model, {**mat, "model": name}).startswith(entry.description)
    assert material_model("shell", {**mat, "model": "stvk_nm", "bending_stiffness": 1.0}) == "stvk_nm"
    with pytest.raises(ValueError, match="material.bending_stiffness applies to model 'shell' with material.model 'stvk_nm' only"):
        material_model("tets", {**mat, "model": "stvk_nm", "bending_stiffness": 1.0})
    with pytest.raises(ValueError, match="model 'plates': use one of rods, shell, tets"):
        material_model("plates", mat)
