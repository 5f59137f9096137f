"""The conditioned integrator: one network for a range of time steps and moduli
(latentsim.latent.conditioning), its loss at each sample's condition, and the condition's scene."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from latentsim.config import ConfigError, condition_name, conditioned_autoencoder_settings, conditions, validate_config
from latentsim.latent.autoencoder import Autoencoder, decode_latents
from latentsim.latent.batch import Triplets
from latentsim.latent.conditioning import AtCondition, Conditioning, scaled_sequence, with_condition
from latentsim.latent.coordinates import RelativeCoordinates
from latentsim.latent.data import build_triplets
from latentsim.latent.integrator import LatentIntegrator
from latentsim.latent.training import fit_integrator
from latentsim.scene import bc_parameters, build_potential, dirichlet_step, dirichlet_trajectory
from latentsim.stages.conditioning import condition_sim_config, frame_rate_rows

sys.path.insert(0, str(Path(__file__).parent))
from test_latent import F64, Chain  # noqa: E402  (the spring chain with its exact implicit-Euler step)
from test_scene import MATERIAL, scene_arrays  # noqa: E402


def test_dirichlet_step_is_one_step_of_the_boundary_condition_program():
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(5, 3))
    p = bc_parameters({"segments": [{"velocity": [0.3, -0.1, 0.2], "angular_velocity": [0.5, 2.0, -1.0]}, {"start": 4, "velocity": [0, 0, 0]}]}, 8)
    for dt in (0.01, 0.1):
        xD = dirichlet_trajectory(rest, p, dt)
        step = dirichlet_step(torch.as_tensor(xD[:-1]), torch.as_tensor(p[1:]), torch.full((7,), dt)).numpy()
        assert np.allclose(step, xD[1:], atol=1e-13)
    # per-sample time steps: each row at its own
    h = torch.tensor([0.01, 0.05])
    both = dirichlet_step(torch.as_tensor(np.stack([rest, rest])), torch.as_tensor(p[[1, 1]]), h).numpy()
    for i, dt in enumerate((0.01, 0.05)):
        assert np.allclose(both[i], dirichlet_trajectory(rest, p[:2], dt)[1], atol=1e-13)


MODELS = [("rods", {}), ("shell", {}), ("shell", {"model": "stvk_nm"}), ("tets", {}), ("tets", {"model": "neohookean"}), ("tets", {"model": "stvk_nm"})]


@pytest.mark.parametrize("model,law", MODELS, ids=[f"{m}-{law.get('model', 'stvk')}" for m, law in MODELS])
def test_the_potential_at_a_condition_is_the_potential_built_there(model, law):
    """Every elastic term is linear in Young's modulus at a fixed Poisson ratio: the scene's potential
    with a per-sample time step and elastic factor E / E_0 is the potential built at (h, E)."""
    arrays = scene_arrays(model)
    X = torch.as_tensor(arrays["rest_positions"], dtype=F64)
    g = torch.Generator().manual_seed(1)
    x = X + 0.02 * torch.randn((3,) + X.shape, generator=g, dtype=F64)
    x1, x2 = X + 0.01 * torch.randn(X.shape, generator=g, dtype=F64), X.clone()
    material = {**MATERIAL, **law}
    base = build_potential(model, arrays, material, 1 / 30, [0, -9.81, 0])
    h, E = torch.tensor([1 / 60, 1 / 30, 1 / 15], dtype=F64), torch.tensor([3e4, 1e5, 1e6], dtype=F64)
    got = base(x, x1, x2, dt=h, stiffness=E / material["youngs_modulus"])
    for i in range(3):
        there = build_potential(model, arrays, {**material, "youngs_modulus": float(E[i])}, float(h[i]), [0, -9.81, 0])
        want = there(x[i], x1, x2)
        assert torch.allclose(got[i], want, rtol=1e-12), (i, float(got[i]), float(want))
    # and the elastic part alone scales: zero at rest, ten times at ten times the modulus
    assert float(base(X, X, X, stiffness=10.0) - base(X, X, X)) == pytest.approx(0.0, abs=1e-9)


def test_normalise_sample_and_contain():
    box = Conditioning((1 / 60, 1 / 15), (3e5, 3e6), 1 / 30, 1e6)
    c = box.normalise(torch.tensor([1 / 60, 1 / 15, 1 / 30]), torch.tensor([3e5, 3e6, math.sqrt(9e11)]))
    assert torch.allclose(c, torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0]]), atol=1e-6)
    h, E = box.sample(1000, torch.Generator().manual_seed(0))
    assert all(box.contains(float(a), float(b)) for a, b in zip(h, E))
    assert float(h.min()) < 1 / 55 and float(h.max()) > 1 / 16  # spread over the box, log-uniformly
    assert not box.contains(1 / 100, 1e6) and box.conditioned
    point = Conditioning.at(1 / 30, 1e6, 1 / 30, 1e6)
    assert not point.conditioned and torch.equal(point.normalise(1 / 30, 1e6), torch.zeros(2))
    assert Conditioning.from_dict(box.to_dict()) == box
    # the loss weight (h / h_0)^p: the schema's p = 2 evens out the inertia term, p = 0 weighs time steps alike
    h = torch.tensor([1 / 60, 1 / 30, 1 / 15], dtype=torch.float64)
    assert torch.allclose(box.weight(h), torch.tensor([0.25, 1.0, 4.0], dtype=torch.float64))
    flat = Conditioning((1 / 60, 1 / 15), (3e5, 3e6), 1 / 30, 1e6, time_step_weight_power=0.0)
    assert torch.equal(flat.weight(h), torch.ones(3, dtype=torch.float64)) and Conditioning.from_dict(flat.to_dict()) == flat
    old = {k: v for k, v in box.to_dict().items() if k != "time_step_weight_power"}  # a file from before the setting
    assert Conditioning.from_dict(old).time_step_weight_power == 2.0
    with pytest.raises(ValueError, match="time_step"):
        Conditioning((0.1, 0.01), (1.0, 2.0), 0.1, 1.0)


def test_at_condition_appends_the_condition_to_every_boundary_condition_vector():
    torch.manual_seed(0)
    net = LatentIntegrator(3, 6 + 2, [8]).eval()
    c = torch.tensor([0.25, -0.5])
    z1, z2, p, p1, p2 = (torch.randn(4, k) for k in (3, 3, 6, 6, 6))
    wrapped = AtCondition(net, c)
    want = net(z1, z2, with_condition(p, c), with_condition(p1, c), with_condition(p2, c))
    assert torch.equal(wrapped(z1, z2, p, p1, p2), want) and wrapped.bc_dim == 6
    assert not torch.equal(AtCondition(net, -c)(z1, z2, p, p1, p2), want)


@pytest.mark.parametrize("k", [2, 0.5])
def test_a_scaled_sequence_is_the_same_motion_in_physical_time(k):
    seq = {"name": "s", "frames": 41, "train_frames": 21, "reverse_every": 10,
           "segments": [{"start": 0, "velocity": [0.2, 0, 0]}, {"start": 11, "angular_velocity": [0, 1.0, 0]}, {"start": 31, "velocity": [0, -0.3, 0]}]}  # fmt: skip
    dt = 0.04
    s = scaled_sequence(seq, k)
    assert s["frames"] == round(40 * k) + 1 and s["train_frames"] == round(20 * k) + 1
    rest = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0, 0.1]])
    coarse = dirichlet_trajectory(rest, bc_parameters(seq, seq["frames"]), dt)
    fine = dirichlet_trajectory(rest, bc_parameters(s, s["frames"]), dt / k)
    if k > 1:  # every k-th fine frame is a coarse frame
        assert np.allclose(fine[:: int(k)], coarse, atol=1e-12)
    else:  # every 1/k-th coarse frame is a fine frame
        assert np.allclose(coarse[:: int(1 / k)], fine, atol=1e-12)


SIM = {"model": "shell", "material": {"youngs_modulus": 1e5}, "dt": 1 / 30, "gravity": [0, -9.81, 0], "newton": {},
       "sequences": [{"name": "a", "split": "test", "frames": 61, "train_frames": 41, "segments": [{"start": 21, "velocity": [0, 0, 1.0]}]},
                     {"name": "b", "split": "train", "frames": 31}]}  # fmt: skip


def test_the_scene_at_a_condition():
    train = condition_sim_config(SIM, {"time_step": 1 / 60, "youngs_modulus": 3e4, "split": "train"})
    assert train["dt"] == 1 / 60 and train["material"]["youngs_modulus"] == 3e4 and SIM["material"]["youngs_modulus"] == 1e5
    assert [(q["name"], q["split"], q["frames"]) for q in train["sequences"]] == [("a", "train", 81), ("b", "train", 61)]
    assert train["sequences"][0]["segments"][0]["start"] == 41 and "train_frames" not in train["sequences"][0]
    test = condition_sim_config(SIM, {"time_step": 1 / 15, "youngs_modulus": 3e5, "split": "test"})
    assert [(q["name"], q["split"], q["frames"], q["train_frames"]) for q in test["sequences"]] == [("a", "test", 31, 21)]


def _scene(**conditioning):
    return {"seeds": [0], "scenes": {"s": {"model": "shell", "mesh": {"generator": "cloth_grid"}, "material": {"thickness": 0.001},
            "sequences": [{"name": "a", "split": "test", "frames": 20, "train_frames": 10}], "conditioning": conditioning}}}  # fmt: skip


def test_the_config_names_the_conditions_and_refuses_what_cannot_be_held_out():
    box = {"time_step": [1 / 60, 1 / 15], "youngs_modulus": [1e5, 1e6]}
    cfg = validate_config(_scene(**box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}]))
    c = conditions(cfg, "s")
    assert [(n, q["split"]) for n, q in c.items()] == [
        ("60hz_1e05pa", "train"), ("60hz_1e06pa", "train"), ("15hz_1e05pa", "train"), ("15hz_1e06pa", "train"), ("30hz_3e05pa", "test")]  # fmt: skip
    assert condition_name(1 / 45, 5.5e5) == "45hz_5p5e05pa"
    # its own autoencoder size (the box holds more deformation than one condition), the scene's other settings
    wider = validate_config(_scene(**box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}], autoencoder={"latent_dim": 6}))
    assert conditioned_autoencoder_settings(wider, "s")["latent_dim"] == 6
    assert conditioned_autoencoder_settings(wider, "s")["epochs"] == wider["scenes"]["s"]["autoencoder"]["epochs"]
    assert conditioned_autoencoder_settings(cfg, "s") == cfg["scenes"]["s"]["autoencoder"]
    for bad, match in [
        (dict(box, test=[{"time_step": 1 / 100, "youngs_modulus": 3e5}]), "outside the box"),
        (dict(box, test=[{"time_step": 1 / 60, "youngs_modulus": 1e6}]), "is a training condition"),
        (dict(box, time_step=[1 / 15, 1 / 60], test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}]), r"conditioning.time_step.*lo <= hi"),
        (dict(box), "conditioning.test"),
        (dict(box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}], integrator={"mode": "supervised"}), "incremental potential alone"),
        (dict(box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}], integrator={"origin_input": True}),
         r"'scenes\.s\.conditioning\.integrator' \(or '\.conditioned'\): origin_input is not for a conditioned integrator"),
        (dict(box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}], conditioned={"own_rollouts_every": 2, "own_rollouts_speeds": [1.0, 2.0]}),
         r"'scenes\.s\.conditioning\.integrator\.own_rollouts_speeds'.*is not for a conditioned integrator"),
    ]:
        with pytest.raises(ConfigError, match=match):
            validate_config(_scene(**bad))
    kb = _scene(**box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}])
    kb["scenes"]["s"]["material"].update(model="stvk_nm", bending_stiffness=1e-3)
    with pytest.raises(ConfigError, match="bending_stiffness"):
        validate_config(kb)
    turning = _scene(**box, test=[{"time_step": 1 / 30, "youngs_modulus": 3e5}])
    turning["scenes"]["s"]["autoencoder"] = {"rigid_frame": True}
    with pytest.raises(ConfigError, match=r"'scenes\.s\.autoencoder\.rigid_frame': not for a conditioned scene"):
        validate_config(turning)


def test_frame_rate_rows_compare_the_shared_times():
    rng = np.random.default_rng(0)
    truth_fine = rng.normal(size=(9, 4, 3))
    truth_coarse = truth_fine[::2] + 0.01
    kept = {("30hz", "a"): (1 / 30, 1e6, truth_coarse + 0.02, truth_coarse, 1.0), ("60hz", "a"): (1 / 60, 1e6, truth_fine, truth_fine, 1.0),
            ("60hz_soft", "a"): (1 / 60, 5e5, truth_fine, truth_fine, 1.0)}  # fmt: skip
    rows = frame_rate_rows(kept, seed=3)
    assert len(rows) == 1 and rows[0]["coarse"] == "30hz" and rows[0]["fine"] == "60hz" and rows[0]["shared_frames"] == 5
    r = rows[0]
    assert r["fine_error"] == 0.0 and r["coarse_error"] == pytest.approx(0.02 * math.sqrt(3))
    assert r["full_space_gap"] == pytest.approx(0.01 * math.sqrt(3)) and r["rollout_gap"] == pytest.approx(0.03 * math.sqrt(3))


def _six(seq):
    """A chain sequence with the root's x-velocity as the first of six BC entries (v, w)."""
    return {**seq, "bc": torch.cat([seq["bc"], torch.zeros(len(seq["bc"]), 5, dtype=F64)], 1)}


def test_the_conditioned_integrator_learns_the_step_at_each_condition():
    """Trained on states of one time step, with the loss at conditions drawn from a box of time steps
    and stiffnesses, the network's one-step prediction at a condition is that condition's exact
    implicit-Euler step, and far from it when it is told another condition."""
    ch = Chain()
    seqs = [_six(ch.simulate(a, f)) for a, f in [(0.5, 1.0), (-0.8, 0.7), (1.0, 1.5)]]
    coords = RelativeCoordinates(ch.n, [0], "roots", root_of=[0] * ch.n)
    ae = Autoencoder(coords.dim, coords.dim, [16], pca_dim=coords.dim)  # an exact linear bijection (latent = full dim)
    ae.init_pca(torch.cat([coords.encode(s["positions"], s["dirichlet_positions"]) for s in seqs]))
    ae.eval()
    box = Conditioning((1 / 60, 1 / 15), (0.5, 2.0), ch.pot.dt, 1.0)
    cfg = dict(widths=[64, 64], epochs=300, lr=3e-3, batch_size=32, noise_scale=0.1, balancing=True)
    integ, hist = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=0, conditioning=box)
    assert integ.bc_dim == 8 and hist["loss"][-1] < hist["loss"][0]
    tr = build_triplets(ae, coords, [_six(ch.simulate(0.7, 1.2))])  # a motion not trained on

    def error(told, true):
        xD = dirichlet_step(tr["xD_prev"], tr["p"], true[0])
        with torch.no_grad():
            z = AtCondition(integ, box.normalise(*told))(tr["z_prev"], tr["z_prev2"], tr["p"], tr["p_prev"], tr["p_prev2"])
            x, x1 = decode_latents(ae, coords, z, xD), decode_latents(ae, coords, tr["z_prev"], tr["xD_prev"])
            x2 = decode_latents(ae, coords, tr["z_prev2"], tr["xD_prev2"])
        exact = ch.exact_step(x1, x2, xD, *true)
        return float((x - exact).norm(dim=-1).mean() / (exact - x1).norm(dim=-1).mean())

    corners = [(1 / 60, 0.5), (1 / 15, 2.0), (1 / 25, 1.0)]  # two corners and a condition inside
    for true in corners:
        right = error(true, true)
        wrong = min(error(told, true) for told in corners if told != true)
        assert right < 0.25 and right < 0.5 * wrong, (true, right, wrong)


def test_conditioned_own_rollouts_run_and_score_each_sequence_at_one_drawn_condition(tmp_path):
    """A conditioned training's own rollouts: each sequence rolled out by the network told one condition
    drawn from the box, its Dirichlet targets the program's at that time step, and its rows' loss taken
    at that condition (the ground truth's rows draw theirs); the rows travel with the checkpoint."""
    from latentsim.latent.data import triplet_rows
    from latentsim.latent.features import at_sampled_conditions, own_rollout_triplets_at_conditions

    ch = Chain()
    seqs = [_six(ch.simulate(a, f)) for a, f in [(0.5, 1.0), (-0.8, 0.7), (1.0, 1.5)]]
    coords = RelativeCoordinates(ch.n, [0], "roots", root_of=[0] * ch.n)
    ae = Autoencoder(coords.dim, coords.dim, [16], pca_dim=coords.dim)
    ae.init_pca(torch.cat([coords.encode(s["positions"], s["dirichlet_positions"]) for s in seqs]))
    ae.eval()
    box = Conditioning((1 / 60, 1 / 15), (0.5, 2.0), ch.pot.dt, 1.0)
    cfg = dict(widths=[16], epochs=1, lr=1e-3, batch_size=32)
    integ, _ = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=0, conditioning=box)
    tr = build_triplets(ae, coords, seqs)
    lengths = triplet_rows(seqs)
    own = own_rollout_triplets_at_conditions(integ, tr, lengths, tr["z"].mean(0), math.inf, box, torch.Generator().manual_seed(1))
    joined = Triplets.of(tr).cat(own)
    own = own.fields()
    assert own["z"].shape == tr["z"].shape and own["condition"].shape == (sum(lengths), 2)
    start, drawn = 0, []
    for seq, n in zip(seqs, lengths):
        rows = slice(start, start + n)
        h, E = (float(v) for v in own["condition"][start])
        assert torch.equal(own["condition"][rows], own["condition"][start].expand(n, 2)) and box.contains(h, E)
        drawn.append(h)
        with torch.no_grad():
            at = AtCondition(integ, box.normalise(h, E))
            pred = at(own["z_prev"][rows], own["z_prev2"][rows], own["p"][rows], own["p_prev"][rows], own["p_prev2"][rows])
            other = AtCondition(integ, box.normalise(1 / 15 if h < 1 / 30 else 1 / 60, E))(
                own["z_prev"][rows], own["z_prev2"][rows], own["p"][rows], own["p_prev"][rows], own["p_prev2"][rows]
            )
        # the rows chain the network's predictions at that condition, not at another
        assert torch.allclose(own["z_prev"][rows][1:], pred[:-1], atol=1e-6)
        assert not torch.allclose(own["z_prev"][rows][1:], other[:-1], atol=1e-4)
        # the Dirichlet targets: the program stepped at h from the sequence's first frame
        xD = dirichlet_trajectory(np.asarray(seq["dirichlet_positions"][0]), np.asarray(seq["bc"]), h)
        assert np.allclose(own["xD"][rows].numpy(), xD[2 : n + 2]) and np.allclose(own["xD_prev2"][rows].numpy(), xD[:n])
        start += n
    assert len(set(drawn)) == len(seqs)
    # in a minibatch the rolled-out rows keep their condition, the ground truth's draw theirs in the box
    batch = at_sampled_conditions(joined, box, torch.Generator().manual_seed(2)).fields()
    m = tr["z"].shape[0]
    assert torch.equal(batch["dt"][m:], own["condition"][:, 0]) and "condition" not in batch
    assert not torch.equal(batch["dt"][:m], tr["z"].new_full((m,), float(ch.pot.dt), dtype=torch.float64))
    assert ((batch["dt"][:m] >= 1 / 60 - 1e-12) & (batch["dt"][:m] <= 1 / 15 + 1e-12)).all()
    # each row's loss weight follows its own time step, to the box's power
    assert torch.allclose(batch["scale"], (batch["dt"] / ch.pot.dt) ** 2)
    flat = Conditioning(box.time_step, box.youngs_modulus, box.base_time_step, box.base_modulus, time_step_weight_power=0.0)
    assert torch.equal(at_sampled_conditions(joined, flat, torch.Generator().manual_seed(2)).scale, torch.ones_like(batch["scale"]))
    # a training on them, resumed between two rollouts, equals the uninterrupted one to the bit
    cfg = dict(widths=[16], epochs=5, lr=1e-3, batch_size=40, own_rollouts_every=2, own_rollouts_start=1)
    full, hf = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, conditioning=box)
    assert len(hf["own_triplets"]) == 2
    path = tmp_path / "ckpt.pt"
    fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "epochs": 2}, seed=3, conditioning=box, checkpoint_path=path, checkpoint_every=1)
    resumed, hr = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, conditioning=box, checkpoint_path=path, checkpoint_every=1)
    assert hr["start_epoch"] == 2 and hr["loss"] == hf["loss"]
    assert all(torch.equal(full.state_dict()[k], v) for k, v in resumed.state_dict().items())
