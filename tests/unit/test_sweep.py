"""The sizing sweep's choice: the smallest model within the tolerance that never diverged."""

import warnings

import pandas as pd
import pytest

from latentsim.labels import parse_label, point_label
from latentsim.stages.sweep import choose, chosen_label, recorded_choice_note


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


def test_the_chosen_point_is_labelled_by_its_size_index_and_compared_with_the_configs_record():
    sizes = [{"autoencoder": [8, 8], "integrator": [8, 8]}, {"autoencoder": [32, 32], "integrator": [8, 8]}]
    t = choose(_rows([(2, "8 8", 100, [0.05], False), (4, "32 32", 900, [0.004], False)]), tolerance=0.01)
    assert chosen_label(t, sizes) == "r4_s1"
    assert chosen_label(choose(_rows([(2, "8 8", 100, [0.05], False)]), tolerance=0.01), sizes) == "none"
    with pytest.raises(ValueError, match="none of the sweep's sizes"):
        chosen_label(t, sizes[:1])
    same = recorded_choice_note("r4_s1", {"point": "r4_s1", "commit": "abc1234", "seeds": 3}, "cloth")
    assert "the choice the config records (at abc1234)" in same
    other = recorded_choice_note("r2_s0", {"point": "r4_s1", "commit": "abc1234", "seeds": 3}, "cloth")
    assert "not r4_s1 as the config records" in other and "scenes.cloth.sweep.chosen" in other
    assert "records no choice (scenes.cloth.sweep.chosen)" in recorded_choice_note("r2_s0", None, "cloth")


def test_a_model_that_fails_a_stress_condition_is_not_chosen(tmp_path):
    """Within the tolerance on the test sequences, but diverged at twice the boundary speed: the next
    smallest model that survives every stress condition is chosen."""
    df = _rows([(2, "8 8", 100, [0.001], False), (4, "8 8", 200, [0.004], False), (8, "8 8", 300, [0.002], False)])
    df["stress_conditions"] = 8
    df["stress_failed"] = [1, 0, 0]
    df["stress_failures"] = ["speed_x2@177", "", ""]
    t = choose(df, tolerance=0.01)
    assert t["within_tolerance"].tolist() == [True, True, True]
    assert t["passes"].tolist() == [False, True, True]
    assert t[t["chosen"]].iloc[0]["parameters"] == 200
    assert t.loc[0, "stress_failures"] == "speed_x2@177"
    # read back from CSV, an all-empty failure column is float NaN: choose still gives strings, without warnings
    path = tmp_path / "metrics.csv"
    df.assign(stress_failed=0, stress_failures="").to_csv(path, index=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = choose(pd.read_csv(path), tolerance=0.01)
    assert back["passes"].all() and (back["stress_failures"] == "").all()
    # measured without stress conditions (older metrics): judged on the test sequences alone
    assert choose(df.drop(columns=["stress_conditions", "stress_failed", "stress_failures"]), tolerance=0.01)["passes"].all()


def test_nothing_chosen_when_no_model_meets_the_tolerance():
    t = choose(_rows([(2, "8 8", 100, [0.5], False), (4, "8 8", 200, [0.2], False)]), tolerance=0.01)
    assert not t["chosen"].any() and not t["passes"].any()


def test_point_labels_round_trip():
    assert parse_label(point_label(12, 3)) == (12, 3)
    with pytest.raises(ValueError, match="sweep point label"):
        parse_label("12_3")


def test_sizes_table_sets_ours_beside_the_papers_and_the_sweeps_choice(tmp_path):
    from latentsim.labels import layers_text
    from latentsim.report.tables import sizes_table

    df = _rows([(2, "8 8", 100, [0.001, 0.004], False), (4, "32 32", 900, [0.0005, 0.001], False)])
    path = tmp_path / "choice.csv"
    choose(df, tolerance=0.01).to_csv(path, index=False)
    sizes = {
        "cloth": {"latent_dim": 2, "decoder_layers": layers_text([8, 8], 50), "integrator_layers": layers_text([8, 8]), "tolerance": 0.01},
        "cantilever": {"latent_dim": 4, "decoder_layers": layers_text([200], 50), "integrator_layers": layers_text([64])},
    }
    t = sizes_table(sizes, {"cloth": path}).set_index("scene")
    assert t.loc["cloth", "decoder_layers"] == "8, 8, 50" and t.loc["cloth", "paper_decoder_layers"] == "200, 200, 200, 50"
    assert t.loc["cloth", "paper_latent"] == 4 and t.loc["cloth", "sweep_points"] == 2 and t.loc["cloth", "sweep_passing"] == 2
    assert t.loc["cloth", "chosen_latent"] == 2 and t.loc["cloth", "chosen_decoder"] == "8, 8"
    assert t.loc["cloth", "chosen_error"] == pytest.approx(0.004)  # the chosen point's worst sequence
    assert t.loc["cloth", "reference_error"] == pytest.approx(0.001) and "32 32" in t.loc["cloth", "reference_point"]  # no paper size: the largest
    assert pd.isna(t.loc["cantilever", "chosen_latent"]) and t.loc["cantilever", "paper_decoder_layers"] == ""  # no sweep, no paper row


def test_sizes_table_names_a_choice_file_without_the_columns_it_needs(tmp_path):
    from latentsim.report.tables import sizes_table

    bad = tmp_path / "choice.csv"
    pd.DataFrame({"latent_dim": [2]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="choice.csv.*lacks columns"):
        sizes_table({"cloth": {"latent_dim": 2, "decoder_layers": "8", "integrator_layers": "8"}}, {"cloth": bad})


def test_sizes_table_compares_with_the_papers_size_where_the_sweep_trained_it(tmp_path):
    from latentsim.report.tables import sizes_table

    df = _rows([(2, "32 32", 100, [0.010], False), (4, "200 200 200", 900, [0.004], False), (8, "200 200 200", 950, [0.5], True)])
    df["integrator_widths"] = "32 32"
    path = tmp_path / "choice.csv"
    choose(df, tolerance=0.02).to_csv(path, index=False)
    own = {"latent_dim": 2, "decoder_layers": "32, 32, 50", "integrator_layers": "32, 32", "tolerance": 0.02}
    for scene in ("cloth", "cloth_paper"):  # <scene>_paper takes <scene>'s numbers from the paper
        t = sizes_table({scene: own}, {scene: path}).set_index("scene")
        assert t.loc[scene, "reference_point"] == "latent 4; 200 200 200 / 32 32"  # the paper's (Table 2), not the largest
        assert t.loc[scene, "reference_error"] == pytest.approx(0.004) and t.loc[scene, "chosen_latent"] == 2


def test_linear_and_single_width_points_survive_a_csv_round_trip(tmp_path):
    """A linear autoencoder's point ("linear") and a one-layer one ("16", which a CSV reads back as a number)
    keep their own rows through the CSV the stage writes; the linear one, smallest and within the tolerance,
    is chosen."""
    from latentsim.stages.sweep import widths_label

    assert widths_label([]) == "linear" and widths_label([32, 32]) == "32 32"
    df = _rows([(2, "32 32", 900, [0.001], False), (2, "16", 300, [0.003], False), (2, widths_label([]), 60, [0.008], False)])
    path = tmp_path / "metrics.csv"
    df.to_csv(path, index=False)
    t = choose(pd.read_csv(path), tolerance=0.01)
    assert sorted(t["autoencoder_widths"]) == ["16", "32 32", "linear"]
    assert t.loc[t["chosen"], "autoencoder_widths"].tolist() == ["linear"]
