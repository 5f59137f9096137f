"""The sizing sweep's choice: the smallest model within the tolerance that never diverged."""

import pandas as pd
import pytest

from latentsim.sweep import choose, parse_label, point_label


def _rows(points):
    rows = []
    for r, widths, params, errors, diverged in points:
        for k, e in enumerate(errors):
            rows.append(dict(latent_dim=r, autoencoder_widths=widths, integrator_widths="8 8", parameters=params, sequence=f"s{k}",
                             mean_error=e, max_error=2 * e, diverged_frame=(5 if diverged and k == 0 else -1), step_ms=0.01 * params,
                             train_seconds=1.0))  # fmt: skip
    return pd.DataFrame(rows)


def test_smallest_passing_model_is_chosen_judged_on_its_worst_sequence():
    df = _rows([
        (2, "8 8", 100, [0.001, 0.05], False),   # worst sequence over the tolerance
        (4, "8 8", 150, [0.001, 0.002], True),   # accurate but diverged
        (4, "32 32", 900, [0.001, 0.004], False),
        (8, "32 32", 950, [0.0005, 0.001], False),
    ])  # fmt: skip
    t = choose(df, tolerance=0.01)
    assert len(t) == 4
    assert t["passes"].tolist() == [False, False, True, True]
    chosen = t[t["chosen"]]
    assert len(chosen) == 1 and chosen.iloc[0]["parameters"] == 900 and chosen.iloc[0]["latent_dim"] == 4
    assert t.loc[0, "mean_error"] == pytest.approx(0.05)  # the worst sequence counts


def test_nothing_chosen_when_no_model_meets_the_tolerance():
    t = choose(_rows([(2, "8 8", 100, [0.5], False), (4, "8 8", 200, [0.2], False)]), tolerance=0.01)
    assert not t["chosen"].any() and not t["passes"].any()


def test_point_labels_round_trip():
    assert parse_label(point_label(12, 3)) == (12, 3)
    with pytest.raises(ValueError, match="sweep point label"):
        parse_label("12_3")
