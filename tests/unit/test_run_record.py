"""tools/run_record.py: a run's record from Snakemake's logs and benchmark files."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("run_record", ROOT / "tools" / "run_record.py")
run_record = importlib.util.module_from_spec(spec)
spec.loader.exec_module(run_record)


def _log(folder: Path, name: str, command: str, commit: str, events: list[str], total: int = 3):
    head = ["SNAKEMAKE", "=========", "  Date: 2026-12-05 02:00:00", f"  Command: {command}", "Job stats:", "job  count",
            f"total  {total}", "", f"latentsim commit: {commit}", "latentsim machine: Some CPU, 2 cpus"]  # fmt: skip
    path = folder / ".snakemake" / "log" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(head + events) + "\n")


def _bench(folder: Path, rel: str, s: float, cpu: float):
    path = folder / "results" / "benchmarks" / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"s\th:m:s\tmax_rss\tcpu_time\n{s}\t0:00:01\t1.0\t{cpu}\n")


def test_a_run_in_two_parts_is_recorded_part_by_part_and_in_all(tmp_path):
    cmd = "snakemake --cores 2 all --config progress=False"
    _log(tmp_path, "2026-12-05T020000.1.snakemake.log", cmd, "abc1234",
         ["[Sat Dec  5 02:00:05 2026]", "Finished jobid: 1 (Rule: simulate)", "1 of 3 steps (33.3%) done", "[Sat Dec  5 02:30:00 2026]"])
    _log(tmp_path, "2026-12-05T030000.1.snakemake.log", "snakemake -n all", "abc1234", [])  # a dry run: not a part
    _log(tmp_path, "2026-12-05T040000.1.snakemake.log", cmd, "def5678",
         ["[Sat Dec  5 04:10:00 2026]", "Finished jobid: 2 (Rule: train_integrator)", "2 of 2 steps (100%) done"])  # fmt: skip
    (tmp_path / ".snakemake/log/2026-12-05T040000.1.snakemake.log").write_text(
        (tmp_path / ".snakemake/log/2026-12-05T040000.1.snakemake.log").read_text().replace("Date: 2026-12-05 02:00:00", "Date: 2026-12-05 04:00:00"))
    _bench(tmp_path, "sim/cloth.tsv", 60.0, 50.0)
    _bench(tmp_path, "integrator/cloth/self_supervised/seed0.tsv", 600.0, 590.0)
    _bench(tmp_path, "integrator/cloth/self_supervised/seed1.tsv", 300.0, 280.0)
    rec = run_record.run_record(tmp_path)
    assert [p["commit"] for p in rec["parts"]] == ["abc1234", "def5678"] and rec["commits"] == ["abc1234", "def5678"]
    assert [p["wall_min"] for p in rec["parts"]] == [30.0, 10.0] and rec["wall_min"] == 40.0
    assert [p["ended"] for p in rec["parts"]] == ["stopped", "complete"] and rec["complete"]
    assert rec["jobs_finished"] == 2 and rec["parts"][0]["steps_planned"] == 3 and rec["machines"] == ["Some CPU, 2 cpus"]
    assert rec["stages"][0] == {"stage": "integrator", "jobs": 2, "job_min": 15.0, "cpu_min": 14.5}
    assert rec["job_min"] == 16.0 and rec["cpu_min"] == pytest.approx(15.3)
    out = tmp_path / "docs" / "all.json"
    run_record.main([str(tmp_path), "--out", str(out)])
    assert json.loads(out.read_text()) == rec


def test_a_failed_part_names_its_rules_and_a_folder_without_a_run_is_refused(tmp_path):
    _log(tmp_path, "a.snakemake.log", "snakemake --cores 2 all", "abc1234",
         ["[Sat Dec  5 02:10:00 2026]", "Error in rule evaluate:", "    jobid: 4", "Error in rule summary:"])  # fmt: skip
    assert run_record.run_record(tmp_path)["parts"][0]["ended"] == "failed: evaluate, summary"
    with pytest.raises(SystemExit, match="no Snakemake log of a run of 'sizing'"):
        run_record.run_record(tmp_path, "sizing")


def test_an_unfinished_run_estimates_what_is_left_from_its_finished_jobs(tmp_path):
    def job(stamp, rule, jobid):
        return [f"[Sat Dec  5 {stamp} 2026]", f"rule {rule}:", "    output: x", f"    jobid: {jobid}"]

    def done(stamp, rule, jobid):
        return [f"[Sat Dec  5 {stamp} 2026]", f"Finished jobid: {jobid} (Rule: {rule})"]

    events = job("02:00:00", "simulate", 1) + job("02:00:00", "simulate", 2) + done("02:04:00", "simulate", 1)
    events += done("02:06:00", "simulate", 2) + job("02:06:00", "train_integrator", 3) + done("02:16:00", "train_integrator", 3)
    events += job("02:16:00", "train_integrator", 4)  # started, not finished: still left
    path = tmp_path / ".snakemake" / "log" / "a.snakemake.log"
    _log(tmp_path, "a.snakemake.log", "snakemake --cores 2 all", "abc1234", events)
    path.write_text(path.read_text().replace("job  count\n", "job  count\nsimulate  3\ntrain_integrator  5\nevaluate  2\n"))
    rest = run_record.run_record(tmp_path)["remaining"]
    assert rest["cores"] == 2 and rest["rules_without_a_finished_job"] == ["evaluate"]
    # train_integrator: 4 left of 5 at 10 min each, two at a time; simulate: 1 left at (4 + 6) / 2 min
    assert rest["rules"] == [
        {"rule": "train_integrator", "jobs_left": 4, "mean_job_min": 10.0, "wall_min": 20.0},
        {"rule": "simulate", "jobs_left": 1, "mean_job_min": 5.0, "wall_min": 2.5},
    ]
    assert rest["wall_min_known"] == 22.5


def test_a_part_that_redoes_some_files_counts_its_jobs_once_in_the_wall_time_and_not_as_completion(tmp_path):
    """A part that rebuilds some of the run's outputs (what a change touched) beside a part of the whole target: its jobs
    count, the minutes both ran count once, and its completion is not the target's; unlocks and other rules are no parts."""
    cmd = "snakemake --cores 2 all --config progress=False"
    _log(tmp_path, "2026-12-05T020000.1.snakemake.log", cmd, "abc1234",
         ["[Sat Dec  5 02:00:05 2026]", "Finished jobid: 1 (Rule: simulate)", "1 of 3 steps (33.3%) done", "[Sat Dec  5 03:00:00 2026]"])
    files = "snakemake --cores 1 results/evaluation/cloth/metrics.csv --nolock"
    _log(tmp_path, "2026-12-05T023000.1.snakemake.log", files, "def5678",
         ["[Sat Dec  5 03:30:00 2026]", "Finished jobid: 4 (Rule: evaluate)", "1 of 1 steps (100%) done"])  # fmt: skip
    path = tmp_path / ".snakemake/log/2026-12-05T023000.1.snakemake.log"
    path.write_text(path.read_text().replace("Date: 2026-12-05 02:00:00", "Date: 2026-12-05 02:30:00"))
    _log(tmp_path, "2026-12-05T050000.1.snakemake.log", "snakemake --unlock --cores 1", "def5678", ["[Sat Dec  5 05:00:00 2026]"])
    _log(tmp_path, "2026-12-05T060000.1.snakemake.log", "snakemake --cores 2 sizing", "def5678", ["[Sat Dec  5 06:00:00 2026]"])
    rec = run_record.run_record(tmp_path)
    assert [p["targets"] for p in rec["parts"]] == ["all", "subset"]
    assert [p["wall_min"] for p in rec["parts"]] == [60.0, 60.0] and rec["wall_min"] == 90.0  # 02:00-03:30, not 120
    assert rec["jobs_finished"] == 2 and not rec["complete"] and rec["commits"] == ["abc1234", "def5678"]
    assert run_record.busy_minutes(rec["parts"][:1]) == 60.0
    assert run_record.asks_for("snakemake --cores 2 all --omit-from results/a.pt", "all") == "subset"  # all short of some jobs
