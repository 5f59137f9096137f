"""Tables of the evaluation: per scene, across scenes, and next to the papers' numbers.

Each function takes the per-sequence metrics (one row per scene, method and test
sequence, as :func:`latentsim.stages.evaluate.evaluate_scene` writes them; columns in
:mod:`latentsim.report.metrics`) or artefact paths and returns a
:class:`pandas.DataFrame`; :func:`write_table` writes one atomically.

- :func:`table1` / :func:`table2`: Li et al. 2025 Tables 1 and 2 (full-space vs latent
  time; single-vertex Jvp and layer sizes), ours beside the paper's (:mod:`latentsim.report.paper`);
- :func:`stability_table`: frames survived per test sequence (Li et al. Figs. 8-11);
  :func:`stress_table`: the stress conditions' rows of the stability map;
- :func:`reconstruction_table`: the autoencoder's reconstruction error;
- :func:`sizes_table`: model size per scene, the paper's and the sizing sweep's choice;
- :func:`speed_accuracy_rows`, :func:`glance_table`, :func:`glance_grid`: the speed-accuracy
  comparison of every method, as the chart's points and as the summary's opening tables;
- :func:`markdown`: any of them as a Markdown table;
- :func:`write_table_html`: a table file (CSV, or this package's Markdown) as an HTML page, which the
  Snakemake report shows inline (it offers a CSV only for download); :func:`html_table` one table;
  :func:`write_glance_html` the glance page and the grid the report's landing page shows.
"""

from __future__ import annotations

import html
import re
from pathlib import Path

import numpy as np
import pandas as pd

from latentsim.io import atomic_path, open_artefact, require
from latentsim.report.metrics import pareto_front
from latentsim.report.paper import li2025_table1, li2025_table2

__all__ = [
    "GLANCE_METHODS",
    "glance_grid",
    "glance_table",
    "html_table",
    "layers_text",
    "markdown",
    "reconstruction_table",
    "sizes_table",
    "speed_accuracy_rows",
    "stability_table",
    "stress_table",
    "table1",
    "table2",
    "write_table",
    "write_glance_html",
    "write_table_html",
]


def write_table(df: pd.DataFrame, path):
    """Write ``df`` as CSV atomically (no index, floats to 6 significant digits)."""
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g")


def stress_table(scene: str, rollouts) -> pd.DataFrame:
    """Stability map rows (method x stress condition) from the rollouts' ``stability`` groups.

    Columns: scene, method, condition, frames, frames_survived, diverged,
    bc_error (mean Dirichlet error / bbox diagonal at the last surviving frame).
    """
    rows = []
    for path in rollouts:
        with open_artefact(path) as f:
            method = str(f.attrs.get("method", "self_supervised"))
            for cond, g in f.get("stability", {}).items():
                frames, survived = int(g.attrs["frames"]), int(g.attrs["survived"])
                rows.append(dict(scene=scene, method=method, condition=cond, frames=frames, frames_survived=survived,
                                 diverged=survived < frames, bc_error=float(g.attrs["dirichlet_error_end"])))  # fmt: skip
    return pd.DataFrame(rows, columns=["scene", "method", "condition", "frames", "frames_survived", "diverged", "bc_error"])


def speed_accuracy_rows(df: pd.DataFrame) -> pd.DataFrame:
    """Rows for :func:`latentsim.report.plots.speed_accuracy_chart`: every method, plus the full-space solver at error 0."""
    pts = df.assign(ms_per_frame=df["latent_ms"])[["scene", "method", "sequence", "ms_per_frame", "mean_error", "max_error", "diverged_frame"]]
    full = df.groupby(["scene", "sequence"], sort=False)["full_ms"].first().reset_index()
    full = full.assign(method="full_space", ms_per_frame=full["full_ms"], mean_error=0.0, max_error=0.0, diverged_frame=-1)
    return pd.concat([full[pts.columns], pts], ignore_index=True)


def reconstruction_table(scene: str, latents) -> pd.DataFrame:
    """Autoencoder reconstruction error per sequence (mean and max vertex error / bbox diagonal) from ``latents.h5``."""
    rows = []
    with open_artefact(latents) as f:
        for name, g in require(f, "sequences").items():
            rows.append(dict(scene=scene, sequence=name, split=str(g.attrs["split"]),
                             mean_error=float(g.attrs["mean_error"]), max_error=float(g.attrs["max_error"])))  # fmt: skip
    return pd.DataFrame(rows)


def table1(df: pd.DataFrame, sized=()) -> pd.DataFrame:
    """Li et al. Table 1: ours (self-supervised integrator, mean over test sequences) next to the paper's.

    sized : variants that are whole models of another size (their own autoencoder); each gets a row of
        its own below its scene's, so the table shows the speed of the model a scene needs beside the
        paper-size one.
    """
    rows = []
    for scene, method, _, g in _own_models(df, sized):
        paper = li2025_table1(scene)
        row = dict(
            scene=scene,
            method=method,
            dof=int(g["dof"].iloc[0]),
            latent_dof=int(g["latent_dim"].iloc[0]),
            full_ms=g["full_ms"].mean(),
            integrate_ms=g["integrate_ms"].mean(),
            decode_ms=g["decode_ms"].mean(),
            total_ms=g["latent_ms"].mean(),
            runtime=" ".join(sorted(set(g["runtime"].astype(str)))) if "runtime" in g else "",
            numpy_ms=g["numpy_step_ms"].mean() if "numpy_step_ms" in g else np.nan,
        )
        row["speedup"] = row["full_ms"] / row["total_ms"]
        if paper is not None:
            row.update(paper_dof=paper[0], paper_latent=paper[1], paper_full_ms=paper[2], paper_integrate_ms=paper[3],
                       paper_decode_ms=paper[4], paper_total_ms=paper[5], paper_speedup=paper[2] / paper[5])  # fmt: skip
        row["method"] = _with_divergence(method, g)
        rows.append(row)
    return pd.DataFrame(rows)


def _with_divergence(method: str, own: pd.DataFrame) -> str:
    """Tables 1-2's name of a method whose rows are ``own``: ``method``, or ``method (diverged on k/N test
    sequences)`` where some rollout diverged (the table times a step whose rollout failed)."""
    n = int((own["diverged_frame"] >= 0).sum()) if "diverged_frame" in own else 0
    return method if n == 0 else f"{method} (diverged on {n}/{len(own)} test sequences)"


def _own_models(df: pd.DataFrame, sized=()):
    """(scene, method, the scene's rows, the method's rows) of each scene's self-supervised integrator and then its
    ``sized`` variants (see :func:`table1`), scenes in the metrics' order; methods a scene did not run are left out."""
    methods = ["self_supervised"] + [m for m in sized if m != "self_supervised"]
    for scene, g in df.groupby("scene", sort=False):
        for method in methods:
            own = g[g["method"] == method]
            if not own.empty:
                yield scene, method, g, own


def table2(df: pd.DataFrame, layers: dict | None = None, sized=()) -> pd.DataFrame:
    """Li et al. Table 2: the single-vertex Jvp (torch.func.jvp as the paper, and forward mode), our whole
    latent step, and the whole Fulton-style reduced step when the scene ran that baseline; paper's alongside.

    layers : optional {scene: (decoder layers, integrator layers)} strings of our networks, and
        {(scene, method): ...} for the ``sized`` variants (see :func:`table1`), which get rows of their own.
    """
    layers = layers or {}
    return pd.DataFrame([_table2_row(scene, method, g, own, layers.get(scene if method == "self_supervised" else (scene, method)))
                         for scene, method, g, own in _own_models(df, sized)])  # fmt: skip


def _table2_row(scene: str, method: str, g: pd.DataFrame, own: pd.DataFrame, layers) -> dict:
    """One row of :func:`table2`: ``own``, the method's rows of the scene's metrics ``g``; ``layers`` its layer strings."""
    row = dict(scene=scene, method=_with_divergence(method, own), dof=int(own["dof"].iloc[0]), latent_dof=int(own["latent_dim"].iloc[0]))
    if layers:
        row["decoder_layers"], row["integrator_layers"] = layers
    row.update(jvp_torch_ms=own["jvp_torch_ms"].median(), jvp_forward_ms=own["jvp_forward_ms"].median(), ours_ms=own["latent_ms"].median())
    fulton = g[g["method"] == "fulton_reduced"]
    row["fulton_step_ms"] = fulton["latent_ms"].median() if not fulton.empty else np.nan
    paper = li2025_table2(scene)
    if paper is not None:
        row.update(paper_decoder_layers=paper[0], paper_integrator_layers=paper[1], paper_jvp_ms=paper[2], paper_ours_ms=paper[3])
    return row


def layers_text(widths, pca_dim=None) -> str:
    """Layer widths as the paper's Table 2 prints them: decoder ``"200, 200, 200, 50"`` (hidden layers, then the PCA layer)."""
    w = [int(v) for v in widths] + ([int(pca_dim)] if pca_dim else [])
    return ", ".join(map(str, w))


def sizes_table(sizes: dict, choices: dict | None = None) -> pd.DataFrame:
    """Model no more than a scene needs: per scene the paper's model, ours, and the sizing sweep's choice.

    Parameters
    ----------
    sizes : {scene: {"latent_dim", "decoder_layers", "integrator_layers"[, "tolerance", "variants"]}}, the
        config's model of each scene (layers as :func:`layers_text` writes them), its sweep tolerance, and
        the same of its variants that are models of their own size ({method: {...}}; column ``variant_models``).
    choices : {scene: path of the sweep's ``choice.csv``} for the scenes that ran a sweep.

    Returns
    -------
    One row per scene: ours, the paper's (Li et al. Tables 1-2; empty where the paper has no such
    scene), and from the sweep: points trained, points within the tolerance, the chosen point
    (latent dimension, decoder and integrator widths), its worst mean error and ms per step, and the
    same of a reference point: the paper's size where the sweep trained it, else the largest point.
    """
    rows = []
    for scene, own in sizes.items():
        row = dict(scene=scene, latent_dim=int(own["latent_dim"]), decoder_layers=own["decoder_layers"],
                   integrator_layers=own["integrator_layers"])  # fmt: skip
        if own.get("variants"):  # models of their own size beside the scene's (Tables 1-2 give their speed)
            row["variant_models"] = "; ".join(f"{m}: latent {int(w['latent_dim'])}, {w['decoder_layers']} / {w['integrator_layers']}"
                                              for m, w in own["variants"].items())  # fmt: skip
        t1, t2 = li2025_table1(scene), li2025_table2(scene)
        row.update(paper_latent=t1[1] if t1 else np.nan, paper_decoder_layers=t2[0] if t2 else "", paper_integrator_layers=t2[1] if t2 else "")
        path = (choices or {}).get(scene)
        if path is not None:
            ch = pd.read_csv(path)
            need = {"latent_dim", "autoencoder_widths", "integrator_widths", "parameters", "mean_error", "step_ms", "passes", "chosen"}
            if not need <= set(ch.columns):
                raise ValueError(f"{path}: sweep choice table lacks columns {sorted(need - set(ch.columns))}")
            pick = ch[ch["chosen"].astype(bool)]
            big = ch.sort_values(["parameters", "latent_dim"]).iloc[-1]
            row.update(tolerance=float(own.get("tolerance", np.nan)), sweep_points=len(ch), sweep_passing=int(ch["passes"].astype(bool).sum()))
            if len(pick):
                c = pick.iloc[0]
                row.update(chosen_latent=int(c["latent_dim"]), chosen_decoder=str(c["autoencoder_widths"]).replace(" ", ", "),
                           chosen_integrator=str(c["integrator_widths"]).replace(" ", ", "), chosen_error=float(c["mean_error"]),
                           chosen_step_ms=float(c["step_ms"]))  # fmt: skip
            if t1 and t2:  # the paper's size, where the sweep trained it (decoder widths without the PCA layer)
                same = ch[(ch["latent_dim"] == t1[1]) & (ch["autoencoder_widths"].astype(str) == " ".join(t2[0].split(", ")[:-1]))
                          & (ch["integrator_widths"].astype(str) == " ".join(t2[1].split(", ")))]  # fmt: skip
                big = same.iloc[0] if len(same) else big
            row.update(reference_point=f"latent {int(big['latent_dim'])}; {big['autoencoder_widths']} / {big['integrator_widths']}",
                       reference_error=float(big["mean_error"]), reference_step_ms=float(big["step_ms"]))  # fmt: skip
        rows.append(row)
    return pd.DataFrame(rows)


def stability_table(df: pd.DataFrame) -> pd.DataFrame:
    """Frames survived per scene, method and test sequence (Li et al. Fig. 8), with the errors and KE ratio."""
    out = df[["scene", "method", "sequence", "frames", "diverged_frame", "mean_error", "dirichlet_error", "kinetic_ratio",
              "end_error", "end_motion", "end_motion_truth"]].copy()  # fmt: skip
    out["survived"] = np.where(out["diverged_frame"] < 0, out["frames"], out["diverged_frame"])
    return out


# the methods of the comparison (issue order), as the glance's columns; variants stay in its long table
GLANCE_METHODS = ("full_space", "newton_1it", "pca_reduced", "modes_reduced", "fulton_reduced", "neural_modes_reduced",
                  "self_supervised", "supervised_5x256")  # fmt: skip


def glance_table(df: pd.DataFrame, pts: pd.DataFrame, stress: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per scene and method: what the speed-accuracy chart and the stability map show, as numbers.

    ``df``: the per-sequence metrics (:func:`latentsim.stages.evaluate.summarise`'s table); ``pts``: the chart's points
    (:func:`latentsim.report.plots.speed_accuracy_chart`'s return, with the ``full_space`` rows); ``stress``: the
    stress-condition rows (:func:`stress_table`), optional.

    Columns: ``scene``, ``method``, ``ms_per_frame`` (median over test sequences), ``speedup`` (full-space
    over latent or reduced ms, both means timed in the method's own job, as Table 1), ``mean_error``
    (mean), ``max_error`` (max; both infinite where a test sequence diverged: the frames from the divergence
    on count as failed, see :mod:`latentsim.report.metrics`), ``kinetic_ratio`` (mean; 1 for the full space,
    NaN where a test sequence diverged), ``test_survived`` (test sequences stable to the end, ``k/N``),
    ``stress_survived`` (stress conditions survived, ``k/N``, empty where none ran), ``on_front`` (the chart's
    Pareto front; never a method that diverged).
    Sorted by scene, then ms per frame.
    """
    g = pts.copy()
    own = df.groupby(["scene", "method"], sort=False)
    # each method's job timed full-space frames in its own process: the speed-up is that ratio
    ratio = own["full_ms"].mean() / own["latent_ms"].mean()
    ke = own["kinetic_ratio"].agg(lambda s: s.mean(skipna=False))  # NaN where a sequence diverged (not measurable)
    ok = own["diverged_frame"].agg(lambda s: f"{int((s < 0).sum())}/{len(s)}")
    key = list(zip(g["scene"], g["method"]))
    g["speedup"] = [1.0 if k[1] == "full_space" else ratio.get(k, np.nan) for k in key]
    g["kinetic_ratio"] = [1.0 if k[1] == "full_space" else ke.get(k, np.nan) for k in key]
    n_seq = df.groupby("scene")["sequence"].nunique()
    g["test_survived"] = [f"{n_seq.get(k[0], 0)}/{n_seq.get(k[0], 0)}" if k[1] == "full_space" else ok.get(k, "") for k in key]
    surv = {}
    if stress is not None and not stress.empty:
        for k, s in stress.groupby(["scene", "method"], sort=False):
            surv[k] = f"{int((~s['diverged'].astype(bool)).sum())}/{len(s)}"
    g["stress_survived"] = [surv.get(k, "") for k in key]
    cols = ["scene", "method", "ms_per_frame", "speedup", "mean_error", "max_error", "kinetic_ratio", "test_survived",
            "stress_survived", "on_front"]  # fmt: skip
    return g[cols].sort_values(["scene", "ms_per_frame"], kind="stable").reset_index(drop=True)


def glance_grid(glance: pd.DataFrame, methods=GLANCE_METHODS) -> pd.DataFrame:
    """Scenes x the comparison's methods, each cell ``mean error (ms per frame)``; ``*`` marks the Pareto
    front of these methods alone (the long table's ``on_front`` also counts the scene's variants), ``-`` a
    method the scene did not run.  A method that diverged on a test sequence (infinite error) reads
    ``diverged k/N (ms per frame)``, k of its N test sequences survived, and is never on the front."""
    present = [m for m in methods if m in set(glance["method"])]
    rows = []
    for scene, g in glance.groupby("scene", sort=True):
        by = g[g["method"].isin(present)].set_index("method")
        stable = [s.split("/")[0] == s.split("/")[1] for s in by["test_survived"]]
        front = pareto_front(by["ms_per_frame"], np.where(stable, by["mean_error"], np.nan))
        row = {"scene": scene}
        for m in present:
            if m not in by.index:
                row[m] = "-"
                continue
            r, i = by.loc[m], by.index.get_loc(m)
            error = f"{r['mean_error']:.3g}" if stable[i] else f"diverged {r['test_survived']}"
            row[m] = f"{error} ({r['ms_per_frame']:.3g})" + (" *" if front[i] else "")
        rows.append(row)
    return pd.DataFrame(rows, columns=["scene", *present])


def markdown(df: pd.DataFrame) -> str:
    """``df`` as a Markdown table (floats to 4 significant digits); ``(no rows)`` when empty."""
    cols = list(df.columns)
    if df.empty:
        return "(no rows)"
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |")
    return "\n".join(lines)



# --------------------------------------------------------------------------- HTML pages of the tables

_PAGE_STYLE = """
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", sans-serif; color: #222; margin: 1em 1.2em; }
h1 { font-size: 1.25em; margin: 0 0 .3em; } h2 { font-size: 1.05em; margin: 1.4em 0 .4em; }
p { max-width: 60em; } p.source { color: #666; font-size: .9em; margin-top: 0; }
.scroll { overflow-x: auto; margin-bottom: 1em; }
table { border-collapse: collapse; font-size: 13px; }
th, td { border: 1px solid #d0d0d0; padding: 3px 8px; white-space: nowrap; }
th { background: #eef1f5; position: sticky; top: 0; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tbody tr:nth-child(even) td { background: #f8f9fa; }
code { background: #f3f3f3; padding: 0 .2em; }
"""


def _cell(value) -> tuple[str, bool, str]:
    """(text, numeric, full value) of a table cell: floats to 4 significant digits (as :func:`markdown`), NaN blank."""
    if isinstance(value, (bool, np.bool_)) or value is None:
        return ("" if value is None else str(value)), False, ""
    if isinstance(value, (int, np.integer)):
        return str(value), True, ""
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            return ("" if np.isnan(value) else str(value)), True, ""
        return f"{value:.4g}", True, repr(float(value))
    text = str(value)
    try:
        float(text)
        return text, True, ""
    except ValueError:
        return text, False, ""


def html_table(df: pd.DataFrame, align=None) -> str:
    """``df`` as an HTML ``<table>`` (in a horizontally scrolling ``div``), cells escaped.

    Floats show 4 significant digits (the full value in the cell's tooltip), NaN as a blank cell, numbers
    right-aligned.  ``align``: optional list of ``"left"``/``"right"``/``None`` per column (a Markdown
    table's own alignment), overriding the number test.
    """
    cols = list(df.columns)
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
    rows = []
    for values in df.itertuples(index=False, name=None):
        cells = []
        for j, v in enumerate(values):
            text, numeric, full = _cell(v)
            if align is not None and align[j] is not None:
                numeric = align[j] == "right"
            attrs = (' class="num"' if numeric else "") + (f' title="{full}"' if full and full != text else "")
            cells.append(f"<td{attrs}>{html.escape(text)}</td>")
        rows.append("<tr>" + "".join(cells) + "</tr>")
    if not rows:
        rows.append(f'<tr><td colspan="{max(len(cols), 1)}">(no rows)</td></tr>')
    return f'<div class="scroll"><table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n' + "\n".join(rows) + "\n</tbody></table></div>"


_SEPARATOR = re.compile(r"^\|(\s*:?-+:?\s*\|)+$")


def _markdown_table(lines: list[str]) -> str:
    """A pipe table of this package's Markdown as HTML.

    Two writers make them: :func:`markdown` (``| a | b |`` rows, ``|---|---|``) and pandas' ``to_markdown``
    (tabulate: every row padded to the separator's column widths).  A cell may hold a ``|`` itself (``max
    |cos(l, y)|``), so where every row has its bars where the separator has them, those positions cut the
    cells; otherwise rows split at `` | ``.
    """
    if len(lines) < 2 or not _SEPARATOR.match(lines[1].strip()):
        raise ValueError(f"not a Markdown pipe table (no separator line under the header): {lines[:2]}")
    sep = lines[1].rstrip()
    bars = [i for i, ch in enumerate(sep) if ch == "|"]
    rows = [lines[0]] + lines[2:]
    if all(len(r.rstrip()) == len(sep) and all(r[i] == "|" for i in bars) for r in rows):
        cut = [[r[a + 1 : b].strip() for a, b in zip(bars, bars[1:])] for r in rows]
    else:
        cut = [[c.strip() for c in r.strip()[1:-1].split(" | ")] for r in rows]
    specs = [s.strip() for s in sep.strip()[1:-1].split("|")]
    align = [("right" if s.endswith(":") and not s.startswith(":") else "left" if s.startswith(":") else None) for s in specs]
    width = len(cut[0])
    if any(len(r) != width for r in cut) or len(align) != width:
        raise ValueError(f"Markdown table rows of unequal width: header {cut[0]}")
    return html_table(pd.DataFrame(cut[1:], columns=cut[0], dtype=object), align=align)


def _inline(text: str) -> str:
    """Escape ``text``; Markdown ``code`` spans become ``<code>``."""
    parts = text.split("`")
    return "".join(f"<code>{html.escape(p)}</code>" if i % 2 else html.escape(p) for i, p in enumerate(parts))


def _markdown_html(text: str) -> tuple[str, int, str | None]:
    """(HTML, number of tables, first level-1 heading) of this package's Markdown: ``#`` headings,
    paragraphs and pipe tables, blocks separated by blank lines (what :func:`markdown`, the summary and the
    Neural Modes stages write)."""
    out, tables, title = [], 0, None
    for block in re.split(r"\n\s*\n", text.strip()):
        lines = [ln for ln in block.splitlines() if ln.strip()]
        while lines and lines[0].lstrip().startswith("#"):
            head = lines.pop(0).strip()
            level = len(head) - len(head.lstrip("#"))
            content = head[level:].strip()
            if level == 1 and title is None:
                title = content
                continue
            out.append(f"<h{min(level, 6)}>{_inline(content)}</h{min(level, 6)}>")
        if not lines:
            continue
        if all(ln.lstrip().startswith("|") for ln in lines):
            out.append(_markdown_table([ln.strip() for ln in lines]))
            tables += 1
        else:
            out.append(f"<p>{_inline(' '.join(ln.strip() for ln in lines))}</p>")
    return "\n".join(out), tables, title


def html_page(title: str, body: str, source: str = "") -> str:
    """A standalone HTML page (inline style, no scripts or external files) around ``body``."""
    note = f'<p class="source">{html.escape(source)}</p>\n' if source else ""
    return (f'<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
            f"<style>{_PAGE_STYLE}</style>\n</head>\n<body>\n<h1>{html.escape(title)}</h1>\n{note}{body}\n</body>\n</html>\n")  # fmt: skip


def write_table_html(source, path, title: str | None = None, before: str = "") -> int:
    """Write a table file as an HTML page, atomically; returns the number of tables on it.

    Parameters
    ----------
    source : a ``.csv`` (one table, every column; its page says where the CSV is) or a ``.md`` as this
        package writes them (``#`` headings, paragraphs, pipe tables: ``summary.md``, the Neural Modes
        studies' ``tables.md``, ``table5.md`` ...; its first level-1 heading is the default title).
    path : the ``.html`` to write.
    title : the page's heading; default the Markdown's title, else the file's name.
    before : HTML put above the table (e.g. :func:`html_table` of a digest of it).
    """
    source = Path(source)
    if source.suffix == ".csv":
        df = pd.read_csv(source)
        body, tables, found = html_table(df), 1, None
        note = f"{source.name}: {len(df)} rows x {len(df.columns)} columns (beside this page in results/)"
    elif source.suffix == ".md":
        body, tables, found = _markdown_html(source.read_text())
        note = f"{source.name}, as a page"
    else:
        raise ValueError(f"write_table_html: {source}: expected a .csv or .md table file")
    with atomic_path(path) as tmp:
        Path(tmp).write_text(html_page(title or found or source.name, before + body, note), encoding="utf-8")
    return tables


GLANCE_GRID_NOTE = ("Mean vertex error / bounding-box diagonal (ms per frame) of each compared method, median over the "
                    "scene's test sequences; * marks the methods on the scene's speed-accuracy Pareto front (a method "
                    "that diverged on a test sequence never is), - a method the scene did not run.")  # fmt: skip


def write_glance_html(glance_csv, path, fragment, title: str = "At a glance: every method on every scene") -> pd.DataFrame:
    """The glance page and the landing page's grid, atomically; returns the grid.

    ``path``: a page with :func:`glance_grid` (scenes x the comparison's methods, built from ``glance_csv``,
    :func:`glance_table`'s CSV) above the whole glance table.  ``fragment``: the grid alone as an HTML
    fragment (a ``div`` with its own scoped style) for the report's landing page to include.
    """
    glance = pd.read_csv(glance_csv)
    grid = glance_grid(glance)
    note = f"<p>{html.escape(GLANCE_GRID_NOTE)}</p>"
    before = f"<h2>Scenes x compared methods</h2>\n{note}\n{html_table(grid)}\n<h2>Every method per scene (variants too)</h2>\n"
    write_table_html(glance_csv, path, title, before=before)
    style = ("<style>.latentsim-glance table{border-collapse:collapse;font-size:13px;margin:.4em 0}"
             ".latentsim-glance th,.latentsim-glance td{border:1px solid #ccc;padding:2px 7px;white-space:nowrap}"
             ".latentsim-glance th{background:#eef1f5;text-align:left}.latentsim-glance td.num{text-align:right}"
             ".latentsim-glance .scroll{overflow-x:auto}.latentsim-glance p{font-size:.9em;color:#555}</style>")  # fmt: skip
    with atomic_path(fragment) as tmp:
        Path(tmp).write_text(f'<div class="latentsim-glance">{style}\n{html_table(grid)}\n{note}\n</div>\n', encoding="utf-8")
    return grid
