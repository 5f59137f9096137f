"""Honest divergence: a rollout that diverged fails every frame from its first diverged frame on, so its
errors are infinite over the whole sequence, it never ranks best, is never on a Pareto front (chart,
glance table and grid), Tables 1-2 name it; a divergence at frame 0 (a tight ``rollout.max_extent``,
NaN weights) is detected, scored and leaves every other method's metrics in the scene's evaluation."""

import h5py
import numpy as np
import pandas as pd
import pytest
import torch

from latentsim import latent
from latentsim.latent import stability
from latentsim.report.metrics import DIVERGED_ERROR, bbox_diagonal, pareto_front, rollout_metrics
from latentsim.report.plots import speed_accuracy_chart
from latentsim.report.tables import glance_grid, glance_table, speed_accuracy_points, stability_table, stress_table, table1, table2
from latentsim.stages.evaluate import summarise, write_scene_evaluation

ERRORS = ("mean_error", "max_error", "dirichlet_error", "end_error")


def _motion(T=30, n=8):
    """(T,n,3) a row of vertices swinging about the first (vertex 0, the Dirichlet vertex, fixed); (n,3) rest."""
    rest = np.stack([0.1 * np.arange(n), np.zeros(n), np.zeros(n)], axis=1)
    x = np.repeat(rest[None], T, axis=0)
    x[..., 1] = 0.05 * np.sin(0.3 * np.arange(T))[:, None] * rest[None, :, 0]
    return x, rest


def _diverged(x, frame, kept=None):
    """``x`` exact before ``frame``, the frame itself at ``kept`` (its computed values: e.g. blown up), NaN after."""
    out = x.copy()
    out[frame] = x[frame] if kept is None else kept
    out[frame + 1 :] = np.nan
    return out


def _metrics(pred, x, rest, div):
    D = np.array([0])
    return rollout_metrics(pred, x, x[:, D], D, np.ones(len(rest)), 0.01, bbox_diagonal(rest), div)


@pytest.mark.parametrize("frame", [0, 2, 17])
def test_a_diverged_rollout_has_infinite_errors_over_the_whole_sequence(frame):
    """Exact (the encoded ground truth) up to the divergence: the errors over the frames survived would be 0,
    the best of any method; the frames from the divergence on fail, so the whole sequence's errors are infinite."""
    x, rest = _motion()
    m, c = _metrics(_diverged(x, frame, kept=10.0 * x[frame]), x, rest, frame)
    assert m["frames"] == len(x) and m["diverged_frame"] == frame
    for k in ERRORS:
        assert m[k] == DIVERGED_ERROR == np.inf, k
    assert np.isnan(m["kinetic_ratio"]) and np.isnan(m["end_motion"]) and m["end_motion_truth"] > 0
    # the curves (errors over time) keep the frames survived, exact here; none for a divergence at frame 0
    assert len(c["mean_error"]) == len(c["dirichlet_error"]) == len(c["ke_pred"]) == len(c["ke_truth"]) == frame
    np.testing.assert_array_equal(c["mean_error"], np.zeros(frame))


def test_a_stable_rollout_is_scored_over_every_frame():
    x, rest = _motion()
    pred = x + np.array([0.0, 0.0, 0.02])
    m, c = _metrics(pred, x, rest, -1)
    for k in ERRORS:
        assert np.isclose(m[k], 0.02 / bbox_diagonal(rest)), k
    assert np.isclose(m["kinetic_ratio"], 1.0) and len(c["mean_error"]) == len(x)


@pytest.mark.parametrize("div", [-2, 30, 31])
def test_a_diverged_frame_outside_the_sequence_is_an_error_naming_it(div):
    x, rest = _motion()
    with pytest.raises(ValueError, match=f"diverged_frame {div} is outside -1"):
        _metrics(x, x, rest, div)


def _scene_metrics():
    """One scene, one test sequence each, through rollout_metrics: two stable methods (accurate & slow,
    rough & fast), one exact until it diverges at frame 2 and the fastest, one diverged at frame 0."""
    x, rest = _motion()
    runs = {"newton_1it": (x + [0, 0, 0.001], -1, 2.0), "self_supervised": (x + [0, 0, 0.01], -1, 0.1),
            "supervised_5x256": (_diverged(x, 2), 2, 0.05), "pca_reduced": (_diverged(x, 0, kept=5 * x[0]), 0, 0.08)}  # fmt: skip
    rows = []
    for method, (pred, div, ms) in runs.items():
        m, _ = _metrics(pred, x, rest, div)
        rows.append(dict(scene="a", method=method, sequence="s", **m, full_ms=10.0, latent_ms=ms, integrate_ms=ms / 3,
                         decode_ms=2 * ms / 3, jvp_torch_ms=1.0, jvp_forward_ms=0.01, dof=rest.size, latent_dim=2))  # fmt: skip
    return pd.DataFrame(rows)


def test_a_diverged_method_never_ranks_best_nor_sits_on_a_pareto_front(tmp_path):
    df = _scene_metrics()
    assert df.sort_values("mean_error")["method"].iloc[0] == "newton_1it"
    assert df.sort_values("max_error")["method"].iloc[0] == "newton_1it"
    # the chart's points (and its picture), then the glance table and the grid of the summary
    pts = speed_accuracy_points(df)
    speed_accuracy_chart(pts, tmp_path / "chart.png", scene="a")
    assert (tmp_path / "chart.png").stat().st_size > 1000
    pts = pts.set_index("method")
    assert not pts.loc["supervised_5x256", "on_front"] and not pts.loc["pca_reduced", "on_front"]
    assert pts.loc["self_supervised", "on_front"] and pts.loc["newton_1it", "on_front"] and pts.loc["full_space", "on_front"]
    glance = glance_table(df).set_index("method")
    assert list(glance.loc[["supervised_5x256", "pca_reduced"], "on_front"]) == [False, False]
    assert (glance.loc[["supervised_5x256", "pca_reduced"], "mean_error"] == np.inf).all()
    assert glance["mean_error"].drop("full_space").idxmin() == "newton_1it"
    grid = glance_grid(glance.reset_index()).set_index("scene")
    assert grid.loc["a", "supervised_5x256"] == "diverged 0/1 (0.05)" and grid.loc["a", "pca_reduced"] == "diverged 0/1 (0.08)"
    assert grid.loc["a", "self_supervised"].endswith("*") and grid.loc["a", "newton_1it"].endswith("*")
    # with the error over the frames survived (0 for both), the diverged methods would have been the front
    survived = np.where(df["diverged_frame"] >= 0, 0.0, df["mean_error"])
    assert pareto_front(df["latent_ms"], survived)[df["method"].isin(["supervised_5x256"])].all()


def test_tables_1_and_2_name_a_method_that_diverged():
    df = _scene_metrics()
    stable = df[df["method"] != "supervised_5x256"]
    assert list(table1(stable)["method"]) == ["self_supervised"] and list(table2(stable)["method"]) == ["self_supervised"]
    df.loc[df["method"] == "self_supervised", ["diverged_frame", "mean_error"]] = (7, np.inf)
    assert list(table1(df)["method"]) == list(table2(df)["method"]) == ["self_supervised (diverged on 1/1 test rollouts)"]
    st = stability_table(df).set_index("method")
    assert st.loc["pca_reduced", "survived"] == 0 and st.loc["supervised_5x256", "survived"] == 2 and st.loc["newton_1it", "survived"] == 30


def _trajectory_file(path, rest, sequences, method=None, stress=None):
    """A trajectory-layout file: ground truth (no method) or a rollout (method, latents, step_ms, diverged_frame,
    stress conditions {name: (frames, survived, dirichlet_error_end)})."""
    with h5py.File(path, "w") as f:
        f.attrs["dt"] = 0.01
        f["rest_positions"], f["masses"], f["dirichlet"] = rest, np.ones(len(rest)), np.array([0])
        if method:
            f.attrs["method"] = method
        for name, (x, div) in sequences.items():
            g = f.create_group(f"sequences/{name}")
            g["positions"], g["dirichlet_positions"], g["frame_ms"] = x, x[:, [0]], np.full(len(x), 4.0)
            if method:
                g["latents"] = np.zeros((len(x), 2))
                g.attrs["diverged_frame"], g.attrs["step_ms"], g.attrs["runtime"] = div, 0.5, "compiled"
        for cond, (frames, survived, bc) in (stress or {}).items():
            g = f.create_group(f"stability/{cond}")
            g.attrs.update(frames=frames, survived=survived, dirichlet_error_end=bc)
    return path


def test_evaluation_of_a_scene_with_a_frame_0_divergence_keeps_every_other_method(tmp_path):
    x, rest = _motion()
    gt = _trajectory_file(tmp_path / "trajectories.h5", rest, {"s": (x, -1), "t": (x, -1)})
    ok = _trajectory_file(tmp_path / "ok.h5", rest, {"s": (x + [0, 0, 0.01], -1), "t": (x, -1)}, method="self_supervised",
                          stress={"speed_x5": (30, 30, 1e-9), "long_x10": (300, 0, np.nan)})  # fmt: skip
    frame0 = _trajectory_file(tmp_path / "frame0.h5", rest, {"s": (np.full_like(x, np.nan), 0), "t": (_diverged(x, 0, 9 * x[0]), 0)},
                              method="supervised_5x256", stress={"speed_x5": (30, 0, np.nan)})  # fmt: skip
    with h5py.File(tmp_path / "latents.h5", "w") as f:
        for name in ("s", "t"):
            f.create_group(f"sequences/{name}").attrs.update(split="test", mean_error=0.001, max_error=0.002)
    out = {k: tmp_path / f"{k}.{ext}" for k, ext in (("metrics", "csv"), ("reconstruction", "csv"), ("stress", "csv"), ("chart", "png"),
                                                    ("figure", "png"))}  # fmt: skip
    write_scene_evaluation("a", gt, [ok, frame0], tmp_path / "latents.h5", **out)
    assert all(p.stat().st_size > 0 for p in out.values())
    m = pd.read_csv(out["metrics"]).set_index(["method", "sequence"])
    assert len(m) == 4
    assert np.isclose(m.loc[("self_supervised", "s"), "mean_error"], 0.01 / bbox_diagonal(rest))
    assert m.loc[("self_supervised", "t"), "mean_error"] == 0.0 and (m.loc["self_supervised", "diverged_frame"] == -1).all()
    for seq in ("s", "t"):  # the row says so: diverged at frame 0 (no frame survived), infinite errors
        r = m.loc[("supervised_5x256", seq)]
        assert r["diverged_frame"] == 0 and all(r[k] == np.inf for k in ERRORS) and np.isnan(r["kinetic_ratio"])
    # the stress rows: a condition that failed at frame 0 survived 0 frames (no Dirichlet error at a survived frame)
    st = pd.read_csv(out["stress"]).set_index(["method", "condition"])
    assert st.loc[("supervised_5x256", "speed_x5"), "frames_survived"] == 0 and st.loc[("supervised_5x256", "speed_x5"), "diverged"]
    assert np.isnan(st.loc[("supervised_5x256", "speed_x5"), "bc_error"]) and st.loc[("self_supervised", "long_x10"), "diverged"]
    assert not st.loc[("self_supervised", "speed_x5"), "diverged"]
    # and the summary over it
    summarise([out["metrics"]], tmp_path / "s.csv", tmp_path / "s.md", tmp_path / "s.png", stress=[out["stress"]],
              stress_paths=(tmp_path / "stress_all.csv", tmp_path / "stress_all.png"), glance_path=tmp_path / "glance.csv")  # fmt: skip
    g = pd.read_csv(tmp_path / "glance.csv").set_index("method")
    assert not g.loc["supervised_5x256", "on_front"] and g.loc["supervised_5x256", "test_survived"] == "0/2"
    assert g.loc["self_supervised", "on_front"] and g.loc["supervised_5x256", "stress_survived"] == "0/1"
    text = (tmp_path / "s.md").read_text()
    assert f"| a | 0 (4) * | {0.005 / bbox_diagonal(rest):.3g} (0.5) * | diverged 0/2 (0.5) |" in text  # s and t: 0.01 and 0
    assert "errors are infinite" in text


def test_stress_table_of_a_rollout_file_with_a_frame_0_failure(tmp_path):
    x, rest = _motion()
    p = _trajectory_file(tmp_path / "r.h5", rest, {"s": (x, -1)}, method="m", stress={"c0": (30, 0, np.nan), "c1": (30, 30, 0.0)})
    st = stress_table("a", [p]).set_index("condition")
    assert list(st["frames_survived"]) == [0, 30] and list(st["diverged"]) == [True, False]


# --------------------------------------------------------------------------- detection at frame 0


def _tiny_autoencoder(n=6):
    rest = torch.tensor(np.random.default_rng(0).normal(size=(n, 3)))
    coords = latent.RelativeCoordinates(n, [0], mode="mean")
    X = rest[None] + 0.01 * torch.randn(40, n, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ae = latent.Autoencoder(coords.dim, 2, [], pca_dim=2)
    ae.init_pca(coords.encode(X, X[:, :1]).float())
    return ae.eval(), coords, rest


def _still(z1, z2, p, p1, p2):
    return z1


def test_rollout_diverges_at_frame_0_under_a_tight_extent_or_nan_weights():
    ae, coords, rest = _tiny_autoencoder()
    T = 12
    xD = rest[None, :1].repeat(T, 1, 1)
    z = latent.encode_positions(ae, coords, rest[None], rest[None, :1])[0]
    out = latent.rollout(_still, ae, coords, z, z, torch.zeros(T, 6), xD, max_extent=2.0, rest_positions=rest)
    assert out["diverged_frame"] == -1 and torch.isfinite(out["positions"]).all()
    # a legal but tight bound: frame 0 (the rest shape itself) is already beyond it
    out = latent.rollout(_still, ae, coords, z, z, torch.zeros(T, 6), xD, max_extent=0.1, rest_positions=rest)
    assert out["diverged_frame"] == 0
    assert torch.isfinite(out["positions"][0]).all() and torch.isnan(out["positions"][1:]).all() and torch.isnan(out["latents"][1:]).all()
    # NaN weights: frame 0 decodes to NaN
    with torch.no_grad():
        ae.pca_out.weight.fill_(float("nan"))
    out = latent.rollout(_still, ae, coords, z, z, torch.zeros(T, 6), xD)
    assert out["diverged_frame"] == 0 and torch.isnan(out["positions"]).all()
    x = np.repeat(rest.numpy()[None], T, 0)
    m, c = _metrics(out["positions"].numpy(), x, rest.numpy(), out["diverged_frame"])
    assert m["mean_error"] == np.inf and len(c["mean_error"]) == 0


def test_a_stress_condition_that_fails_at_frame_0_survives_0_frames():
    ae, coords, rest = _tiny_autoencoder()
    T = 20
    cond = stability.Condition("still", np.zeros((T, 6)), np.repeat(rest[None, :1].numpy(), T, 0))
    diag = bbox_diagonal(rest.numpy())
    z = latent.encode_positions(ae, coords, rest[None], rest[None, :1])[0]
    ok = stability.survive_latent(_still, ae, coords, z, z, cond, np.array([0]), diag, max_extent=2.0)
    assert ok["survived"] == T and np.isfinite(ok["dirichlet_error_end"])
    bad = stability.survive_latent(_still, ae, coords, z, z, cond, np.array([0]), diag, max_extent=0.1)
    assert bad["frames"] == T and bad["survived"] == 0 and len(bad["dirichlet_error"]) == 0 and np.isnan(bad["dirichlet_error_end"])
