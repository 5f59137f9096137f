"""Wall time of every stage of a pipeline run, per scene, from Snakemake's benchmark files.

    python benchmarks/stage_times.py [results/benchmarks] [--before OTHER/results/benchmarks]

Every rule that simulates, trains, rolls out, sweeps or evaluates writes
``results/benchmarks/<stage>/<scene>[/<method or point>][/seed<k>].tsv`` (Snakemake's ``benchmark:``:
the job's wall seconds and CPU seconds; a learned stage writes one per seed, all counted under its
scene); the Neural Modes rules write ``neural_modes/<scene>[_<job>].tsv`` and are split back into their
stages here.  Prints one Markdown row per stage: the number of jobs, the
wall seconds of each scene's jobs summed, and the stage total; then the grand total.  Jobs run two
at a time on 2 cores, so the sum of job times exceeds the run's elapsed time.

With ``--before``, the benchmark folder of another run (an earlier commit's, say): one row per stage with
both runs' jobs, wall and CPU minutes, and the ratio of CPU minutes (now over before), then the totals.
CPU time is the fairer comparison where the two runs shared their cores differently.
"""

import argparse
import re
import sys
from collections import defaultdict
from pathlib import Path

import pandas as pd


# Neural Modes benchmark names, neural_modes/<scene>[_<study>]<suffix>[_seed<k>].tsv, by suffix (nm_train has none).
NM_SUFFIXES = {
    "_dynamics": "nm_dynamics",
    "_energy_table": "nm_energy_table",
    "_sheet_study": "nm_sheet_study",
    "_ground_truth": "nm_ground_truth",
    "_aspect_ratio": "nm_aspect_ratio",
}


ACROSS = "across scenes"  # the column of stages that serve every scene (summary/summary.tsv)


def split_stage(parts) -> tuple[str, str]:
    """(stage, scene) of a benchmark file's path parts relative to the benchmark folder."""
    stage, scene = parts[0], parts[1] if len(parts) > 1 else "-"
    if len(parts) == 2 and scene == stage:  # <stage>/<stage>.tsv: one job over every scene
        return stage, ACROSS
    if stage != "neural_modes" or len(parts) != 2:
        return stage, scene
    scene = re.sub(r"_seed\d+$", "", scene)  # a study run once per seed: <scene>_<job>_seed<k>
    for suffix, nm_stage in NM_SUFFIXES.items():
        if scene.endswith(suffix):
            scene = scene[: -len(suffix)]
            if nm_stage == "nm_ground_truth":  # <scene>_<study>: study names hold no underscore
                scene = scene.rsplit("_", 1)[0]
            return nm_stage, scene
    return "nm_train", scene


def stage_times(root) -> pd.DataFrame:
    """(stage, scene) -> jobs, wall s, CPU s, from every ``<stage>/<scene>[/...].tsv`` under root."""
    root = Path(root)
    rows = defaultdict(lambda: [0, 0.0, 0.0])
    for path in sorted(root.rglob("*.tsv")):
        parts = path.relative_to(root).with_suffix("").parts
        stage, scene = split_stage(parts)
        t = pd.read_csv(path, sep="\t")
        r = rows[stage, scene]
        r[0] += len(t)
        r[1] += float(t["s"].sum())
        r[2] += float(t["cpu_time"].sum())
    return pd.DataFrame([(st, sc, *v) for (st, sc), v in rows.items()], columns=["stage", "scene", "jobs", "wall_s", "cpu_s"])


def compare(now: pd.DataFrame, before: pd.DataFrame) -> pd.DataFrame:
    """Per stage (summed over scenes): ``jobs``, ``wall_min``, ``cpu_min`` of both runs (``_before``,
    ``_now``) and ``cpu_ratio`` (now over before; NaN where a run has none of the stage), then a row
    ``all stages``."""
    cols = ["jobs", "wall_s", "cpu_s"]
    a, b = (d.groupby("stage", sort=False)[cols].sum().add_suffix(f"_{run}") for d, run in ((before, "before"), (now, "now")))
    t = a.join(b, how="outer").fillna(0.0)
    t.loc["all stages"] = t.sum()
    out = pd.DataFrame(index=t.index)
    for run in ("before", "now"):
        out[f"jobs_{run}"] = t[f"jobs_{run}"].astype(int)
        out[f"wall_min_{run}"] = t[f"wall_s_{run}"] / 60
        out[f"cpu_min_{run}"] = t[f"cpu_s_{run}"] / 60
    out["cpu_ratio"] = (t["cpu_s_now"] / t["cpu_s_before"]).where(t["cpu_s_before"] > 0)
    return out.reset_index(names="stage")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", default="results/benchmarks", help="the run's benchmark folder")
    ap.add_argument("--before", help="another run's benchmark folder, to compare with stage by stage")
    args = ap.parse_args(argv)
    root = args.root
    df = stage_times(root)
    if df.empty:
        sys.exit(f"no benchmark files under {root}")
    if args.before:
        before = stage_times(args.before)
        if before.empty:
            sys.exit(f"no benchmark files under {args.before}")
        t = compare(df, before)
        print(f"Per stage, summed over its jobs (minutes): before = {args.before}, now = {root}\n")
        print("| stage | jobs before | jobs now | wall before | wall now | CPU before | CPU now | CPU now / before |")
        print("|---|---|---|---|---|---|---|---|")
        for r in t.itertuples(index=False):
            ratio = "" if pd.isna(r.cpu_ratio) else f"{r.cpu_ratio:.2f}"
            print(f"| {r.stage} | {r.jobs_before} | {r.jobs_now} | {r.wall_min_before:.1f} | {r.wall_min_now:.1f} | {r.cpu_min_before:.1f} | "
                  f"{r.cpu_min_now:.1f} | {ratio} |")  # fmt: skip
        return
    scenes = sorted(df["scene"].unique(), key=lambda s: (s == ACROSS, s))
    print("Wall time per stage (minutes; sum of the stage's jobs per scene):\n")
    print("| stage | jobs | " + " | ".join(scenes) + " | total |")
    print("|---|---|" + "---|" * len(scenes) + "---|")
    for stage, g in df.groupby("stage", sort=False):
        by = dict(zip(g["scene"], g["wall_s"] / 60))
        cells = " | ".join(f"{by[s]:.1f}" if s in by else "" for s in scenes)
        print(f"| {stage} | {int(g['jobs'].sum())} | {cells} | {g['wall_s'].sum() / 60:.1f} |")
    per_scene = df.groupby("scene")["wall_s"].sum() / 60
    print("| all stages | " + f"{int(df['jobs'].sum())} | " + " | ".join(f"{per_scene[s]:.1f}" for s in scenes)
          + f" | {df['wall_s'].sum() / 60:.1f} |")  # fmt: skip
    print(f"\nCPU time of every job: {df['cpu_s'].sum() / 3600:.2f} h; wall time summed over jobs: {df['wall_s'].sum() / 3600:.2f} h.")


if __name__ == "__main__":
    main()
