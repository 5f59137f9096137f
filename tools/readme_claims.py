"""Write the README's "Stability over seeds" from the per-scene evaluations of a run over several seeds.

    python tools/readme_claims.py                          # every scene in results/ run with several seeds
    python tools/readme_claims.py --scenes cloth_paper cantilever_paper --commit abc1234
    python tools/readme_claims.py --check                  # exit 1 if README.md is not what it would write

The block between the README's ``claims: begin`` and ``claims: end`` markers is replaced by the commit,
date and processor of the run and the comparison's claims as sentences with their seed counts and spread
(``latentsim.report.tables.claims``, from the glance and Li et al.'s Fig. 8 over seeds,
``divergence_table``), all computed from ``evaluation/<scene>/metrics.csv`` and ``stress.csv``: nothing
in the block is typed.  The divergence table itself, with each failing seed's frames per stress
condition, is ``results/evaluation/divergence.csv`` after ``all``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path


import pandas as pd
from readme_glance import replace_block, run_commit

from latentsim.io import read_csv
from latentsim.provenance import recorded_environment
from latentsim.report.tables import claims, divergence_table, glance_table

BEGIN = "<!-- claims: begin (written by python tools/readme_claims.py; do not edit by hand) -->"
END = "<!-- claims: end -->"


def seeded_scenes(results: Path) -> list[str]:
    """Scenes whose evaluation holds a method run with several seeds."""
    out = []
    for f in sorted((results / "evaluation").glob("*/metrics.csv")):
        df = read_csv(f)
        if "seed" in df and (df.groupby("method")["seed"].nunique() > 1).any():
            out.append(f.parent.name)
    return out


def processor(results: Path, scene: str) -> str:
    """The processor the scene's rollouts ran on, from the first one's recorded environment."""
    for path in sorted((results / "rollout" / scene).glob("*/seed*/rollout.h5")):
        env = recorded_environment(path)
        if env:
            return str(env.get("processor", "unknown processor"))
    return "unknown processor"


def claims_block(results: Path, scenes: list[str], commit: str) -> str:
    """The Markdown between the markers."""
    if not scenes:
        sys.exit(f"{results}/evaluation: no scene evaluated over several seeds; run one first (README, 'Stability over seeds')")
    frames, stress = [], []
    for scene in scenes:
        d = results / "evaluation" / scene
        for name, into in (("metrics.csv", frames), ("stress.csv", stress)):
            if not (d / name).is_file():
                sys.exit(f"{d / name} not found: run `snakemake --cores 2 results/evaluation/{scene}/metrics.csv` first")
            into.append(read_csv(d / name))
    df = pd.concat(frames, ignore_index=True)
    st = pd.concat(stress, ignore_index=True)
    glance, dv = glance_table(df, st), divergence_table(df, st)
    newest = max((results / "evaluation" / s / "metrics.csv").stat().st_mtime for s in scenes)
    finished = dt.datetime.fromtimestamp(newest, dt.timezone.utc).strftime("%Y-%m-%d")
    cpus = sorted({processor(results, s) for s in scenes})
    targets = " ".join(f"results/evaluation/{s}/metrics.csv" for s in scenes)
    text = [
        BEGIN,
        f"From `snakemake --cores 2 {targets}` at commit {commit}, finished {finished}, on {', '.join(cpus)}; "
        "generated from the scenes' tables. Mean error: over the bounding-box diagonal, on the test sequence; frames "
        "survived per seed as `seed:frames`.",
        "",
        claims(glance, dv).strip() or "(no method ran with several seeds)",
        END,
    ]
    return "\n".join(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=Path("results"), help="the run's results folder")
    ap.add_argument("--scenes", nargs="*", help="the scenes to state (default: every scene evaluated over several seeds)")
    ap.add_argument("--readme", type=Path, default=Path("README.md"))
    ap.add_argument("--commit", help="the run's commit (default: read from the results' checkout)")
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 if the README differs")
    args = ap.parse_args(argv)
    scenes = args.scenes or seeded_scenes(args.results)
    block = claims_block(args.results, scenes, args.commit or run_commit(args.results))
    return replace_block(args.readme, BEGIN, END, block, args.check, str(args.results))


if __name__ == "__main__":
    sys.exit(main())
