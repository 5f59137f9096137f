"""Neural Modes conditioned on a sheet's aspect ratio (Wang et al. 2024, Sec. 4.3, Fig. A2).

- Geometry: the stretch reaches the asked edge ratio and keeps every triangle's area; the folding
  direction of analytic bending fields is their angle.
- Mode family: every tracked mode is an eigenvector of its own ratio's stiffness, and neighbouring
  ratios' modes overlap (tracking), the first mode's fold turning towards the diagonal at 1:1.
- The conditioned network: one MLP shared by every ratio, lower energy than the linear modes at the
  training ratios, and the ratio input is used (told another ratio, the energy rises).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from latentsim import neural_modes as nm
from latentsim.neural_modes import aspect as nm_aspect
from latentsim.latent import save_module
from latentsim.mesh import cloth_grid
from latentsim.solve.modes import stiffness_matrix

ONE_THREAD = True  # tiny networks (conftest)
MATERIAL = {"youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 1000.0, "thickness": 0.003}


def sheet(cells=6, width=0.2):
    V, F = cloth_grid(cells, cells, width, width)
    return {"rest_positions": V, "triangles": F, "dirichlet": np.zeros(0, dtype=np.int64)}


def areas(X, F):
    return 0.5 * np.linalg.norm(np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]]), axis=1)


@pytest.mark.parametrize("ratio", [1.0, 1.37, 2.0, 0.5])
def test_stretch_reaches_the_ratio_and_keeps_areas(ratio):
    arrays = sheet()
    X, F = arrays["rest_positions"], arrays["triangles"]
    Y = nm_aspect.stretched(X, ratio)
    long, short, normal = nm_aspect.sheet_axes(X)
    ext = np.ptp(Y, axis=0)
    assert ext[long] / ext[short] == pytest.approx(ratio, rel=1e-12)
    assert np.allclose(areas(Y, F), areas(X, F), rtol=1e-12)
    assert np.allclose(Y.mean(0), X.mean(0)) and np.array_equal(Y[:, normal], X[:, normal])


def test_stretch_names_a_sheet_that_is_not_flat():
    X = np.random.default_rng(0).random((20, 3))
    with pytest.raises(ValueError, match="flat sheet"):
        nm_aspect.stretched(X, 2.0)


@pytest.mark.parametrize("theta", [0.0, 17.0, 45.0, 63.0, 90.0])
def test_fold_angle_of_a_bending_field_is_its_angle(theta):
    X = nm_aspect.stretched(sheet(10)["rest_positions"], 1.6)
    long, short, normal = nm_aspect.sheet_axes(X)
    P = X - X.mean(0)
    t = np.radians(theta)
    s = np.cos(t) * P[:, long] + np.sin(t) * P[:, short]
    u = np.zeros_like(X)
    u[:, normal] = s * s + 0.3 * P[:, long] + 0.01  # bending across direction theta, plus a tilt and a lift
    assert nm_aspect.fold_angle(X, u) == pytest.approx(theta, abs=1e-6)
    u[:, normal] = P[:, long] * P[:, short]  # a twist: curvatures +-1/2 along the diagonals
    assert nm_aspect.fold_angle(X, u) == pytest.approx(45.0, abs=1e-6)


@pytest.fixture(scope="module")
def family():
    arrays = sheet()
    ratios = np.linspace(1.0, 2.0, 6)
    return arrays, nm_aspect.mode_family(arrays, "shell", MATERIAL, ratios, 4, "free", "euclidean")


def test_family_modes_are_each_ratios_eigenvectors_and_tracked(family):
    arrays, fam = family
    for k in range(len(fam.ratios)):
        pot = nm_aspect.ratio_potential(arrays, "shell", MATERIAL, fam.X[k])
        K, _ = stiffness_matrix(pot, fam.X[k], np.arange(3 * len(fam.X[k])))
        m3 = np.repeat(pot.masses.numpy(), 3)
        E = fam.modes[k]
        r = K @ E - (m3[:, None] * E) * fam.omega2[k]
        assert np.linalg.norm(r, axis=0).max() < 1e-6 * np.linalg.norm(K @ E, axis=0).max()
        assert np.all(np.abs(fam.rigid[k].T @ (m3[:, None] * E)) < 1e-8)  # off the ratio's own rigid modes
    assert fam.overlap.min() > 0.8
    unit = fam.modes / np.linalg.norm(fam.modes, axis=1, keepdims=True)
    for k in range(len(fam.ratios) - 1):  # each mode overlaps most with itself at the neighbouring ratio
        cos = np.abs(unit[k].T @ unit[k + 1])
        assert np.array_equal(cos.argmax(1), np.arange(4))
    folds = [nm_aspect.fold_angle(fam.X[k], fam.modes[k][:, 0].reshape(-1, 3)) for k in range(len(fam.ratios))]
    assert folds[0] > 35 and folds[-1] < 15  # the first mode folds nearer the diagonal at 1:1 than at 2:1
    assert np.all(np.diff(folds) < 0)


def test_conditioned_network_uses_its_ratio_and_beats_linear_modes(family, tmp_path):
    arrays, fam = family
    cfg = {"modes": 4, "widths": [32, 32], "box": 0.5, "orthogonality": "exact", "lam": 1e5, "eta": 1e5, "lbfgs_max_iter": 10}
    torch.manual_seed(0)
    model = nm_aspect.RatioConditionedModes.build(fam, cfg, arrays["triangles"], symmetric=False)
    assert len(list(model.parameters())) == len(list(model.member(0).mlp.parameters()))  # one MLP for every ratio
    train = [0, len(fam.ratios) - 1]
    pots = {k: nm_aspect.ratio_potential(arrays, "shell", MATERIAL, fam.X[k]) for k in range(len(fam.ratios))}
    hist = nm_aspect.train_family(model, {k: pots[k] for k in train}, cfg, batch_size=32, epochs=8, seed=0)
    assert hist["energy"][-1] < 0.8 * hist["energy"][0]
    z = nm.modal_samples("stochastic", 4, cfg["box"], 16, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        for k in train:
            e_nm = pots[k].elastic(model(z, k)).mean()
            e_lin = pots[k].elastic((model.member(k).X + model.member(k).linear(z)).reshape(len(z), -1, 3)).mean()
            e_far = pots[k].elastic(model(z, k, ratio=fam.ratios[train[1] if k == train[0] else train[0]])).mean()
            assert e_nm < 0.8 * e_lin, k
            assert e_far > 1.05 * e_nm, k  # equal if the network ignored its ratio
            assert torch.allclose(model(torch.zeros(1, 4), k)[0], model.member(k).X.reshape(-1, 3), atol=1e-12)  # n(0) = X(r)
    save_module(tmp_path / "model.pt", model)
    again = nm_aspect.load_family_model(tmp_path / "model.pt")
    with torch.no_grad():
        assert torch.equal(again(z, 2), model(z, 2))
    again.member(0).mlp[0].weight.data += 1.0  # still one shared MLP after loading
    assert torch.equal(again.member(3).mlp[0].weight, again.member(0).mlp[0].weight)
