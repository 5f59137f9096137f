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
- :func:`markdown`: any of them as a Markdown table.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from latentsim.io import atomic_path, open_artefact, require
from latentsim.report.metrics import pareto_front
from latentsim.report.paper import li2025_table1, li2025_table2

__all__ = [
    "GLANCE_METHODS",
    "glance_grid",
    "glance_table",
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
        rows.append(row)
    return pd.DataFrame(rows)


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
    row = dict(scene=scene, method=method, dof=int(own["dof"].iloc[0]), latent_dof=int(own["latent_dim"].iloc[0]))
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
    (mean), ``max_error`` (max), ``kinetic_ratio`` (mean; 1 for the full space), ``test_survived`` (test sequences stable to the end, ``k/N``), ``stress_survived``
    (stress conditions survived, ``k/N``, empty where none ran), ``on_front`` (the chart's Pareto front).
    Sorted by scene, then ms per frame.
    """
    g = pts.copy()
    own = df.groupby(["scene", "method"], sort=False)
    # each method's job timed full-space frames in its own process: the speed-up is that ratio
    ratio = own["full_ms"].mean() / own["latent_ms"].mean()
    ke = own["kinetic_ratio"].mean()
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
    method the scene did not run.  A method that diverged on a test sequence is never on the front."""
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
            r = by.loc[m]
            row[m] = f"{r['mean_error']:.3g} ({r['ms_per_frame']:.3g})" + (" *" if front[by.index.get_loc(m)] else "")
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

