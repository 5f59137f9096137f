"""The training features' pieces (latentsim.latent.features) on the spring chain of test_latent:
own rollouts (chained predictions, at other speeds, resumed from a checkpoint) and the checks of
which settings go together."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from latentsim.latent import LatentIntegrator, build_triplets, encode_positions, fit_integrator

sys.path.insert(0, str(Path(__file__).parent))
from test_latent import F64, _untrained, chain_setup  # noqa: E402,F401  (the spring chain and its fixture)

ONE_THREAD = True  # tiny networks (conftest)


def test_own_rollouts_chain_the_integrators_own_predictions_sequence_by_sequence(chain_setup):
    """Each training sequence rolled out by the integrator from its first two ground-truth latents: a
    row's inputs are the two latents before it in that rollout, its boundary conditions and targets
    the frame's own; a rollout that leaves the range stops there."""
    from latentsim.latent.data import triplet_rows
    from latentsim.latent.features import own_rollout_triplets

    ch, seqs, coords, ae = chain_setup
    integ, tr = _untrained(chain_setup)
    lengths = triplet_rows(seqs)
    assert sum(lengths) == tr["z"].shape[0]  # build_triplets' rows, sequence by sequence
    centre = tr["z"].mean(0)
    own = own_rollout_triplets(integ, tr, lengths, centre, math.inf).fields()
    assert own["z"].shape == tr["z"].shape
    for key in ("z", "p", "p_prev", "p_prev2", "xD", "xD_prev", "xD_prev2"):
        assert torch.equal(own[key], tr[key])
    with torch.no_grad():
        pred = integ(own["z_prev"], own["z_prev2"], own["p"], own["p_prev"], own["p_prev2"])
    start = 0
    for n in lengths:
        rows = slice(start, start + n)
        assert torch.equal(own["z_prev"][start], tr["z_prev"][start]) and torch.equal(own["z_prev2"][start], tr["z_prev2"][start])
        # from the second row on, the inputs are the rollout's: the previous row's prediction and input
        assert torch.allclose(own["z_prev"][rows][1:], pred[rows][:-1], atol=1e-6)
        assert torch.equal(own["z_prev2"][rows][1:], own["z_prev"][rows][:-1])
        start += n
    # an untrained integrator drifts: its own inputs are not the ground truth's
    assert not torch.allclose(own["z_prev"], tr["z_prev"], atol=1e-3)
    # a range it leaves at once: each sequence keeps the rows up to its first prediction outside
    short = own_rollout_triplets(integ, tr, lengths, centre, 0.0)
    assert len(short) == len(lengths)
    with pytest.raises(ValueError, match="rows_per_sequence"):
        own_rollout_triplets(integ, tr, lengths[:-1], centre, math.inf)


def test_own_rollouts_stop_before_the_first_input_that_is_not_clear(chain_setup):
    """With a check of which states are clear, each sequence keeps the rows of the unstopped rollout up to the
    first whose input latent is not clear: a prefix, every input in it clear, the next one not."""
    from latentsim.latent.data import triplet_rows
    from latentsim.latent.features import own_rollout_triplets

    ch, seqs, coords, ae = chain_setup
    integ, tr = _untrained(chain_setup)
    lengths, centre = triplet_rows(seqs), tr["z"].mean(0)
    full = own_rollout_triplets(integ, tr, lengths, centre, math.inf)
    far = (full.z_prev - centre).norm(dim=-1)
    limit = float(far.median())  # about half the rolled-out inputs lie beyond it
    seen = []

    def clear(z, xD):
        assert xD.shape == (len(z), 1, 3)  # the frames' Dirichlet positions come with the latents
        seen.append(len(z))
        return (z - centre).norm(dim=-1) < limit

    own = own_rollout_triplets(integ, tr, lengths, centre, math.inf, clear)
    assert seen == lengths  # one call a sequence, on its whole rollout
    assert 0 < len(own) < len(full)
    start, kept = 0, 0
    for n in lengths:
        ok = (far[start : start + n] < limit).tolist()
        k = ok.index(False) if False in ok else n
        assert torch.equal(own.z_prev[kept : kept + k], full.z_prev[start : start + k])
        assert torch.equal(own.z_prev2[kept : kept + k], full.z_prev2[start : start + k])
        assert torch.equal(own.xD[kept : kept + k], full.xD[start : start + k])
        start, kept = start + n, kept + k
    assert kept == len(own)
    # nothing clear: no rows (the trainer's data then has no own rows beside it)
    assert len(own_rollout_triplets(integ, tr, lengths, centre, math.inf, lambda z, xD: torch.zeros(len(z), dtype=torch.bool))) == 0


def test_a_training_with_contact_rolls_out_only_states_clear_of_its_collider(chain_setup, tmp_path, monkeypatch):
    """The chain, which swings in its plane (y = 0), beside a wall 2 cm off it: the own rows a training keeps (in its
    checkpoint) all decode no deeper into the wall than the allowed depth (OWN_ROLLOUT_DEPTH of the diagonal of the
    training states), by the contact's own measure and by the plane's distance computed here; without the stop the
    same training's rollouts drift out of the plane and deeper into the wall, so the check can fail."""
    import dataclasses

    import numpy as np

    from latentsim.latent import decode_latents
    from latentsim.latent import features
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    ch, seqs, coords, ae = chain_setup
    assert all(float(abs(s["positions"][..., 1]).max()) == 0 for s in seqs)
    wall = 0.02  # inside: y beyond the wall
    contact = ContactBarrier(ch.n, [HalfSpace((0.0, wall, 0.0), (0.0, -1.0, 0.0))], d_hat=0.01, kappa=1.0)
    pot = dataclasses.replace(ch.pot, contact=contact)
    cfg = dict(widths=[16], epochs=3, lr=1e-2, batch_size=40, own_rollouts_every=1, own_rollouts_start=0, noise_scale=0.0)
    pts = np.concatenate([np.asarray(s["positions"]).reshape(-1, 3) for s in seqs])
    depth = features.OWN_ROLLOUT_DEPTH * float(np.linalg.norm(pts.max(0) - pts.min(0)))
    assert 0 < depth < 0.1

    def too_deep(path):
        own = torch.load(path, weights_only=False)["own"]
        x = decode_latents(ae, coords, own["z_prev"], own["xD_prev"])
        return int((x[..., 1] >= wall + depth).any(-1).sum()), int((contact.clearance(x, own["xD_prev"]) <= -depth).sum()), len(x)

    fit_integrator(ae, coords, pot, seqs, cfg, seed=2, checkpoint_path=tmp_path / "stopped.pt", checkpoint_every=1)
    by_hand, by_measure, kept = too_deep(tmp_path / "stopped.pt")
    assert by_hand == by_measure == 0 and kept > 0
    monkeypatch.setattr(features.ClearStates, "of", classmethod(lambda cls, *a: None))
    fit_integrator(ae, coords, pot, seqs, cfg, seed=2, checkpoint_path=tmp_path / "unstopped.pt", checkpoint_every=1)
    by_hand, by_measure, n = too_deep(tmp_path / "unstopped.pt")
    assert by_hand == by_measure > 0 and n > kept


def test_a_state_is_clear_up_to_its_allowed_depth_inside_a_collider(chain_setup):
    """ClearStates on the chain's frames moved sideways through a wall: clear outside it and up to ``depth`` inside (the
    deepest vertex), not beyond; its depth from ``of`` is OWN_ROLLOUT_DEPTH of the sequences' diagonal; no contact, no check."""
    import numpy as np

    from latentsim.latent import encode_positions
    from latentsim.latent.features import OWN_ROLLOUT_DEPTH, ClearStates
    from latentsim.physics.colliders import HalfSpace
    from latentsim.physics.contact import ContactBarrier

    ch, seqs, coords, ae = chain_setup
    x = torch.as_tensor(seqs[0]["positions"][10])
    xD = torch.as_tensor(seqs[0]["dirichlet_positions"][10])
    contact = ContactBarrier(ch.n, [HalfSpace((0.0, 0.05, 0.0), (0.0, -1.0, 0.0))], d_hat=0.01, kappa=1.0)
    shifts = [-0.03, 0.045, 0.055, 0.059, 0.061, 0.08]  # the free vertices' y: the wall at 0.05, the depth 0.01
    X = x.repeat(len(shifts), 1, 1)
    X[:, 1:, 1] = torch.tensor(shifts, dtype=X.dtype)[:, None]
    XD = xD.repeat(len(shifts), 1, 1)
    z = encode_positions(ae, coords, X, XD)
    clear = ClearStates(ae, coords, contact, depth=0.01)
    assert clear(z, XD).tolist() == [True, True, True, True, False, False]
    assert ClearStates(ae, coords, contact)(z, XD).tolist() == [True, True, False, False, False, False]
    pts = np.concatenate([np.asarray(s["positions"]).reshape(-1, 3) for s in seqs])
    assert ClearStates.of(ae, coords, contact, seqs).depth == pytest.approx(OWN_ROLLOUT_DEPTH * np.linalg.norm(pts.max(0) - pts.min(0)))
    assert ClearStates.of(ae, coords, None, seqs) is None


def test_a_training_on_its_own_rollouts_resumes_them_from_its_checkpoint(chain_setup, tmp_path):
    """The rolled-out triplets in use travel with the checkpoint: a run resumed between two rollouts
    equals the uninterrupted one to the bit."""
    ch, seqs, coords, ae = chain_setup
    cfg = dict(widths=[16], epochs=6, lr=1e-3, batch_size=40, own_rollouts_every=2, own_rollouts_start=1)
    full, hf = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3)
    assert hf["own_triplets"] and len(hf["own_triplets"]) == 3 and all(0 < n <= 3 * 38 for n in hf["own_triplets"])
    path = tmp_path / "ckpt.pt"
    fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "epochs": 4}, seed=3, checkpoint_path=path, checkpoint_every=1)
    resumed, hr = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, checkpoint_path=path, checkpoint_every=1)
    assert hr["start_epoch"] == 4 and hr["loss"] == hf["loss"] and hr["own_triplets"] == hf["own_triplets"]
    assert all(torch.equal(full.state_dict()[k], v) for k, v in resumed.state_dict().items())
    with pytest.raises(ValueError, match="own_rollouts_every"):
        fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "mode": "supervised"}, seed=3)


def _programs6(seqs):
    """The chain's sequences with their program as the pipeline writes it: (T, 6), velocity and angular velocity."""
    out = []
    for s in seqs:
        bc = torch.zeros(len(s["bc"]), 6, dtype=F64)
        bc[:, 0] = s["bc"][:, 0]
        out.append({**s, "bc": bc})
    return out


def test_own_rollouts_at_speeds_roll_each_sequence_out_under_its_program_scaled(chain_setup):
    """Each moving sequence's program scaled by a drawn factor: the rows' boundary conditions are the
    scaled program, their Dirichlet targets where it carries the root, their inputs the integrator's
    own chain from the recorded first two latents; a still sequence gives none; factor 1 is
    :func:`own_rollout_triplets` itself."""
    from latentsim.latent.data import triplet_rows
    from latentsim.latent.features import own_rollout_triplets, own_rollout_triplets_at_speeds, speed_programs

    ch, seqs, coords, ae = chain_setup
    seqs = _programs6(seqs)
    still = {**seqs[0], "bc": torch.zeros_like(seqs[0]["bc"])}
    seqs = [*seqs, still]
    tr = build_triplets(ae, coords, seqs)
    torch.manual_seed(1)
    integ = LatentIntegrator(coords.dim, 6, [64, 64])
    integ.fit_normalization(*(tr[k] for k in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")))
    integ.eval()
    lengths, centre = triplet_rows(seqs), tr["z"].mean(0)
    programs = speed_programs(seqs, [2.0, 2.0])
    assert programs[-1][0] is None and all(bc is not None for bc, _ in programs[:-1])
    dt = float(ch.pot.dt)
    own = own_rollout_triplets_at_speeds(integ, tr, lengths, centre, math.inf, programs, (2.0, 2.0), torch.Generator().manual_seed(0), dt, False).fields()
    assert own["z"].shape[0] == sum(lengths[:-1])  # the still sequence: nothing to scale
    assert torch.all(own["speed"] == 2.0)
    with torch.no_grad():
        pred = integ(own["z_prev"], own["z_prev2"], own["p"], own["p_prev"], own["p_prev2"])
    start = 0
    for s, n in zip(seqs[:-1], lengths[:-1]):
        rows = slice(start, start + n)
        assert torch.allclose(own["p"][rows].double(), 2.0 * s["bc"][2:], atol=1e-6)
        root = s["dirichlet_positions"]  # the root from rest: twice as fast, twice as far
        assert torch.allclose(own["xD"][rows], root[0] + 2.0 * (root[2:] - root[0]), atol=1e-12)
        assert torch.allclose(own["xD_prev2"][rows], root[0] + 2.0 * (root[:-2] - root[0]), atol=1e-12)
        assert torch.equal(own["z_prev"][start], tr["z_prev"][start])
        assert torch.allclose(own["z_prev"][rows][1:], pred[rows][:-1], atol=1e-6)
        start += n
    same = own_rollout_triplets_at_speeds(integ, tr, lengths, centre, math.inf, programs, (1.0, 1.0), torch.Generator().manual_seed(0), dt, False)
    ref = own_rollout_triplets(integ, tr, lengths, centre, math.inf)
    n = len(same)
    for key in ("z_prev", "z_prev2", "p", "xD"):
        assert torch.allclose(getattr(same, key), getattr(ref, key)[:n], atol=1e-6), key
    drawn = own_rollout_triplets_at_speeds(integ, tr, lengths, centre, math.inf, programs, (0.5, 2.0), torch.Generator().manual_seed(0), dt, False)
    factors = torch.unique(drawn.speed)
    assert len(factors) == 3 and torch.all((factors >= 0.5) & (factors <= 2.0))


def test_own_rollouts_at_faster_programs_teach_the_integrator_faster_motion(chain_setup):
    """Trained also on its own rollouts at three times its data's speed, the integrator follows the
    exact physics of motions about three times as fast better than the same training at the data's
    speed alone (mean over three seeds; on this chain about 0.6 of the error, 0.9 at the worst of
    twelve seeds)."""
    from latentsim.latent.rollout import rollout

    ch, seqs, coords, ae = chain_setup
    seqs = _programs6(seqs)
    fast = _programs6([ch.simulate(a, f, T=60) for a, f in [(1.8, 0.9), (-2.7, 1.2)]])

    def error(integ):
        out = []
        for s in fast:
            z = encode_positions(ae, coords, s["positions"][:2], s["dirichlet_positions"][:2])
            r = rollout(integ, ae, coords, z[0], z[1], s["bc"], s["dirichlet_positions"])
            assert r["diverged_frame"] < 0
            out.append(float((r["positions"] - s["positions"]).norm(dim=-1).mean()))
        return sum(out) / len(out)

    cfg = dict(widths=[32, 32], epochs=100, lr=3e-3, batch_size=32, own_rollouts_every=5, own_rollouts_start=0)
    recorded, faster = [], []
    for seed in range(3):
        recorded.append(error(fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=seed)[0]))
        integ, hist = fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "own_rollouts_speeds": [3.0, 3.0]}, seed=seed)
        assert max(hist["own_triplets"]) > sum(len(s["positions"]) - 2 for s in seqs)  # both rollouts joined the data
        faster.append(error(integ))
    assert np.mean(faster) < 0.85 * np.mean(recorded), (faster, recorded)


def test_own_rollouts_at_speeds_refuse_what_they_cannot_scale(chain_setup):
    """The setting names itself where it cannot apply: no own rollouts, a conditioned integrator, a
    supervised term (whose targets exist only at the recorded speeds) (the combinations, checked by
    ``config.check_training_features``), a program that is not (velocity, angular velocity),
    nothing that moves, a range upside down (the data's and the range's, :func:`speed_programs`)."""
    from latentsim.config import with_defaults
    from latentsim.latent.conditioning import Conditioning
    from latentsim.latent.features import speed_programs, training_features

    ch, seqs, coords, ae = chain_setup
    seqs6 = _programs6(seqs)
    ok = {"own_rollouts_speeds": [0.5, 2.0], "own_rollouts_every": 1, "supervised_weight": 0.0}
    assert len(speed_programs(seqs6, ok["own_rollouts_speeds"])) == 3
    assert speed_programs(seqs6, None) is None
    assert len(training_features(with_defaults("integrator", ok, "test"), seqs6, coords, ch.pot.dt, None, "scene x").own.programs) == 3
    box = Conditioning((0.02, 0.04), (1e5, 2e5), 1.0 / 30.0, 1e5)
    for cfg, sq, cond, match in [
        ({**ok, "own_rollouts_every": 0}, seqs6, None, "own_rollouts_every is 0"),
        (ok, seqs6, box, "conditioned"),
        (ok, seqs, None, "6 numbers a frame"),
        (ok, [{**s, "bc": torch.zeros_like(s["bc"])} for s in seqs6], None, "no training sequence has a program"),
        ({**ok, "own_rollouts_speeds": [2.0, 0.5]}, seqs6, None, "0 < lo <= hi"),
        ({**ok, "supervised_weight": 1.0}, seqs6, None, "supervised term"),
    ]:
        with pytest.raises(ValueError, match=rf"scene x: integrator.own_rollouts_speeds.*{match}"):
            training_features(with_defaults("integrator", cfg, "test"), sq, coords, ch.pot.dt, cond, "scene x")


def test_the_plateau_rule_compares_the_least_loss_of_the_last_window_with_the_least_before():
    from latentsim.latent.base import PlateauStop

    rule = PlateauStop(window=3, tolerance=0.1)
    assert PlateauStop.of(None) is None and PlateauStop.of({"window": 3, "tolerance": 0.1}).window == 3
    assert not rule.reached([5.0, 4.0, 3.0, 2.9, 2.8])  # fewer than two windows
    assert not rule.reached([5.0, 4.0, 3.0, 2.6, 2.9, 2.9])  # 2.6 is more than 10% below 3.0
    assert rule.reached([5.0, 4.0, 3.0, 2.8, 2.9, 2.9])  # 2.8 is not
    assert rule.reached([5.0, 4.0, 3.0, 3.5, 3.1, 3.2])  # no fall at all
    assert not PlateauStop(3, 0.0).reached([5.0, 4.0, 3.0, 3.5, 3.1, 2.99])  # any fall counts at tolerance 0


def test_a_supervised_training_ends_at_its_plateau_and_a_resumed_one_at_the_same_epoch(chain_setup, tmp_path):
    """With a plateau rule the supervised training runs fewer epochs than asked, the last window
    without progress; stopped and resumed from a checkpoint, it ends at the same epoch with the same
    weights; the rule is refused for the energy loss."""
    from latentsim.config import ConfigError
    from latentsim.latent.base import PlateauStop

    ch, seqs, coords, ae = chain_setup
    cfg = dict(mode="supervised", widths=[16], epochs=300, lr=3e-3, batch_size=40, noise_scale=0.0, plateau_stop={"window": 10, "tolerance": 0.2})
    full, hf = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3)
    n = len(hf["loss"])
    rule = PlateauStop(10, 0.2)
    assert 20 <= n < 300 and rule.reached(hf["loss"]) and not rule.reached(hf["loss"][:-1])
    # the stopped training is the first n epochs of the one that runs them all
    _, h_all = fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "plateau_stop": None, "epochs": n + 5}, seed=3)
    assert h_all["loss"][:n] == hf["loss"] and len(h_all["loss"]) == n + 5
    path = tmp_path / "ckpt.pt"
    fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "epochs": n - 3}, seed=3, checkpoint_path=path, checkpoint_every=1)
    resumed, hr = fit_integrator(ae, coords, ch.pot, seqs, cfg, seed=3, checkpoint_path=path, checkpoint_every=1)
    assert hr["loss"] == hf["loss"]
    assert all(torch.equal(full.state_dict()[k], resumed.state_dict()[k]) for k in full.state_dict())
    with pytest.raises(ConfigError, match="plateau_stop is for a supervised training only"):
        fit_integrator(ae, coords, ch.pot, seqs, {**cfg, "mode": "self_supervised"}, seed=3)
