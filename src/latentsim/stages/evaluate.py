"""Evaluation stages: every method's rollouts against the full-space ground truth, and the summary.

- :func:`evaluate_scene` / :func:`write_scene_evaluation` (rule ``evaluate``): per scene, one row
  per method and test sequence with the metrics of :mod:`latentsim.report.metrics` (errors and
  Dirichlet error relative to the rest bounding-box diagonal, kinetic energy ratio, the steady
  state's error and motion, first diverged frame; a rollout that diverged, even at frame 0, gets a
  row with infinite errors) and the timings: ``full_ms`` (the full-space
  Newton frame, timed once per scene by :func:`write_full_space_time`, rule ``time_full_space``, so that every
  method's speed-up divides by the same time) against ``latent_ms`` (one latent step: integration + decoding,
  plus the contact projection where it is on), ``speedup``; beside it the reconstruction and stress tables, the scene's
  speed-accuracy chart and its curves over time;
- :func:`summarise` (rule ``summary``): the scenes' tables together, Li et al. Tables 1-2, the
  stability, reconstruction and model-size tables (:mod:`latentsim.report.tables`), a Markdown copy
  opening with the glance tables, the speed-accuracy chart and the stress map;
- :func:`render_scene` (rule ``render``): frames, a clip and ParaView series of a scene's first test
  sequence (:mod:`latentsim.report.render`, :mod:`latentsim.report.paraview`).
"""

from __future__ import annotations

import functools
import json

from pathlib import Path

import numpy as np
import pandas as pd

from latentsim.io import atomic_path, open_artefact, read_csv, require
from latentsim.latent.timing import time_full_space
from latentsim.report.metrics import bbox_diagonal, penetration, rollout_metrics
from latentsim.report.paraview import write_xdmf_series
from latentsim.report.plots import empty_figure, rollout_curves, speed_accuracy_chart, stability_heatmap
from latentsim.report.render import render_clip, render_frames
from latentsim.report.tables import (
    claims,
    divergence_table,
    glance_grid,
    glance_table,
    markdown,
    reconstruction_table,
    sizes_table,
    speed_accuracy_points,
    stability_table,
    stress_over_seeds,
    stress_table,
    table1,
    table2,
    write_table,
)
from latentsim.scene import CONTACT_ATTR, collider_meshes, contact_from_artefact, posed_collider_entries

__all__ = ["evaluate_scene", "render_scene", "summarise", "write_scene_evaluation"]

# per-step timings a rollout may record beside ``step_ms`` (NaN where it did not)
_STEP_PARTS = ("integrate_ms", "decode_ms", "numpy_step_ms", "compiled_step_ms", "floor_ms", "jvp_torch_ms", "jvp_forward_ms", "projection_ms")
_TRAIN_SECONDS = ("autoencoder_train_seconds", "integrator_train_seconds")


def write_full_space_time(trajectories, out_csv, frames: int = 20) -> pd.DataFrame:
    """Rule ``time_full_space``: the scene's full-space Newton frame timed once, in this one process
    (:func:`latentsim.latent.timing.time_full_space` on the first test sequence, ``frames`` frames spread over it),
    the time every method's speed-up divides by.  One row: sequence, full_ms, full_iterations, full_frames_timed."""
    with open_artefact(trajectories) as f:
        tests = [name for name, g in require(f, "sequences").items() if str(g.attrs.get("split", "test")) == "test"]
        if not tests:
            raise ValueError(f"{trajectories}: no test sequence to time the full space on")
        row = dict(sequence=tests[0], **time_full_space(f, tests[0], int(frames)))
    table = pd.DataFrame([row])
    write_table(table, out_csv)
    return table


def read_full_space_time(path) -> float:
    """The scene's one full-space ms per frame from :func:`write_full_space_time`'s table (the file named if it is not one)."""
    table = read_csv(path)
    if list(table.columns[:2]) != ["sequence", "full_ms"] or len(table) != 1 or not np.isfinite(table["full_ms"].iloc[0]):
        raise ValueError(f"{path}: not a full-space timing (one row: sequence, full_ms, ...); delete it and rerun")
    return float(table["full_ms"].iloc[0])


def evaluate_scene(scene: str, trajectories, rollouts, full_ms: float | None = None):
    """Metrics of every method's rollouts against the full simulation.

    Parameters
    ----------
    scene : scene name (a column of the table).
    trajectories : the simulator's ``trajectories.h5`` (ground truth).
    rollouts : one path or a list of rollout files (trajectory layout, attrs
        ``method`` and ``seed``, -1 for a method no seed changes); each holds some of the ground
        truth's sequences; a method may have one file per seed.
    full_ms : the scene's one full-space ms per frame (:func:`write_full_space_time`), every row's; None: the
        rollout job's own timing where it made one, else the simulator's median ms per frame.

    Returns
    -------
    table : one row per (method, seed, sequence): the metrics of
        :func:`latentsim.report.metrics.rollout_metrics` (over the whole sequence: infinite errors for a
        rollout that diverged, at any frame),
        full_ms (``full_ms``, or as there),
        latent_ms (one latent step) and its parts, runtime, speedup, dof, latent_dim and the
        training seconds.
    curves : {method: {sequence: per-frame arrays}} for :func:`latentsim.report.plots.rollout_curves`
        (of each method's first rollout file, i.e. its first seed).
    """
    if isinstance(rollouts, (str, bytes)) or hasattr(rollouts, "__fspath__"):
        rollouts = [rollouts]
    rows, curves = [], {}
    with open_artefact(trajectories) as ft:
        rest = require(ft, "rest_positions")[()]
        masses = require(ft, "masses")[()]
        D = require(ft, "dirichlet")[()]
        dt = float(ft.attrs["dt"])
        diag = bbox_diagonal(rest)
        contact = contact_from_artefact(ft)
        for path in rollouts:
            with open_artefact(path) as fr:
                method = str(fr.attrs.get("method", "self_supervised"))
                seed = int(fr.attrs.get("seed", -1))
                train_s = {k: float(fr.attrs.get(k, np.nan)) for k in _TRAIN_SECONDS}
                for name, g in require(fr, "sequences").items():
                    gt = require(ft["sequences"], name)
                    truth = gt["positions"][()]
                    pred = g["positions"][()]
                    if pred.shape != truth.shape:
                        raise ValueError(f"{path}: sequence {name!r} has positions {pred.shape}, ground truth {truth.shape}")
                    try:
                        metrics, curve = rollout_metrics(pred, truth, gt["dirichlet_positions"][()], D, masses, dt, diag,
                                                         int(g.attrs["diverged_frame"]))  # fmt: skip
                    except ValueError as e:
                        raise ValueError(f"{path}: sequence {name!r}: {e}") from e
                    if contact is not None:
                        metrics.update(penetration(contact, pred, diag, int(g.attrs["diverged_frame"]), gt["dirichlet_positions"][()]))
                    curves.setdefault(method, {}).setdefault(name, curve)  # the curves of the method's first seed
                    full = full_ms if full_ms is not None else float(fr.attrs.get("full_ms", np.median(gt["frame_ms"][1:])))
                    latent_ms = float(g.attrs["step_ms"])
                    parts = {k: float(g.attrs.get(k, np.nan)) for k in _STEP_PARTS}
                    rows.append(dict(scene=scene, method=method, seed=seed, sequence=name, **metrics, full_ms=full, latent_ms=latent_ms,
                                     runtime=str(g.attrs.get("runtime", "")), **parts, speedup=full / latent_ms,
                                     dof=int(rest.size), latent_dim=int(g["latents"].shape[-1]), **train_s))  # fmt: skip
    return pd.DataFrame(rows), curves


def _posed_at(entries, rest_dirichlet, dirichlet_positions, frame: int) -> list[dict]:
    """The collider entries where a sequence's program (its ``dirichlet_positions`` (T, m, 3)) carries them at ``frame``."""
    return posed_collider_entries(entries, rest_dirichlet, dirichlet_positions[frame])


def write_scene_evaluation(scene: str, trajectories, rollouts, latents, *, metrics, reconstruction, stress, chart, figure,
                           full_time=None) -> pd.DataFrame:  # fmt: skip
    """Rule ``evaluate``: :func:`evaluate_scene`'s table to ``metrics``, the autoencoder's reconstruction
    and the stress conditions' tables, the scene's speed-accuracy ``chart`` and its curves over time
    (``figure``); ``full_time``: the scene's full-space timing table (:func:`write_full_space_time`).
    Returns the metrics table."""
    rollouts = list(rollouts)
    table, curves = evaluate_scene(scene, trajectories, rollouts, None if full_time is None else read_full_space_time(full_time))
    write_table(table, metrics)
    write_table(reconstruction_table(scene, latents), reconstruction)
    write_table(stress_table(scene, rollouts), stress)
    speed_accuracy_chart(speed_accuracy_points(table), chart, scene=scene)
    rollout_curves(scene, curves, figure)
    return table


def _reconstruction_summary(paths) -> pd.DataFrame:
    """The scenes' reconstruction tables as one row per scene and split: mean of the sequence means, max of the maxima
    (and of the depths inside the colliders, where a scene has them)."""
    rec = pd.concat([read_csv(t) for t in paths], ignore_index=True) if paths else pd.DataFrame()
    if not rec.empty:
        depth = {"max_penetration": ("max_penetration", "max")} if "max_penetration" in rec else {}
        rec = rec.groupby(["scene", "split"], sort=False).agg(mean_error=("mean_error", "mean"), max_error=("max_error", "max"), **depth).reset_index()
    return rec


def _sized_layers(sizes: dict | None):
    """From :func:`summarise`'s ``sizes``: the layer strings of :func:`latentsim.report.tables.table2`
    ({scene: ...} and {(scene, variant): ...}) and the variants that are models of their own size."""
    layers = {k: (v["decoder_layers"], v["integrator_layers"]) for k, v in (sizes or {}).items()}
    for scene, v in (sizes or {}).items():
        layers.update({(scene, m): (w["decoder_layers"], w["integrator_layers"]) for m, w in v.get("variants", {}).items()})
    sized = sorted({m for v in (sizes or {}).values() for m in v.get("variants", {})})
    return layers, sized


# how the tables score a rollout that diverged (:mod:`latentsim.report.metrics`), under the summary's first heading
_DIVERGENCE_NOTE = ("A rollout that diverged (non-finite, or beyond `rollout.max_extent` times the rest diagonal) fails every frame "
                    "from its first diverged frame on: its errors are infinite (`inf`), the grid reads `diverged k/N` (k of N test "
                    "sequences survived) or, over several seeds, `diverged in j/n seeds`, `diverged_frame` gives the frames it "
                    "survived, and it is never on a Pareto front (nor is a method that diverged in any seed).")  # fmt: skip


_SEEDS_NOTE = ("Every learned method runs once per seed (config `seeds`). Each number is the median over the seeds, with the "
               "least and largest beside it ([least-largest], `_min`, `_max`); divergence counts read k/n, k of the n seeds. "
               "Methods no seed changes (the linear baselines, the full-space Newton) ran once.")  # fmt: skip


def _summary_markdown(glance, t1, t2, st, sz, rec, df, dv=None, said="") -> str:
    """The summary's Markdown: the claims and glance tables first, then the divergence over seeds, Tables 1-2,
    stability, sizes, reconstruction, every row."""
    text = ["## What the tables say, with the seeds' spread (generated from the tables below)", "", said.strip() or "(no method ran with several seeds)", "",
            "## At a glance: mean error / bbox diagonal (ms per frame) of the compared methods; * on their Pareto front", "",
            _SEEDS_NOTE, "", _DIVERGENCE_NOTE, "",
            markdown(glance_grid(glance)), "",
            "## Divergence over seeds (Li et al. Fig. 8): seeds that diverged, frames each seed survived (seed:frames)", "",
            markdown(dv if dv is not None else pd.DataFrame()), "",
            "## Every method per scene: median ms per frame, speed-up over the full space, errors, kinetic energy ratio, "
            "test sequences and stress conditions survived, Pareto front", "", markdown(glance), "",
            "## Li et al. Table 1: full space vs latent integrator (ours, then the paper's)", "",
            "`full_ms`: one full-space Newton frame of the scene, timed once in one process (every method's speed-up divides "
            "by it); `total_ms`: one latent step, `integrate_ms` + `decode_ms` + `projection_ms` (the contact projection, "
            "where the scene has it on; empty elsewhere), one thread.", "", markdown(t1), "",
            "## Li et al. Table 2: single-vertex Jvp (torch.func.jvp, forward mode), our latent step, a Fulton-style reduced step", "",
            markdown(t2), "",
            "## Stability: frames survived per method, seed and test sequence (Li et al. Fig. 8-11)", "", markdown(st), "",
            "## Model size per scene: ours, the paper's, and the sizing sweep (smallest model within the tolerance)", "",
            markdown(sz), "",
            "## Autoencoder reconstruction error / bbox diagonal (train and test frames)", "",
            *(["With colliders, `max_penetration` is how deep the reconstruction of the ground truth (which never enters) goes into them "
               "/ bbox diagonal: a floor under every method that decodes through the autoencoder.", ""] if "max_penetration" in rec else []),
            markdown(rec), "",
            "## Every method and test sequence", "", markdown(df)]  # fmt: skip
    return "\n".join(text) + "\n"


def summarise(tables: list, csv_path, md_path, fig_path, table1_path=None, stability_path=None, reconstruction=(), stress=(), stress_paths=None,
              table2_path=None, sizes=None, sweep_choices=None, sizes_path=None, glance_path=None, divergence_path=None,
              claims_path=None):  # fmt: skip
    """Concatenate the scene tables; Tables 1-2, the stability, reconstruction and model-size tables;
    Markdown copy, opening with the glance tables (:func:`~latentsim.report.tables.glance_grid`,
    :func:`~latentsim.report.tables.glance_table`; the latter also to ``glance_path``); speed-accuracy chart.
    ``sizes`` and ``sweep_choices``: see :func:`~latentsim.report.tables.sizes_table`; a scene's
    ``sizes[scene]["variants"]`` ({method: latent_dim, decoder_layers, integrator_layers}) names the
    variants that are models of their own size, which get rows of their own in Tables 1-2.  With several
    seeds every table states the spread over them; ``divergence_path`` gets
    :func:`~latentsim.report.tables.divergence_table` and ``claims_path`` the sentences of
    :func:`~latentsim.report.tables.claims` (also the summary's first section)."""
    df = pd.concat([read_csv(t) for t in tables], ignore_index=True)
    rec = _reconstruction_summary(reconstruction)
    write_table(df, csv_path)
    layers, sized = _sized_layers(sizes)
    t1, t2, st = table1(df, sized), table2(df, layers, sized), stability_table(df)
    sz = sizes_table(sizes, sweep_choices) if sizes else pd.DataFrame()
    for table, path in ((sz, sizes_path), (t1, table1_path), (t2, table2_path), (st, stability_path)):
        if path is not None:
            write_table(table, path)
    frames = [read_csv(t) for t in stress]
    st_all = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    speed_accuracy_chart(speed_accuracy_points(df), fig_path, scene=None, title="speed vs accuracy, every scene (full space at error 0)")
    glance = glance_table(df, st_all)
    dv = divergence_table(df, st_all)
    said = claims(glance, dv)
    if glance_path is not None:
        write_table(glance, glance_path)
    if divergence_path is not None:
        write_table(dv, divergence_path)
    if claims_path is not None:
        with atomic_path(claims_path) as tmp:
            tmp.write_text(said)
    with atomic_path(md_path) as tmp:
        tmp.write_text(_summary_markdown(glance, t1, t2, st, sz, rec, df, dv, said))
    if stress_paths is not None:
        csv, png = stress_paths
        write_table(st_all, csv)
        if not st_all.empty:
            agg = stress_over_seeds(st_all)
            agg = agg.assign(method=agg["scene"] + " / " + agg["method"])
            stability_heatmap(agg, png, title="stress conditions: seeds that survived (fraction coloured)")
        else:
            empty_figure(png, "no stress conditions were run")
    return df


def render_scene(scene: str, trajectories, rollouts, frames_png, clip_gif, paraview_dir, clip_frames: int = 60) -> dict:
    """Pictures of one scene's first test sequence: every method beside the ground truth.

    - ``frames_png``: four frames (start, a third (with colliders: the ground truth's nearest approach
      to one), two thirds, end), one column per method, the colliders drawn;
    - ``clip_gif``: the ground truth, the self-supervised integrator and the method that
      diverged first (if any, the most telling failure) as an animation;
    - ``paraview_dir``: an XDMF series per method with displacement and per-vertex error.

    Returns {"sequence", "clip_methods"}.
    """
    methods, diverged = {}, {}
    for path in rollouts:
        with open_artefact(path) as f:
            m = str(f.attrs.get("method", Path(path).parent.name))
            seqs = list(require(f, "sequences"))
            if not seqs:
                continue
            methods[m] = str(path)
            diverged[m] = int(f["sequences"][seqs[0]].attrs["diverged_frame"])
    if not methods:
        raise ValueError(f"scene {scene}: no rollout holds a test sequence")
    with open_artefact(rollouts[0]) as f:
        sequence = next(iter(require(f, "sequences")))
    with open_artefact(trajectories) as f:
        g = require(f["sequences"], sequence)
        T = g["positions"].shape[0]
        colliders = json.loads(str(f.attrs[CONTACT_ATTR]))["colliders"] if CONTACT_ATTR in f.attrs else []
        meshes = collider_meshes(f)  # a mesh collider is drawn from the surface the file holds
        colliders = [dict(q, vertices=meshes[i][0], triangles=meshes[i][1]) if q["type"] == "mesh" else q for i, q in enumerate(colliders)]
        if any(q.get("attached") for q in colliders):  # drawn where the sequence's program carries them at each frame
            colliders = functools.partial(_posed_at, colliders, f["rest_positions"][()][f["dirichlet"][()]], g["dirichlet_positions"][()])
        # with colliders, the second picture is the ground truth's nearest approach to one
        second = int(np.argmin(g["min_contact_distance"][()])) if colliders and "min_contact_distance" in g else T // 3
    picks = sorted({0, second, (2 * T) // 3, T - 1})
    render_frames(trajectories, methods, sequence, picks, frames_png, title=f"{scene} / {sequence}: ground truth and every method", colliders=colliders)
    clip = {m: methods[m] for m in ("self_supervised",) if m in methods}
    failed = sorted((d, m) for m, d in diverged.items() if d >= 0)
    if failed:
        clip[failed[0][1]] = methods[failed[0][1]]
    if not clip:
        first = next(iter(methods))
        clip[first] = methods[first]
    stride = max(1, T // clip_frames)
    render_clip(trajectories, clip, sequence, clip_gif, stride=stride, max_frames=clip_frames, title=f"{scene} / {sequence}", colliders=colliders)
    out = Path(paraview_dir)
    out.mkdir(parents=True, exist_ok=True)
    for m, p in methods.items():
        write_xdmf_series(p, sequence, out / f"{m}_{sequence}.xdmf", reference=trajectories)
    return {"sequence": sequence, "clip_methods": list(clip)}
