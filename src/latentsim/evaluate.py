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

from .io import atomic_path, require  # noqa: E402


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


def evaluate_scene(scene: str, trajectories, rollout):
    """Metrics table (one row per rolled-out sequence) and per-frame curves."""
    rows, curves = [], {}
    with h5py.File(trajectories, "r") as ft, h5py.File(rollout, "r") as fr:
        rest = require(ft, "rest_positions")[()]
        masses = require(ft, "masses")[()]
        D = require(ft, "dirichlet")[()]
        dt = float(ft.attrs["dt"])
        diag = bbox_diagonal(rest)
        for name, g in require(fr, "sequences").items():
            gt = require(ft["sequences"], name)
            truth = gt["positions"][()]
            pred = g["positions"][()]
            T = len(truth)
            div = int(g.attrs["diverged_frame"])
            ok = slice(0, T if div < 0 else div)
            mean_e, max_e = vertex_errors(pred[ok], truth[ok], diag)
            bc_e = np.linalg.norm(pred[ok][:, D] - gt["dirichlet_positions"][ok], axis=-1).mean(-1) / diag
            ke_t, ke_p = kinetic_energy(truth[ok], masses, dt), kinetic_energy(pred[ok], masses, dt)
            full_ms = float(gt["frame_ms"][1:].mean())
            latent_ms = float(g.attrs["step_ms"])
            rows.append(
                dict(
                    scene=scene,
                    sequence=name,
                    method="latent_" + str(g.attrs.get("method", "self_supervised")),
                    frames=T,
                    diverged_frame=div,
                    mean_error=float(mean_e.mean()),
                    max_error=float(max_e.max()),
                    dirichlet_error=float(bc_e.mean()),
                    kinetic_ratio=float(ke_p.mean() / max(ke_t.mean(), 1e-300)),
                    full_ms=full_ms,
                    latent_ms=latent_ms,
                    speedup=full_ms / latent_ms,
                    dof=int(rest.size),
                    latent_dim=int(g["latents"].shape[-1]),
                )
            )
            curves[name] = dict(mean_error=mean_e, dirichlet_error=bc_e, ke_truth=ke_t, ke_pred=ke_p, dt=dt)
    return pd.DataFrame(rows), curves


def plot_curves(scene: str, curves: dict, path):
    """Error and kinetic energy over time, one column per sequence."""
    n = max(len(curves), 1)
    fig, axes = plt.subplots(2, n, figsize=(4.5 * n, 6), squeeze=False)
    for j, (name, c) in enumerate(curves.items()):
        t = np.arange(len(c["mean_error"])) * c["dt"]
        ax = axes[0, j]
        ax.semilogy(t, np.maximum(c["mean_error"], 1e-12), label="mean vertex error")
        ax.semilogy(t, np.maximum(c["dirichlet_error"], 1e-12), label="Dirichlet error")
        ax.set_title(f"{scene} / {name}")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("error / bbox diagonal")
        ax.legend(fontsize=8)
        ax = axes[1, j]
        ax.plot(t, c["ke_truth"], label="full space")
        ax.plot(t, c["ke_pred"], "--", label="latent rollout")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("kinetic energy [J]")
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)


def write_table(df: pd.DataFrame, path):
    with atomic_path(path) as tmp:
        df.to_csv(tmp, index=False, float_format="%.6g")


def summarise(tables: list, csv_path, md_path, fig_path):
    """Concatenate the scene tables; Markdown copy; speed-accuracy chart."""
    df = pd.concat([pd.read_csv(t) for t in tables], ignore_index=True)
    write_table(df, csv_path)
    with atomic_path(md_path) as tmp:
        tmp.write_text(_markdown(df) + "\n")
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for scene, g in df.groupby("scene"):
        line = ax.scatter(g["latent_ms"], g["mean_error"].clip(lower=1e-12), label=f"{scene}: latent")
        ax.scatter(g["full_ms"], np.full(len(g), 1e-12), marker="s", color=line.get_facecolor()[0], label=f"{scene}: full space (reference)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("ms per frame")
    ax.set_ylabel("mean vertex error / bbox diagonal")
    ax.set_title("speed vs accuracy (full space drawn at error 1e-12)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(fig_path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return df


def _markdown(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        lines.append("| " + " | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |")
    return "\n".join(lines)
