"""Stages of the conditioned integrator (workflow/rules/conditioning.smk; beyond Li et al. 2025,
:mod:`latentsim.latent.conditioning`): a scene's config at each condition (:func:`condition_sim_config`, which
the rule's script gives to the simulate stage), the conditioned
integrator and the per-condition references evaluated at the held-out conditions, and the summary
over seeds (table and figure).

The autoencoder and the integrators train through the scene pipeline's own stages
(:func:`latentsim.stages.autoencoder.train_autoencoder`,
:func:`latentsim.stages.integrator.train_integrator`), given the training conditions' files.
"""

from __future__ import annotations

import logging

import matplotlib.pyplot as plt
from matplotlib.ticker import NullFormatter
import numpy as np
import pandas as pd
import torch

from latentsim.config import with_defaults
from latentsim.io import atomic_path, open_artefact, read_csv
from latentsim.latent.autoencoder import encode_positions
from latentsim.latent.conditioning import AtCondition, Conditioning, frame_factor, scaled_sequence
from latentsim.latent.data import load_sequences
from latentsim.latent.rollout import rollout
from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder, load_extra, load_integrator
from latentsim.latent.stability import stress_test
from latentsim.latent.timing import EagerStepper, time_full_space, time_steppers
from latentsim.report.metrics import bbox_diagonal, rollout_metrics, vertex_errors
from latentsim.report.plots import save_figure
from latentsim.report.tables import markdown, write_table
from latentsim.scene import potential_from_artefact

log = logging.getLogger(__name__)

#: the columns of the frame-rate comparison's rows
FRAME_RATE_COLUMNS = ["seed", "coarse", "fine", "factor", "sequence", "shared_frames", "coarse_error", "fine_error", "rollout_gap", "full_space_gap"]
#: the method names of the evaluation's rows: the conditioned integrator, and the reference trained at the row's condition alone
CONDITIONED, REFERENCE = "conditioned", "reference"


def condition_sim_config(sim: dict, condition: dict) -> dict:
    """The simulation settings of a scene (the ``simulate`` rule's params) at one condition: its time
    step and Young's modulus, and its sequences as the same motions in physical time
    (:func:`~latentsim.latent.conditioning.scaled_sequence`).  A training condition simulates each
    sequence's training frames alone (those of split train, and the first ``train_frames`` of the
    others); a test condition the test sequences (with their first ``train_frames`` as the training
    length the stress conditions scale with)."""
    k = frame_factor(sim["dt"], condition["time_step"])
    seqs = []
    for q in sim["sequences"]:
        q = scaled_sequence(q, k)
        split = q.get("split", "train")
        if condition["split"] == "train":
            if q.get("train_frames"):
                q = {**{key: v for key, v in q.items() if key != "train_frames"}, "frames": q["train_frames"], "split": "train"}
            elif split != "train":
                continue
        elif split != "test":
            continue
        if q["frames"] < 3:
            raise ValueError(f"sequence {q['name']!r} at time step {condition['time_step']:g} s has {q['frames']} frames; a sequence needs at least 3")
        seqs.append(q)
    material = {**sim["material"], "youngs_modulus": float(condition["youngs_modulus"])}
    return {**sim, "dt": float(condition["time_step"]), "material": material, "sequences": seqs}


def _scene_at(path, ae_path) -> dict:
    """What the evaluation needs of one test condition's trajectories file."""
    with open_artefact(path) as f:
        tests = load_sequences(f, "test")
        try:
            train_frames = max(len(s["positions"]) for s in load_sequences(f, "train").values())
        except ValueError:  # no test sequence trains on its first frames: the stress conditions scale with the test's length
            train_frames = max(len(s["positions"]) for s in tests.values())
        return {
            "coords": autoencoder_coordinates(f, ae_path),
            "tests": tests,
            "train_frames": train_frames,
            "potential": potential_from_artefact(f),
            "rest": f["rest_positions"][()],
            "masses": f["masses"][()],
            "dirichlet": f["dirichlet"][()],
            "time_step": float(f.attrs["dt"]),
            "youngs_modulus": float(f.attrs["youngs_modulus"]),
            "full": time_full_space(f, next(iter(tests)), 10),
        }


def evaluate_conditioned(tests: dict, ae_path, models: dict, rollout_settings: dict, seed: int, out_csv, out_frame_rate) -> None:
    """Roll the conditioned integrator and each condition's reference out on the test sequences of
    every held-out condition, against the full space; the stress conditions at each; one step timed.

    Parameters
    ----------
    tests : {condition name: its trajectories file}.
    models : {``conditioned``: its integrator file, and one entry per test condition's name: the
        reference trained there}.
    rollout_settings : the scene's ``rollout`` block (max_extent, timing_repeats, stability).
    out_csv : one row per condition, sequence and method: errors (``rollout_metrics``), the stress
        conditions survived, the step and full-space frame in ms, measured in this process.
    out_frame_rate : one row per pair of test conditions of one modulus whose time steps differ by an
        integer factor m, and test sequence: the conditioned integrator's error at the shared times
        (every frame of the coarser, every m-th of the finer), and the distance between the two
        rollouts at those times beside that between the two full-space runs.
    """
    cfg = with_defaults("rollout", rollout_settings, "evaluate_conditioned")
    ae = load_autoencoder(ae_path)
    conditioned = load_integrator(models[CONDITIONED])
    box = Conditioning.from_dict(load_extra(models[CONDITIONED])["conditioning"])
    rows, kept = [], {}
    for name, path in tests.items():
        sc = _scene_at(path, ae_path)
        h, E = sc["time_step"], sc["youngs_modulus"]
        if not box.contains(h, E):
            raise ValueError(f"{path}: its condition (time step {h:g} s, modulus {E:g} Pa) lies outside the box the integrator trained over {box.to_dict()}")
        candidates = {CONDITIONED: AtCondition(conditioned, box.normalise(h, E)), REFERENCE: load_integrator(models[name])}
        for method, integ in candidates.items():
            for seq_name, s in sc["tests"].items():
                row, positions = _evaluate_one(integ, ae, sc, seq_name, s, cfg)
                rows.append({"seed": seed, "condition": name, "time_step": h, "youngs_modulus": E, "method": method, "sequence": seq_name, **row})
                if method == CONDITIONED:
                    kept[(name, seq_name)] = (h, E, positions, s["positions"], bbox_diagonal(sc["rest"]))
                log.info("%s at %s, %s: mean error %.4g, diverged at %d, stress %d of %d survived, %.3f ms a step",
                         method, name, seq_name, row["mean_error"], row["diverged_frame"], row["stress_survived"], row["stress_total"], row["step_ms"])  # fmt: skip
    write_table(pd.DataFrame(rows), out_csv)
    write_table(pd.DataFrame(frame_rate_rows(kept, seed), columns=FRAME_RATE_COLUMNS), out_frame_rate)


def _evaluate_one(integ, ae, sc: dict, seq_name: str, s: dict, cfg: dict) -> tuple[dict, np.ndarray]:
    """One integrator on one test sequence: the metrics, the stress conditions, the step's time."""
    coords = sc["coords"]
    x, xD = torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])
    z01 = encode_positions(ae, coords, x[:2], xD[:2])
    res = rollout(integ, ae, coords, z01[0], z01[1], torch.as_tensor(s["bc"]), xD, max_extent=cfg["max_extent"], rest_positions=torch.as_tensor(sc["rest"]))
    diag = bbox_diagonal(sc["rest"])
    pred = res["positions"].numpy()
    metrics, _ = rollout_metrics(pred, s["positions"], s["dirichlet_positions"], sc["dirichlet"], sc["masses"], sc["time_step"], diag, res["diverged_frame"])
    survived, total = 0, 0
    if cfg["stability"]["enabled"]:
        for c, r in stress_test(integ, ae, coords, s, sc["rest"], sc["dirichlet"], sc["time_step"], sc["train_frames"], cfg["stability"], float(cfg["max_extent"])):
            total += 1
            survived += int(r["survived"] == r["frames"])
    timing = time_steppers({"eager": EagerStepper(ae, integ, coords)}, z01[1], z01[0], s["bc"][-1], s["dirichlet_positions"][-1], int(cfg["timing_repeats"]))
    row = {
        "frames": metrics["frames"], "diverged_frame": metrics["diverged_frame"], "mean_error": metrics["mean_error"],
        "max_error": metrics["max_error"], "end_error": metrics["end_error"], "stress_survived": survived, "stress_total": total,
        "step_ms": timing["step_ms"], "full_ms": sc["full"]["full_ms"],
    }  # fmt: skip
    return row, pred


def frame_rate_rows(kept: dict, seed: int) -> list[dict]:
    """The frame-rate comparison of :func:`evaluate_conditioned` (``out_frame_rate``) from the
    conditioned rollouts ``kept[(condition, sequence)] = (h, E, rollout, truth, diag)``."""
    rows = []
    for (c1, seq), (h1, E1, pred1, truth1, diag) in kept.items():
        for (c2, seq2), (h2, E2, pred2, truth2, _) in kept.items():
            m = h1 / h2
            if seq2 != seq or not np.isclose(E1, E2, rtol=1e-9) or not (m > 1.5 and abs(m - round(m)) < 1e-6):
                continue
            m = int(round(m))
            n = min(len(pred1), (len(pred2) - 1) // m + 1)
            fine, fine_truth = pred2[: (n - 1) * m + 1 : m], truth2[: (n - 1) * m + 1 : m]
            coarse, coarse_truth = pred1[:n], truth1[:n]
            gap = vertex_errors(coarse, fine, diag)[0]
            gap_truth = vertex_errors(coarse_truth, fine_truth, diag)[0]
            rows.append({
                "seed": seed, "coarse": c1, "fine": c2, "factor": m, "sequence": seq, "shared_frames": n,
                "coarse_error": float(vertex_errors(coarse, coarse_truth, diag)[0].mean()),
                "fine_error": float(vertex_errors(fine, fine_truth, diag)[0].mean()),
                "rollout_gap": float(np.mean(gap)), "full_space_gap": float(np.mean(gap_truth)),
            })  # fmt: skip
    return rows


def summarise_conditioned(scene: str, metrics: list, frame_rates: list, tolerance: float, train_conditions: dict, out_csv, out_md, out_png) -> None:
    """The conditioned integrator against the references over the seeds: a table (csv and Markdown,
    median and range over seeds, and the ratio of the medians) and a figure of the mean error
    against the time step and against the modulus.

    tolerance : the scene's accuracy tolerance (``sweep.tolerance``, mean vertex error / bbox
        diagonal), against which the frame-rate check's errors are read.
    train_conditions : {name: {time_step, youngs_modulus}} of the training sequences (marked in the figure).
    """
    df = pd.concat([read_csv(p) for p in metrics], ignore_index=True)
    fr = pd.concat([read_csv(p) for p in frame_rates], ignore_index=True) if frame_rates else pd.DataFrame(columns=FRAME_RATE_COLUMNS)
    table = conditioned_table(df)
    write_table(table, out_csv)
    with atomic_path(out_md) as tmp:
        tmp.write_text(_summary_markdown(scene, table, fr, tolerance, df["seed"].nunique()))
    conditioned_figure(df, train_conditions, out_png, scene)


def conditioned_table(df: pd.DataFrame) -> pd.DataFrame:
    """One row per test condition and sequence: each method's mean error (median, least and largest
    over seeds), its diverged seeds and the stress conditions survived in every seed, the ratio of
    the conditioned median to the reference's, the ratio's range over seeds, and the step's and a
    full-space frame's median ms."""
    out = []
    for (cond, seq), g in df.groupby(["condition", "sequence"], sort=False):
        row = {"condition": cond, "time_step": g["time_step"].iloc[0], "youngs_modulus": g["youngs_modulus"].iloc[0], "sequence": seq, "seeds": g["seed"].nunique()}
        for method in (CONDITIONED, REFERENCE):
            m = g[g["method"] == method]
            e = m["mean_error"].to_numpy(float)
            row[f"{method}_error"], row[f"{method}_error_min"], row[f"{method}_error_max"] = float(np.median(e)), float(e.min()), float(e.max())
            row[f"{method}_diverged_seeds"] = int((m["diverged_frame"] >= 0).sum())
            row[f"{method}_stress"] = f"{int(m['stress_survived'].min())}/{int(m['stress_total'].max())}"
            row[f"{method}_step_ms"] = float(m["step_ms"].median())
        per_seed = g.pivot_table(index="seed", columns="method", values="mean_error")
        ratio = (per_seed[CONDITIONED] / per_seed[REFERENCE]).to_numpy(float)
        ratio = ratio[np.isfinite(ratio) & (ratio > 0)]  # the seeds where both stayed stable
        both = np.isfinite(row[f"{CONDITIONED}_error"]) and np.isfinite(row[f"{REFERENCE}_error"])
        row["ratio"] = row[f"{CONDITIONED}_error"] / row[f"{REFERENCE}_error"] if both else float("nan")
        row["ratio_min"], row["ratio_max"] = (float(ratio.min()), float(ratio.max())) if len(ratio) else (float("nan"), float("nan"))
        row["full_ms"] = float(g["full_ms"].median())
        row["speedup"] = row["full_ms"] / row[f"{CONDITIONED}_step_ms"]
        out.append(row)
    return pd.DataFrame(out)


def _summary_markdown(scene: str, table: pd.DataFrame, fr: pd.DataFrame, tolerance: float, seeds: int) -> str:
    t = pd.DataFrame({
        "condition": table["condition"], "dt [s]": table["time_step"].map(lambda v: f"1/{1 / v:.3g}"),
        "E [Pa]": table["youngs_modulus"].map(lambda v: f"{v:.3g}"), "sequence": table["sequence"],
        "conditioned error": [f"{r.conditioned_error:.3g} ({r.conditioned_error_min:.3g}-{r.conditioned_error_max:.3g})" for r in table.itertuples()],
        "reference error": [f"{r.reference_error:.3g} ({r.reference_error_min:.3g}-{r.reference_error_max:.3g})" for r in table.itertuples()],
        "ratio": [_ratio_text(r) for r in table.itertuples()],
        "diverged (cond./ref.)": [f"{r.conditioned_diverged_seeds}/{r.reference_diverged_seeds}" for r in table.itertuples()],
        "stress survived (cond./ref.)": [f"{r.conditioned_stress} / {r.reference_stress}" for r in table.itertuples()],
        "step ms": table["conditioned_step_ms"].map(lambda v: f"{v:.3g}"), "full ms": table["full_ms"].map(lambda v: f"{v:.3g}"),
        "speed-up": table["speedup"].map(lambda v: f"{v:.0f}x"),
    })  # fmt: skip
    worst = float(table["ratio"].max()) if table["ratio"].notna().any() else float("nan")
    lines = [
        f"# {scene}: one integrator for a range of time steps and moduli",
        "",
        f"Mean vertex error / bbox diagonal over each held-out test sequence, median over {seeds} seed(s) (least-largest); the "
        "reference is an unconditioned integrator trained at that condition alone, on the same autoencoder and training states. "
        "ratio: conditioned median / reference median (the per-seed ratios' range). A diverged rollout's error is infinite. Stress: conditions survived in every seed, of "
        "those run. Step: one eager PyTorch step; full: one full-space Newton frame, both timed in the evaluation's process.",
        "",
        markdown(t),
        "",
        f"Largest ratio over the held-out conditions where both medians are finite: {worst:.2f}.",
    ]
    if not fr.empty:
        g = fr.groupby(["coarse", "fine", "sequence"], sort=False).agg(
            factor=("factor", "first"), coarse_error=("coarse_error", "median"), fine_error=("fine_error", "median"),
            rollout_gap=("rollout_gap", "median"), full_space_gap=("full_space_gap", "median"),
            worst=("coarse_error", "max"), worst_fine=("fine_error", "max"),
        ).reset_index()  # fmt: skip
        g["within tolerance"] = [
            "yes" if max(r.worst, r.worst_fine) <= tolerance else "no" for r in g.itertuples()
        ]
        lines += [
            "",
            "## Frame-rate independence",
            "",
            f"The same motion at two time steps, compared at the shared times (every frame of the coarser, every factor-th of the "
            f"finer), medians over seeds: each rollout's error against its own full space, and the distance between the two "
            f"rollouts beside that between the two full-space runs (implicit Euler damps more at the larger step). Within "
            f"tolerance: both errors at most {tolerance:g} in every seed.",
            "",
            markdown(g.drop(columns=["worst", "worst_fine"])),
        ]
    return "\n".join(lines) + "\n"


def _ratio_text(r) -> str:
    """The ratio of the medians with the per-seed range over the seeds where both stayed stable; a
    median that is infinite (the method diverged in most seeds) named instead."""
    spread = f" ({r.ratio_min:.2f}-{r.ratio_max:.2f} where both stable)" if np.isfinite(r.ratio_min) else ""
    if np.isfinite(r.ratio):
        return f"{r.ratio:.2f}{spread}"
    who = [m for m, e in (("conditioned", r.conditioned_error), ("reference", r.reference_error)) if not np.isfinite(e)]
    return f"- ({' and '.join(who)} median diverged){spread}"


def conditioned_figure(df: pd.DataFrame, train_conditions: dict, path, scene: str) -> None:
    """Mean error against the time step and against the modulus, the conditioned integrator beside
    the references (median over the stable seeds, bars from the least to the largest; the seeds that
    diverged named at the top), the training conditions' values dashed."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    g = df[df["diverged_frame"] < 0].groupby(["condition", "method"]).agg(
        h=("time_step", "first"), E=("youngs_modulus", "first"), e=("mean_error", "median"), lo=("mean_error", "min"), hi=("mean_error", "max")
    ).reset_index()  # fmt: skip
    styles = {CONDITIONED: dict(marker="o", color="tab:blue", label="conditioned (one network)"),
              REFERENCE: dict(marker="s", color="tab:orange", label="reference (trained at that condition)", mfc="none")}  # fmt: skip
    diverged = df.assign(d=df["diverged_frame"] >= 0).groupby(["condition", "method"]).agg(
        h=("time_step", "first"), E=("youngs_modulus", "first"), k=("d", "sum"), n=("seed", "nunique")
    ).reset_index()  # fmt: skip
    diverged = diverged[diverged["k"] > 0]
    for ax, key, xlabel, train_key in ((axes[0], "h", "time step [s]", "time_step"), (axes[1], "E", "Young's modulus [Pa]", "youngs_modulus")):
        for method, st in styles.items():
            m = g[g["method"] == method]
            ax.errorbar(m[key], m["e"], yerr=[m["e"] - m["lo"], m["hi"] - m["e"]], linestyle="none", capsize=3, **st)
        for r in diverged.itertuples():  # the seeds left out above: a cross on the top edge, with how many diverged
            y = 0.97 if r.method == REFERENCE else 0.91
            ax.plot([getattr(r, key)], [y], marker="x", color=styles[r.method]["color"], transform=ax.get_xaxis_transform(), clip_on=False)
            ax.annotate(f"{r.k}/{r.n} diverged", (getattr(r, key), y), xycoords=("data", "axes fraction"), xytext=(5, 0),
                        textcoords="offset points", ha="left", va="center", fontsize=7, color=styles[r.method]["color"])  # fmt: skip
        for v in sorted({float(c[train_key]) for c in train_conditions.values()}):
            ax.axvline(v, color="0.6", linestyle="--", linewidth=0.8)
        ax.set_xscale("log")
        if (g["e"] > 0).any():  # every rollout diverged: nothing to draw on a log scale
            ax.set_yscale("log")
        ticks = sorted({float(f"{v:.4g}") for v in [*g[key], *(float(c[train_key]) for c in train_conditions.values())]})
        ax.set_xticks(ticks, [f"1/{1 / v:.3g}" if key == "h" else f"{v:.2g}" for v in ticks], rotation=45)
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean vertex error / bbox diagonal")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{scene}: held-out conditions (dashed: the training sequences' values)")
    save_figure(fig, path)
