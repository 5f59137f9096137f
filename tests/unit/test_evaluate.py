"""Evaluation: the metrics of a rollout (report.metrics), the per-scene table (stages.evaluate), and the
summary's tables (report.tables): one row per scene and method, and the grid of the compared methods."""

import h5py
import html
import re

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest

from latentsim.report.metrics import bbox_diagonal, kinetic_energy, rollout_metrics, vertex_errors
from latentsim.report.plots import rollout_curves, speed_accuracy_chart
from latentsim.report.tables import glance_grid, glance_table, speed_accuracy_points, table1, table2, write_glance_html, write_table_html
from latentsim.stages.evaluate import evaluate_scene, read_full_space_time, summarise


def _swing(T=20, n=6):
    """(T,n,3) a row of vertices swinging about the first; (n,3) its rest shape."""
    rest = np.stack([0.1 * np.arange(n), np.zeros(n), np.zeros(n)], axis=1)
    t = np.arange(T)[:, None]
    x = np.repeat(rest[None], T, axis=0)
    x[..., 1] = 0.05 * np.sin(0.4 * t) * rest[None, :, 0]
    return x, rest


def test_bbox_diagonal_and_vertex_errors():
    assert np.isclose(bbox_diagonal(np.array([[0.0, 0, 0], [3, 0, 0], [1, 4, 0]])), 5.0)
    x, _ = _swing()
    pred = x.copy()
    pred[..., 2] += 0.01  # every vertex 0.01 away ...
    pred[:, -1, 2] += 0.02  # ... but the last, 0.03 away
    d = np.full(x.shape[1], 0.01)
    d[-1] = 0.03
    mean_e, max_e = vertex_errors(pred, x, 0.5)
    np.testing.assert_allclose(mean_e, np.full(len(x), d.mean() / 0.5))
    np.testing.assert_allclose(max_e, np.full(len(x), 0.03 / 0.5))


def test_kinetic_energy_of_uniform_motion():
    """Every vertex at velocity v: 1/2 (sum m) |v|^2 from frame 1 on, 0 at frame 0 (no previous frame)."""
    rest = np.random.default_rng(0).normal(size=(5, 3))
    m, v, dt = np.array([1.0, 2.0, 0.5, 0.25, 1.25]), np.array([0.3, -0.4, 1.2]), 0.01
    x = rest[None] + v * dt * np.arange(7)[:, None, None]
    ke = kinetic_energy(x, m, dt)
    assert ke[0] == 0.0
    np.testing.assert_allclose(ke[1:], 0.5 * m.sum() * (v @ v))


def test_rollout_metrics_of_a_shifted_and_a_diverged_rollout():
    x, rest = _swing()
    diag, D = bbox_diagonal(rest), np.array([0])
    shifted = x + np.array([0.0, 0.0, 0.01])
    m, c = rollout_metrics(shifted, x, x[:, D], D, np.ones(len(rest)), 0.01, diag, -1)
    m1 = m
    assert list(m) == ["frames", "diverged_frame", "mean_error", "max_error", "dirichlet_error", "kinetic_ratio", "end_error",
                       "end_motion", "end_motion_truth"]  # fmt: skip
    assert m["frames"] == 20 and m["diverged_frame"] == -1
    for k in ("mean_error", "max_error", "dirichlet_error", "end_error"):
        assert np.isclose(m[k], 0.01 / diag), k
    # a rigid shift moves nothing: the same kinetic energy and the same residual motion as the truth
    assert np.isclose(m["kinetic_ratio"], 1.0) and np.isclose(m["end_motion"], m["end_motion_truth"]) and m["end_motion"] > 0
    np.testing.assert_allclose(c["ke_pred"], c["ke_truth"], atol=1e-15)
    diverged = shifted.copy()
    diverged[12:] = np.nan
    m, c = rollout_metrics(diverged, x, x[:, D], D, np.ones(len(rest)), 0.01, diag, 12)
    # frames 12-19 failed: infinite errors over the whole sequence; the curves keep the 12 frames survived
    for k in ("mean_error", "max_error", "dirichlet_error", "end_error"):
        assert m[k] == np.inf, k
    assert np.isnan(m["kinetic_ratio"]) and np.isnan(m["end_motion"]) and np.isclose(m["end_motion_truth"], m1["end_motion_truth"])
    assert len(c["mean_error"]) == len(c["ke_pred"]) == 12 and c["frames"] == 20 and c["diverged_frame"] == 12
    np.testing.assert_allclose(c["mean_error"], 0.01 / diag)


def _write(path, rest, sequences, method=None):
    """A trajectory-layout file: ground truth (no method) or a rollout (method, latents, step_ms, diverged_frame)."""
    with h5py.File(path, "w") as f:
        f.attrs["dt"] = 0.01
        f["rest_positions"], f["masses"], f["dirichlet"] = rest, np.ones(len(rest)), np.array([0])
        if method:
            f.attrs["method"] = method
        for name, (x, div) in sequences.items():
            g = f.create_group(f"sequences/{name}")
            g["positions"], g["dirichlet_positions"], g["frame_ms"] = x, x[:, [0]], np.full(len(x), 4.0)
            if method:
                g["latents"] = np.zeros((len(x), 3))
                g.attrs["diverged_frame"], g.attrs["step_ms"] = div, 0.5
    return path


def test_evaluate_scene_one_row_per_method_and_sequence(tmp_path):
    x, rest = _swing()
    gt = _write(tmp_path / "trajectories.h5", rest, {"s0": (x, -1), "s1": (x, -1)})
    ok = _write(tmp_path / "ok.h5", rest, {"s0": (x + [0, 0, 0.01], -1), "s1": (x, -1)}, method="self_supervised")
    bad = x.copy()
    bad[8:] = np.nan
    div = _write(tmp_path / "div.h5", rest, {"s1": (bad, 8)}, method="supervised_5x256")
    df, curves = evaluate_scene("a", gt, [ok, div])
    assert list(zip(df["method"], df["sequence"])) == [("self_supervised", "s0"), ("self_supervised", "s1"), ("supervised_5x256", "s1")]
    assert list(df.columns[:13]) == ["scene", "method", "seed", "sequence", "frames", "diverged_frame", "mean_error", "max_error",
                                     "dirichlet_error", "kinetic_ratio", "end_error", "end_motion", "end_motion_truth"]  # fmt: skip
    r = df.set_index(["method", "sequence"])
    assert np.isclose(r.loc[("self_supervised", "s0"), "mean_error"], 0.01 / bbox_diagonal(rest))
    assert r.loc[("self_supervised", "s1"), "mean_error"] == 0.0 and r.loc[("supervised_5x256", "s1"), "diverged_frame"] == 8
    assert r.loc[("supervised_5x256", "s1"), "mean_error"] == np.inf  # exact for 8 frames, then failed
    # the simulator's median frame time over one latent step
    assert np.isclose(r.loc[("self_supervised", "s0"), "speedup"], 8.0) and (r["dof"] == rest.size).all() and (r["latent_dim"] == 3).all()
    assert set(curves) == {"self_supervised", "supervised_5x256"} and len(curves["supervised_5x256"]["s1"]["mean_error"]) == 8
    rollout_curves("a", curves, tmp_path / "errors.png")
    assert (tmp_path / "errors.png").stat().st_size > 0
    # a free body has no Dirichlet error to draw: its figure has the error and energy rows alone
    free = {m: {q: dict(c, dirichlet_error=np.full_like(c["dirichlet_error"], np.nan)) for q, c in per.items()} for m, per in curves.items()}
    rollout_curves("a", free, tmp_path / "free.png")
    height = {k: plt.imread(tmp_path / f"{k}.png").shape[0] for k in ("errors", "free")}
    assert height["free"] == pytest.approx(2 / 3 * height["errors"], rel=0.02)


def test_every_methods_speedup_divides_by_the_scenes_one_full_space_time(tmp_path):
    """With the scene's timing table, every row's full_ms is that one time, not a rollout job's own (here 9 ms)."""
    x, rest = _swing()
    gt = _write(tmp_path / "trajectories.h5", rest, {"s0": (x, -1)})
    ok = _write(tmp_path / "ok.h5", rest, {"s0": (x, -1)}, method="self_supervised")
    other = _write(tmp_path / "other.h5", rest, {"s0": (x, -1)}, method="no_noise")
    with h5py.File(ok, "a") as f:
        f.attrs["full_ms"] = 9.0
    assert evaluate_scene("a", gt, [ok])[0]["full_ms"].tolist() == [9.0]  # without the table: the job's own
    df, _ = evaluate_scene("a", gt, [ok, other], full_ms=2.0)
    assert df["full_ms"].tolist() == [2.0, 2.0] and df["speedup"].tolist() == [4.0, 4.0]
    pd.DataFrame([{"sequence": "s0", "full_ms": 3.5, "full_iterations": 2.0, "full_frames_timed": 20}]).to_csv(tmp_path / "t.csv", index=False)
    assert read_full_space_time(tmp_path / "t.csv") == 3.5
    (tmp_path / "bad.csv").write_text("sequence,full_ms\ns0,nan\n")
    with pytest.raises(ValueError, match=r"bad\.csv: not a full-space timing"):
        read_full_space_time(tmp_path / "bad.csv")


def _metrics():
    """Two scenes. On 'a', no_noise (a variant) is a hair faster and more accurate than self_supervised;
    supervised diverges on one of two sequences (there its errors are infinite, as rollout_metrics
    reports them). 'b' runs self_supervised alone."""
    rows = []

    def add(scene, method, seq, err, ms, full, ke, div=-1):
        err, ke, bc = (np.inf, np.nan, np.inf) if div >= 0 else (err, ke, 0.0)
        rows.append(dict(scene=scene, method=method, sequence=seq, mean_error=err, max_error=3 * err, diverged_frame=div,
                         kinetic_ratio=ke, full_ms=full, latent_ms=ms, integrate_ms=ms / 3, decode_ms=2 * ms / 3,
                         jvp_torch_ms=1.0, jvp_forward_ms=0.01, dof=30, latent_dim=2, frames=100, dirichlet_error=bc,
                         end_error=err, end_motion=0.1, end_motion_truth=0.1))  # fmt: skip

    for seq, full in (("s0", 10.0), ("s1", 12.0)):
        add("a", "self_supervised", seq, 0.020, 0.10, full, 0.9)
        add("a", "no_noise", seq, 0.019, 0.099, full, 0.8)
        add("a", "pca_reduced", seq, 0.001, 2.0, full, 1.0)
        add("a", "supervised_5x256", seq, 0.005, 0.05, full, 1.1, div=40 if seq == "s1" else -1)
    add("b", "self_supervised", "t", 0.3, 0.2, 5.0, 1.2)
    return pd.DataFrame(rows)


def _stress():
    def row(method, c, diverged):
        return dict(scene="a", method=method, condition=c, frames=50, frames_survived=20 if diverged else 50,
                    diverged=diverged, bc_error=0.0)  # fmt: skip

    return pd.DataFrame([row("self_supervised", c, False) for c in "xyz"] + [row("supervised_5x256", c, c != "x") for c in "xyz"])


def test_glance_table_rows(tmp_path):
    df = _metrics()
    speed_accuracy_chart(speed_accuracy_points(df), tmp_path / "c.png")
    g = glance_table(df, _stress()).set_index(["scene", "method"])
    ss = g.loc[("a", "self_supervised")]
    # own job's ratio: mean full ms (11) over mean latent ms (0.1)
    assert np.isclose(ss["speedup"], 110.0)
    assert np.isclose(ss["mean_error"], 0.020) and np.isclose(ss["max_error"], 0.060)
    assert np.isclose(ss["kinetic_ratio"], 0.9)
    assert ss["test_survived"] == "2/2" and ss["stress_survived"] == "3/3"
    sup = g.loc[("a", "supervised_5x256")]
    assert sup["test_survived"] == "1/2" and sup["stress_survived"] == "1/3"
    assert not sup["on_front"]  # diverged: off the front though fastest
    full = g.loc[("a", "full_space")]
    assert full["speedup"] == 1.0 and full["mean_error"] == 0.0 and full["test_survived"] == "2/2" and full["on_front"]
    assert g.loc[("a", "pca_reduced"), "stress_survived"] == ""  # no stress conditions ran
    # the chart's front counts variants: no_noise dominates self_supervised
    assert g.loc[("a", "no_noise"), "on_front"] and not ss["on_front"]
    # sorted by scene, then ms per frame
    flat = g.reset_index()
    for _, s in flat.groupby("scene"):
        assert list(s["ms_per_frame"]) == sorted(s["ms_per_frame"])


def test_glance_grid_front_of_the_compared_methods():
    df = _metrics()
    grid = glance_grid(glance_table(df, _stress())).set_index("scene")
    # columns: the comparison's methods present, in the comparison's order; variants left out
    assert list(grid.columns) == ["full_space", "pca_reduced", "self_supervised", "supervised_5x256"]
    assert grid.loc["a", "self_supervised"] == "0.02 (0.1) *"  # no_noise is not in the grid's front
    assert grid.loc["a", "supervised_5x256"] == "diverged 1/2 (0.05)"  # diverged: no error, no star
    assert grid.loc["a", "pca_reduced"].endswith("*") and grid.loc["a", "full_space"].endswith("*")
    assert grid.loc["b", "pca_reduced"] == "-"


def test_summary_markdown_opens_with_the_glance(tmp_path):
    df = _metrics()
    df.to_csv(tmp_path / "m.csv", index=False)
    _stress().to_csv(tmp_path / "st.csv", index=False)
    summarise([tmp_path / "m.csv"], tmp_path / "s.csv", tmp_path / "s.md", tmp_path / "s.png",
              stress=[tmp_path / "st.csv"], stress_paths=(tmp_path / "stress.csv", tmp_path / "stress.png"),
              glance_path=tmp_path / "glance.csv")  # fmt: skip
    text = (tmp_path / "s.md").read_text()
    assert text.startswith("## What the tables say") and "\n## At a glance" in text
    assert "| a | 0 (11) * | 0.001 (2) * | 0.02 (0.1) * | diverged 1/2 (0.05) |" in text
    assert "| a | supervised_5x256 | 1 | 0.05 | 0.05 | 0.05 | 220 | 220 | 220 | inf | nan | nan | inf | nan | nan | nan | 0/1 | 1/2 | 1/3 | False |" in text
    assert "| a | self_supervised | 1 | 0.1 | 0.1 | 0.1 | 110 | 110 | 110 | 0.02 | 0.02 | 0.02 | 0.06 | 0.9 | 0.9 | 0.9 | 1/1 | 2/2 | 3/3 | False |" in text
    assert "| a | supervised_5x256 | 1 | 1/1 | 100/40 | 100/100 | 1/1 | 0/1 | 1/1 (20) | 1/1 (20) |" in text  # Fig. 8 over seeds
    g = pd.read_csv(tmp_path / "glance.csv", keep_default_na=False)
    assert len(g) == 7 and set(g["method"]) == {"full_space", "self_supervised", "no_noise", "pca_reduced", "supervised_5x256"}


def _html_tables(text: str) -> list:
    """[(header cells, body rows)] of the tables of a page as write_table_html writes them (cells unescaped)."""
    out = []
    for table in re.findall(r"<table>(.*?)</table>", text, re.S):
        rows = [[html.unescape(c) for c in re.findall(r"<t[hd][^>]*>(.*?)</t[hd]>", tr, re.S)] for tr in re.findall(r"<tr>(.*?)</tr>", table, re.S)]
        out.append((rows[0], rows[1:]))
    return out


def test_table_pages_show_every_table_every_row(tmp_path):
    """The report's pages: a CSV's every column and row (4 significant digits, the full value in the tooltip),
    every table of the summary's Markdown under its heading, the glance grid above the glance table and alone
    in the landing page's fragment."""
    df = _metrics()
    df.to_csv(tmp_path / "m.csv", index=False)
    _stress().to_csv(tmp_path / "st.csv", index=False)
    summarise([tmp_path / "m.csv"], tmp_path / "s.csv", tmp_path / "s.md", tmp_path / "s.png", table1_path=tmp_path / "t1.csv",
              stress=[tmp_path / "st.csv"], stress_paths=(tmp_path / "stress.csv", tmp_path / "stress.png"),
              glance_path=tmp_path / "glance.csv")  # fmt: skip
    t1 = pd.read_csv(tmp_path / "t1.csv")
    assert write_table_html(tmp_path / "t1.csv", tmp_path / "t1.html", title="Table 1") == 1
    text = (tmp_path / "t1.html").read_text()
    assert "<title>Table 1</title>" in text and "t1.csv: 2 rows x" in text
    [(head, rows)] = _html_tables(text)
    assert head == list(t1.columns) and len(rows) == len(t1)
    assert rows[0][head.index("speedup")] == f"{t1['speedup'][0]:.4g}" and rows[0][0] == "a"
    v = float(t1["integrate_ms"][0])  # 0.1 / 3, to the CSV's 6 digits: 4 shown, all in the tooltip
    assert rows[0][head.index("integrate_ms")] == "0.03333" and f'title="{v!r}"' in text
    md = (tmp_path / "s.md").read_text()
    assert write_table_html(tmp_path / "s.md", tmp_path / "s.html") == md.count("## ") - md.count("(no rows)") - 1  # a table per heading, but empty ones and the claims
    tables = _html_tables((tmp_path / "s.html").read_text())
    assert tables[0][1][0] == ["a", "0 (11) *", "0.001 (2) *", "0.02 (0.1) *", "diverged 1/2 (0.05)"]  # the glance grid
    assert tables[-1][0] == list(df.columns) and len(tables[-1][1]) == len(df)  # every method and test sequence
    grid = write_glance_html(tmp_path / "glance.csv", tmp_path / "glance.html", tmp_path / "grid.html")
    page = _html_tables((tmp_path / "glance.html").read_text())
    assert [r[0] for r in page[0][1]] == list(grid["scene"]) == ["a", "b"] and len(page[1][1]) == 7
    fragment = (tmp_path / "grid.html").read_text()
    assert fragment.startswith('<div class="latentsim-glance">') and _html_tables(fragment)[0] == page[0]
    assert "<html" not in fragment


def test_table_pages_of_tabulate_markdown_and_bad_input(tmp_path):
    """pandas' Markdown (tabulate) may hold a bar inside a cell: its columns are cut where the separator's
    bars are; cells are escaped; a file that is not a table is refused by name."""
    df = pd.DataFrame({"ratio": [1.0, 1.5], "max |cos(l, y)|": [3.8e-16, 2.8e-16], "split": ["train", "<held out>"]})
    (tmp_path / "a.md").write_text("# Aspect\n\nText with `code`.\n\n## Per ratio\n\n" + df.to_markdown(index=False, floatfmt=".4g") + "\n")
    assert write_table_html(tmp_path / "a.md", tmp_path / "a.html") == 1
    text = (tmp_path / "a.html").read_text()
    assert "<h1>Aspect</h1>" in text and "<code>code</code>" in text and "<h2>Per ratio</h2>" in text and "&lt;held out&gt;" in text
    [(head, rows)] = _html_tables(text)
    assert head == list(df.columns) and rows == [["1", "3.8e-16", "train"], ["1.5", "2.8e-16", "<held out>"]]
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(ValueError, match="x.txt: expected a .csv or .md"):
        write_table_html(tmp_path / "x.txt", tmp_path / "x.html")
    (tmp_path / "b.md").write_text("| a | b |\n| 1 | 2 |\n")
    with pytest.raises(ValueError, match="no separator line"):
        write_table_html(tmp_path / "b.md", tmp_path / "b.html")
    assert not (tmp_path / "b.html").exists()


def test_tables_1_and_2_give_a_variant_of_another_size_a_row_of_its_own():
    df = _metrics()
    small = df[(df["scene"] == "a") & (df["method"] == "no_noise")].assign(method="small", latent_dim=1, latent_ms=0.01, decode_ms=0.006)
    df = pd.concat([small, df], ignore_index=True)  # listed first: the tables still put the scene's own model first
    t1 = table1(df, sized=["small"])
    assert list(zip(t1["scene"], t1["method"])) == [("a", "self_supervised"), ("a", "small"), ("b", "self_supervised")]
    row = t1.set_index(["scene", "method"]).loc[("a", "small")]
    assert row["latent_dof"] == 1 and np.isclose(row["full_ms"], 11.0) and np.isclose(row["speedup"], 1100.0)
    assert list(table1(df)["method"]) == ["self_supervised", "self_supervised"]  # no_noise, supervised: the scene's size
    layers = {"a": ("8, 8", "8"), ("a", "small"): ("4", "4")}
    t2 = table2(df, layers, sized=["small"]).set_index(["scene", "method"])
    assert t2.loc[("a", "small"), "decoder_layers"] == "4" and t2.loc[("a", "self_supervised"), "decoder_layers"] == "8, 8"
    assert np.isclose(t2.loc[("a", "small"), "ours_ms"], 0.01) and ("b", "small") not in t2.index
