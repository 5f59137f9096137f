"""Wall time of every stage of a pipeline run, per scene, from Snakemake's benchmark files.

    python benchmarks/stage_times.py [results/benchmarks]

Every rule that simulates, trains, rolls out, sweeps or evaluates writes
``results/benchmarks/<stage>/<scene>[/<method or point>][/seed<k>].tsv`` (Snakemake's ``benchmark:``:
the job's wall seconds and CPU seconds; a learned stage writes one per seed, all counted under its
scene); the Neural Modes rules write ``neural_modes/<scene>[_<job>].tsv`` and are split back into their
stages here.  Prints one Markdown row per stage: the number of jobs, the
wall seconds of each scene's jobs summed, and the stage total; then the grand total.  Jobs run two
at a time on 2 cores, so the sum of job times exceeds the run's elapsed time.
"""

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


def main(root="results/benchmarks"):
    df = stage_times(root)
    if df.empty:
        sys.exit(f"no benchmark files under {root}")
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
    main(*sys.argv[1:])
