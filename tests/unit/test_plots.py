"""Charts, renders, clips and ParaView series (latentsim.report.plots, .render, .paraview; the Pareto front of .metrics).

Everything runs on hand-made points and tiny synthetic trajectory files (a
3-rod comb, a 4x3 cloth, a two-tet block), so the module takes a few seconds.
"""

import h5py
import matplotlib.image as mpimg
import meshio
import numpy as np
import pandas as pd
import pytest
from PIL import Image

from latentsim.report import metrics, paraview, plots, render
from latentsim.io import ArtefactError
from latentsim.neural_modes.figures import grid_wrap
from latentsim.utils import working_directory

# --------------------------------------------------------------------------- Pareto front


def test_pareto_front_hand_made_points():
    #            A    B    C    D    E    F
    times = [1.0, 2.0, 3.0, 2.5, 0.5, 4.0]
    errors = [0.5, 0.2, 0.1, 0.3, 2.0, 0.1]
    # D is dominated by B (faster, more accurate); F ties C's error but is slower
    expected = [True, True, True, False, True, False]
    np.testing.assert_array_equal(metrics.pareto_front(times, errors), expected)


def test_pareto_front_ties_duplicates_and_nan():
    # duplicates: both on the front; same time, larger error: dominated
    m = metrics.pareto_front([1.0, 1.0, 1.0, 2.0], [0.3, 0.3, 0.4, 0.1])
    np.testing.assert_array_equal(m, [True, True, False, True])
    # a diverged method (NaN error), however fast, is excluded and dominates nothing
    m = metrics.pareto_front([0.1, 1.0, 2.0, np.inf], [np.nan, 0.5, 0.6, 0.01])
    np.testing.assert_array_equal(m, [False, True, False, False])
    # all NaN: empty front; one point: on the front
    assert not metrics.pareto_front([np.nan], [np.nan]).any()
    assert metrics.pareto_front([3.0], [1e-9]).all()
    with pytest.raises(ValueError, match="differ in length"):
        metrics.pareto_front([1.0, 2.0], [1.0])


# --------------------------------------------------------------------------- charts


def _png(path):
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    # not blank: a chart has both dark and light pixels
    assert img[..., :3].min() < 0.3 and img[..., :3].max() > 0.9
    return img


def _speed_metrics():
    """Per-sequence metrics of two scenes as the evaluate stage writes them (one sequence, one seed): the
    full space at 20 ms (x10 on the armadillo), five methods."""
    rows = []
    for scene, scale in [("cloth", 1.0), ("armadillo", 10.0)]:
        for method, ms, error, diverged in [("newton_1it", 5, 0.02, -1), ("pca", 0.5, 0.08, -1), ("supervised", 0.3, 0.01, 120),
                                            ("self_supervised", 0.4, 0.03, -1), ("neural_modes", 2.0, 0.05, -1)]:  # fmt: skip
            rows.append({"scene": scene, "method": method, "seed": 0, "sequence": "q", "latent_ms": ms * scale, "full_ms": 20 * scale,
                         "mean_error": error, "max_error": 2 * error, "kinetic_ratio": 1.0, "diverged_frame": diverged})  # fmt: skip
    return pd.DataFrame(rows)


def _speed_df():
    """The chart's points of :func:`_speed_metrics` (:func:`latentsim.report.tables.speed_accuracy_points`)."""
    from latentsim.report.tables import speed_accuracy_points

    return speed_accuracy_points(_speed_metrics())


def test_speed_accuracy_points_and_chart_one_scene_and_summary(tmp_path):
    pts = _speed_df()
    cloth = pts[pts["scene"] == "cloth"]
    assert len(cloth) == 6 and "full_space" in set(cloth["method"])
    # supervised is the fastest and most accurate but diverged: off the front;
    # neural_modes is slower and less accurate than self_supervised; pca less accurate and slower than it too
    assert set(cloth.loc[cloth["on_front"], "method"]) == {"full_space", "newton_1it", "self_supervised"}
    assert pts.groupby("scene")["on_front"].sum().tolist() == [3, 3]
    plots.speed_accuracy_chart(pts, tmp_path / "cloth.png", scene="cloth", dpi=60)
    _png(tmp_path / "cloth.png")
    plots.speed_accuracy_chart(pts, tmp_path / "summary.png", dpi=60)
    _png(tmp_path / "summary.png")


def _marker_path(marker):
    """A marker's outline in points, as :meth:`~matplotlib.axes.Axes.scatter` stores it."""
    from matplotlib.markers import MarkerStyle

    style = MarkerStyle(marker)
    return style.get_path().transformed(style.get_transform())


@pytest.mark.parametrize("scene", ["cloth", None])
def test_speed_accuracy_legend_markers_are_the_plotted_ones(scene):
    """Each method's legend handle has the marker its points are drawn with (the full space's triangle at
    error 0, a circle for a measured error), on one scene's chart and on the summary's small multiples."""
    import matplotlib.pyplot as plt

    pts = _speed_df()
    fig = plots.speed_accuracy_figure(pts, scene=scene)
    legend = fig.axes[0].get_legend() if scene else fig.legends[0]
    in_legend = {t.get_text(): h.get_marker() for t, h in zip(legend.get_texts(), legend.legend_handles)}
    plotted = {}
    for ax in fig.axes:
        for c in ax.collections:
            if (c.get_gid() or "").startswith("point "):
                plotted.setdefault(c.get_gid().removeprefix("point "), []).append(c.get_paths()[0])
    plt.close(fig)
    assert set(plotted) == set(pts["method"]) and len(plotted["full_space"]) == (1 if scene else 2)
    assert in_legend["full_space"] == "v" and in_legend["pca"] == "o"
    for method, paths in plotted.items():
        drawn = _marker_path(in_legend[method])
        for path in paths:
            np.testing.assert_allclose(path.vertices, drawn.vertices, err_msg=method)


def test_speed_accuracy_points_aggregate_sequences():
    from latentsim.report.tables import speed_accuracy_points

    base = {"scene": "s", "seed": 0, "full_ms": 10.0, "kinetic_ratio": 1.0}
    df = pd.DataFrame(
        [
            {**base, "method": "a", "sequence": "q1", "latent_ms": 1.0, "mean_error": 0.1, "max_error": 0.5, "diverged_frame": -1},
            {**base, "method": "a", "sequence": "q2", "latent_ms": 3.0, "mean_error": 0.3, "max_error": 0.9, "diverged_frame": -1},
            {**base, "method": "b", "sequence": "q1", "latent_ms": 2.0, "mean_error": 0.1, "max_error": 0.2, "diverged_frame": -1},
            {**base, "method": "b", "sequence": "q2", "latent_ms": 2.0, "mean_error": 0.1, "max_error": 0.2, "diverged_frame": 50},
        ]
    )
    pts = speed_accuracy_points(df).set_index("method")
    assert pts.loc["a", "ms_per_frame"] == pytest.approx(2.0)
    assert pts.loc["a", "mean_error"] == pytest.approx(0.2)
    assert pts.loc["a", "max_error"] == pytest.approx(0.9)
    assert pts.loc["b", "diverged_frame"] == 50 and pts.loc["b", "diverged_seeds"] == 1
    assert pts["on_front"].to_dict() == {"a": True, "b": False, "full_space": True}


def test_a_method_that_enters_a_collider_is_off_the_front_and_ringed(tmp_path):
    """With colliders (column max_penetration): the deepest entry of each seed, its median over seeds; a
    method whose median exceeds 1% of the diagonal is off the front however fast and accurate, the full
    space stands at 0, and the chart still draws."""
    from latentsim.report.metrics import PENETRATION_LIMIT
    from latentsim.report.tables import speed_accuracy_points

    base = {"scene": "s", "sequence": "q", "frames": 100, "full_ms": 10.0, "kinetic_ratio": 1.0, "diverged_frame": -1}
    rows = [{**base, "method": "fast", "seed": k, "latent_ms": 0.01, "mean_error": 0.01, "max_error": 0.05, "max_penetration": pen}
            for k, pen in enumerate([0.02, 0.12, 0.0])]  # fmt: skip
    rows += [{**base, "method": "shallow", "seed": k, "latent_ms": 1.0, "mean_error": 0.02, "max_error": 0.05, "max_penetration": pen}
             for k, pen in enumerate([0.004, 0.0, 0.009])]  # fmt: skip
    pts = speed_accuracy_points(pd.DataFrame(rows)).set_index("method")
    assert pts.loc["fast", "max_penetration"] == pytest.approx(0.02) and 0.02 > PENETRATION_LIMIT
    assert (pts.loc["fast", "max_penetration_min"], pts.loc["fast", "max_penetration_max"]) == pytest.approx((0.0, 0.12))
    assert pts.loc["full_space", "max_penetration"] == 0.0
    assert pts["on_front"].to_dict() == {"fast": False, "full_space": True, "shallow": True}
    plots.speed_accuracy_chart(pts.reset_index(), tmp_path / "s.png", scene="s", dpi=60)
    _png(tmp_path / "s.png")
    # a scene without colliders has no such column
    assert "max_penetration" not in speed_accuracy_points(_speed_metrics()).columns
    # the tables say it too: the grid's cell and front, the long table's columns, the claims' sentence
    from latentsim.report.tables import claims, divergence_table, glance_grid, glance_table

    df = pd.DataFrame(rows)
    glance = glance_table(df)
    assert {"max_penetration", "max_penetration_min", "max_penetration_max"} <= set(glance.columns)
    grid = glance_grid(glance, methods=("full_space", "fast", "shallow")).set_index("scene")
    assert grid.loc["s", "fast"].endswith("inside 2%") and grid.loc["s", "shallow"].endswith("inside 0.4% *")
    text = claims(glance, divergence_table(df))
    assert "- s, fast: " in text and "enters a collider by 2% of the diagonal (median of 3 seeds; 0% to 12%)" in text


def test_speed_accuracy_labels_of_nearby_divergences_do_not_overlap():
    """Two methods that diverged at nearly the same speed and error get their labels a line apart;
    a far one keeps the first line."""
    import matplotlib.pyplot as plt

    pts = pd.DataFrame(
        [
            {"scene": "s", "method": "a", "ms_per_frame": 0.12, "mean_error": 0.80, "diverged_frame": 335, "on_front": False},
            {"scene": "s", "method": "b", "ms_per_frame": 0.13, "mean_error": 0.76, "diverged_frame": 687, "on_front": False},
            {"scene": "s", "method": "c", "ms_per_frame": 50.0, "mean_error": 0.01, "diverged_frame": 40, "on_front": False},
        ]
    )
    fig, ax = plt.subplots()
    plots._draw_speed_accuracy(ax, pts, {"a": "r", "b": "g", "c": "b"}, annotate=False)
    offsets = {t.get_text(): t.xyann for t in ax.texts}
    plt.close(fig)
    assert offsets["diverged @ 335"] == (5, 4) and offsets["diverged @ 687"] == (5, 13)
    assert offsets["diverged @ 40"] == (5, 4)


def test_speed_accuracy_labels_stay_inside_their_axes():
    """A long label of a point near the right edge is written to its left, inside the axes (not over
    the legend); one near the left edge, and a failed row's label (under the top edge), stay right."""
    import matplotlib.pyplot as plt

    pts = pd.DataFrame(
        [
            {"scene": "s", "method": "a_method_with_a_long_name", "ms_per_frame": 9.0, "mean_error": 0.01, "diverged_frame": -1,
             "on_front": False, "max_penetration": 0.123},
            {"scene": "s", "method": "fast", "ms_per_frame": 0.01, "mean_error": 0.02, "diverged_frame": -1, "on_front": False},
            {"scene": "s", "method": "failed", "ms_per_frame": 0.02, "mean_error": np.inf, "diverged_frame": 7, "on_front": False},
        ]
    )
    fig, ax = plt.subplots(figsize=(4, 3))
    plots._draw_speed_accuracy(ax, pts, {m: "k" for m in pts["method"]}, annotate=True)
    plots._place_labels(fig, [ax])
    renderer = fig.canvas.get_renderer()
    box = ax.get_window_extent(renderer)
    labels = {t.get_text().split(" ")[0]: t for t in ax.texts if hasattr(t, "xyann")}
    long = labels["a_method_with_a_long_name"]
    assert long.get_horizontalalignment() == "right" and long.xyann[0] < 0
    assert long.get_window_extent(renderer).x1 <= box.x1
    assert labels["fast"].get_horizontalalignment() == "left"
    assert labels["failed"].get_horizontalalignment() == "left" and labels["failed"].xyann[1] < 0
    plt.close(fig)


def test_speed_accuracy_labels_of_crowded_points_do_not_overlap():
    """Four methods with long names a little over half a decade of ms apart, at nearly the same error
    (drawn as they come, 3 pairs of labels overlap and 2 labels leave the axes): after placement no two
    labels overlap, and each stays inside the axes."""
    import matplotlib.pyplot as plt

    pts = pd.DataFrame(
        [{"scene": "s", "method": f"a_method_with_a_long_name_{k}", "ms_per_frame": 0.01 * 4.0**k, "mean_error": 0.01 * 1.1**k,
          "diverged_frame": -1, "on_front": False} for k in range(4)]  # fmt: skip
    )
    fig, ax = plt.subplots(figsize=(4, 3))
    plots._draw_speed_accuracy(ax, pts, {m: "k" for m in pts["method"]}, annotate=True)
    plots._place_labels(fig, [ax])
    renderer = fig.canvas.get_renderer()
    box = ax.get_window_extent(renderer)
    extents = [t.get_window_extent(renderer) for t in ax.texts if hasattr(t, "xyann")]
    plt.close(fig)
    assert len(extents) == 4
    for i, a in enumerate(extents):
        assert box.x0 <= a.x0 and a.x1 <= box.x1 and box.y0 <= a.y0 and a.y1 <= box.y1
        for b in extents[:i]:
            assert min(a.x1, b.x1) <= max(a.x0, b.x0) or min(a.y1, b.y1) <= max(a.y0, b.y0), (a, b)


def test_speed_accuracy_chart_bad_input_names_the_problem(tmp_path):
    df = _speed_df()
    with pytest.raises(KeyError, match="ms_per_frame"):
        plots.speed_accuracy_chart(df.drop(columns="ms_per_frame"), tmp_path / "x.png")
    with pytest.raises(KeyError, match="'bunny'"):
        plots.speed_accuracy_chart(df, tmp_path / "x.png", scene="bunny")
    bad = df.copy()
    bad.loc[(bad["scene"] == "cloth") & (bad["method"] == "pca"), "ms_per_frame"] = 0.0
    with pytest.raises(ValueError, match="pca"):
        plots.speed_accuracy_chart(bad, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_stability_heatmap_cells(tmp_path):
    df = pd.DataFrame(
        [
            {"method": "supervised", "condition": "speed x0.1", "frames_survived": 300, "frames": 300, "bc_error": 1e-4, "diverged_frame": -1},
            {"method": "supervised", "condition": "speed x5", "frames_survived": 42, "frames": 300, "bc_error": 0.5, "diverged_frame": 42},
            {"method": "self_supervised", "condition": "speed x5", "frames_survived": 300, "frames": 300, "bc_error": 2e-3, "diverged_frame": -1},
            {"method": "self_supervised", "condition": "10x longer", "frames_survived": 2500, "frames": 3000, "bc_error": 0.1, "diverged_frame": 2500},
        ]
    )
    out = plots.stability_heatmap(df, tmp_path / "stab.png")
    assert out["methods"] == ["supervised", "self_supervised"]
    assert out["conditions"] == ["speed x0.1", "speed x5", "10x longer"]
    F = out["frames"]
    assert F[0, 1] == 42 and F[1, 1] == 300 and F[1, 2] == 2500 and F[0, 0] == 300
    assert np.isnan(F[0, 2]) and np.isnan(F[1, 0])  # pairs with no run
    assert out["colour"][1, 2] == pytest.approx(2500 / 3000)
    np.testing.assert_array_equal(out["diverged"], [[False, True, False], [False, False, True]])
    assert out["bc_error"][0, 1] == pytest.approx(0.5)
    _png(tmp_path / "stab.png")


def test_stability_heatmap_text_in_the_right_cell(tmp_path, monkeypatch):
    """The annotated number and BC error sit at the cell's (column, row) position."""
    import matplotlib.pyplot as plt

    seen = {}
    real_close = plt.close

    def grab(fig=None):
        if fig is not None and hasattr(fig, "axes") and fig.axes:
            seen["texts"] = [(t.get_position(), t.get_text()) for t in fig.axes[0].texts]
        real_close(fig)

    monkeypatch.setattr(plots.plt, "close", grab)
    df = pd.DataFrame(
        [
            {"method": "m1", "condition": "c1", "frames_survived": 17, "bc_error": 0.25, "diverged": True},
            {"method": "m2", "condition": "c2", "frames_survived": 99, "bc_error": 0.001, "diverged": False},
            {"method": "m1", "condition": "c3", "frames_survived": 5, "bc_error": 0.5, "diverged": False},
        ]
    )
    plots.stability_heatmap(df, tmp_path / "s.png", dpi=50)
    texts = dict(seen["texts"])  # position (column, row) -> text
    assert len(texts) == 6
    assert texts[(0, 0)].startswith("✗ 17") and "BC 2.5e-01" in texts[(0, 0)]
    assert texts[(1, 1)].startswith("99") and "BC 1.0e-03" in texts[(1, 1)]
    assert texts[(2, 0)].startswith("5\n") and "BC 5.0e-01" in texts[(2, 0)]
    assert texts[(1, 0)] == texts[(0, 1)] == texts[(2, 1)] == "n/a"


def test_stability_heatmap_rejects_duplicates(tmp_path):
    df = pd.DataFrame([{"method": "a", "condition": "c", "frames_survived": 1}] * 2)
    with pytest.raises(ValueError, match=r"\('a', 'c'\)"):
        plots.stability_heatmap(df, tmp_path / "s.png")
    with pytest.raises(KeyError, match="frames_survived"):
        plots.stability_heatmap(df.drop(columns="frames_survived"), tmp_path / "s.png")


def test_energy_and_training_curves(tmp_path):
    t = np.linspace(0, 1, 50)
    ke = np.sin(3 * t) ** 2
    bad = ke.copy()
    bad[30:] = np.nan
    drawn = plots.energy_curves(
        {
            "ground truth": {"kinetic": ke, "incremental_potential": -ke},
            "pca": {"kinetic": 0.9 * ke},
            "supervised": {"kinetic": bad, "incremental_potential": -bad},
        },
        tmp_path / "e.png",
        dt=0.02,
        dpi=60,
    )
    assert drawn == {"kinetic": ["ground truth", "pca", "supervised"], "incremental_potential": ["ground truth", "supervised"]}
    _png(tmp_path / "e.png")
    with pytest.raises(KeyError, match="'ground truth'"):
        plots.energy_curves({"pca": {"kinetic": ke}}, tmp_path / "e2.png", dt=0.02)
    with pytest.raises(ValueError, match="'pca'.*'kinetic'"):
        plots.energy_curves({"ground truth": {"kinetic": ke}, "pca": {"kinetic": np.ones((3, 2))}}, tmp_path / "e2.png", dt=0.02)

    h5 = tmp_path / "history.h5"
    with h5py.File(h5, "w") as f:
        f["loss"] = np.geomspace(1.0, 1e-3, 20)
    out = plots.training_curves({"from file": h5, "array": np.geomspace(2.0, 1e-2, 30)}, tmp_path / "t.png")
    assert out["yscale"] == "log" and len(out["runs"]["from file"]) == 20
    _png(tmp_path / "t.png")
    out = plots.training_curves({"energy loss": np.linspace(1.0, -2.0, 10)}, tmp_path / "t2.png")
    assert out["yscale"] == "symlog"
    with pytest.raises(ArtefactError, match="latent_mse"):
        plots.training_curves({"run": h5}, tmp_path / "t3.png", key="latent_mse")


def test_empty_figure_says_why(tmp_path):
    plots.empty_figure(tmp_path / "none.png", "no stress conditions were run")
    _png(tmp_path / "none.png")  # the text: dark pixels on white


# --------------------------------------------------------------------------- tiny trajectory files


def _write_traj(path, model, rest, cells, sequences, method=None, dirichlet=(0,)):
    with h5py.File(path, "w") as f:
        f.attrs["model"] = model
        f.attrs["dt"] = 0.05
        f.attrs["gravity"] = [0.0, -9.81, 0.0]
        if method:
            f.attrs["method"] = method
        f["rest_positions"] = rest
        f["masses"] = np.ones(len(rest))
        f["dirichlet"] = np.asarray(dirichlet, dtype=np.int64)
        for k, v in cells.items():
            f[k] = v
        for name, (pos, div) in sequences.items():
            g = f.create_group(f"sequences/{name}")
            g["positions"] = pos
            g.attrs["split"] = "test"
            if div is not None:
                g.attrs["diverged_frame"] = div
    return path


def _swing(rest, T, amp=0.05):
    t = np.arange(T)[:, None, None]
    pos = np.repeat(rest[None], T, axis=0)
    pos[..., 0] += amp * np.sin(0.3 * t[..., 0]) * (rest[None, :, 1] - rest[:, 1].max())
    return pos


def _rods():
    # 3 hanging rods of 4 vertices each
    rest = np.array([[x, -0.1 * k, 0.0] for x in (0.0, 0.1, 0.2) for k in range(4)])
    edges = np.array([[4 * r + k, 4 * r + k + 1] for r in range(3) for k in range(3)])
    return "rods", rest, {"edges": edges}, [0, 4, 8]


def _cloth():
    xs, ys = np.meshgrid(np.linspace(0, 0.3, 4), np.linspace(0, -0.2, 3))
    rest = np.stack([xs.ravel(), ys.ravel(), np.zeros(12)], axis=1)
    tris = []
    for i in range(2):
        for j in range(3):
            a, b, c, d = 4 * i + j, 4 * i + j + 1, 4 * (i + 1) + j, 4 * (i + 1) + j + 1
            tris += [[a, c, b], [b, c, d]]
    return "shell", rest, {"triangles": np.array(tris)}, [0, 3]


def _tets():
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=float) * 0.1
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    # orient both positively
    for k, t in enumerate(tets):
        a, b, c, d = rest[t]
        if np.dot(np.cross(b - a, c - a), d - a) < 0:
            tets[k] = t[[0, 2, 1, 3]]
    return "tets", rest, {"tets": tets}, [0]


@pytest.fixture(params=["rods", "cloth", "tets"])
def example(request, tmp_path):
    model, rest, cells, D = {"rods": _rods, "cloth": _cloth, "tets": _tets}[request.param]()
    T = 12
    truth = _swing(rest, T)
    good = truth + 0.002
    bad = truth * 1.0
    bad[5:] = np.nan
    gt = _write_traj(tmp_path / "trajectories.h5", model, rest, cells, {"seq": (truth, None)}, dirichlet=D)
    ok = _write_traj(tmp_path / "ok.h5", model, rest, cells, {"seq": (good, -1)}, method="self_supervised", dirichlet=D)
    div = _write_traj(tmp_path / "div.h5", model, rest, cells, {"seq": (bad, 5)}, method="supervised", dirichlet=D)
    return {"model": model, "rest": rest, "cells": cells, "truth": truth, "good": good, "gt": gt, "ok": ok, "div": div, "T": T, "D": D}


def test_render_frames(example, tmp_path):
    out = tmp_path / "frames.png"
    r = render.render_frames(example["gt"], {"self": example["ok"], "sup": example["div"]}, "seq", [0, 4, 8], out, dpi=50)
    assert r["labels"] == ["ground truth", "self", "sup"]
    np.testing.assert_array_equal(
        r["status"], [["ok", "ok", "ok"], ["ok", "ok", "ok"], ["ok", "ok", "diverged"]]
    )
    # shared limits contain every ground-truth vertex shown
    x = example["truth"][[0, 4, 8]].reshape(-1, 3)
    lim = r["limits"]
    assert lim.shape == (3, 3, 2) and (lim == lim[0]).all()
    assert (x >= lim[0, :, 0]).all() and (x <= lim[0, :, 1]).all()
    img = _png(out)
    # 3 rows x 3 panels, taller than wide
    assert img.shape[0] > img.shape[1]
    err = r["max_error"]
    np.testing.assert_allclose(err[:, 0], 0.0)
    np.testing.assert_allclose(err[:, 1], np.sqrt(3) * 0.002)  # the rollout is the truth shifted by 0.002 per axis
    np.testing.assert_allclose(err[:2, 2], 0.0)  # the diverging rollout equals the truth until frame 5
    assert np.isnan(err[2, 2])
    r2 = render.render_frames(example["gt"], {"self": example["ok"]}, "seq", [4], tmp_path / "err.png", dpi=80, color_by_error=True)
    np.testing.assert_allclose(r2["max_error"], [[0.0, np.sqrt(3) * 0.002]])
    img = _png(tmp_path / "err.png")[..., :3]
    # every vertex is at the top of the scale: the method is drawn in viridis' yellow, the truth is not
    yellow = (img[..., 0] > 0.5) & (img[..., 1] > 0.5) & (img[..., 2] < 0.45)
    panels = img.shape[0] * 0.8  # above the colour bar
    w = img.shape[1]
    assert yellow[: int(panels), w // 2 :].sum() > 3 and yellow[: int(panels), : w // 2].sum() == 0


def test_render_frames_wrap_lays_many_frames_out_as_a_grid(example, tmp_path):
    """Seven frames of two motions, four to a line: two lines of two panel rows, four panels wide (not a
    strip of seven rows); the status keeps one row per frame."""
    out = tmp_path / "grid.png"
    r = render.render_frames(example["gt"], {"self": example["ok"]}, "seq", list(range(7)), out, panel_size=1.0, dpi=20, wrap=4)
    assert r["status"].shape == (7, 2) and (r["status"] == "ok").all()
    assert Image.open(out).size == (4 * 20, round((2 * 2 * 1.0 + 0.9) * 20))
    with pytest.raises(ValueError, match="wrap must be a positive"):
        render.render_frames(example["gt"], {}, "seq", [0], tmp_path / "w.png", wrap=0)
    # the keyframes' strip (7 steps x 2 columns) becomes this 4 x 4 grid; short strips stay as they are
    assert grid_wrap(7, 2) == 4 and grid_wrap(9, 2) == 5 and grid_wrap(4, 2) is None and grid_wrap(3, 8) is None


def test_render_frames_row_bounds(tmp_path):
    model, rest, cells, D = _rods()
    truth = _swing(rest, 6, amp=0.5)
    gt = _write_traj(tmp_path / "gt.h5", model, rest, cells, {"seq": (truth, None)}, dirichlet=D)
    rows = render.render_frames(gt, {}, "seq", [0, 4], tmp_path / "rows.png", bounds="row", dpi=40)["limits"]
    for k, fr in enumerate([0, 4]):
        assert (truth[fr] >= rows[k, :, 0]).all() and (truth[fr] <= rows[k, :, 1]).all()
    assert not np.allclose(rows[0], rows[1])  # the swing moves the frame-4 box
    with pytest.raises(ValueError, match="'row'"):
        render.render_frames(gt, {}, "seq", [0], tmp_path / "x.png", bounds="rows")


def test_render_frames_draws_the_mesh(tmp_path):
    """The panel is not blank: the drawn cloth darkens pixels that stay white without it."""
    model, rest, cells, D = _cloth()
    gt = _write_traj(tmp_path / "gt.h5", model, rest, cells, {"seq": (_swing(rest, 3), None)}, dirichlet=D)
    render.render_frames(gt, {}, "seq", [1], tmp_path / "a.png", dpi=60)
    far = rest + np.array([5.0, 0.0, 0.0])  # a different mesh far outside the ground truth's view
    m = render.Motion("far", "seq", "shell", far[None], np.array([1]), 3, far, np.zeros(0, int), None, cells["triangles"], 0.05)
    r = render.render_frames(gt, {"far": m}, "seq", [1], tmp_path / "b.png", dpi=60)
    a = mpimg.imread(tmp_path / "a.png")[..., :3]
    b = mpimg.imread(tmp_path / "b.png")[..., :3]
    assert (a < 0.6).mean() > 0.01  # the ground truth's surface is drawn
    left, right = b[:, : b.shape[1] // 2], b[:, b.shape[1] // 2 :]
    assert (left < 0.6).mean() > 2 * (right < 0.6).mean()  # the far mesh is clipped out of its view
    assert r["status"].tolist() == [["ok", "ok"]]
    same = render.Motion("same", "seq", "shell", rest[None], np.array([1]), 3, rest, np.zeros(0, int), None, cells["triangles"], 0.05)
    render.render_frames(gt, {"same": same}, "seq", [1], tmp_path / "c.png", dpi=60)
    c = mpimg.imread(tmp_path / "c.png")[..., :3]
    dark_left, dark_right = (c[:, : c.shape[1] // 2] < 0.6).mean(), (c[:, c.shape[1] // 2 :] < 0.6).mean()
    assert dark_right == pytest.approx(dark_left, rel=0.3)  # a mesh in view is drawn in its panel


def test_the_stability_map_prints_and_frames_a_deep_entry_into_a_collider(tmp_path):
    df = pd.DataFrame([{"method": "a", "condition": "x2", "frames": 10, "frames_survived": 10, "max_penetration": 0.12},
                       {"method": "a", "condition": "x5", "frames": 10, "frames_survived": 10, "max_penetration": 0.0}])  # fmt: skip
    out = plots.stability_heatmap(df, tmp_path / "m.png", dpi=60)
    assert out["max_penetration"].tolist() == [[0.12, 0.0]]
    _png(tmp_path / "m.png")
    assert np.isnan(plots.stability_heatmap(df.drop(columns="max_penetration"), tmp_path / "n.png", dpi=60)["max_penetration"]).all()


def test_collider_wireframes_lie_on_their_shapes_and_are_drawn(tmp_path):
    """Every segment end of a sphere's wireframe lies on the sphere, of a capsule's at its radius from the
    axis segment, of a half-space's in its plane; a panel with a collider has more dark pixels."""
    limits = np.array([[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]])
    sphere = {"type": "sphere", "centre": [0.1, -0.2, 0.3], "radius": 0.25}
    capsule = {"type": "capsule", "a": [0.0, 0.0, 0.0], "b": [0.3, 0.4, 0.0], "radius": 0.1}
    plane = {"type": "half_space", "point": [0.0, -0.5, 0.0], "normal": [0.0, 1.0, 1.0]}
    p = render.collider_segments([sphere], limits).reshape(-1, 3)
    assert np.allclose(np.linalg.norm(p - sphere["centre"], axis=1), 0.25)
    p = render.collider_segments([capsule], limits).reshape(-1, 3)
    a, b = np.array(capsule["a"]), np.array(capsule["b"])
    t = np.clip((p - a) @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    assert np.allclose(np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1), 0.1)
    p = render.collider_segments([plane], limits).reshape(-1, 3)
    assert np.allclose((p - plane["point"]) @ (np.array(plane["normal"]) / np.sqrt(2)), 0.0)
    with pytest.raises(ValueError, match="cone"):
        render.collider_segments([{"type": "cone"}], limits)
    model, rest, cells, D = _cloth()
    gt = _write_traj(tmp_path / "gt.h5", model, rest, cells, {"seq": (_swing(rest, 3), None)}, dirichlet=D)
    ball = {"type": "sphere", "centre": [0.15, -0.1, 0.05], "radius": 0.05}
    render.render_frames(gt, {}, "seq", [1], tmp_path / "a.png", dpi=60)
    render.render_frames(gt, {}, "seq", [1], tmp_path / "b.png", dpi=60, colliders=[ball])
    a, b = (mpimg.imread(tmp_path / f)[..., :3] for f in ("a.png", "b.png"))
    assert (b < 0.8).mean() > (a < 0.8).mean()
    # colliders that move with the program: a function of the frame, drawn where it places them at that frame
    away = {**ball, "centre": [5.0, 5.0, 5.0]}
    render.render_frames(gt, {}, "seq", [1], tmp_path / "c.png", dpi=60, colliders=lambda frame: [ball] if frame == 1 else [away])
    assert np.array_equal(mpimg.imread(tmp_path / "c.png"), mpimg.imread(tmp_path / "b.png"))


def test_render_frames_errors_name_sequence_and_frame(example, tmp_path):
    with pytest.raises(ArtefactError, match="no sequence 'nope'"):
        render.render_frames(example["gt"], {"x": example["ok"]}, "nope", [0], tmp_path / "x.png")
    with pytest.raises(ValueError, match=r"frames \[99\].*'seq'"):
        render.render_frames(example["gt"], {}, "seq", [0, 99], tmp_path / "x.png")
    model, rest, cells, _D = _rods()
    other = _write_traj(tmp_path / "other.h5", model, rest[:8], {"edges": cells["edges"][:6]}, {"seq": (rest[None, :8], -1)})
    with pytest.raises(ValueError, match="method 'm'.*8 vertices"):
        render.render_frames(example["gt"], {"m": other}, "seq", [0], tmp_path / "x.png")
    with h5py.File(tmp_path / "nocells.h5", "w") as f:
        f.attrs["model"] = example["model"]
        f["rest_positions"] = example["rest"]
        f["sequences/seq/positions"] = example["truth"]
    key = {"rods": "edges", "shell": "triangles", "tets": "tets"}[example["model"]]
    with pytest.raises(ArtefactError, match=f"'/{key}'"):
        render.load_motion(tmp_path / "nocells.h5", "seq")
    assert not (tmp_path / "x.png").exists()


def test_render_clip_gif(tmp_path):
    model, rest, cells, D = _rods()
    truth = _swing(rest, 30)
    bad = truth.copy()
    bad[12:] = np.nan
    gt = _write_traj(tmp_path / "gt.h5", model, rest, cells, {"seq": (truth, None)}, dirichlet=D)
    ro = _write_traj(tmp_path / "ro.h5", model, rest, cells, {"seq": (bad, 12)}, method="supervised", dirichlet=D)
    out = tmp_path / "clip.gif"
    r = render.render_clip(gt, ro, "seq", out, stride=4, max_frames=5, dpi=40)
    assert r["frames"] == [0, 4, 8, 12, 16]
    assert r["bytes"] == out.stat().st_size > 0
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == 5
        w, h = im.size
        assert w > h > 50  # two panels side by side
        shots = []
        for k in (0, 1, 4):
            im.seek(k)
            shots.append(np.asarray(im.convert("L"), dtype=float))
    assert np.abs(shots[1] - shots[0]).mean() > 0.1  # the rods swing between frames 0 and 4
    # frame 16: the rollout has diverged (frame 12): its panel drops the grey panes and
    # shows only the label, while the ground truth's panel is drawn as before
    half = w // 2

    def pane(img):
        return ((img > 200) & (img < 250)).mean()

    assert pane(shots[2][:, half:]) < 0.3 * pane(shots[1][:, half:])
    assert pane(shots[2][:, :half]) == pytest.approx(pane(shots[1][:, :half]), rel=0.2)
    r = render.render_clip(gt, {"a": ro}, "seq", out, start=20, stride=3, max_frames=100, dpi=40, color_by_error=True)
    assert r["frames"] == [20, 23, 26, 29]
    with Image.open(out) as im:
        assert im.n_frames == 4 and im.size[1] > h  # the colour bar adds a strip below the panels
    with pytest.raises(ValueError, match="'row'"):
        render.render_clip(gt, ro, "seq", out, bounds="row")
    with pytest.raises(ValueError, match="'.avi'"):
        render.render_clip(gt, ro, "seq", tmp_path / "clip.avi")
    if not render.have_ffmpeg():
        with pytest.raises(RuntimeError, match="ffmpeg"):
            render.render_clip(gt, ro, "seq", tmp_path / "clip.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.gif", "gt.h5", "ro.h5"]  # no temporaries left


def test_write_xdmf_series_reads_back(example, tmp_path):
    out = tmp_path / "paraview" / "seq_rollout.xdmf"
    r = paraview.write_xdmf_series(example["ok"], "seq", out, reference=example["gt"])
    n, T = len(example["rest"]), example["T"]
    assert r["frames"] == T and r["fields"] == ["displacement", "dirichlet", "error"]
    assert out.exists() and (out.parent / "seq_rollout.h5").exists()
    assert sorted(p.name for p in out.parent.iterdir()) == ["seq_rollout.h5", "seq_rollout.xdmf"]
    cell_type = {"rods": "line", "shell": "triangle", "tets": "tetra"}[example["model"]]
    with working_directory(out.parent), meshio.xdmf.TimeSeriesReader(out.name) as rd:
        points, cells = rd.read_points_cells()
        assert points.shape == (n, 3) and rd.num_steps == T
        np.testing.assert_allclose(points, example["rest"])
        assert cells[0].type == cell_type
        np.testing.assert_array_equal(cells[0].data, next(iter(example["cells"].values())))
        t, pd_, _ = rd.read_data(7)
        assert t == pytest.approx(7 * 0.05)
        assert pd_["displacement"].shape == (n, 3) and pd_["error"].shape == (n,)
        np.testing.assert_allclose(pd_["displacement"], example["good"][7] - example["rest"])
        np.testing.assert_allclose(pd_["error"], np.sqrt(3) * 0.002)
        np.testing.assert_array_equal(np.flatnonzero(pd_["dirichlet"]), example["D"])
    assert_one_block(out, T)


def assert_one_block(xdmf, steps):
    """ParaView reads the series as one block: the domain holds the temporal collection alone (no static
    ``mesh`` grid drawn over the animation), and every step holds its geometry and topology."""
    import xml.etree.ElementTree as ET

    domain = ET.parse(xdmf).getroot().find("Domain")
    grids = domain.findall("Grid")
    assert [g.get("GridType") for g in grids] == ["Collection"] and grids[0].get("CollectionType") == "Temporal"
    assert len(grids[0].findall("Grid")) == steps
    for step in grids[0].findall("Grid"):
        assert step.find("Geometry") is not None and step.find("Topology") is not None and step.find("Time") is not None
        assert not [e for e in step if "include" in e.tag]


def test_single_block_xdmf_rewrites_meshios_series_once(tmp_path):
    """meshio's own series (a static mesh grid beside the collection) becomes one block that meshio reads back
    unchanged; a second pass leaves it as it is; a file that is no time series is refused by name."""
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with working_directory(tmp_path):
        with meshio.xdmf.TimeSeriesWriter("s.xdmf") as w:
            w.write_points_cells(points, [("triangle", np.array([[0, 1, 2]]))])
            for t in range(3):
                w.write_data(0.5 * t, point_data={"displacement": np.full((3, 3), float(t))})
        assert len(_domain_grids(tmp_path / "s.xdmf")) == 2  # meshio's: the static mesh and the collection
        assert paraview.single_block_xdmf("s.xdmf") == 3
        assert_one_block(tmp_path / "s.xdmf", 3)
        once = (tmp_path / "s.xdmf").read_text()
        assert paraview.single_block_xdmf("s.xdmf") == 3 and (tmp_path / "s.xdmf").read_text() == once
        with meshio.xdmf.TimeSeriesReader("s.xdmf") as rd:
            p, cells = rd.read_points_cells()
            np.testing.assert_array_equal(p, points)
            np.testing.assert_array_equal(cells[0].data, [[0, 1, 2]])
            t, pd_, _ = rd.read_data(2)
            assert t == 1.0 and (pd_["displacement"] == 2.0).all()
        meshio.write("m.xdmf", meshio.Mesh(points, [("triangle", np.array([[0, 1, 2]]))]))
        with pytest.raises(ValueError, match="m.xdmf: expected one temporal collection"):
            paraview.single_block_xdmf("m.xdmf")


def _domain_grids(path):
    import xml.etree.ElementTree as ET

    return ET.parse(path).getroot().find("Domain").findall("Grid")


def test_write_xdmf_series_divergence_and_guards(example, tmp_path):
    r = paraview.write_xdmf_series(example["div"], "seq", tmp_path / "d.xdmf")
    assert r["frames"] == 5 and r["fields"] == ["displacement", "dirichlet"]
    with working_directory(tmp_path), meshio.xdmf.TimeSeriesReader("d.xdmf") as rd:
        rd.read_points_cells()
        assert rd.num_steps == 5
        assert np.isfinite(rd.read_data(4)[1]["displacement"]).all()
    r = paraview.write_xdmf_series(example["div"], "seq", tmp_path / "all.xdmf", stop_at_divergence=False)
    assert r["frames"] == example["T"]
    with pytest.raises(ValueError, match="overwrite the input"):
        paraview.write_xdmf_series(example["ok"], "seq", tmp_path / "trajectories.xdmf", reference=example["gt"])
    with pytest.raises(ArtefactError, match="no sequence 'other'"):
        paraview.write_xdmf_series(example["ok"], "other", tmp_path / "o.xdmf")
    with pytest.raises(ValueError, match=r"\.xdmf"):
        paraview.write_xdmf_series(example["ok"], "seq", tmp_path / "o.vtu")


def test_energy_curves_from_files(example, tmp_path):
    series = plots.energy_curves_from_files(
        example["gt"], {"self": example["ok"], "sup": example["div"]}, "seq", tmp_path / "ke.png"
    )
    x, dt = example["truth"], 0.05
    v = np.diff(x, axis=0) / dt
    expected = np.concatenate([[0.0], 0.5 * (v * v).sum(axis=(1, 2))])  # unit masses
    np.testing.assert_allclose(series["ground truth"]["kinetic"], expected)
    np.testing.assert_allclose(series["self"]["kinetic"], expected, atol=1e-12)  # a constant shift has no velocity
    sup = series["sup"]["kinetic"]
    assert np.isfinite(sup[:5]).all() and np.isnan(sup[6:]).all()
    _png(tmp_path / "ke.png")
    with pytest.raises(ArtefactError, match="'/sequences/other'"):
        plots.energy_curves_from_files(example["gt"], {}, "other", tmp_path / "ke2.png")
