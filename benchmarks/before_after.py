"""Two runs' learned results over seeds, side by side: is a change that is not exact inside the spread?

    python benchmarks/before_after.py BEFORE/results/evaluation AFTER/results/evaluation [--scenes a b] [--methods m n]

A change to training that is not exact to the bit (a saving that approximates, a rule that stops early) is
accepted where its results stay inside the seeds' own spread.  From each run's ``glance.csv`` and
``divergence.csv`` (the summary's tables; where a run has no summary, as a run of some scenes' targets,
from each ``<scene>/metrics.csv`` and ``stress.csv`` by the summary's own functions), one row per scene and learned method that both runs hold: the
median mean error over seeds with its range over the stable seeds, before and after; the seeds whose every
test sequence survived; the test rollouts and stress conditions survived (``k/N``); the seeds in which a
test sequence diverged (each such cell "before / after"); and ``inside``: whether the new median lies in the old range (``no`` where it does
not, ``-`` where either run has no stable seed).  Methods without seeds (the full space, the reduced
baselines, ``newton_1it``) are left out.  Prints a Markdown table and the count of rows outside; exits 1
where a row is outside, so a script can stop on it.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
from latentsim.io import read_csv  # noqa: E402 (the checked reading of the pipeline's tables)
from latentsim.report.tables import divergence_table, glance_table  # noqa: E402

KEYS = ["scene", "method"]
SEEDLESS = {"full_space", "newton_1it"}  # and every *_reduced baseline


def _learned(table: pd.DataFrame) -> pd.DataFrame:
    keep = ~table["method"].isin(SEEDLESS) & ~table["method"].str.endswith("_reduced")
    return table[keep]


def _tables(folder: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A run's glance and divergence tables: the summary's, or made from its scenes' tables as the summary does."""
    if (folder / "glance.csv").exists():
        divergence = folder / "divergence.csv"
        return read_csv(folder / "glance.csv"), read_csv(divergence) if divergence.exists() else pd.DataFrame(columns=KEYS)
    metrics = [read_csv(p) for p in sorted(folder.glob("*/metrics.csv"))]
    if not metrics:
        raise SystemExit(f"{folder}: neither glance.csv nor any <scene>/metrics.csv")
    stress = [read_csv(p) for p in sorted(folder.glob("*/stress.csv"))]
    df, st = pd.concat(metrics, ignore_index=True), pd.concat(stress, ignore_index=True) if stress else pd.DataFrame()
    return glance_table(df, st), divergence_table(df, st)


def _run(folder: Path) -> pd.DataFrame:
    """(scene, method) -> the glance's error, survival and stress columns, and the divergence count."""
    glance, divergence = _tables(folder)
    cols = KEYS + ["seeds", "mean_error", "mean_error_min", "mean_error_max", "seeds_stable", "test_survived", "stress_survived"]
    out = _learned(glance)[cols]
    if "test_diverged" in divergence.columns:
        out = out.merge(_learned(divergence)[KEYS + ["test_diverged"]], on=KEYS, how="left")
    return out


def _text(value) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) or value == "" else str(value)


def _error(median, low, high) -> str:
    if not math.isfinite(median):
        return "diverged"
    return f"{median:.4g} ({low:.4g} to {high:.4g})"


def _inside(b, a) -> str:
    if not (math.isfinite(a.mean_error) and math.isfinite(b.mean_error_min) and math.isfinite(b.mean_error_max)):
        return "-"
    return "yes" if b.mean_error_min <= a.mean_error <= b.mean_error_max else "no"


def before_after(before_dir, after_dir, scenes=None, methods=None) -> pd.DataFrame:
    """One row per scene and learned method both runs hold (the module's docstring)."""
    before, after = _run(Path(before_dir)), _run(Path(after_dir))
    both = before.merge(after, on=KEYS, suffixes=("_b", "_a"))
    if scenes:
        both = both[both["scene"].isin(scenes)]
    if methods:
        both = both[both["method"].isin(methods)]
    rows = []
    for r in both.itertuples(index=False):
        b = pd.Series({k[:-2]: v for k, v in r._asdict().items() if k.endswith("_b")})
        a = pd.Series({k[:-2]: v for k, v in r._asdict().items() if k.endswith("_a")})
        rows.append({
            "scene": r.scene, "method": r.method, "seeds": f"{int(b.seeds)} / {int(a.seeds)}",
            "mean error before": _error(b.mean_error, b.mean_error_min, b.mean_error_max),
            "mean error after": _error(a.mean_error, a.mean_error_min, a.mean_error_max),
            "inside": _inside(b, a),
            "seeds stable": f"{b.seeds_stable} / {a.seeds_stable}",
            "test survived": f"{b.test_survived} / {a.test_survived}",
            "stress survived": f"{_text(b.stress_survived)} / {_text(a.stress_survived)}",
            "diverged": f"{_text(b.get('test_diverged'))} / {_text(a.get('test_diverged'))}",
        })  # fmt: skip
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", help="the earlier run's results/evaluation folder")
    ap.add_argument("after", help="the later run's results/evaluation folder")
    ap.add_argument("--scenes", nargs="*", help="only these scenes")
    ap.add_argument("--methods", nargs="*", help="only these methods")
    args = ap.parse_args(argv)
    table = before_after(args.before, args.after, args.scenes, args.methods)
    if table.empty:
        print("no scene and learned method is in both runs")
        return 1
    print(table.fillna("-").to_markdown(index=False))
    outside = int((table["inside"] == "no").sum())
    print(f"\n{outside} of {len(table)} rows with the new median outside the old range")
    return 1 if outside else 0


if __name__ == "__main__":
    sys.exit(main())
