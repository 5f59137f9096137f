"""Figures of the Neural Modes studies (Wang et al. 2024, Figs. 2, 3, 4, 6, A2).

Each function takes a study result (``neural_modes.sheet.run_sheet_study``, read back with
``io.read_tree``) or positions, writes one image atomically (``plots.save_figure``,
``render.render_frames``) and returns what it drew, so tests can check the numbers without
reading pixels.

- :func:`learning_curves` (Fig. 2): train L2, test L2, test energy and test stress of every method
  along its training;
- :func:`correlation_heatmaps` (Fig. 4): the correlation matrices of the latent directions at the
  origin, eigenvalues in the titles;
- :func:`shape_strips` (Figs. 3 and 6): decoded shapes, one column per walk or subspace, one row per
  step (or a grid, when that strip would be tall), drawn by ``render.render_frames`` (same axes in
  every panel);
- :func:`aspect_ratio_figure` (Fig. A2): the modes of a sheet at several aspect ratios, the first
  mode's folding direction and the energies against the ratio.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.lines import Line2D

from latentsim.neural_modes.metrics import METRICS
from latentsim.report.plots import method_colours, save_figure
from latentsim.report.render import Motion, render_frames

__all__ = ["aspect_ratio_figure", "correlation_heatmaps", "learning_curves", "shape_strips"]

CURVES = (  # (panel title, set, metric); "train" is each method's own training set
    ("train L2 (own training set)", "train", "l2"),
    ("test L2", "test", "l2"),
    ("test energy E_avg [J]", "test", "E_avg"),
    ("test stress |S|_avg (area-weighted) [Pa]", "test", "Sw_avg"),
)


def learning_curves(study: dict, path, dpi=100) -> dict:
    """Fig. 2: each method's train L2, test L2, test E_avg and test |S|_avg against its epochs.

    The checkpoint each table uses is circled (the last epoch for Neural Modes, the least validation
    L2 for the supervised methods); the ground truth's test E_avg is a dashed line in the energy panel.  One legend for all panels, below them.
    Returns {panel title: {method label: (epochs, values)}}.
    """
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    methods = study["methods"]
    colours = method_colours([r["label"] for r in methods.values()])
    drawn = {}
    for ax, (title, part, metric) in zip(axes.ravel(), CURVES):
        drawn[title] = {}
        for r in methods.values():
            epochs = np.asarray(r["epochs"])
            y = np.asarray(r["train_l2"]) if part == "train" else np.asarray(r[part])[:, METRICS.index(metric)]
            ax.plot(epochs, y, "-o", ms=2.5, lw=1.2, color=colours[r["label"]], label=r["label"])
            k = int(r[f"stop_{r['table_stopping']}"])
            ax.plot(epochs[k], y[k], "o", ms=9, mfc="none", color=colours[r["label"]])
            drawn[title][r["label"]] = (epochs, y)
        if part == "test" and metric != "l2":
            ref = {"E_avg": "E_gt", "Sw_avg": None}[metric]
            if ref is not None:
                first = next(iter(methods.values()))
                ax.axhline(np.asarray(first["test"])[0, METRICS.index(ref)], color="k", ls="--", lw=1)
        ax.set_xscale("symlog", linthresh=1)
        ax.set_xlim(left=0)
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
    # one legend for the four panels, below them: no panel's curves under it
    handles = [Line2D([], [], color=colours[r["label"]], marker="o", ms=3, lw=1.2, label=r["label"]) for r in methods.values()]
    handles += [Line2D([], [], color="0.3", marker="o", ms=9, mfc="none", ls="", label="checkpoint in Tables 2, 4, A1"),
                Line2D([], [], color="k", ls="--", lw=1, label="ground truth's test E_avg (Eq. 9)")]  # fmt: skip
    ncol = min(len(handles), 4)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=8, frameon=False)
    fig.suptitle("Learning curves (Wang et al. Fig. 2)", fontsize=11)
    fig.tight_layout(rect=(0, 0.035 * -(-len(handles) // ncol), 1, 1))
    save_figure(fig, path, dpi=dpi)
    return drawn


def correlation_heatmaps(correlation: dict, path, title=None, dpi=100) -> dict:
    """Fig. 4: one heat map per model of its latent directions' correlation matrix (values in the
    cells, eigenvalues in the title).  ``correlation``: {key: {label, matrix, eigenvalues}}.
    Returns {label: eigenvalues}."""
    items = list(correlation.values())
    fig, axes = plt.subplots(1, len(items), figsize=(3.6 * len(items), 3.9), squeeze=False)
    for ax, c in zip(axes[0], items):
        C = np.asarray(c["matrix"])
        im = ax.imshow(C, vmin=-1, vmax=1, cmap="RdBu_r")
        for (i, j), v in np.ndenumerate(C):
            ax.text(j, i, f"{v:.2f}", ha="center", va="center", fontsize=8, color="white" if abs(v) > 0.6 else "black")
        ticks = np.arange(len(C))
        ax.set_xticks(ticks, [f"z{i + 1}" for i in ticks])
        ax.set_yticks(ticks, [f"z{i + 1}" for i in ticks])
        ax.set_title(f"{c['label']}\neigenvalues {' '.join(f'{w:.2f}' for w in c['eigenvalues'])}", fontsize=9)
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8)
    fig.suptitle(title or "Correlation of the latent directions at the origin (Wang et al. Fig. 4)", fontsize=10)
    save_figure(fig, path, dpi=dpi)
    return {c["label"]: np.asarray(c["eigenvalues"]) for c in items}


def shape_strips(columns: dict, rest, cells, model: str, path, title: str, rows=None, panel_size=1.9, dpi=100, dirichlet=None) -> dict:
    """Decoded shapes side by side: ``columns`` {label: (S, n, 3) positions}, one column each, one row
    per step (``rows``: the steps drawn, all by default); every panel on the same axes.

    ``model``: ``shell`` (``cells`` the triangles) or ``tets`` (``cells`` the boundary faces).  Many steps
    of few columns (Fig. 6's keyframes) are laid out as a grid instead (:func:`grid_wrap`): the steps left
    to right, each a column of the labels.  Returns ``render.render_frames``' result.
    """
    motions = []
    for label, pos in columns.items():
        pos = np.asarray(pos, dtype=np.float64)
        motions.append(
            Motion(label, "shapes", model, pos, np.arange(len(pos)), len(pos), np.asarray(rest), np.asarray([] if dirichlet is None else dirichlet, dtype=np.int64),
                   None, np.asarray(cells), 1.0)  # fmt: skip
        )
    rows = list(range(len(motions[0].positions))) if rows is None else [int(r) for r in rows]
    first, *others = motions
    return render_frames(first, {m.label: m for m in others}, "shapes", rows, path, bounds="all", panel_size=panel_size, dpi=dpi, title=title,
                         wrap=grid_wrap(len(rows), len(motions)))  # fmt: skip


def grid_wrap(steps: int, columns: int) -> int | None:
    """Steps per line for :func:`shape_strips`: None (one row per step) unless the strip would be over twice as
    tall as wide; then the count that makes the grid of ``columns``-high blocks closest to square."""
    if steps <= 2 * columns:
        return None
    return min(range(1, steps + 1), key=lambda n: (abs(columns * -(-steps // n) - n), -n))


def aspect_ratio_figure(ratios, train, X, shapes, cells, normal: int, evaluation: dict, path, rows=None, amplitude=0.5, panel_size=2.3, dpi=100) -> dict:
    """Fig. A2: each mode at z_i = ``amplitude`` box (columns) on sheets of several aspect ratios (``rows``: indices into
    ``ratios``), coloured by the displacement along the sheet's normal (one scale, its colour bar beside); below,
    the first mode's folding direction and the mean energies against the ratio (filled markers: training ratios,
    open: held out).

    ``X`` (K,n,3) rest shapes, ``shapes`` (K,m,n,3) decoded modes, ``evaluation``: ``nm_aspect.evaluate_family``.
    Returns {row ratio: [max |normal displacement| per mode]}.
    """
    ratios, train = np.asarray(ratios), np.asarray(train, dtype=bool)
    K, m = shapes.shape[:2]
    rows = list(range(K)) if rows is None else [int(r) for r in rows]
    # the modes fill the width the two charts below need (no empty columns whatever m), a colour bar beside them
    width = max(panel_size * m, 8.4)
    row_height = min(width / m, 1.4 * panel_size) * 0.6  # a sheet seen from above is wider than tall
    chart_height, header, footer = 3.2, 1.1, 0.55  # inches
    height = row_height * len(rows) + chart_height + header + 0.5 + footer
    fig = plt.figure(figsize=(width + 1.4, height))
    outer = fig.add_gridspec(2, 1, height_ratios=[row_height * len(rows), chart_height], hspace=0.5 / (height - header - footer) * 2,
                             left=0.9 / (width + 1.4), right=1 - 1.0 / (width + 1.4), top=1 - header / height, bottom=footer / height)  # fmt: skip
    top = outer[0].subgridspec(len(rows), m + 1, width_ratios=[1.0] * m + [0.06], wspace=0.02, hspace=0.05)
    lim = np.abs(shapes[rows] - X[rows][:, None]).max()
    centred = shapes[rows] - shapes[rows].mean(axis=2, keepdims=True)
    span = np.abs(centred).max()  # one scale for every panel: the largest half-extent drawn
    drawn = {}
    tangent = [a for a in range(3) if a != normal]
    for i, k in enumerate(rows):
        drawn[float(ratios[k])] = []
        for j in range(m):
            ax = fig.add_subplot(top[i, j], projection="3d")
            p = shapes[k, j]
            w = (p - X[k])[:, normal]
            surf = ax.plot_trisurf(p[:, tangent[0]], p[:, tangent[1]], p[:, normal], triangles=np.asarray(cells), cmap="coolwarm", linewidth=0.1,
                                   edgecolor="0.3", antialiased=True)  # fmt: skip
            surf.set_array(w[np.asarray(cells)].mean(1))
            surf.set_clim(-lim, lim)
            c = p.mean(0)
            ax.set_xlim(c[tangent[0]] - span, c[tangent[0]] + span)
            ax.set_ylim(c[tangent[1]] - span, c[tangent[1]] + span)
            ax.set_zlim(c[normal] - span, c[normal] + span)
            ax.set_box_aspect((1, 1, 1), zoom=1.5)
            ax.set_axis_off()
            ax.view_init(elev=28, azim=-60)
            if j == 0:
                ax.text2D(-0.05, 0.5, f"{ratios[k]:.2f}:1", transform=ax.transAxes, rotation=90, va="center", ha="right")
            if i == 0:
                ax.set_title(f"mode {j + 1}")
            drawn[float(ratios[k])].append(float(np.abs(w).max()))
    colours = plt.cm.ScalarMappable(norm=plt.Normalize(-lim, lim), cmap="coolwarm")
    fig.colorbar(colours, cax=fig.add_subplot(top[:, m]), label="displacement along the sheet's normal [m]")
    bottom = outer[1].subgridspec(1, 2, wspace=0.3)
    ax = fig.add_subplot(bottom[0, 0])
    _against_ratio(ax, ratios, train, evaluation, (("fold_nm", "Neural Modes", "C0"), ("fold_linear", "linear mode", "C1")))
    ax.set_xlabel("aspect ratio (long : short)")
    ax.set_ylabel("mode 1 folding direction [deg]\n0: short axis, 45: diagonal")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(bottom[0, 1])
    series = (("E_gt", "ground truth (Eq. 9)", "k"), ("E_nm", "Neural Modes", "C0"), ("E_linear", "linear modes", "C1"),
              ("E_wrong_ratio", "Neural Modes, told the far ratio", "C3"))  # fmt: skip
    _against_ratio(ax, ratios, train, evaluation, series)
    ax.set_yscale("log")
    ax.set_xlabel("aspect ratio (long : short)")
    ax.set_ylabel("mean elastic energy, test samples [J]")
    ax.legend(fontsize=7)
    fig.suptitle(f"Fig. A2: Neural Modes conditioned on the aspect ratio\n(each mode at z_i = {amplitude:g} box; open markers: ratios held out of training)")
    save_figure(fig, path, dpi=dpi)
    return drawn


def _against_ratio(ax, ratios, train, evaluation: dict, series):
    """Lines of ``evaluation[key]`` against the ratio for each (key, label, colour); filled markers train, open held out."""
    for key, label, colour in series:
        v = np.asarray(evaluation[key])
        ax.plot(ratios, v, "-", color=colour, label=label)
        ax.plot(ratios[train], v[train], "o", color=colour)
        ax.plot(ratios[~train], v[~train], "o", mfc="white", color=colour)
