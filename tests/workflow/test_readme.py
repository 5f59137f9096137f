"""The README's commands, as written: every one is either run here or named with the reason it is not.

The quick ones run in the tiny run's copy of the repository (``conftest.tiny_run``, itself the
README's tiny command), in the README's order.
"""

from __future__ import annotations

import re
import shutil
import subprocess

import torch
from workflow_support import ROOT, TINY_COMMAND, shell

README = ROOT / "README.md"

# Commands the README shows that this test does not run, and why.
NOT_RUN = {
    "pip install -r envs/requirements.txt -e .": "the install: .ci/run runs it before the tests",
    "snakemake --cores 2 all": "the default run takes hours; its dry run is run below and in test_workflow",
    "snakemake --cores 2 sizing": "the default config's sweeps take hours; the tiny run's sweep (sizing_in_all) runs the same rules, "
                                  "and test_workflow dry-runs the target",
    "snakemake --report report.html": "needs the default run's results; the tiny run's report is built below",
    "snakemake --cores 2 all --configfile config/examples/ring.yaml": "run by test_example_scene.py",
    "snakemake --cores 2 all --configfile config/my_part.yaml": "the same run as the example's, in test_example_scene.py",
    "snakemake --workflow-profile profiles/slurm all": "needs a SLURM cluster; test_workflow dry-runs the profile",
    "python -m pytest -q -n auto --dist loadgroup tests": "the test command itself",
    "python -m pytest -q tests": "the test command itself, on one process",
    "python tools/run_record.py FOLDER": "needs a run's folder; tests/unit/test_run_record.py runs it on a made-up two-part run",
    "snakemake --cores 2 results/evaluation/cloth_paper/metrics.csv results/evaluation/cantilever_paper/metrics.csv":
        "the Fig. 8 scenes over five seeds take 24 min; the tiny run's two-seed scene checks the same rules, tables and claims",
    'python -m pytest -q -m "not slow" tests': "a part of the test command itself",
    "snakemake --cores 2 results/conditioned/cloth/summary.md results/conditioned/cantilever/summary.md":
        "the two conditioned scenes over three seeds take about 45 min; the tiny run's tiny_cloth runs the same rules",
    "snakemake --cores 2 results/evaluation/{cloth_sphere,cantilever_floor,hair_head,bunny_drop,cloth_drape,cloth_fold}/metrics.csv":
        "the six contact scenes over three seeds take over an hour (cloth_drape's and cloth_fold's integrators the longest); the tiny run's tiny_contact runs the same rules",
}
if not torch.cuda.is_available():
    NOT_RUN["snakemake --cores 2 all --config device=cuda"] = "needs a GPU; test_latent checks the error without one"

# Commands run after the tiny run, in this order, each with a check of what it made.
RUN = [
    TINY_COMMAND,
    "snakemake --report report.html --configfile config/tiny.yaml",
    "snakemake -n all",
    "python tools/readme_glance.py",
    "python tools/readme_claims.py",
    "snakemake -n all --configfile config/tiny.yaml --config seeds=nan",
    "snakemake --unlock",
    "python examples/step_trained_model.py",
    "python config/examples/make_mesh.py",
    "cp config/examples/ring.yaml config/my_part.yaml",
    "snakemake --cores 1 results/mesh/ring/mesh.h5 --configfile config/my_part.yaml",
    "grep quality logs/mesh/ring.log",
]


def readme_commands(text: str) -> list[str]:
    """Every command the README shows: each line of its ``bash`` blocks, and inline ``snakemake ...``/``python ...``."""
    out = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        out += [line.split("  #")[0].strip() for line in block.splitlines() if line.strip() and not line.startswith("#")]
    out += re.findall(r"`((?:snakemake|python) [^`]+)`", text)
    return list(dict.fromkeys(out))


def test_every_readme_command_is_run_or_has_a_reason():
    shown = readme_commands(README.read_text())
    assert TINY_COMMAND in shown
    unclassified = [c for c in shown if c not in NOT_RUN and c not in RUN]
    assert not unclassified, f"README commands neither run by this test nor listed in NOT_RUN: {unclassified}"
    gone = [c for c in [*NOT_RUN, *RUN] if c not in shown and "device=cuda" not in c]
    assert not gone, f"listed here but no longer in the README: {gone}"


def test_the_example_scene_test_runs_the_readme_command():
    assert "config/examples/ring.yaml" in (ROOT / "tests" / "workflow" / "test_example_scene.py").read_text()


def test_readme_quick_commands_run_as_written(tiny_run, tmp_path):
    # on a copy of the tiny run: these commands add files (a report, another scene's mesh) that the other
    # tests of the shared run must not see
    work = tmp_path / "latentsim"
    shutil.copytree(tiny_run[0], work, symlinks=True)
    shared = tiny_run[0].parent / "shared"
    if shared.exists():
        (tmp_path / "shared").symlink_to(shared.resolve(), target_is_directory=True)
    # the copy has no history: make it a checkout of its own, so the glance script can name its commit
    subprocess.run("git init -q && git add -A && git -c user.name=t -c user.email=t@t commit -qm copy",
                   shell=True, cwd=work, check=True, capture_output=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=work, capture_output=True, text=True).stdout.strip()
    for command in RUN[1:]:
        fails = "seeds=nan" in command  # shown as an example of the error
        out = shell(command, work, check=not fails)
        if fails:
            assert out.returncode != 0 and "config key 'seeds': nan is not a finite number" in out.stdout + out.stderr
            assert "Job stats" not in out.stdout + out.stderr  # stopped before planning any job
        elif "--report" in command:
            html = (work / "report.html").read_text(errors="replace")
            assert len(html) > 100_000 and "tiny_cloth" in html
        elif command.startswith("snakemake -n"):
            assert "rule train_integrator" in out.stdout and "This was a dry-run" in out.stdout
        elif "readme_glance" in command:
            text = (work / "README.md").read_text()
            block = text.split("glance: begin", 1)[1].split("glance: end", 1)[0]
            assert f"at commit {commit}" in block
            assert all(s in block for s in ("| tiny_cloth |", "| tiny_rods |", "| tiny_nm |"))
            assert shell("python tools/readme_glance.py --check", work).returncode == 0
        elif "readme_claims" in command:  # tiny_rods runs two seeds
            block = (work / "README.md").read_text().split("claims: begin", 1)[1].split("claims: end", 1)[0]
            assert f"at commit {commit}" in block and "results/evaluation/tiny_rods/metrics.csv" in block
            assert "- tiny_rods, self_supervised: mean error" in block and "every test sequence in 2 of 2 seeds" in block
            assert "tiny_cloth" not in block  # one seed: nothing to state over seeds
            assert shell("python tools/readme_claims.py --check", work).returncode == 0
        elif "make_mesh" in command:
            assert shell("git diff --quiet -- config/examples/ring.stl", work).returncode == 0  # the same bytes
        elif command == "snakemake --unlock":
            assert "Unlocked working directory" in out.stdout + out.stderr
        elif command.startswith("grep quality"):
            assert "vertices" in out.stdout
        elif "step_trained_model" in command:
            assert "torch.export" in out.stdout and "error" in out.stdout


def test_readme_python_snippet_runs_on_the_tiny_run(tiny_run, monkeypatch):
    """The README's ``python`` block, given a test sequence's frames, steps the tiny rods' model."""
    import h5py
    import numpy as np

    work, _ = tiny_run
    (snippet,) = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    with h5py.File(work / "results/sim/tiny_rods/trajectories.h5", "r") as f:
        seq = next(g for g in f["sequences"].values() if g.attrs["split"] == "test")
        x = seq["positions"][()]
        names = {"x0": x[0], "x1": x[1], "xD": seq["dirichlet_positions"][()], "p": seq["bc"][()]}
    monkeypatch.chdir(work)
    exec(compile(snippet, "README.md", "exec"), names)
    x2 = names["x2"]
    assert x2.shape == x[2].shape and np.isfinite(x2).all()
    extent = np.ptp(x.reshape(-1, 3), axis=0).max()
    assert np.abs(x2 - x[2]).max() < 0.2 * extent  # a learned step near the simulated frame, not garbage
