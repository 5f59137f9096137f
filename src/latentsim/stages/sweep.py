"""Model no more than a scene needs: a sizing sweep over latent dimension and network size.

Each sweep point trains the scene's autoencoder and self-supervised latent
integrator at one latent dimension and one pair of layer widths (everything
else as the scene's config says), rolls the integrator out on the test
sequences and records the error against the full simulation, the frames
survived and the time of one step with the fastest deployable runtime (NumPy, or the
compiled one where numba imports).  With
``stress`` on, it also runs the scene's stress conditions (those of the
rollout stage's stability map, :func:`latentsim.latent.stability.stress_test`): a test
sequence alone cannot tell a model that holds from one that fails at twice the
boundary speed (the armadillo's 64-wide latent-12 point did).  The summary
picks the smallest model (fewest parameters) whose mean vertex error stays
within the scene's tolerance on every test sequence without diverging, and
that survives every stress condition, in every seed it was trained with (or in
the config's ``sweep.pass_fraction`` of them): one lucky training run does not
choose a model.  A point's seeds run one after another, and once the seeds measured
already decide that the point cannot pass, the rest are not trained
(:func:`prune_reason`; ``sweep.prune``): they are written as ``pruned`` rows, and the
choice is the same as with every seed trained.
"""

from __future__ import annotations

import logging
import time

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import torch

from latentsim import runtime
from latentsim.config import with_defaults
from latentsim.io import open_artefact, read_csv
from latentsim.labels import point_label
from latentsim.latent.autoencoder import encode_positions, fit_autoencoder
from latentsim.latent.coordinates import coordinates_for
from latentsim.latent.data import load_sequences
from latentsim.latent.integrator import boundary_inputs
from latentsim.latent.rollout import rollout as latent_rollout
from latentsim.latent.serialization import autoencoder_coordinates, load_autoencoder, load_extra, load_integrator
from latentsim.latent.stability import stress_test
from latentsim.latent.timing import rigid_frame_steppers, time_steppers
from latentsim.latent.training import fit_integrator
from latentsim.report.metrics import bbox_diagonal, vertex_errors
from latentsim.report.tables import write_table
from latentsim.report.plots import save_figure
from latentsim.runtime import compiled as runtime_compiled
from latentsim.scene import potential_from_artefact

log = logging.getLogger(__name__)


def widths_label(widths) -> str:
    """Hidden widths as the sweep's tables write them: ``"32 32"``, or ``"linear"`` for none (a linear
    autoencoder; an empty string would read back from the CSV as NaN and drop out of a groupby)."""
    return " ".join(map(str, widths)) or "linear"


def chosen_label(table: pd.DataFrame, sizes: list[dict]) -> str:
    """The label (:func:`point_label`) of the point :func:`choose` marked ``chosen`` in ``table``, ``"none"`` when no
    point passes; ``sizes`` is the scene's ``sweep.sizes``, whose index the label carries."""
    rows = table[table["chosen"].astype(bool)]
    if rows.empty:
        return "none"
    row = rows.iloc[0]
    for i, size in enumerate(sizes):
        if (widths_label(size["autoencoder"]), widths_label(size["integrator"])) == (str(row["autoencoder_widths"]), str(row["integrator_widths"])):
            return point_label(int(row["latent_dim"]), i)
    raise ValueError(f"sweep choice: widths {row['autoencoder_widths']!r}, {row['integrator_widths']!r} are none of the sweep's sizes")


def recorded_choice_note(label: str, recorded: dict | None, scene: str) -> str:
    """A sentence comparing a sweep's new choice ``label`` with the one the config records (``sweep.chosen``)."""
    if not recorded:
        return f"sweep of {scene} chose {label}; the config records no choice (scenes.{scene}.sweep.chosen)"
    if recorded["point"] == label:
        return f"sweep of {scene} chose {label}, the choice the config records (at {recorded['commit']})"
    return (f"sweep of {scene} chose {label}, not {recorded['point']} as the config records (at {recorded['commit']}): "
            f"set scenes.{scene}.sweep.chosen and the scene's sizes to the new choice, or keep them and say why")


def parameter_count(module: torch.nn.Module) -> int:
    return int(sum(p.numel() for p in module.parameters()))


def sweep_point(trajectories, autoencoder: dict, integrator: dict, rollout: dict, seed: int, out_csv, device="cpu",
                stress: bool = True, trained: tuple | None = None, earlier: dict | None = None) -> pd.DataFrame:  # fmt: skip
    """Train, roll out and measure one model size; one CSV row per test sequence.

    Parameters
    ----------
    trajectories : the simulator's ``trajectories.h5``.
    autoencoder, integrator : settings of this point (the scene's, with
        latent_dim and widths replaced; keys absent take the schema's defaults).
    rollout : the scene's rollout settings (``max_extent``, ``timing_repeats``,
        ``stability``; keys absent take the schema's defaults).
    stress : run the stress conditions of ``rollout["stability"]`` (unless
        that says ``enabled: false``) on the first test sequence.  Every row
        gets ``stress_conditions`` (how many ran), ``stress_failed`` (how many
        the model did not survive) and ``stress_failures`` (``name@frame``).
    seed : the seed of every stochastic step of the training, in the rows' ``seed`` column.
    trained : (autoencoder path, integrator path) of the scene's method that is this point, trained with
        these settings and ``seed`` (:func:`latentsim.config.sweep_point_method`): measured, not trained
        again (:func:`trained_point`).
    earlier : the point's seeds already run, as ``{"metrics": [their CSVs], "tolerance", "pass_fraction",
        "seeds"}`` (the scene's tolerance, ``sweep.pass_fraction`` and number of seeds): when they decide
        that the point cannot pass (:func:`prune_reason`), this seed is not trained and ``out_csv`` gets
        its :func:`pruned_row`.
    """
    if earlier:
        before = pd.concat([read_csv(p) for p in earlier["metrics"]], ignore_index=True)
        reason = prune_reason(before, float(earlier["tolerance"]), float(earlier["pass_fraction"]), int(earlier["seeds"]))
        if reason is not None:
            log.info("seed %d not trained: the point %s", seed, reason)
            df = pruned_row(before, seed, reason)
            write_table(df, out_csv)
            return df
    point = trained_point(trajectories, *trained) if trained else train_point(trajectories, autoencoder, integrator, seed, device=device)
    df = measure_point(point, rollout, stress=stress).assign(seed=int(seed))
    write_table(df, out_csv)
    return df


def trained_point(trajectories, autoencoder_path, integrator_path) -> dict:
    """A sweep point whose model the pipeline has already trained (a method of the scene with exactly the
    point's settings and seed, :func:`latentsim.config.sweep_point_method`): that autoencoder and
    integrator, loaded, as :func:`train_point` returns a point; ``train_seconds`` is the two trainings' time
    as their files record it."""
    with open_artefact(trajectories) as f:
        coords = autoencoder_coordinates(f, autoencoder_path)
        scene = _scene_data(f)
    ae, integ = load_autoencoder(autoencoder_path), load_integrator(integrator_path)
    seconds = sum(float(load_extra(p).get("train_seconds", np.nan)) for p in (autoencoder_path, integrator_path))
    return dict(ae=ae, integrator=integ, coords=coords, **scene, train_seconds=seconds, latent_dim=int(ae.hparams["latent_dim"]),
                autoencoder_widths=list(ae.hparams["widths"]), integrator_widths=list(integ.hparams["widths"]))  # fmt: skip


def _scene_data(f) -> dict:
    """What a point needs of the open trajectories file ``f`` besides its model: the ``train`` and ``tests``
    sequences, ``rest`` positions, ``dirichlet`` indices and ``dt``."""
    return dict(train=load_sequences(f, "train"), tests=load_sequences(f, "test"), rest=f["rest_positions"][()], dirichlet=f["dirichlet"][()],
                dt=float(f.attrs["dt"]))  # fmt: skip


def train_point(trajectories, autoencoder: dict, integrator: dict, seed: int, device="cpu") -> dict:
    """Train one model size on a scene's training sequences (see :func:`sweep_point`).

    Returns the eval-mode autoencoder ``ae`` and integrator ``integrator`` (on
    the CPU), their ``coords``, the scene's ``train`` and ``tests`` sequences,
    ``rest`` positions, ``dirichlet`` indices, ``dt``, and ``train_seconds``;
    :func:`measure_point` takes it.
    """
    ae_cfg = with_defaults("autoencoder", autoencoder, "train_point")
    int_cfg = with_defaults("integrator", integrator, "train_point")
    with open_artefact(trajectories) as f:
        coords = coordinates_for(f, ae_cfg["coordinates"], ae_cfg["rigid_frame"])
        scene = _scene_data(f)
        potential = potential_from_artefact(f)
    train = scene["train"]
    U = torch.cat([coords.encode(torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])) for s in train.values()])
    t0 = time.perf_counter()
    ae, _ = fit_autoencoder(U.to(torch.float32), ae_cfg, seed=seed, device=device)
    ae = ae.cpu().eval()
    integ, _ = fit_integrator(ae, coords, potential, list(train.values()), int_cfg, seed=seed, device=device)
    return dict(ae=ae, integrator=integ.cpu().eval(), coords=coords, **scene, train_seconds=time.perf_counter() - t0, latent_dim=int(ae_cfg["latent_dim"]),
                autoencoder_widths=list(ae_cfg["widths"]), integrator_widths=list(int_cfg["widths"]))  # fmt: skip


def measure_point(point: dict, rollout: dict, stress: bool = True) -> pd.DataFrame:
    """Roll out, time and stress-test a trained point (:func:`train_point`); one row per test sequence.

    ``rollout``: the scene's rollout settings (keys absent take the schema's defaults).
    """
    rollout = with_defaults("rollout", rollout, "measure_point")
    ae, integ, coords, train, tests, rest = (point[k] for k in ("ae", "integrator", "coords", "train", "tests", "rest"))
    diag = bbox_diagonal(rest)
    # as the rollout stage: the fastest deployable runtime is timed
    steppers = rigid_frame_steppers(runtime_compiled.deployable_steppers(runtime.fold_networks(ae, integ, coords)), coords)
    rows = []
    for name, s in tests.items():
        x, xD = torch.as_tensor(s["positions"]), torch.as_tensor(s["dirichlet_positions"])
        z = encode_positions(ae, coords, x[:2], xD[:2])
        res = latent_rollout(integ, ae, coords, z[0], z[1], torch.as_tensor(s["bc"]), xD,
                             max_extent=float(rollout["max_extent"]), rest_positions=torch.as_tensor(rest))  # fmt: skip
        T, div = len(x), int(res["diverged_frame"])
        ok = slice(0, T if div < 0 else div)
        mean_e, max_e = vertex_errors(res["positions"].numpy()[ok], s["positions"][ok], diag)
        p_last = boundary_inputs(s["bc"], s["dirichlet_positions"], integ.origin, coords)[-1]
        timing = time_steppers(steppers, z[1], z[0], p_last, s["dirichlet_positions"][-1], int(rollout["timing_repeats"]))
        rows.append(dict(
            latent_dim=point["latent_dim"], autoencoder_widths=widths_label(point["autoencoder_widths"]),
            integrator_widths=widths_label(point["integrator_widths"]), decoder_parameters=parameter_count(ae.dec_branch) + parameter_count(ae.pca_out),
            integrator_parameters=parameter_count(integ), sequence=name, frames=T, diverged_frame=div,
            mean_error=float(mean_e.mean()) if len(mean_e) else np.nan, max_error=float(max_e.max()) if len(max_e) else np.nan,
            step_ms=timing["step_ms"], runtime=timing["runtime"], train_seconds=point["train_seconds"],
        ))  # fmt: skip
    st = rollout["stability"]
    failed, n_conditions = [], 0
    if stress and st["enabled"] and tests:
        train_frames = max(len(s["positions"]) for s in train.values())
        for c, res in stress_test(integ, ae, coords, next(iter(tests.values())), rest, point["dirichlet"], point["dt"], train_frames, st,
                                  float(rollout["max_extent"])):  # fmt: skip
            n_conditions += 1
            if res["survived"] < res["frames"]:
                failed.append(f"{c.name}@{res['survived']}")
    for row in rows:
        row.update(stress_conditions=n_conditions, stress_failed=len(failed), stress_failures=" ".join(failed))
    df = pd.DataFrame(rows)
    df["parameters"] = df["decoder_parameters"] + df["integrator_parameters"]
    return df


KEYS = ["latent_dim", "autoencoder_widths", "integrator_widths"]


def _normalised(df: pd.DataFrame) -> pd.DataFrame:
    """Point rows as :func:`choose` reads them: stress columns filled, the seed an int, widths as strings,
    ``pruned`` a bool (rows written before pruning existed are measured rows)."""
    df = df.copy()
    for col in ("stress_conditions", "stress_failed"):
        df[col] = df[col].fillna(0).astype(int) if col in df else 0
    # a CSV reads back an empty failure list as NaN (a float column when every entry is empty)
    df["stress_failures"] = df["stress_failures"].astype("string").fillna("") if "stress_failures" in df else ""
    df["seed"] = df["seed"].astype(int) if "seed" in df else 0
    df["pruned"] = df["pruned"].fillna(False).astype(bool) if "pruned" in df else False
    for k in KEYS[1:]:  # "16" reads back from a CSV as a number, "32 32" as a string
        df[k] = df[k].astype(str)
    return df


def _per_seed(df: pd.DataFrame, tolerance: float) -> pd.DataFrame:
    """One row per point and measured seed of normalised rows (pruned rows left out): the worst sequence's
    errors, ``diverged``, the stress results, ``within_tolerance`` and ``passes`` (no sequence diverged,
    every mean error within ``tolerance``, no stress condition failed)."""
    per_seed = df[~df["pruned"]].groupby(KEYS + ["seed"], sort=False, dropna=False).agg(
        parameters=("parameters", "first"), mean_error=("mean_error", "max"), max_error=("max_error", "max"),
        diverged=("diverged_frame", lambda d: bool((d >= 0).any())), step_ms=("step_ms", "median"), train_seconds=("train_seconds", "first"),
        stress_conditions=("stress_conditions", "first"), stress_failed=("stress_failed", "first"), stress_failures=("stress_failures", "first"),
    ).reset_index()  # fmt: skip
    per_seed["within_tolerance"] = (~per_seed["diverged"]) & (per_seed["mean_error"] <= tolerance)
    per_seed["passes"] = per_seed["within_tolerance"] & (per_seed["stress_failed"] == 0)
    return per_seed


def _seeds_needed(n_seeds: int, pass_fraction: float) -> int:
    """Seeds of ``n_seeds`` in which a point must pass: ceil(pass_fraction n)."""
    return int(np.ceil(pass_fraction * n_seeds - 1e-9))


def prune_reason(earlier: pd.DataFrame, tolerance: float, pass_fraction: float, n_seeds: int) -> str | None:
    """Why one point's next seed need not be trained, or None.

    ``earlier``: the point's rows of its seeds already run (measured or pruned); ``n_seeds``: how many seeds
    the scene runs.  The point must pass in ``ceil(pass_fraction n_seeds)`` seeds (:func:`choose`); once more
    seeds have failed (or were pruned) than that leaves room for, no later seed can make it pass, and the
    choice is the same whatever they would measure.
    """
    df = _normalised(earlier)
    failed = int(df["pruned"].groupby(df["seed"]).any().sum())
    per_seed = _per_seed(df, tolerance)
    failed += int((~per_seed["passes"]).sum())
    allowed = n_seeds - _seeds_needed(n_seeds, pass_fraction)
    if failed > allowed:
        return f"failed in {failed} of its first seeds; it must pass in {n_seeds - allowed} of {n_seeds} (sweep.pass_fraction {pass_fraction:g})"
    return None


def pruned_row(earlier: pd.DataFrame, seed: int, reason: str) -> pd.DataFrame:
    """The row a pruned seed writes: the point's size (from its earlier rows), its seed, ``pruned`` and why;
    no measurement."""
    first = earlier.iloc[0]
    size = [k for k in KEYS + ["decoder_parameters", "integrator_parameters", "parameters"] if k in earlier]
    return pd.DataFrame([{**{k: first[k] for k in size}, "seed": int(seed), "pruned": True, "pruned_because": reason}])


def choose(df: pd.DataFrame, tolerance: float, pass_fraction: float = 1.0) -> pd.DataFrame:
    """One row per sweep point over its seeds, with ``passes`` and the ``chosen`` smallest passing point.

    A point passes in one seed when no test sequence diverged, every sequence's mean vertex error / bbox
    diagonal is at most ``tolerance`` and it failed no stress condition (points measured without them,
    ``stress_conditions`` 0 or the columns absent, are judged on the test sequences alone).  A point
    passes when it passes in at least ``pass_fraction`` of its seeds (rows without a ``seed`` column are
    one seed; a ``pruned`` seed, :func:`prune_reason`, counts as a seed that did not pass); among passing
    points the one with the fewest parameters (then the lowest latent dimension, then the fastest step)
    is chosen.

    Columns: the point's ``latent_dim``, ``autoencoder_widths``, ``integrator_widths``, ``parameters``;
    ``seeds`` (every seed, pruned ones included), ``seeds_pruned``; over its measured seeds
    ``seeds_passing``, the median (``mean_error``), least and largest
    (``mean_error_min``, ``mean_error_max``) of the worst sequence's mean error, ``max_error`` (largest),
    ``diverged`` (in any seed), ``diverged_seeds``, ``step_ms`` and ``train_seconds`` (medians), the
    stress conditions (``stress_failed``: failures summed over seeds, ``stress_failures``: each seed's
    list, ``;``-separated), ``within_tolerance`` (in every seed), ``passes``, ``chosen``.
    """
    if not 0 < pass_fraction <= 1:
        raise ValueError(f"choose: pass_fraction {pass_fraction!r} must be in (0, 1]")
    df = _normalised(df)
    keys = KEYS
    per_seed = _per_seed(df, tolerance)
    g = per_seed.groupby(keys, sort=False, dropna=False).agg(
        parameters=("parameters", "first"), seeds=("seed", "nunique"), seeds_passing=("passes", "sum"),
        mean_error=("mean_error", "median"), mean_error_min=("mean_error", "min"), mean_error_max=("mean_error", "max"),
        max_error=("max_error", "max"), diverged=("diverged", "any"), diverged_seeds=("diverged", "sum"),
        step_ms=("step_ms", "median"), train_seconds=("train_seconds", "median"), stress_conditions=("stress_conditions", "first"),
        stress_failed=("stress_failed", "sum"), stress_failures=("stress_failures", lambda f: "; ".join(f)),
        within_tolerance=("within_tolerance", "all"),
    ).reset_index()  # fmt: skip
    pruned = df[df["pruned"]].groupby(keys, sort=False, dropna=False)["seed"].nunique().rename("seeds_pruned")
    g = g.join(pruned, on=keys)
    g["seeds_pruned"] = g["seeds_pruned"].fillna(0).astype(int)
    g["seeds"] = g["seeds"] + g["seeds_pruned"]
    g["seeds_passing"] = g["seeds_passing"].astype(int)
    g["diverged_seeds"] = g["diverged_seeds"].astype(int)
    g["passes"] = g["seeds_passing"] >= np.ceil(pass_fraction * g["seeds"] - 1e-9)
    g["chosen"] = False
    ok = g[g["passes"]].sort_values(["parameters", "latent_dim", "step_ms"])
    if len(ok):
        g.loc[ok.index[0], "chosen"] = True
    return g


def sweep_chart(table: pd.DataFrame, tolerance: float, scene: str, path, method: str = "self_supervised") -> None:
    """Error and ms per step against parameter count, one marker per latent dimension; the choice circled.

    ``method``: whose loss the points trained with (the config's ``sweep.method``), named in the title.
    """
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for k, (r, g) in enumerate(table.groupby("latent_dim")):
        colour = f"C{k % 10}"
        for diverged, h in g.groupby("diverged"):
            axes[0].scatter(h["parameters"], h["mean_error"].clip(lower=1e-12), edgecolors=colour,
                            facecolors="none" if diverged else colour, label=f"latent {r}" + (" (diverged)" if diverged else ""))  # fmt: skip
        if "mean_error_min" in g and (g.get("seeds", 1) > 1).any():  # the seeds' spread: least to largest
            lo, hi, mid = (g[c].clip(lower=1e-12).to_numpy(float) for c in ("mean_error_min", "mean_error_max", "mean_error"))
            finite = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(mid)
            axes[0].errorbar(g["parameters"].to_numpy(float)[finite], mid[finite], yerr=[mid[finite] - lo[finite], hi[finite] - mid[finite]],
                             fmt="none", ecolor=colour, capsize=3, lw=1)  # fmt: skip
        axes[1].scatter(g["parameters"], g["step_ms"], color=colour, label=f"latent {r}")
    stressed = table[table["stress_failed"] > 0] if "stress_failed" in table else table.iloc[:0]
    if len(stressed):
        axes[0].scatter(stressed["parameters"], stressed["mean_error"], marker="x", s=80, color="r", label="fails a stress condition")
    pick = table[table["chosen"]]
    if len(pick):
        axes[0].scatter(pick["parameters"], pick["mean_error"], s=250, facecolors="none", edgecolors="k", label="chosen")
        axes[1].scatter(pick["parameters"], pick["step_ms"], s=250, facecolors="none", edgecolors="k", label="chosen")
    axes[0].axhline(tolerance, color="r", ls="--", label="tolerance")
    def wide(v):  # log axes only where the values span a decade or more
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v) & (v > 0)]
        return len(v) > 1 and v.max() / v.min() >= 10.0

    for ax, ylabel, col in zip(axes, ("worst mean vertex error / bbox diagonal", "ms per latent step (fastest runtime)"), ("mean_error", "step_ms")):
        if wide(table["parameters"]):
            ax.set_xscale("log")
        if wide(table[col]):
            ax.set_yscale("log")
        ax.set_xlabel("parameters (decoder + integrator)")
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)
    seeds = int(table["seeds"].max()) if "seeds" in table else 1
    spread = f"median of {seeds} seeds, bars least to largest; " if seeds > 1 else ""
    if "seeds_pruned" in table and (table["seeds_pruned"] > 0).any():
        spread += "points that failed their first seeds were not trained further (seeds measured only); "
    fig.suptitle(f"{scene}: sizing sweep, {method} loss ({spread}hollow: diverged on a test sequence in a seed; x: failed a stress condition)",
                 fontsize=9)  # fmt: skip
    fig.tight_layout()
    save_figure(fig, path)
