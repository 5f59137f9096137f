"""Evaluation: a method's rollout against the full-space ground truth.

Metrics per test sequence (all lengths relative to the rest bounding-box diagonal):

- ``mean_error`` / ``max_error``: mean over frames of the mean / max vertex
  distance to the ground truth;
- ``dirichlet_error``: mean distance of the Dirichlet vertices to their
  prescribed positions;
- ``kinetic_ratio``: mean kinetic energy of the rollout over that of the
  ground truth (1 = no numerical damping);
- ``diverged_frame``: first diverged frame, -1 if stable to the end;
- ``full_ms`` / ``latent_ms`` / ``speedup``: mean full-space Newton frame time
  against the median latent step (integration + decoding).
"""

from __future__ import annotations

import h5py
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from latentsim.io import atomic_path, require  # noqa: E402
from latentsim.report.paper import li2025_table1, li2025_table2  # noqa: E402
from latentsim.report.plots import pareto_front, speed_accuracy_chart, stability_heatmap  # noqa: E402


def bbox_diagonal(x: np.ndarray) -> float:
    return float(np.linalg.norm(x.max(axis=0) - x.min(axis=0)))


def kinetic_energy(positions: np.ndarray, masses: np.ndarray, dt: float) -> np.ndarray:
    """(T,) kinetic energy with backward-difference velocities (frame 0: 0)."""
    v = np.diff(positions, axis=0) / dt
    ke = 0.5 * np.einsum("n,tn->t", masses, (v * v).sum(-1))
    return np.concatenate([[0.0], ke])


def vertex_errors(pred: np.ndarray, truth: np.ndarray, diag: float):
    """Per-frame mean and max vertex distance / diag, each (T,)."""
    d = np.linalg.norm(pred - truth, axis=-1) / diag
    return d.mean(axis=-1), d.max(axis=-1)


def evaluate_scene(scene: str, trajectories, rollouts):
    """Metrics of every method's rollouts against the full simulation.

    Parameters
    ----------
    scene : scene name (a column of the table).
    trajectories : the simulator's ``trajectories.h5`` (ground truth).
    rollouts : one path or a list of rollout files (trajectory layout, attrs
        ``method``); each holds some of the ground truth's sequences.

    Returns
    -------
    table : one row per (method, sequence): frames, diverged_frame, mean/max
        vertex error and Dirichlet error / bbox diagonal (over the frames
        before divergence), kinetic_ratio (mean rollout KE / mean ground-truth
        KE), full_ms (the simulator's mean ms/frame), latent_ms (one latent
        step), speedup, dof, latent_dim.
    curves : {method: {sequence: per-frame arrays}} for :func:`plot_curves`.
    """
    if isinstance(rollouts, (str, bytes)) or hasattr(rollouts, "__fspath__"):
        rollouts = [rollouts]
    rows, curves = [], {}
    with h5py.File(trajectories, "r") as ft:
        rest = require(ft, "rest_positions")[()]
        masses = require(ft, "masses")[()]
        D = require(ft, "dirichlet")[()]
        dt = float(ft.attrs["dt"])
        diag = bbox_diagonal(rest)
        for path in rollouts:
            with h5py.File(path, "r") as fr:
                method = str(fr.attrs.get("method", "self_supervised"))
                train_s = {k: float(fr.attrs.get(k, np.nan)) for k in ("autoencoder_train_seconds", "integrator_train_seconds")}
                for name, g in require(fr, "sequences").items():
                    gt = require(ft["sequences"], name)
                    truth = gt["positions"][()]
                    pred = g["positions"][()]
                    if pred.shape != truth.shape:
                        raise ValueError(f"{path}: sequence {name!r} has positions {pred.shape}, ground truth {truth.shape}")
                    T = len(truth)
                    div = int(g.attrs["diverged_frame"])
                    ok = slice(0, T if div < 0 else div)
                    mean_e, max_e = vertex_errors(pred[ok], truth[ok], diag)
                    bc_e = np.linalg.norm(pred[ok][:, D] - gt["dirichlet_positions"][ok], axis=-1).mean(-1) / diag
                    ke_t, ke_p = kinetic_energy(truth[ok], masses, dt), kinetic_energy(pred[ok], masses, dt)
                    # the end of the sequence (last 10% of frames; Li et al. Fig. 10's steady state): error and
                    # residual motion (RMS vertex displacement per frame / diag; 0 at rest)
                    tail = slice(max(1, T - max(T // 10, 2)), T)
                    end_ok = div < 0
                    end_error = float(mean_e[tail].mean()) if end_ok else np.nan
                    step = np.linalg.norm(np.diff(pred[tail.start - 1 : T], axis=0), axis=-1) if end_ok else np.full(1, np.nan)
                    end_motion = float(np.sqrt((step**2).mean()) / diag)
                    step_t = np.linalg.norm(np.diff(truth[tail.start - 1 : T], axis=0), axis=-1)
                    end_motion_truth = float(np.sqrt((step_t**2).mean()) / diag)
                    # same-run timing of full-space frames when the rollout stage measured it
                    full_ms = float(fr.attrs.get("full_ms", np.median(gt["frame_ms"][1:])))
                    latent_ms = float(g.attrs["step_ms"])
                    parts = {k: float(g.attrs.get(k, np.nan))
                             for k in ("integrate_ms", "decode_ms", "numpy_step_ms", "compiled_step_ms", "jvp_torch_ms", "jvp_forward_ms")}  # fmt: skip
                    rows.append(
                        dict(
                            scene=scene,
                            method=method,
                            sequence=name,
                            frames=T,
                            diverged_frame=div,
                            mean_error=float(mean_e.mean()),
                            max_error=float(max_e.max()),
                            dirichlet_error=float(bc_e.mean()),
                            kinetic_ratio=float(np.nanmean(ke_p) / max(np.nanmean(ke_t), 1e-300)),
                            end_error=end_error,
                            end_motion=end_motion,
                            end_motion_truth=end_motion_truth,
                            full_ms=full_ms,
                            latent_ms=latent_ms,
                            runtime=str(g.attrs.get("runtime", "")),
                            **parts,
                            speedup=full_ms / latent_ms,
                            dof=int(rest.size),
                            latent_dim=int(g["latents"].shape[-1]),
                            **train_s,
                        )
                    )
                    curves.setdefault(method, {})[name] = dict(
                        mean_error=mean_e, dirichlet_error=bc_e, ke_truth=ke_t, ke_pred=ke_p, dt=dt, frames=T, diverged_frame=div
                    )
    return pd.DataFrame(rows), curves


def plot_curves(scene: str, curves: dict, path):
    """Per test sequence (columns): vertex error, Dirichlet error and kinetic energy over time, one line per method.

    A method's curve ends where it diverged (marked with a cross).  This one
    figure holds the paper's Figs. 8-12 for the scene: stability of the
    supervised baselines, the ablations' errors, BC satisfaction and the
    kinetic energy of the rollout against the ground truth.
    """
    sequences = list(dict.fromkeys(name for per in curves.values() for name in per))
    n = max(len(sequences), 1)
    fig, axes = plt.subplots(3, n, figsize=(4.8 * n, 9), squeeze=False)
    for j, name in enumerate(sequences):
        truth = None  # ground-truth KE: the longest (undiverged) copy among the methods
        for k, (method, per) in enumerate(curves.items()):
            if name not in per:
                continue
            c = per[name]
            colour = f"C{k % 10}"
            t = np.arange(len(c["mean_error"])) * c["dt"]
            axes[0, j].semilogy(t, np.maximum(c["mean_error"], 1e-12), color=colour, label=method)
            axes[1, j].semilogy(t, np.maximum(c["dirichlet_error"], 1e-12), color=colour, label=method)
            axes[2, j].plot(t, c["ke_pred"], color=colour, ls="--", label=method)
            if c["diverged_frame"] >= 0 and len(t):
                axes[0, j].plot(t[-1], max(c["mean_error"][-1], 1e-12), "x", color=colour, ms=9)
            if truth is None or len(c["ke_truth"]) > len(truth[1]):
                truth = (c["dt"], c["ke_truth"])
        if truth is not None:
            axes[2, j].plot(np.arange(len(truth[1])) * truth[0], truth[1], color="k", lw=2.0, alpha=0.5, label="full space")
        axes[0, j].set_title(f"{scene} / {name}")
        axes[0, j].set_ylabel("mean vertex error / bbox diag")
        axes[1, j].set_ylabel("Dirichlet error / bbox diag")
        axes[2, j].set_ylabel("kinetic energy [J]")
        axes[2, j].set_xlabel("time [s]")
        for i in range(3):
            axes[i, j].legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def write_table(df: pd.DataFrame, path):
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g")


def stress_table(scene: str, rollouts) -> pd.DataFrame:
    """Stability map rows (method x stress condition) from the rollouts' ``stability`` groups.

    Columns: scene, method, condition, frames, frames_survived, diverged,
    bc_error (mean Dirichlet error / bbox diagonal at the last surviving frame).
    """
    rows = []
    for path in rollouts:
        with h5py.File(path, "r") as f:
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
    with h5py.File(latents, "r") as f:
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

    ``df``: the per-sequence metrics (:func:`summarise`'s table); ``pts``: the chart's points
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


def summarise(tables: list, csv_path, md_path, fig_path, table1_path=None, stability_path=None, reconstruction=(), stress=(), stress_paths=None,
              table2_path=None, sizes=None, sweep_choices=None, sizes_path=None, glance_path=None):  # fmt: skip
    """Concatenate the scene tables; Tables 1-2, the stability, reconstruction and model-size tables;
    Markdown copy, opening with the glance tables (:func:`glance_grid`, :func:`glance_table`; the latter also
    to ``glance_path``); speed-accuracy chart.  ``sizes`` and ``sweep_choices``: see :func:`sizes_table`; a
    scene's ``sizes[scene]["variants"]`` ({method: latent_dim, decoder_layers, integrator_layers}) names the
    variants that are models of their own size, which get rows of their own in Tables 1-2."""
    df = pd.concat([pd.read_csv(t) for t in tables], ignore_index=True)
    rec = pd.concat([pd.read_csv(t) for t in reconstruction], ignore_index=True) if reconstruction else pd.DataFrame()
    if not rec.empty:  # one row per scene and split: mean of the sequence means, max of the maxima
        rec = rec.groupby(["scene", "split"], sort=False).agg(mean_error=("mean_error", "mean"), max_error=("max_error", "max")).reset_index()
    write_table(df, csv_path)
    layers = {k: (v["decoder_layers"], v["integrator_layers"]) for k, v in (sizes or {}).items()}
    for scene, v in (sizes or {}).items():
        layers.update({(scene, m): (w["decoder_layers"], w["integrator_layers"]) for m, w in v.get("variants", {}).items()})
    sized = sorted({m for v in (sizes or {}).values() for m in v.get("variants", {})})
    t1, t2, st = table1(df, sized), table2(df, layers, sized), stability_table(df)
    sz = sizes_table(sizes, sweep_choices) if sizes else pd.DataFrame()
    if sizes_path is not None:
        write_table(sz, sizes_path)
    if table1_path is not None:
        write_table(t1, table1_path)
    if table2_path is not None:
        write_table(t2, table2_path)
    if stability_path is not None:
        write_table(st, stability_path)
    frames = [pd.read_csv(t) for t in stress]
    st_all = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    pts = speed_accuracy_chart(speed_accuracy_rows(df), fig_path, scene=None, title="speed vs accuracy, every scene (full space at error 0)")
    glance = glance_table(df, pts, st_all)
    if glance_path is not None:
        write_table(glance, glance_path)
    text = ["## At a glance: mean error / bbox diagonal (ms per frame) of the compared methods; * on their Pareto front", "",
            _markdown(glance_grid(glance)), "",
            "## Every method per scene: median ms per frame, speed-up over the full space, errors, kinetic energy ratio, "
            "test sequences and stress conditions survived, Pareto front", "", _markdown(glance), "",
            "## Li et al. Table 1: full space vs latent integrator (ours, then the paper's)", "", _markdown(t1), "",
            "## Li et al. Table 2: single-vertex Jvp (torch.func.jvp, forward mode), our latent step, a Fulton-style reduced step", "",
            _markdown(t2), "",
            "## Stability: frames survived per method (Li et al. Fig. 8-11)", "", _markdown(st), "",
            "## Model size per scene: ours, the paper's, and the sizing sweep (smallest model within the tolerance)", "",
            _markdown(sz), "",
            "## Autoencoder reconstruction error / bbox diagonal (train and test frames)", "", _markdown(rec), "",
            "## Every method and test sequence", "", _markdown(df)]  # fmt: skip
    with atomic_path(md_path) as tmp:
        tmp.write_text("\n".join(text) + "\n")
    if stress_paths is not None:
        csv, png = stress_paths
        write_table(st_all, csv)
        if not st_all.empty:
            st_all = st_all.assign(method=st_all["scene"] + " / " + st_all["method"])
            stability_heatmap(st_all, png, title="stress conditions: frames survived (fraction coloured)")
        else:
            _empty_figure(png, "no stress conditions were run")
    return df


def _empty_figure(path, text: str) -> None:
    fig, ax = plt.subplots(figsize=(4, 2))
    ax.text(0.5, 0.5, text, ha="center", va="center")
    ax.axis("off")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def _markdown(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    if df.empty:
        return "(no rows)"
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |")
    return "\n".join(lines)


def render_scene(scene: str, trajectories, rollouts, frames_png, clip_gif, paraview_dir, clip_frames: int = 60) -> dict:
    """Pictures of one scene's first test sequence: every method beside the ground truth.

    - ``frames_png``: four frames (start, a third, two thirds, end), one column per method;
    - ``clip_gif``: the ground truth, the self-supervised integrator and the method that
      diverged first (if any, the most telling failure) as an animation;
    - ``paraview_dir``: an XDMF series per method with displacement and per-vertex error.

    Returns {"sequence", "clip_methods"}.
    """
    from pathlib import Path

    from latentsim.report.render import render_clip, render_frames, write_xdmf_series

    methods, diverged = {}, {}
    for path in rollouts:
        with h5py.File(path, "r") as f:
            m = str(f.attrs.get("method", Path(path).parent.name))
            seqs = list(require(f, "sequences"))
            if not seqs:
                continue
            methods[m] = str(path)
            diverged[m] = int(f["sequences"][seqs[0]].attrs["diverged_frame"])
    if not methods:
        raise ValueError(f"scene {scene}: no rollout holds a test sequence")
    with h5py.File(rollouts[0], "r") as f:
        sequence = next(iter(require(f, "sequences")))
    with h5py.File(trajectories, "r") as f:
        T = require(f["sequences"], sequence)["positions"].shape[0]
    picks = [0, T // 3, (2 * T) // 3, T - 1]
    render_frames(trajectories, methods, sequence, picks, frames_png, title=f"{scene} / {sequence}: ground truth and every method")
    clip = {m: methods[m] for m in ("self_supervised",) if m in methods}
    failed = sorted((d, m) for m, d in diverged.items() if d >= 0)
    if failed:
        clip[failed[0][1]] = methods[failed[0][1]]
    if not clip:
        first = next(iter(methods))
        clip[first] = methods[first]
    stride = max(1, T // clip_frames)
    render_clip(trajectories, clip, sequence, clip_gif, stride=stride, max_frames=clip_frames, title=f"{scene} / {sequence}")
    out = Path(paraview_dir)
    out.mkdir(parents=True, exist_ok=True)
    for m, p in methods.items():
        write_xdmf_series(p, sequence, out / f"{m}_{sequence}.xdmf", reference=trajectories)
    return {"sequence": sequence, "clip_methods": list(clip)}
