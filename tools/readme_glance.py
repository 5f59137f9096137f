"""Write the README's "Results at a glance" from one `all` run's results.

    python tools/readme_glance.py                      # results/ of this checkout -> README.md
    python tools/readme_glance.py --results DIR --readme README.md --commit abc1234
    python tools/readme_glance.py --check              # exit 1 if README.md is not what it would write

The block between the README's ``glance: begin`` and ``glance: end`` markers is replaced by: the
commit and date of the run, the Li et al. comparison grid (mean error / bounding-box diagonal and ms per
frame of every compared method on each scene, from ``evaluation/glance.csv``, as
``latentsim.report.tables.glance_grid`` lays it out), the self-supervised integrator's speed-up and
stress conditions survived, and the Neural Modes energy ratios (``neural_modes/summary.csv``).
Run it right after ``snakemake --cores 2 all`` in the checkout that made the results: the commit
is read from there unless ``--commit`` names it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import subprocess
import sys
from pathlib import Path

import pandas as pd

from latentsim.io import read_csv
from latentsim.report.tables import glance_grid, markdown

BEGIN = "<!-- glance: begin (written by python tools/readme_glance.py; do not edit by hand) -->"
END = "<!-- glance: end -->"


def run_commit(results: Path) -> str:
    """Short hash of the commit checked out where ``results`` lives (with ``+dirty`` if tracked files changed)."""
    where = results.resolve().parent
    head = subprocess.run(["git", "-C", str(where), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if head.returncode != 0:
        sys.exit(f"{where}: not a git checkout; name the run's commit with --commit")
    dirty = subprocess.run(["git", "-C", str(where), "diff", "--quiet", "HEAD", "--", "src", "workflow", "config"])
    return head.stdout.strip() + ("+dirty" if dirty.returncode else "")


def glance_block(results: Path, commit: str) -> str:
    """The Markdown between the markers."""
    li = results / "evaluation" / "glance.csv"
    nm = results / "neural_modes" / "summary.csv"
    for f in (li, nm):
        if not f.is_file():
            sys.exit(f"{f} not found: run `snakemake --cores 2 all` first")
    glance = read_csv(li)
    finished = dt.datetime.fromtimestamp(li.stat().st_mtime, dt.timezone.utc).strftime("%Y-%m-%d")
    ss = glance[glance["method"] == "self_supervised"].set_index("scene")
    speed = pd.DataFrame({
        "scene": ss.index,
        "speed-up over the full space": [f"{v:,.0f}x" for v in ss["speedup"]],
        "test sequences stable": ss["test_survived"].fillna("").astype(str).values,
        "stress conditions survived": ss["stress_survived"].fillna("").astype(str).values,
        "kinetic-energy ratio": [f"{v:.2f}" for v in ss["kinetic_ratio"]],
    })
    nm_table = read_csv(nm)
    nm_cols = {"scene": "scene", "modes": "modes", "E_avg neural": "mean energy, Neural Modes",
               "E_avg linear": "mean energy, linear modes", "E ratio": "ratio"}
    nm_table = nm_table[list(nm_cols)].rename(columns=nm_cols)
    text = [
        BEGIN,
        f"From `snakemake --cores 2 all` at commit {commit}, finished {finished} (`results/evaluation/summary.md`, "
        "`results/neural_modes/summary.md`).",
        "",
        "**Li et al. scenes.** Mean vertex error over the bounding-box diagonal on the test sequences, and in "
        "brackets ms per frame (one thread, median over test sequences). `*`: on the Pareto front of these "
        "methods (none both faster and more accurate); `-`: not run on that scene; `diverged k/N`: the "
        "method's rollout diverged on k of the N test sequences (its frames from there on count as failed). "
        "The full space is the ground truth.",
        "",
        markdown(glance_grid(glance)),
        "",
        "The self-supervised integrator (speed-up: full-space over latent time per frame, both timed in the "
        "rollout job; stress conditions: 10x longer, 0.1x-5x the speeds, sudden stop and reversal, perturbed "
        "start):",
        "",
        markdown(speed),
        "",
        "**Neural Modes scenes.** Mean elastic energy over the test set of the nonlinear map and of the "
        "linear modes alone (lower is better):",
        "",
        markdown(nm_table),
        END,
    ]
    return "\n".join(text)


def replace_block(readme: Path, begin: str, end: str, block: str, check: bool, source: str) -> int:
    """Put ``block`` (markers included) in place of the README's text from ``begin`` to ``end``; with
    ``check`` only compare (1 where it differs).  Written atomically."""
    text = readme.read_text()
    if begin not in text or end not in text:
        sys.exit(f"{readme}: no markers ({begin!r} ... {end!r})")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    new = head + block + tail
    if check:
        if new != text:
            print(f"{readme}: the block is not the one {source} gives", file=sys.stderr)
            return 1
        return 0
    if new != text:
        tmp = readme.with_name(f".{readme.name}.tmp")
        tmp.write_text(new)
        tmp.replace(readme)
    print(f"{readme}: block from {source}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", type=Path, default=Path("results"), help="the run's results folder")
    ap.add_argument("--readme", type=Path, default=Path("README.md"))
    ap.add_argument("--commit", help="the run's commit (default: read from the results' checkout)")
    ap.add_argument("--check", action="store_true", help="only compare; exit 1 if the README differs")
    args = ap.parse_args(argv)
    if BEGIN not in args.readme.read_text():
        sys.exit(f"{args.readme}: no glance markers ({BEGIN!r} ... {END!r})")
    block = glance_block(args.results, args.commit or run_commit(args.results))
    return replace_block(args.readme, BEGIN, END, block, args.check, str(args.results))


if __name__ == "__main__":
    sys.exit(main())
