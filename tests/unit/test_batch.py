"""The training rows as typed records (latentsim.latent.batch): what each operation keeps, drops and fills."""

import torch

from latentsim.latent.batch import Batch, Triplets
from latentsim.latent.data import BATCH_KEYS
from latentsim.latent.loss import with_training_noise


def _rows(n, start=0.0, **extra):
    g = torch.arange(n, dtype=torch.float64) + start
    out = {k: g[:, None].expand(n, 3).to(torch.float32).clone() for k in ("z", "z_prev", "z_prev2", "p", "p_prev", "p_prev2")}
    out.update({k: g[:, None, None].expand(n, 2, 3).clone() for k in ("xD", "xD_prev", "xD_prev2")})
    return Triplets(**out, **extra)


def test_records_convert_index_and_list_the_fields_in_use():
    t = _rows(4)
    assert len(t) == 4 and list(t.fields()) == list(BATCH_KEYS)
    assert Triplets.of(t) is t and all(v is t.fields()[k] for k, v in Triplets.of(t.fields()).fields().items())
    b = Batch.of(t)
    assert isinstance(b, Batch) and b.dt is None and torch.equal(b.z, t.z) and Batch.of(b) is b
    r = t.rows(torch.tensor([3, 1]))
    assert torch.equal(r.z[:, 0], torch.tensor([3.0, 1.0])) and r.condition is None
    assert torch.equal(t.rows(slice(1, 3)).xD_prev2, t.xD_prev2[1:3])


def test_cat_fills_a_condition_that_some_rows_lack_and_drops_what_only_some_hold():
    plain = _rows(2)
    rolled = _rows(3, 10.0, condition=torch.tensor([[0.1, 2.0]] * 3, dtype=torch.float64), speed=torch.full((3,), 2.0, dtype=torch.float64))
    both = plain.cat(rolled)
    assert len(both) == 5 and torch.equal(both.z[:, 0], torch.tensor([0.0, 1.0, 10.0, 11.0, 12.0]))
    assert torch.isnan(both.condition[:2]).all() and torch.equal(both.condition[2:], rolled.condition)
    assert both.speed is None  # only the rolled-out rows have one
    again = rolled.cat(rolled, rolled)
    assert len(again) == 9 and torch.equal(again.speed, torch.full((9,), 2.0, dtype=torch.float64))


def test_training_noise_doubles_every_field_and_perturbs_only_the_inputs():
    b = Batch.of(_rows(5)).replace(dt=torch.full((5,), 0.01, dtype=torch.float64), scale=torch.ones(5, dtype=torch.float64))
    out = with_training_noise(b, 0.5, torch.Generator().manual_seed(0))
    assert isinstance(out, Batch) and len(out) == 10
    for key in ("z", "p", "p_prev", "p_prev2", "xD", "xD_prev", "xD_prev2", "dt", "scale"):
        v = getattr(out, key)
        assert torch.equal(v[:5], getattr(b, key)) and torch.equal(v[5:], getattr(b, key)), key
    assert torch.equal(out.z_prev[:5], b.z_prev) and not torch.equal(out.z_prev[5:], b.z_prev)
    assert out.stiffness is None and out.balance is None
