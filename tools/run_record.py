"""The record of a pipeline run, from Snakemake's own logs and benchmark files, as JSON.

    python tools/run_record.py RUN_FOLDER [--out docs/runs/all.json] [--target all]

A long run (the default ``all`` takes hours on 2 cores) may take several parts: a part stops when its
session ends and the next resumes it from the same folder (``snakemake --unlock``, then the same command;
the default profile sets ``rerun-incomplete``).  Each part is one Snakemake log in
``RUN_FOLDER/.snakemake/log/``; the workflow writes its commit and machine at the top of each
(``onstart`` in the Snakefile).  The record holds, per part: the log, the command, its commit and machine,
start and end (UTC as the log gives them), wall minutes, jobs finished, the steps done of the steps
planned, how it ended (``complete``, ``failed``, naming the rules, or ``stopped``) and what it asked
for (``targets``: the target, or ``subset`` for a part that builds some of its outputs, ``results/...``,
as a part that redoes what a change touched, or runs the target with ``--omit-from`` or ``--until``); in all: wall minutes (the time some part was running, parts
that ran side by side counted once), jobs, whether the target completed (the last part that asks for
it), CPU and job minutes, and minutes per stage summed over each stage's jobs
(``benchmarks/stage_times.py`` on ``results/benchmarks``).  Dry runs and parts that ask for other rules
(``sizing``, ``--unlock``) are left out.

A run not yet complete also gets ``remaining``: per rule, the jobs the first part planned that no part has
finished, the mean wall minutes of the rule's finished jobs (start to finish in the log, so under whatever
shared the cores), and the wall minutes they would take at ``--cores`` jobs at a time; rules none of whose
jobs has finished are named, without a time.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from stage_times import stage_times  # noqa: E402 (the one reading of the benchmark files)

STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
STEPS = re.compile(r"^(\d+) of (\d+) steps \(([\d.]+)%\) done$")


def _time(text: str) -> datetime:
    return datetime.strptime(" ".join(text.split()), "%a %b %d %H:%M:%S %Y")


def read_part(path: Path) -> dict:
    """One Snakemake log: its command, commit, machine, start, end, jobs and how it ended."""
    lines = path.read_text(errors="replace").splitlines()
    field = lambda key: next((ln.split(":", 1)[1].strip() for ln in lines if ln.strip().startswith(key + ":")), None)  # noqa: E731
    start = field("Date")
    stamps = [_time(m.group(1)) for ln in lines if (m := STAMP.match(ln.strip()))]
    steps = [m.groups() for ln in lines if (m := STEPS.match(ln.strip()))]
    failed = sorted({m.group(1) for ln in lines if (m := re.match(r"^Error in rule (\w+):", ln.strip()))})
    begin = datetime.strptime(start, "%Y-%m-%d %H:%M:%S") if start else (stamps[0] if stamps else None)
    end = stamps[-1] if stamps else begin
    done = bool(steps) and steps[-1][0] == steps[-1][1]
    planned = next((int(m.group(1)) for ln in lines if (m := re.match(r"^total\s+(\d+)$", ln.strip()))), None)
    return {
        "log": path.name,
        "command": re.sub(r"^\S*/", "", field("Command") or "") or None,  # the program's name, not where it is installed
        "commit": field("latentsim commit"),
        "machine": field("latentsim machine"),
        "start": begin.isoformat() if begin else None,
        "end": end.isoformat() if end else None,
        "wall_min": round((end - begin).total_seconds() / 60, 2) if begin and end else 0.0,
        "jobs_finished": sum(ln.startswith("Finished jobid") for ln in lines),
        "steps_done": int(steps[-1][0]) if steps else 0,
        "steps_planned": int(steps[-1][1]) if steps else planned,
        "ended": "complete" if done else ("failed: " + ", ".join(failed) if failed else "stopped"),
    }


def job_minutes(lines) -> dict:
    """Rule -> wall minutes of each job the log saw start and finish."""
    started, out, stamp, rule = {}, {}, None, None
    for ln in (x.strip() for x in lines):
        if m := STAMP.match(ln):
            stamp = _time(m.group(1))
        elif m := re.match(r"^(?:local)?rule (\w+):$", ln):
            rule = m.group(1)
        elif (m := re.match(r"^jobid: (\d+)$", ln)) and rule:
            started[m.group(1)], rule = (rule, stamp), None
        elif (m := re.match(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$", ln)) and m.group(1) in started:
            name, begin = started.pop(m.group(1))
            out.setdefault(name, []).append((stamp - begin).total_seconds() / 60)
    return out


def planned_jobs(lines) -> dict:
    """Rule -> jobs, from the log's "Job stats" table."""
    start = next((i for i, ln in enumerate(lines) if ln.strip() == "Job stats:"), None)
    rows = {}
    for ln in lines[start + 1 :] if start is not None else []:
        if m := re.match(r"^(\w+)\s+(\d+)$", ln.strip()):
            if m.group(1) == "total":
                break
            rows[m.group(1)] = int(m.group(2))
    return rows


def remaining(logs, cores: int) -> dict:
    """What is left of a run: per rule, jobs not finished, mean job minutes, their wall minutes at ``cores``."""
    texts = [p.read_text(errors="replace").splitlines() for p in logs]
    plan = planned_jobs(texts[0])
    done = {}
    for lines in texts:
        for rule, mins in job_minutes(lines).items():
            done.setdefault(rule, []).extend(mins)
    rules, unknown = [], []
    for rule, n in plan.items():
        left = n - len(done.get(rule, []))
        if left <= 0 or rule == "all":
            continue
        if rule not in done:
            unknown.append(rule)
            continue
        mean = sum(done[rule]) / len(done[rule])
        rules.append({"rule": rule, "jobs_left": left, "mean_job_min": round(mean, 2), "wall_min": round(left * mean / cores, 1)})
    rules.sort(key=lambda r: -r["wall_min"])
    return {"cores": cores, "wall_min_known": round(sum(r["wall_min"] for r in rules), 1), "rules": rules, "rules_without_a_finished_job": unknown}


def asks_for(command: str | None, target: str) -> str | None:
    """What a logged command runs of ``target``'s run: ``target``, ``"subset"`` (outputs under ``results/``, or the
    target short of some jobs: ``--omit-from``, ``--until``), or None (a dry run, an unlock, another rule)."""
    words = (command or "").split()
    if {"-n", "--dry-run", "--dryrun", "--unlock"} & set(words):
        return None
    if target in words and not {"--omit-from", "--until"} & set(words):
        return target
    return "subset" if target in words or any(w.startswith("results/") for w in words) else None


def busy_minutes(parts: list[dict]) -> float:
    """The minutes in which some part was running: overlapping parts counted once."""
    spans = sorted((datetime.fromisoformat(p["start"]), datetime.fromisoformat(p["end"])) for p in parts if p["start"] and p["end"])
    total, reach = 0.0, None
    for a, b in spans:
        a = a if reach is None else max(a, reach)
        if b > a:
            total += (b - a).total_seconds()
        reach = b if reach is None else max(reach, b)
    return total / 60


def run_record(folder, target: str = "all") -> dict:
    """The record of the run of ``target`` in ``folder`` (see the module's docstring)."""
    folder = Path(folder)
    logs = sorted((folder / ".snakemake" / "log").glob("*.snakemake.log"))
    parts = [{**p, "targets": asks_for(p["command"], target)} for p in map(read_part, logs)]
    parts = [p for p in parts if p["targets"]]
    whole = [p for p in parts if p["targets"] == target]
    if not whole:
        raise SystemExit(f"{folder}: no Snakemake log of a run of {target!r} under .snakemake/log/")
    stages = stage_times(folder / "results" / "benchmarks")
    per_stage = []
    if not stages.empty:
        g = stages.groupby("stage")[["jobs", "wall_s", "cpu_s"]].sum().sort_values("wall_s", ascending=False)
        per_stage = [{"stage": s, "jobs": int(r.jobs), "job_min": round(r.wall_s / 60, 1), "cpu_min": round(r.cpu_s / 60, 1)} for s, r in g.iterrows()]
    record = {
        "target": target,
        "complete": whole[-1]["ended"] == "complete",
        "commits": sorted({p["commit"] for p in parts if p["commit"]}),
        "machines": sorted({p["machine"] for p in parts if p["machine"]}),
        "wall_min": round(busy_minutes(parts), 1),
        "jobs_finished": sum(p["jobs_finished"] for p in parts),
        "job_min": round(float(stages["wall_s"].sum()) / 60, 1) if not stages.empty else 0.0,
        "cpu_min": round(float(stages["cpu_s"].sum()) / 60, 1) if not stages.empty else 0.0,
        "parts": parts,
        "stages": per_stage,
    }
    if not record["complete"]:
        own = [folder / ".snakemake" / "log" / p["log"] for p in [whole[0]] + [p for p in parts if p is not whole[0]]]  # the plan: the first whole part's
        cores = re.search(r"--cores[ =](\d+)", whole[0]["command"] or "")
        record["remaining"] = remaining(own, int(cores.group(1)) if cores else 1)
    return record


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="the folder the run ran in (its .snakemake/log/ and results/benchmarks/)")
    ap.add_argument("--target", default="all", help="the target whose run to record (default: all)")
    ap.add_argument("--out", help="write the record here (default: print it)")
    args = ap.parse_args(argv)
    text = json.dumps(run_record(args.folder, args.target), indent=1) + "\n"
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)


if __name__ == "__main__":
    main()
