"""Figures of the Neural Modes studies (Wang et al. 2024, Figs. 2, 3, 4, 6).

Each function takes a study result (``nm_sheet.run_sheet_study``, read back with
``io.read_tree``) or positions, writes one image atomically (``plots.save_figure``,
``render.render_frames``) and returns what it drew, so tests can check the numbers without
reading pixels.

- :func:`learning_curves` (Fig. 2): train L2, test L2, test energy and test stress of every method
  along its training;
- :func:`correlation_heatmaps` (Fig. 4): the correlation matrices of the latent directions at the
  origin, eigenvalues in the titles;
- :func:`shape_strips` (Figs. 3 and 6): decoded shapes, one column per walk or subspace, one row per
  step, drawn by ``render.render_frames`` (same axes in every panel).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from .nm_sheet import METRICS
from .plots import method_colours, save_figure
from .render import Motion, render_frames

__all__ = ["correlation_heatmaps", "learning_curves", "shape_strips"]

CURVES = (  # (panel title, set, metric); "train" is each method's own training set
    ("train L2 (own training set)", "train", "l2"),
    ("test L2", "test", "l2"),
    ("test energy E_avg [J]", "test", "E_avg"),
    ("test stress |S|_avg (area-weighted) [Pa]", "test", "Sw_avg"),
)


def learning_curves(study: dict, path, dpi=100) -> dict:
    """Fig. 2: each method's train L2, test L2, test E_avg and test |S|_avg against its epochs.

    The checkpoint each table uses is circled (the last epoch for Neural Modes, the least validation
    L2 for the supervised methods); the ground truth's test E_avg and |S|_avg are dashed lines.
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
                ax.axhline(np.asarray(first["test"])[0, METRICS.index(ref)], color="k", ls="--", lw=1, label="ground truth")
        ax.set_xscale("symlog", linthresh=1)
        ax.set_xlim(left=0)
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_title(title, fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Learning curves (Wang et al. Fig. 2); circles: the checkpoint in Tables 2, 4, A1", fontsize=11)
    fig.tight_layout()
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

    ``model``: ``shell`` (``cells`` the triangles) or ``tets`` (``cells`` the boundary faces).  Returns
    ``render.render_frames``' result.
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
    return render_frames(first, {m.label: m for m in others}, "shapes", rows, path, bounds="all", panel_size=panel_size, dpi=dpi, title=title)
