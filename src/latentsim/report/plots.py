"""Charts for the cross-method evaluation (matplotlib, Agg backend, no display).

Every function takes plain arrays, a :class:`pandas.DataFrame` or artefact
paths, writes one image atomically (:func:`save_figure`; the format follows
the path's suffix, PNG by default) and returns what it drew, so tests and
callers can check the numbers without reading pixels.  The numbers drawn
come from :mod:`latentsim.report.metrics`.

- :func:`speed_accuracy_chart`: log ms/frame against log error per method,
  Pareto front (:func:`latentsim.report.metrics.pareto_front`) marked; one
  scene or small multiples across scenes;
- :func:`rollout_curves`: per test sequence, vertex error, Dirichlet error and
  kinetic energy over time, one line per method (Li et al. Figs. 8-12);
- :func:`stability_heatmap`: method x condition -> frames survived, with the
  end boundary-condition error; diverged cells hatched;
- :func:`energy_curves`: kinetic energy (and incremental potential) over time,
  ground truth against methods (:func:`energy_curves_from_files` recomputes
  the kinetic energy from trajectory files);
- :func:`training_curves`: loss histories of several runs on one log axis;
- :func:`empty_figure`: a figure that only says why there is nothing to draw.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.lines import Line2D
from matplotlib.ticker import NullFormatter

from latentsim.io import ArtefactError, atomic_path, open_artefact, require
from latentsim.report.metrics import PENETRATION_LIMIT, kinetic_energy

__all__ = [
    "empty_figure",
    "energy_curves",
    "energy_curves_from_files",
    "method_colours",
    "rollout_curves",
    "save_figure",
    "speed_accuracy_chart",
    "speed_accuracy_figure",
    "stability_heatmap",
    "training_curves",
]


def save_figure(fig, path, dpi=100):
    """Save ``fig`` atomically to ``path`` (format from the suffix) and close it."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or "png"
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=fmt)
    plt.close(fig)
    return path


def _require_columns(df: pd.DataFrame, columns, what: str):
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise KeyError(f"{what}: DataFrame lacks column(s) {missing}; has {list(df.columns)}")


def method_colours(methods) -> dict:
    """Stable colour per method name (sorted order through the tab10/tab20 cycle)."""
    names = sorted({str(m) for m in methods})
    cmap = plt.get_cmap("tab10" if len(names) <= 10 else "tab20")
    return {m: cmap(i % cmap.N) for i, m in enumerate(names)}


# --------------------------------------------------------------------------- speed vs accuracy


def _point_marker(error: float) -> str:
    """A speed-accuracy point's marker: a circle for a measured error, a down triangle for error 0 (the
    full space itself), a cross for none (NaN, or infinite: diverged)."""
    if np.isfinite(error) and error > 0:
        return "o"
    return "v" if error == 0 else "X"


def _method_marker(errors) -> str:
    """The legend's marker of a method drawn with ``errors`` (its points' mean errors): the marker all its
    points share (the full space's triangle), else the circle."""
    markers = {_point_marker(float(x)) for x in errors}
    return markers.pop() if len(markers) == 1 else "o"


def _draw_speed_accuracy(ax, pts: pd.DataFrame, colours: dict, annotate=True):
    """Scatter one scene's points on ``ax`` with their front (``on_front``)."""
    t = pts["ms_per_frame"].to_numpy(float)
    e = pts["mean_error"].to_numpy(float)
    diverged = pts["diverged_frame"].to_numpy() >= 0
    positive = np.isfinite(e) & (e > 0)
    floor = np.nanmin(e[positive]) / 3 if positive.any() else 1e-6
    emax = pts["max_error"].to_numpy(float) if "max_error" in pts.columns else np.full(len(pts), np.nan)
    seeds = pts["seeds"].to_numpy(int) if "seeds" in pts.columns else np.ones(len(pts), dtype=int)
    lo = pts["mean_error_min"].to_numpy(float) if "mean_error_min" in pts.columns else np.full(len(pts), np.nan)
    hi = pts["mean_error_max"].to_numpy(float) if "mean_error_max" in pts.columns else np.full(len(pts), np.nan)
    pen = np.nan_to_num(pts["max_penetration"].to_numpy(float)) if "max_penetration" in pts.columns else np.zeros(len(pts))
    top = np.concatenate([e[positive], emax[np.isfinite(emax) & (emax > 0)]])
    ceil = top.max() * 3 if len(top) else 1.0
    # exact (zero-error) rows sit in a shaded band at the bottom (a log axis has no 0), wholly inside the
    # axes; failed (NaN, or infinite: diverged) rows on the top edge
    bottom = floor / 4
    y = np.where(positive, e, np.where(e == 0, floor / 2, ceil))
    if (e == 0).any():
        ax.axhspan(bottom, floor, color="0.9", zorder=0)
        ax.text(0.01, np.sqrt(bottom * floor), "error 0 (exact)", transform=ax.get_yaxis_transform(), fontsize=7, va="center", color="0.35")
    placed = []  # (log10 ms, log10 error) of the labels so far: a label near one moves up a line
    for i, r in enumerate(pts.itertuples(index=False)):
        c = colours[str(r.method)]
        face = "none" if diverged[i] else c
        ax.scatter([t[i]], [y[i]], s=60, marker=_point_marker(e[i]), facecolors=face, edgecolors=[c], linewidths=1.5, zorder=3,
                   clip_on=False, gid=f"point {r.method}")  # fmt: skip
        if positive[i] and seeds[i] > 1 and np.isfinite(lo[i]) and np.isfinite(hi[i]) and lo[i] > 0:
            # several seeds: a bar from the least to the largest mean error of the stable seeds
            ax.errorbar([t[i]], [e[i]], yerr=[[max(e[i] - lo[i], 0.0)], [max(hi[i] - e[i], 0.0)]], fmt="none", ecolor=c, capsize=4,
                        lw=1.6, zorder=2)  # fmt: skip
        elif positive[i] and np.isfinite(emax[i]) and emax[i] > e[i]:
            # whisker up to the max error (over frames and vertices)
            ax.plot([t[i], t[i]], [e[i], emax[i]], color=c, lw=1.0, alpha=0.6, zorder=1)
            ax.plot([t[i]], [emax[i]], marker="_", ms=8, color=c, alpha=0.8, zorder=1)
        if pts["on_front"].iloc[i]:
            ax.scatter([t[i]], [y[i]], s=190, marker="o", facecolors="none", edgecolors="k", linewidths=1.0, zorder=2, clip_on=False)
        # small multiples name only the divergences (colours name the methods)
        label = str(r.method) if annotate else ""
        if diverged[i] and seeds[i] > 1:
            n_div = int(pts["diverged_seeds"].iloc[i])
            label += f" (diverged in {n_div}/{seeds[i]} seeds)" if annotate else f"diverged {n_div}/{seeds[i]}; "
        elif diverged[i]:
            label += f" (diverged @ {int(r.diverged_frame)})" if annotate else f"diverged @ {int(r.diverged_frame)}; "
        elif e[i] == 0 and annotate:
            label += " (exact)"
        if pen[i] > 0:  # entered a collider: a red ring, and how deep
            ax.scatter([t[i]], [y[i]], s=120, marker="o", facecolors="none", edgecolors="tab:red", linewidths=1.2, zorder=2, clip_on=False)
            label += f" (inside by {100 * pen[i]:.2g}%)" if annotate else f"inside {100 * pen[i]:.2g}%"
        label = label.removesuffix("; ")
        if label:
            at = (np.log10(max(t[i], 1e-300)), np.log10(max(y[i], 1e-300)))
            near = sum(abs(at[0] - p[0]) < 0.5 and abs(at[1] - p[1]) < 0.25 for p in placed)
            placed.append(at)
            dy = -11 - 9 * near if y[i] >= ceil else 4 + 9 * near  # a failed row's label under the top edge
            ax.annotate(label, (t[i], y[i]), xytext=(5, dy), textcoords="offset points", fontsize=7)
    front = pts["on_front"].to_numpy()
    if front.any():
        order = np.argsort(t[front], kind="stable")
        ft, fy = t[front][order], y[front][order]
        # staircase: the region a front point dominates extends right and up
        ax.step(ft, fy, where="post", color="k", lw=1.0, ls="--", zorder=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(bottom, ceil)
    # whole decades: at least two labelled major ticks, and no labels on the minor ones (on a range
    # under two decades matplotlib labels its minor ticks, which overlap)
    ms = t[np.isfinite(t) & (t > 0)]
    if len(ms):
        ax.set_xlim(10.0 ** np.floor(np.log10(ms.min())), 10.0 ** np.ceil(np.log10(ms.max()) + 1e-9))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.grid(True, which="both", alpha=0.25)


def speed_accuracy_chart(pts: pd.DataFrame, path, scene=None, title=None, dpi=100) -> None:
    """:func:`speed_accuracy_figure` of ``pts``, saved to ``path`` (PNG unless the suffix says otherwise)."""
    save_figure(speed_accuracy_figure(pts, scene=scene, title=title), path, dpi=dpi)


def speed_accuracy_figure(pts: pd.DataFrame, scene=None, title=None):
    """Log ms per frame (x) against log error (y), one point per method, Pareto front marked.

    ``pts``: one row per scene and method, as :func:`latentsim.report.tables.speed_accuracy_points` gives
    them (the aggregation over sequences and seeds is done there, once, for the chart and the glance table):

    - ``scene`` (str), ``method`` (str);
    - ``ms_per_frame`` (float > 0): wall time of one step [ms];
    - ``mean_error`` (float): error relative to the bounding-box diagonal
      (0 for the ground truth itself, drawn as a down triangle in a shaded
      band "error 0" at the bottom; NaN when not measurable or infinite for a
      method that diverged (:mod:`latentsim.report.metrics`), drawn as a cross
      on the top edge);
    - ``max_error`` (float, optional): with one seed, a whisker from the point up
      to it (the largest vertex error of any frame);
    - ``seeds``, ``mean_error_min``, ``mean_error_max`` (optional): with several
      seeds, a bar from the least to the largest error of the stable seeds;
    - ``diverged_frame`` (int): first diverged frame, -1 when stable, and
      ``diverged_seeds``: diverged methods are drawn hollow and labelled;
    - ``on_front`` (bool): circled, and joined by the front's staircase;
    - ``max_penetration`` (optional, scenes with colliders): a method that entered one gets a red ring and
      the depth in its label.

    Parameters
    ----------
    pts : DataFrame, columns as above.
    scene : str or None
        One scene's chart; ``None`` draws small multiples, one panel per scene,
        with one legend (colour = method across all panels; a method's marker is
        the one its points share, the full space's triangle, else the circle).

    Returns
    -------
    The figure (:class:`matplotlib.figure.Figure`), laid out and open.
    """
    df = pts
    _require_columns(df, ["scene", "method", "ms_per_frame", "mean_error", "diverged_frame", "on_front"], "speed_accuracy_chart")
    if df.empty:
        raise ValueError("speed_accuracy_chart: empty DataFrame")
    ms = df["ms_per_frame"].to_numpy(float)
    if (ms[np.isfinite(ms)] <= 0).any():
        bad = df.loc[np.isfinite(ms) & (ms <= 0), ["scene", "method"]].to_dict("records")
        raise ValueError(f"speed_accuracy_chart: ms_per_frame must be > 0 (log axis); offending rows {bad}")
    colours = method_colours(df["method"])
    if scene is not None:
        sub = df[df["scene"] == scene]
        if sub.empty:
            raise KeyError(f"speed_accuracy_chart: scene {scene!r} not in the DataFrame; scenes {sorted(df['scene'].unique())}")
        scenes = [scene]
    else:
        sub = df
        scenes = sorted(sub["scene"].unique())
    pts = sub
    ncol = min(len(scenes), 3)
    nrow = -(-len(scenes) // ncol)
    legend_width = 2.4 if scene is not None else 0.0  # one scene: the legend beside the axes, off the points
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol + legend_width, 4.2 * nrow), squeeze=False)
    for k, s in enumerate(scenes):
        ax = axes.flat[k]
        _draw_speed_accuracy(ax, pts[pts["scene"] == s], colours, annotate=scene is not None)
        ax.set_title(s if scene is None else (title or f"{s}: speed vs accuracy"))
        ax.set_xlabel("ms per frame")
        ax.set_ylabel("mean error / bbox diagonal")
    for ax in axes.flat[len(scenes):]:
        ax.set_visible(False)
    errors = pts.groupby(pts["method"].astype(str))["mean_error"]
    handles = [Line2D([], [], marker=_method_marker(errors.get_group(m)), ls="", color=c, label=m)
               for m, c in colours.items() if m in errors.groups]  # fmt: skip
    handles += [
        Line2D([0, 0], [0, 1], color="0.4", marker="_", ms=8, label="vertical whisker: up to the max vertex error (one seed)"),
        Line2D([0, 0], [0, 1], color="0.4", marker="_", ms=8, lw=1.6, label="bar: least to largest error over the seeds"),
        Line2D([], [], marker="o", ls="", mfc="none", mec="k", ms=11, label="on the Pareto front"),
        Line2D([], [], marker="o", ls="", mfc="none", mec="grey", label="diverged (hollow)"),
        *([Line2D([], [], marker="o", ls="", mfc="none", mec="tab:red", ms=10, label="enters a collider (% of the diagonal, median over seeds)")]
          if "max_penetration" in pts.columns and (np.nan_to_num(pts["max_penetration"].to_numpy(float)) > 0).any() else []),
        Line2D([], [], color="k", ls="--", label="Pareto front"),
    ]
    if scene is None:
        fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 5), fontsize=8, frameon=False)
        fig.suptitle(title or "speed vs accuracy per scene")
        fig.tight_layout(rect=(0, 0.06 + 0.02 * (len(handles) // 5), 1, 0.97))
    else:
        axes[0, 0].legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
        fig.tight_layout()
    _place_labels(fig, axes.flat[: len(scenes)])
    return fig


def _place_labels(fig, axes) -> None:
    """Place each point's label, after layout, where it stays inside its axes (not over the legend or the
    next panel) and clear of the labels placed before it: of the positions right or left of its point, a
    line or more above or below, the first that fits, else the one that overlaps least."""
    renderer = fig.canvas.get_renderer()
    for ax in axes:
        box = ax.get_window_extent(renderer)
        placed = []
        for text in ax.texts:
            if not hasattr(text, "xyann"):
                continue
            dy0 = text.xyann[1]
            candidates = [(dx, dy0 + sign * step) for step in (0, 9, 18, 27) for sign in ((1,) if step == 0 else (1, -1))
                          for dx in (5, -5)]  # fmt: skip
            best, best_cost = None, None
            for dx, dy in candidates:
                text.xyann = (dx, dy)
                text.set_horizontalalignment("left" if dx > 0 else "right")
                e = text.get_window_extent(renderer)
                outside = max(0.0, e.x1 - box.x1) + max(0.0, box.x0 - e.x0) + max(0.0, e.y1 - box.y1) + max(0.0, box.y0 - e.y0)
                overlap = sum(max(0.0, min(e.x1, p.x1) - max(e.x0, p.x0)) * max(0.0, min(e.y1, p.y1) - max(e.y0, p.y0)) for p in placed)
                cost = outside * e.height + overlap
                if best_cost is None or cost < best_cost:
                    best, best_cost = (dx, dy), cost
                if cost == 0:
                    break
            text.xyann = best
            text.set_horizontalalignment("left" if best[0] > 0 else "right")
            placed.append(text.get_window_extent(renderer))


# --------------------------------------------------------------------------- stability map


def stability_heatmap(df: pd.DataFrame, path, title="stability: frames survived", dpi=100) -> dict:
    """Heat map method (rows) x condition (columns) -> frames survived.

    Expected columns of ``df`` (one row per method and condition):

    - ``method`` (str), ``condition`` (str, e.g. ``"speed x5"``, ``"10x longer"``);
    - ``frames_survived`` (int): frames before divergence (all frames if stable);
    - ``frames`` (int, optional): length of the condition's rollout; when
      given, the colour is the fraction survived (conditions of different
      length compare), otherwise the frame count itself;
    - ``bc_error`` (float, optional): Dirichlet error at the last surviving
      frame (relative to the bbox diagonal), printed under the count;
    - ``diverged`` (bool, optional): otherwise ``diverged_frame >= 0`` when that
      column exists, otherwise ``frames_survived < frames``;
    - ``seeds`` and ``seeds_survived`` (int, optional): a row that stands for
      several seeds (``frames_survived`` then the least of them): the colour is
      the fraction of seeds that survived, and the cell reads ``k/n seeds``.
    - ``max_penetration`` (float, optional; scenes with colliders): the deepest
      entry into one / bbox diagonal, printed as ``in p%`` under the count, and
      a cell deeper than ``PENETRATION_LIMIT`` (1% of the diagonal) framed in orange.

    Diverged cells are hatched and their count is printed with a cross;
    method/condition pairs with no row are grey and marked ``n/a``.

    Returns
    -------
    dict with ``methods`` (rows, in first-appearance order), ``conditions``
    (columns), ``frames`` (R,C) float (frames survived, NaN where missing),
    ``colour`` (R,C) float (the values coloured), ``bc_error`` (R,C) float,
    ``diverged`` (R,C) bool and ``max_penetration`` (R,C) float (NaN without colliders).
    """
    _check_stability_rows(df)
    methods = list(dict.fromkeys(df["method"].astype(str)))
    conditions = list(dict.fromkeys(df["condition"].astype(str)))
    R, C = len(methods), len(conditions)
    g = _stability_grid(df, methods, conditions)
    by_seed = {"seeds", "seeds_survived"} <= set(df.columns)
    relative = "frames" in df.columns or by_seed
    frames = g["frames"]
    colour = g["k_seeds"] / g["n_seeds"] if by_seed else (frames / g["total"] if relative else frames)
    fig, ax = plt.subplots(figsize=(3.0 + 1.3 * C, 2.2 + 0.75 * R), layout="constrained")
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.85")
    vmax = 1.0 if relative else np.nanmax(frames)
    im = ax.imshow(np.ma.masked_invalid(colour), cmap=cmap, vmin=0.0, vmax=vmax, aspect="auto")
    for i in range(R):
        for j in range(C):
            _stability_cell(ax, i, j, g, colour[i, j] < 0.6 * vmax, by_seed)
    ax.set_xticks(range(C), conditions, rotation=30, ha="right", fontsize=8)
    ax.set_yticks(range(R), methods, fontsize=8)
    ax.set_title(title)
    fig.colorbar(
        im, ax=ax, label="fraction of seeds that survived" if by_seed else ("fraction of frames survived" if relative else "frames survived"),
        fraction=0.04, pad=0.02,
    )
    save_figure(fig, path, dpi=dpi)
    return {"methods": methods, "conditions": conditions, "frames": frames, "colour": colour, "bc_error": g["bc"], "diverged": g["diverged"],
            "max_penetration": g["pen"]}  # fmt: skip


def _check_stability_rows(df: pd.DataFrame) -> None:
    """Refuse a table :func:`stability_heatmap` cannot draw: a required column missing, no row, or two rows
    of one (method, condition) pair."""
    _require_columns(df, ["method", "condition", "frames_survived"], "stability_heatmap")
    if df.empty:
        raise ValueError("stability_heatmap: empty DataFrame")
    dup = df.duplicated(["method", "condition"], keep=False)
    if dup.any():
        pairs = df.loc[dup, ["method", "condition"]].drop_duplicates().to_records(index=False).tolist()
        raise ValueError(f"stability_heatmap: several rows for (method, condition) {pairs}")


def _stability_grid(df: pd.DataFrame, methods: list, conditions: list) -> dict:
    """The rows of :func:`stability_heatmap`'s table as (R, C) arrays over ``methods`` x ``conditions``, NaN
    (False) where a pair has no row or the table lacks the column: ``frames`` (survived), ``total`` (frames),
    ``bc`` (bc_error), ``n_seeds``, ``k_seeds`` (seeds, seeds_survived), ``pen`` (max_penetration) float and
    ``diverged`` bool (the column, else ``diverged_frame >= 0``, else survived < frames)."""
    R, C = len(methods), len(conditions)
    g = {k: np.full((R, C), np.nan) for k in ("frames", "total", "bc", "n_seeds", "k_seeds", "pen")}
    g["diverged"] = np.zeros((R, C), dtype=bool)
    by_seed = {"seeds", "seeds_survived"} <= set(df.columns)
    for r in df.itertuples(index=False):
        i, j = methods.index(str(r.method)), conditions.index(str(r.condition))
        g["frames"][i, j] = float(r.frames_survived)
        if "frames" in df.columns:
            g["total"][i, j] = float(r.frames)
        if "bc_error" in df.columns:
            g["bc"][i, j] = float(r.bc_error)
        if by_seed:
            g["n_seeds"][i, j], g["k_seeds"][i, j] = float(r.seeds), float(r.seeds_survived)
        if "max_penetration" in df.columns:
            g["pen"][i, j] = float(r.max_penetration)
        if "diverged" in df.columns:
            g["diverged"][i, j] = bool(r.diverged)
        elif "diverged_frame" in df.columns:
            g["diverged"][i, j] = int(r.diverged_frame) >= 0
        elif "frames" in df.columns:
            g["diverged"][i, j] = r.frames_survived < r.frames
    return g


def _stability_cell(ax, i: int, j: int, g: dict, dark: bool, by_seed: bool) -> None:
    """Cell (i, j) of the stability map from the grid ``g`` (:func:`_stability_grid`): ``n/a`` without a row;
    else the frames survived (or seeds), BC error and penetration, hatched where diverged, framed in orange
    beyond ``PENETRATION_LIMIT``; white text on a ``dark`` cell."""
    frames, diverged, bc, pen = g["frames"][i, j], g["diverged"][i, j], g["bc"][i, j], g["pen"][i, j]
    if np.isnan(frames):
        ax.text(j, i, "n/a", ha="center", va="center", fontsize=8, color="0.3")
        return
    if diverged:
        ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="//", edgecolor="red", lw=1.5))
    text = f"{'✗ ' if diverged else ''}{int(frames)}"
    if by_seed:
        text = f"{int(g['k_seeds'][i, j])}/{int(g['n_seeds'][i, j])} seeds" + (f"\nleast {int(frames)}" if diverged else "")
    if not np.isnan(bc):
        text += f"\nBC {bc:.1e}"
    if not np.isnan(pen):
        text += f"\nin {100 * pen:.2g}%"
        if pen > PENETRATION_LIMIT:
            ax.add_patch(plt.Rectangle((j - 0.45, i - 0.45), 0.9, 0.9, fill=False, edgecolor="tab:orange", lw=2.0))
    ax.text(
        j, i, text, ha="center", va="center", fontsize=8, color="white" if dark else "black",
        bbox={"boxstyle": "round,pad=0.15", "fc": "red", "alpha": 0.55, "lw": 0} if diverged else None,
    )


# --------------------------------------------------------------------------- rollouts over time


def rollout_curves(scene: str, curves: dict, path) -> None:
    """Per test sequence (columns): vertex error, Dirichlet error (not for a free body, which has no prescribed
    vertex: every curve NaN) and kinetic energy over time, one line per method.

    A method's curve ends where it diverged (marked with a cross).  This one
    figure holds the paper's Figs. 8-12 for the scene: stability of the
    supervised baselines, the ablations' errors, BC satisfaction and the
    kinetic energy of the rollout against the ground truth.

    Parameters
    ----------
    scene : str, named in the titles.
    curves : {method: {sequence: curves of :func:`latentsim.report.metrics.rollout_metrics`}}.
    path : output image.
    """
    sequences = list(dict.fromkeys(name for per in curves.values() for name in per))
    n = max(len(sequences), 1)
    prescribed = any(np.isfinite(c["dirichlet_error"]).any() for per in curves.values() for c in per.values())
    rows = ["error", "dirichlet", "energy"] if prescribed else ["error", "energy"]
    fig, grid = plt.subplots(len(rows), n, figsize=(4.8 * n, 3 * len(rows)), squeeze=False)
    axes = dict(zip(rows, grid))
    for j, name in enumerate(sequences):
        truth = None  # ground-truth KE: the longest (undiverged) copy among the methods
        for k, (method, per) in enumerate(curves.items()):
            if name not in per:
                continue
            c = per[name]
            colour = f"C{k % 10}"
            t = np.arange(len(c["mean_error"])) * c["dt"]
            axes["error"][j].semilogy(t, np.maximum(c["mean_error"], 1e-12), color=colour, label=method)
            if prescribed:
                axes["dirichlet"][j].semilogy(t, np.maximum(c["dirichlet_error"], 1e-12), color=colour, label=method)
            axes["energy"][j].plot(t, c["ke_pred"], color=colour, ls="--", label=method)
            if c["diverged_frame"] >= 0 and len(t):
                axes["error"][j].plot(t[-1], max(c["mean_error"][-1], 1e-12), "x", color=colour, ms=9)
            if truth is None or len(c["ke_truth"]) > len(truth[1]):
                truth = (c["dt"], c["ke_truth"])
        if truth is not None:
            axes["energy"][j].plot(np.arange(len(truth[1])) * truth[0], truth[1], color="k", lw=2.0, alpha=0.5, label="full space")
        axes["error"][j].set_title(f"{scene} / {name}")
        axes["error"][j].set_ylabel("mean vertex error / bbox diag")
        if prescribed:
            axes["dirichlet"][j].set_ylabel("Dirichlet error / bbox diag")
        axes["energy"][j].set_ylabel("kinetic energy [J]")
        axes["energy"][j].set_xlabel("time [s]")
        for row in axes.values():
            row[j].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def empty_figure(path, text: str) -> None:
    """A small image that says ``text`` (why there is nothing to draw), so a rule's output exists."""
    fig, ax = plt.subplots(figsize=(4, 2))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.axis("off")
    save_figure(fig, path)


# --------------------------------------------------------------------------- energies


_ENERGY_LABELS = {
    "kinetic": "kinetic energy [J]",
    "incremental_potential": "incremental potential [J]",
}


def energy_curves(series: Mapping, path, dt: float, reference="ground truth", title=None, dpi=100) -> dict:
    """Energies over time, ground truth against methods, one panel per quantity.

    Parameters
    ----------
    series : mapping name -> mapping quantity -> (T,) float
        Quantities ``kinetic`` and/or ``incremental_potential`` (any other key
        gets its own panel too); lengths may differ between names (e.g. a
        10x-longer rollout). NaN entries (after divergence) are not drawn; the
        last finite value of a curve that stops early is marked with a cross.
    path : output image.
    dt : float
        Time step [s]; the x axis is time.
    reference : str
        Name in ``series`` drawn as the thick black reference line.

    Returns
    -------
    dict quantity -> list of the names drawn in that panel.
    """
    if not series:
        raise ValueError("energy_curves: no series")
    if reference is not None and reference not in series:
        raise KeyError(f"energy_curves: reference {reference!r} not in series {list(series)}")
    quantities = list(dict.fromkeys(q for s in series.values() for q in s))
    if not quantities:
        raise ValueError("energy_curves: every series is empty")
    colours = method_colours([n for n in series if n != reference])
    fig, axes = plt.subplots(len(quantities), 1, figsize=(7, 2.8 * len(quantities)), squeeze=False, sharex=True)
    drawn = {}
    for ax, q in zip(axes[:, 0], quantities):
        drawn[q] = []
        for name, s in series.items():
            if q not in s:
                continue
            y = np.asarray(s[q], dtype=float)
            if y.ndim != 1:
                raise ValueError(f"energy_curves: series {name!r} quantity {q!r} has shape {y.shape}, expected (T,)")
            t = np.arange(len(y)) * dt
            is_ref = name == reference
            # the reference underneath, wide and grey, so a method that matches it stays visible
            style = {"color": "0.55", "lw": 3.0, "zorder": 1} if is_ref else {"color": colours[name], "lw": 1.2, "ls": "--", "zorder": 2}
            ax.plot(t, y, label=name, **style)
            fin = np.flatnonzero(np.isfinite(y))
            if len(fin) and fin[-1] < len(y) - 1:
                ax.plot(t[fin[-1]], y[fin[-1]], "x", color=style["color"], ms=9, mew=2)
            drawn[q].append(name)
        ax.set_ylabel(_ENERGY_LABELS.get(q, q))
        ax.grid(True, alpha=0.25)
        ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(title or "energies over time (x: diverged)")
    fig.tight_layout()
    save_figure(fig, path, dpi=dpi)
    return drawn


def energy_curves_from_files(truth_h5, rollouts: Mapping, sequence: str, path, title=None) -> dict:
    """Kinetic energy of one sequence: ground truth file against rollout files.

    The kinetic energy is recomputed from positions and lumped masses with
    backward-difference velocities (:func:`latentsim.report.metrics.kinetic_energy`),
    identically for every file.

    Parameters
    ----------
    truth_h5 : path of a trajectory-layout file (``trajectories.h5``).
    rollouts : mapping method name -> path of a trajectory-layout file.
    sequence : str, a sequence present in every file.
    path : output image.

    Returns
    -------
    dict name -> {"kinetic": (T,) float} [J], the curves drawn (NaN after a
    rollout's divergence), the ground truth under ``"ground truth"``.
    """
    def load(p):
        with open_artefact(p) as f:
            g = require(require(f, "sequences"), sequence)
            x = require(g, "positions")[()]
            m = require(f, "masses")[()]
            dt = float(f.attrs["dt"]) if "dt" in f.attrs else None
        return kinetic_energy(x, m, dt or 1.0), dt

    ke, dt = load(truth_h5)
    if dt is None:
        raise ArtefactError(f"{truth_h5}: missing root attribute 'dt'")
    series = {"ground truth": {"kinetic": ke}}
    for name, p in rollouts.items():
        series[name] = {"kinetic": load(p)[0]}
    energy_curves(series, path, dt, title=title or f"kinetic energy, sequence {sequence!r}")
    return series


# --------------------------------------------------------------------------- training


def _load_history(run: str, h, key: str) -> np.ndarray:
    if isinstance(h, (str, Path)):
        with open_artefact(h) as f:
            return np.asarray(require(f, key, path=str(h))[()], dtype=float)
    y = np.asarray(h, dtype=float)
    if y.ndim != 1:
        raise ValueError(f"training_curves: run {run!r} has shape {y.shape}, expected (epochs,)")
    return y


def training_curves(histories: Mapping, path, key="loss", title=None, dpi=100) -> dict:
    """Loss histories of several runs on one log-scale axis.

    Parameters
    ----------
    histories : mapping run name -> (epochs,) float array, or path of an HDF5
        file holding the dataset ``key`` (``history.h5``, ``latents.h5``).
    path : output image.
    key : str
        Dataset read from files (and the y label).

    Returns
    -------
    dict with ``runs`` (run name -> (epochs,) float, the values drawn) and
    ``yscale``: ``"log"`` when every value is positive, otherwise ``"symlog"``
    (the self-supervised loss is an energy and can be negative; the title then
    says so).
    """
    if not histories:
        raise ValueError("training_curves: no runs")
    data = {str(name): _load_history(name, h, key) for name, h in histories.items()}
    allv = np.concatenate([v[np.isfinite(v)] for v in data.values()] + [np.zeros(0)])
    fig, ax = plt.subplots(figsize=(6.5, 4))
    colours = method_colours(data)
    for name, y in data.items():
        ax.plot(np.arange(1, len(y) + 1), y, color=colours[name], lw=1.3, label=f"{name} ({len(y)} epochs)")
    positive = bool(len(allv)) and bool((allv > 0).all())
    if positive:
        ax.set_yscale("log")
        scale = "log"
    else:
        # linear band well below every run's typical magnitude, so each run reads logarithmically
        typical = [np.median(np.abs(v[np.isfinite(v) & (v != 0)])) for v in data.values() if (np.isfinite(v) & (v != 0)).any()]
        ax.set_yscale("symlog", linthresh=0.1 * float(min(typical)) if typical else 1.0)
        scale = "symlog"
    ax.set_xlabel("epoch")
    ax.set_ylabel(key.replace("_", " "))
    ax.set_title((title or "training histories") + ("" if positive else " (symlog: values <= 0)"))
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=dpi)
    return {"runs": data, "yscale": scale}
