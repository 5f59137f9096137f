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
- :func:`speed_accuracy_points`, :func:`glance_table`, :func:`glance_grid`: the speed-accuracy
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

from latentsim.io import atomic_path, open_artefact, read_csv, require, write_csv
from latentsim.report.metrics import PENETRATION_LIMIT, pareto_front
from latentsim.report.paper import li2025_table1, li2025_table2

__all__ = [
    "GLANCE_METHODS",
    "claims",
    "divergence_table",
    "glance_grid",
    "glance_table",
    "over_seeds",
    "per_seed",
    "html_table",
    "markdown",
    "reconstruction_table",
    "sizes_table",
    "speed_accuracy_points",
    "stability_table",
    "stress_over_seeds",
    "stress_table",
    "table1",
    "table2",
    "write_table",
    "write_glance_html",
    "write_table_html",
]


def write_table(df: pd.DataFrame, path):
    """Write ``df`` as CSV atomically (no index, 6 significant digits), its checksum beside it (:func:`latentsim.io.write_csv`)."""
    write_csv(df, path, index=False, float_format="%.6g")


def stress_over_seeds(stress: pd.DataFrame) -> pd.DataFrame:
    """The stress rows (:func:`stress_table`) as one row per scene, method and condition over the seeds:
    ``frames``, ``frames_survived`` (the least), ``diverged`` (in any seed), ``seeds``, ``seeds_survived``,
    ``bc_error`` (the largest) and, with colliders, ``max_penetration`` and (projected) ``max_penetration_own``
    (the deepest); what :func:`latentsim.report.plots.stability_heatmap` colours by seed."""
    st = stress.assign(seed=_seeds(stress), diverged=stress["diverged"].astype(bool))
    extra = {key: (key, "max") for key in ("max_penetration", "max_penetration_own") if key in st.columns}
    return st.groupby(["scene", "method", "condition"], sort=False).agg(
        frames=("frames", "max"), frames_survived=("frames_survived", "min"), diverged=("diverged", "any"), seeds=("seed", "nunique"),
        seeds_survived=("diverged", lambda d: int((~d).sum())), bc_error=("bc_error", "max"), **extra).reset_index()  # fmt: skip


def stress_table(scene: str, rollouts) -> pd.DataFrame:
    """Stability map rows (method x stress condition) from the rollouts' ``stability`` groups.

    Columns: scene, method, seed (-1: no seed changes the method), condition, frames, frames_survived, diverged,
    bc_error (mean Dirichlet error / bbox diagonal at the last surviving frame); in a scene with colliders,
    max_penetration (the deepest entry into one of any surviving frame / bbox diagonal; where the rollout
    projects its frames out of the colliders, the projected frames', and max_penetration_own the network's own).
    """
    rows, depths = [], ("max_penetration", "max_penetration_own")
    for path in rollouts:
        with open_artefact(path) as f:
            method, seed = str(f.attrs.get("method", "self_supervised")), int(f.attrs.get("seed", -1))
            for cond, g in f.get("stability", {}).items():
                frames, survived = int(g.attrs["frames"]), int(g.attrs["survived"])
                rows.append(dict(scene=scene, method=method, seed=seed, condition=cond, frames=frames, frames_survived=survived,
                                 diverged=survived < frames, bc_error=float(g.attrs["dirichlet_error_end"]),
                                 **{k: float(g.attrs[k]) for k in depths if k in g.attrs}))  # fmt: skip
    columns = ["scene", "method", "seed", "condition", "frames", "frames_survived", "diverged", "bc_error"] + [k for k in depths if any(k in r for r in rows)]
    return pd.DataFrame(rows, columns=columns)


def speed_accuracy_points(df: pd.DataFrame) -> pd.DataFrame:
    """The speed-accuracy comparison's points, one per scene and method, the full-space solver included: what
    :func:`latentsim.report.plots.speed_accuracy_chart` draws and :func:`glance_table` lists.

    ``df``: the per-sequence metrics (:func:`latentsim.stages.evaluate.summarise`'s table).  Each method's
    columns are :func:`over_seeds` of :func:`per_seed` (medians over the seeds, least and largest); the
    full space (``method`` ``full_space``, one "seed") runs at the median over the test sequences of its
    ``full_ms``, at error 0, stable.  ``on_front``: the scene's Pareto front over ``ms_per_frame`` and
    ``mean_error``, never a method that diverged in any seed, nor, in a scene with colliders, one whose
    median ``max_penetration`` exceeds :data:`PENETRATION_LIMIT` of the diagonal (the full space's is 0).
    Sorted by scene, then method.
    """
    methods = over_seeds(per_seed(df))
    full = df.groupby(["scene", "sequence"], sort=False)["full_ms"].first().groupby("scene", sort=False).median()
    n_seq = df.groupby("scene", sort=False)["sequence"].nunique()
    ones = {f"{c}{x}": 1.0 for c in ("speedup", "kinetic_ratio") for x in ("", "_min", "_max")}
    full = pd.DataFrame([dict(scene=scene, method="full_space", seeds=1, seeds_stable=1, ms_per_frame=ms, ms_per_frame_min=ms, ms_per_frame_max=ms,
                              mean_error=0.0, mean_error_min=0.0, mean_error_max=0.0, max_error=0.0, **ones, sequences=int(n_seq[scene]),
                              test_survived=f"{n_seq[scene]}/{n_seq[scene]}", diverged_frame=-1, diverged_seeds=0)
                         for scene, ms in full.items()])  # fmt: skip
    if "max_penetration" in methods.columns:  # the full space never enters a collider (simulate refuses a frame that does)
        inside = methods.groupby("scene")["max_penetration"].apply(lambda v: bool(v.notna().any()))
        full["max_penetration"] = [0.0 if inside.get(sc, False) else np.nan for sc in full["scene"]]
    pts = pd.concat([full, methods], ignore_index=True).sort_values(["scene", "method"], kind="stable").reset_index(drop=True)
    pts["on_front"] = False
    for _, g in pts.groupby("scene", sort=False):
        eligible = np.where(g["diverged_frame"].to_numpy() >= 0, np.nan, g["mean_error"].to_numpy(float))
        if "max_penetration" in g.columns:
            eligible = np.where(g["max_penetration"].to_numpy(float) > PENETRATION_LIMIT, np.nan, eligible)
        pts.loc[g.index, "on_front"] = pareto_front(g["ms_per_frame"].to_numpy(float), eligible)
    return pts


def reconstruction_table(scene: str, latents) -> pd.DataFrame:
    """Autoencoder reconstruction error per seed and sequence (mean and max vertex error / bbox diagonal; with colliders
    ``max_penetration``, ``penetrating_frames``) from one ``latents.h5`` or a list of them (one per seed)."""
    rows = []
    for path in [latents] if isinstance(latents, (str, bytes)) or hasattr(latents, "__fspath__") else latents:
        with open_artefact(path) as f:
            seed = int(f.attrs.get("seed", -1))
            for name, g in require(f, "sequences").items():
                rows.append(dict(scene=scene, seed=seed, sequence=name, split=str(g.attrs["split"]),
                                 mean_error=float(g.attrs["mean_error"]), max_error=float(g.attrs["max_error"]),
                                 **{k: g.attrs[k].item() for k in ("max_penetration", "penetrating_frames") if k in g.attrs}))  # fmt: skip
    return pd.DataFrame(rows)


def table1(df: pd.DataFrame, sized=()) -> pd.DataFrame:
    """Li et al. Table 1: ours (self-supervised integrator, mean over test sequences) next to the paper's.

    With several seeds (column ``seed``) each timing is the median over seeds of the seed's mean, and
    ``total_ms`` and ``speedup`` have their least and largest over seeds beside them (``_min``, ``_max``).
    ``floor_ms`` (where the rollouts timed it): one bare pass of the model's output layer over every DoF,
    and ``step_over_floor`` (median, ``_max``) the step's time over it.  ``total_ms``: integrate + decode (+ the
    contact projection's share, ``projection_ms``); ``full_ms``: the scene's one full-space time (``time_full_space``).

    sized : variants that are whole models of another size (their own autoencoder); each gets a row of
        its own below its scene's, so the table shows the speed of the model a scene needs beside the
        paper-size one.
    """
    rows = []
    for scene, method, _, g in _own_models(df, sized):
        paper = li2025_table1(scene)
        # each seed's mean over the test sequences, then the median over seeds (least and largest beside it)
        cols = ["full_ms", "integrate_ms", "decode_ms", "latent_ms"] + [c for c in ("numpy_step_ms", "floor_ms", "projection_ms") if c in g]
        ps = g.assign(seed=_seeds(g)).groupby("seed")[cols].mean()
        ps["speedup"] = ps["full_ms"] / ps["latent_ms"]
        floor = ps["floor_ms"] if "floor_ms" in ps else pd.Series(np.nan, index=ps.index)
        row = dict(
            scene=scene,
            method=method,
            seeds=len(ps),
            dof=int(g["dof"].iloc[0]),
            latent_dof=int(g["latent_dim"].iloc[0]),
            full_ms=ps["full_ms"].median(),
            integrate_ms=ps["integrate_ms"].median(),
            decode_ms=ps["decode_ms"].median(),
            projection_ms=ps["projection_ms"].median() if "projection_ms" in ps else np.nan,
            total_ms=ps["latent_ms"].median(),
            total_ms_min=ps["latent_ms"].min(),
            total_ms_max=ps["latent_ms"].max(),
            runtime=" ".join(sorted(set(g["runtime"].astype(str)))) if "runtime" in g else "",
            numpy_ms=ps["numpy_step_ms"].median() if "numpy_step_ms" in ps else np.nan,
            speedup=ps["speedup"].median(),
            speedup_min=ps["speedup"].min(),
            speedup_max=ps["speedup"].max(),
            floor_ms=floor.median(),
            step_over_floor=(ps["latent_ms"] / floor).median(),
            step_over_floor_max=(ps["latent_ms"] / floor).max(),
        )
        if paper is not None:
            row.update(paper_dof=paper[0], paper_latent=paper[1], paper_full_ms=paper[2], paper_integrate_ms=paper[3],
                       paper_decode_ms=paper[4], paper_total_ms=paper[5], paper_speedup=paper[2] / paper[5])  # fmt: skip
        row["method"] = _with_divergence(method, g)
        rows.append(row)
    return pd.DataFrame(rows)


def _with_divergence(method: str, own: pd.DataFrame) -> str:
    """Tables 1-2's name of a method whose rows are ``own``: ``method``, or ``method (diverged on k/N test
    rollouts)`` where some rollout diverged (the table times a step whose rollout failed); N counts every
    test sequence of every seed."""
    n = int((own["diverged_frame"] >= 0).sum()) if "diverged_frame" in own else 0
    return method if n == 0 else f"{method} (diverged on {n}/{len(own)} test rollouts)"


def _seeds(df: pd.DataFrame) -> pd.Series:
    """The rows' seeds (-1, one unseeded run, where the table has no ``seed`` column)."""
    return df["seed"].fillna(-1).astype(int) if "seed" in df else pd.Series(-1, index=df.index)


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
    row = dict(scene=scene, method=_with_divergence(method, own), seeds=int(_seeds(own).nunique()), dof=int(own["dof"].iloc[0]),
               latent_dof=int(own["latent_dim"].iloc[0]))  # fmt: skip
    if layers:
        row["decoder_layers"], row["integrator_layers"] = layers
    row.update(jvp_torch_ms=own["jvp_torch_ms"].median(), jvp_forward_ms=own["jvp_forward_ms"].median(), ours_ms=own["latent_ms"].median())
    fulton = g[g["method"] == "fulton_reduced"]
    row["fulton_step_ms"] = fulton["latent_ms"].median() if not fulton.empty else np.nan
    paper = li2025_table2(scene)
    if paper is not None:
        row.update(paper_decoder_layers=paper[0], paper_integrator_layers=paper[1], paper_jvp_ms=paper[2], paper_ours_ms=paper[3])
    return row


def sizes_table(sizes: dict, choices: dict | None = None) -> pd.DataFrame:
    """Model no more than a scene needs: per scene the paper's model, ours, and the sizing sweep's choice.

    Parameters
    ----------
    sizes : {scene: {"latent_dim", "decoder_layers", "integrator_layers"[, "tolerance", "variants"]}}, the
        config's model of each scene (layers as ``labels.layers_text`` writes them), its sweep tolerance, and
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
            ch = read_csv(path)
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
    """Frames survived per scene, method, seed and test sequence (Li et al. Fig. 8), with the errors and KE ratio."""
    out = df.assign(seed=_seeds(df))[["scene", "method", "seed", "sequence", "frames", "diverged_frame", "mean_error", "dirichlet_error",
                                      "kinetic_ratio", "end_error", "end_motion", "end_motion_truth"]].copy()  # fmt: skip
    out["survived"] = np.where(out["diverged_frame"] < 0, out["frames"], out["diverged_frame"])
    return out


# the methods of the comparison (issue order), as the glance's columns; variants stay in its long table
GLANCE_METHODS = ("full_space", "newton_1it", "pca_reduced", "modes_reduced", "fulton_reduced", "neural_modes_reduced",
                  "self_supervised", "supervised_5x256")  # fmt: skip


def per_seed(df: pd.DataFrame) -> pd.DataFrame:
    """One row per scene, method and seed: the seed's test sequences together.

    Columns: ``scene``, ``method``, ``seed`` (-1: a method no seed changes), ``ms_per_frame`` (median over
    the sequences), ``full_ms`` and ``latent_ms`` (means), ``speedup`` (their ratio), ``mean_error`` (mean;
    infinite where a sequence diverged), ``max_error`` (max), ``kinetic_ratio`` (mean; NaN where a sequence
    diverged), ``sequences``, ``survived`` (test sequences stable to the end), ``diverged_frame`` (the
    earliest frame a sequence diverged at, -1 where none did); in a scene with colliders (column
    ``max_penetration``), ``max_penetration`` (the deepest entry of any sequence / the diagonal).
    """
    g = df.assign(seed=_seeds(df)).groupby(["scene", "method", "seed"], sort=False)
    extra = {"max_penetration": ("max_penetration", "max")} if "max_penetration" in df.columns else {}
    out = g.agg(ms_per_frame=("latent_ms", "median"), full_ms=("full_ms", "mean"), latent_ms=("latent_ms", "mean"),
                mean_error=("mean_error", lambda v: v.mean(skipna=False)), max_error=("max_error", lambda v: v.max(skipna=False)),
                kinetic_ratio=("kinetic_ratio", lambda v: v.mean(skipna=False)), sequences=("sequence", "nunique"),
                survived=("diverged_frame", lambda v: int((v < 0).sum())), diverged_frame=("diverged_frame", _earliest), **extra).reset_index()  # fmt: skip
    out["speedup"] = out["full_ms"] / out["latent_ms"]
    return out


def _earliest(frames: pd.Series) -> int:
    """The earliest divergence frame among ``frames`` (-1: none diverged)."""
    hit = frames[frames >= 0]
    return int(hit.min()) if len(hit) else -1


def over_seeds(ps: pd.DataFrame) -> pd.DataFrame:
    """One row per scene and method from :func:`per_seed`'s rows: the spread of each metric over the seeds.

    Columns: ``scene``, ``method``, ``seeds`` (how many), ``seeds_stable`` (seeds whose every test sequence
    survived); ``ms_per_frame``, ``speedup``, ``mean_error``, ``kinetic_ratio``: the median over seeds, with
    ``<name>_min`` and ``<name>_max`` the least and largest (the mean error's over the stable seeds alone,
    NaN where none was); ``max_error``: the largest; ``test_survived``: ``k/N`` test rollouts (sequences
    times seeds) stable to the end; ``sequences`` (per seed); ``diverged_frame``: the earliest divergence
    of any seed (-1: none), ``diverged_seeds``: the seeds in which a test sequence diverged; with
    colliders, ``max_penetration`` (median over seeds, ``_min``, ``_max``).
    """
    rows = []
    for (scene, method), g in ps.groupby(["scene", "method"], sort=False):
        stable = g["survived"] == g["sequences"]
        row = dict(scene=scene, method=method, seeds=len(g), seeds_stable=int(stable.sum()), sequences=int(g["sequences"].max()),
                   diverged_frame=_earliest(g["diverged_frame"]), diverged_seeds=int((~stable).sum()))  # fmt: skip
        for c in ("ms_per_frame", "speedup", "mean_error", "kinetic_ratio") + (("max_penetration",) if "max_penetration" in g.columns else ()):
            v = g.loc[stable, c] if c == "mean_error" else g[c]
            row[c] = g[c].median()
            row[f"{c}_min"], row[f"{c}_max"] = (v.min(), v.max()) if len(v) else (np.nan, np.nan)
        row["max_error"] = g["max_error"].max(skipna=False)
        row["test_survived"] = f"{int(g['survived'].sum())}/{int(g['sequences'].sum())}"
        rows.append(row)
    return pd.DataFrame(rows)


def glance_table(df: pd.DataFrame, stress: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per scene and method: what the speed-accuracy chart and the stability map show, as numbers,
    over the seeds.

    ``df``: the per-sequence metrics (:func:`latentsim.stages.evaluate.summarise`'s table, column ``seed``);
    ``stress``: the stress-condition rows (:func:`stress_table`), optional.  The rows are the chart's points
    (:func:`speed_accuracy_points`).

    Columns: ``scene``, ``method``, ``seeds``; over the seeds (:func:`over_seeds`), median with least and largest:
    ``ms_per_frame`` (each seed's median over test sequences), ``speedup`` (full-space over latent or reduced ms,
    both timed in the method's own job, as Table 1), ``mean_error`` (each seed's mean; infinite where a test
    sequence diverged: the frames from the divergence on count as failed, see :mod:`latentsim.report.metrics`;
    least and largest over the stable seeds), ``kinetic_ratio`` (1 for the full space, NaN where a test sequence
    diverged); ``max_error`` (largest); ``seeds_stable`` (``k/n`` seeds whose every test sequence survived),
    ``test_survived`` (``k/N`` test rollouts, sequences times seeds, stable to the end), ``stress_survived``
    (stress conditions survived, ``k/N`` over conditions times seeds, empty where none ran), ``on_front`` (the
    chart's Pareto front over the medians; never a method that diverged in any seed).
    Sorted by scene, then ms per frame.
    """
    pts = speed_accuracy_points(df)
    surv = {}
    if stress is not None and not stress.empty:
        for k, st in stress.groupby(["scene", "method"], sort=False):
            surv[k] = f"{int((~st['diverged'].astype(bool)).sum())}/{len(st)}"
    cols = ["seeds", "ms_per_frame", "ms_per_frame_min", "ms_per_frame_max", "speedup", "speedup_min", "speedup_max", "mean_error",
            "mean_error_min", "mean_error_max", "max_error", "kinetic_ratio", "kinetic_ratio_min", "kinetic_ratio_max"]  # fmt: skip
    if "max_penetration" in pts.columns:  # a config with colliders: how deep each method entered them
        cols += ["max_penetration", "max_penetration_min", "max_penetration_max"]
    out = pts.assign(seeds=pts["seeds"].astype(int), seeds_stable=[f"{int(k)}/{int(n)}" for k, n in zip(pts["seeds_stable"], pts["seeds"])],
                     stress_survived=[surv.get(k, "") for k in zip(pts["scene"], pts["method"])], on_front=pts["on_front"].astype(bool))  # fmt: skip
    order = ["scene", "method", *cols, "seeds_stable", "test_survived", "stress_survived", "on_front"]
    return out[order].sort_values(["scene", "ms_per_frame"], kind="stable").reset_index(drop=True)


def glance_grid(glance: pd.DataFrame, methods=GLANCE_METHODS) -> pd.DataFrame:
    """Scenes x the comparison's methods, each cell ``mean error (ms per frame)``, medians over seeds, with
    ``[least-largest]`` over the seeds where there are several; ``*`` marks the Pareto front of these methods
    alone (the long table's ``on_front`` also counts the scene's variants), ``-`` a method the scene did not
    run.  A method that diverged on a test sequence (infinite error) reads ``diverged k/N (ms per frame)``
    (k of its N test rollouts survived) or, over several seeds, ``diverged in j/n seeds``, and is never on
    the front; nor is one that entered a collider deeper than :data:`PENETRATION_LIMIT` of the diagonal
    (median over seeds), whose cell ends ``inside p%``."""
    present = [m for m in methods if m in set(glance["method"])]
    rows = []
    for scene, g in glance.groupby("scene", sort=True):
        by = g[g["method"].isin(present)].set_index("method")
        stable = [s.split("/")[0] == s.split("/")[1] for s in by["test_survived"]]
        pen = by["max_penetration"].to_numpy(float) if "max_penetration" in by.columns else np.full(len(by), np.nan)
        ok = np.asarray(stable) & ~(pen > PENETRATION_LIMIT)
        front = pareto_front(by["ms_per_frame"], np.where(ok, by["mean_error"], np.nan))
        row = {"scene": scene}
        for m in present:
            if m not in by.index:
                row[m] = "-"
                continue
            r, i = by.loc[m], by.index.get_loc(m)
            n = int(r["seeds"]) if "seeds" in r and pd.notna(r["seeds"]) else 1
            if stable[i]:
                error = f"{r['mean_error']:.3g}"
                if n > 1:
                    error += f" [{r['mean_error_min']:.3g}-{r['mean_error_max']:.3g}]"
            elif n > 1:
                k = int(str(r["seeds_stable"]).split("/")[0])
                error = f"diverged in {n - k}/{n} seeds"
            else:
                error = f"diverged {r['test_survived']}"
            row[m] = f"{error} ({r['ms_per_frame']:.3g})" + (f" inside {100 * pen[i]:.2g}%" if pen[i] > 0 else "") + (" *" if front[i] else "")
        rows.append(row)
    return pd.DataFrame(rows, columns=["scene", *present])


def divergence_table(df: pd.DataFrame, stress: pd.DataFrame | None = None) -> pd.DataFrame:
    """Li et al. Fig. 8 over seeds: per scene and method, how often it diverged and the frames each seed survived.

    Columns: ``scene``, ``method``, ``seeds``, ``test_diverged`` (seeds in which a test sequence diverged),
    ``frames_survived`` (per seed, in seed order, ``seed:frames``, or the frames alone for a method no seed
    changes; several test sequences' frames joined by ``/``), ``frames`` (of the test sequences, ``/``-joined), ``stress_failed`` (seeds that failed a stress
    condition, empty where none ran), and per stress condition ``stress: <condition>`` (seeds that failed
    it, and the frames each failing seed survived).  Each count reads ``k/n``, k of the n seeds.
    """
    d = df.assign(seed=_seeds(df))
    st = stress.assign(seed=_seeds(stress)) if stress is not None and not stress.empty else None
    conditions = list(dict.fromkeys(st["condition"])) if st is not None else []
    rows = []
    for (scene, method), g in d.groupby(["scene", "method"], sort=False):
        seeds = sorted(g["seed"].unique())
        n = len(seeds)
        per = {s: g[g["seed"] == s] for s in seeds}
        survived = {s: "/".join(str(int(f if dv < 0 else dv)) for f, dv in zip(h["frames"], h["diverged_frame"])) for s, h in per.items()}
        row = dict(scene=scene, method=method, seeds=n, test_diverged=f"{sum(int((h['diverged_frame'] >= 0).any()) for h in per.values())}/{n}",
                   frames_survived=" ".join(survived[s] if s < 0 else f"{s}:{survived[s]}" for s in seeds),
                   frames="/".join(str(int(f)) for f in per[seeds[0]]["frames"]))  # fmt: skip
        own = st[(st["scene"] == scene) & (st["method"] == method)] if st is not None else None
        if own is not None and len(own):
            failed = own[own["diverged"].astype(bool)]
            row["stress_failed"] = f"{failed['seed'].nunique()}/{n}"
            for c in conditions:
                fc = failed[failed["condition"] == c].sort_values("seed")
                ran = own[own["condition"] == c]
                row[f"stress: {c}"] = "" if ran.empty else f"{len(fc)}/{ran['seed'].nunique()}" + (
                    " (" + " ".join(f"{int(f)}" if s < 0 else f"{int(s)}:{int(f)}" for s, f in zip(fc["seed"], fc["frames_survived"])) + ")" if len(fc) else "")
        else:
            row["stress_failed"] = ""
        rows.append(row)
    return pd.DataFrame(rows).fillna("")


def claims(glance: pd.DataFrame, divergence: pd.DataFrame) -> str:
    """The comparison's claims as sentences, each with its seed count and spread, from the glance table and
    :func:`divergence_table` (for the README and the report: generated, never typed).

    One line per scene and learned method (several seeds): its mean error (median, least and largest over
    the stable seeds), how many seeds survived the test sequences, the stress conditions it failed in how
    many seeds, and in a scene with colliders how deep it entered them."""
    out = []
    dv = divergence.set_index(["scene", "method"])
    for r in glance.itertuples(index=False):
        if r.method == "full_space" or (r.scene, r.method) not in dv.index or int(r.seeds) < 2:
            continue
        d = dv.loc[(r.scene, r.method)]
        n = int(r.seeds)
        k = int(str(r.seeds_stable).split("/")[0])
        error = (f"mean error {r.mean_error:.3g} (median of {n} seeds; {r.mean_error_min:.3g} to {r.mean_error_max:.3g} over the "
                 f"{k} stable)" if k else "no seed stable")  # fmt: skip
        test = (f"survives every test sequence in {k} of {n} seeds" if k == n else
                f"diverges on a test sequence in {n - k} of {n} seeds (frames survived per seed {d['frames_survived']} of {d['frames']})")  # fmt: skip
        stress_cols = [c for c in dv.columns if c.startswith("stress: ") and isinstance(d[c], str) and d[c]]
        failed = [f"{c.removeprefix('stress: ')} in {d[c].split(' ')[0].split('/')[0]} of {n}" for c in stress_cols
                  if d[c].split("/")[0] != "0"]  # fmt: skip
        if not stress_cols:
            stress_text = ""
        elif failed:
            stress_text = "; fails " + ", ".join(failed)
        else:
            stress_text = f"; survives every stress condition in {n} of {n} seeds"
        pen = float(getattr(r, "max_penetration", float("nan")))
        contact = ""
        if pen == 0 and r.max_penetration_max == 0:
            contact = f"; never enters a collider in {n} of {n} seeds"
        elif pen == pen:
            contact = (f"; enters a collider by {100 * pen:.2g}% of the diagonal (median of {n} seeds; "
                       f"{100 * r.max_penetration_min:.2g}% to {100 * r.max_penetration_max:.2g}%)")  # fmt: skip
        out.append(f"- {r.scene}, {r.method}: {error}; {test}{stress_text}{contact}.")
    return "\n".join(out) + ("\n" if out else "")


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
        df = read_csv(source)
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
    glance = read_csv(glance_csv)
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
