"""A corrupt artefact in a finished run: the job that reads it stops naming the file, and the same command
plans the job that writes it again (on a copy of the shared tiny run, which other tests read)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

from latentsim.io import open_artefact

from workflow_support import TINY_COMMAND


def copy_of_run(work, dest):
    """The finished run ``work`` (results and Snakemake's records) copied to ``dest``, ``../shared`` beside it."""
    copy = dest / "latentsim"
    shutil.copytree(work, copy, symlinks=True)
    if (work.parent / "shared").exists():
        (dest / "shared").symlink_to((work.parent / "shared").resolve(), target_is_directory=True)
    return copy


def run(command, cwd):
    """``command`` as a user types it (as ``workflow_support.shell``), its failure returned, not raised."""
    env = dict(os.environ, CI="1", PATH=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    return subprocess.run(["bash", "-c", command], cwd=cwd, capture_output=True, text=True, env=env)


def test_a_truncated_trajectories_file_stops_its_reader_and_the_same_command_plans_it_anew(tiny_run, tmp_path):
    """The reader names the file and moves it aside; the same command then plans the simulation and its readers
    again (a dry run: rerunning them all is Snakemake's own business and would rerun the whole scene), and the
    simulation job writes the same frames."""
    work = copy_of_run(tiny_run[0], tmp_path)
    rel = "results/sim/tiny_rods/trajectories.h5"
    path = work / rel
    with h5py.File(path, "r") as f:
        before = f["sequences/test_mid/positions"][()]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # as a full disk or an interrupted copy leaves it

    command = TINY_COMMAND  # snakemake --cores 2 all ...: the truncated file is newer, so its readers rerun
    first = run(command, work)
    assert first.returncode != 0
    assert f"{rel}: corrupt artefact" in first.stderr, first.stderr[-3000:]  # the path as the rule names it
    assert "truncated" in first.stderr and "the same snakemake command run again writes it anew" in first.stderr
    assert not path.exists() and (work / (rel + ".corrupt")).exists()

    plan = run(command + " -n", work)
    assert plan.returncode == 0, plan.stderr[-3000:]
    planned = plan.stdout
    assert re.search(rf"output: [^\n]*{re.escape(rel)}", planned), planned[-3000:]  # the producer, then its readers
    assert "results/autoencoder/tiny_rods/seed0/autoencoder.pt" in planned and "results/evaluation/summary.csv" in planned

    second = run(f"snakemake --cores 2 {rel} --configfile config/tiny.yaml", work)
    assert second.returncode == 0, second.stderr[-3000:]
    with open_artefact(path) as f:
        after = f["sequences/test_mid/positions"][()]
    scale = np.abs(before).max()
    np.testing.assert_allclose(after, before, rtol=0, atol=1e-9 * scale)


def test_a_damaged_runtime_or_table_is_named_moved_aside_and_planned_again_by_all(tiny_run, tmp_path):
    """What a user loads and what the summary reads: a runtime.pt with a flipped weight byte and a metrics table with
    a row removed are named and moved aside by their readers; `all` then plans the jobs that write them again."""
    import pandas as pd
    import pytest

    from latentsim import runtime
    from latentsim.checksum import ArtefactError
    from latentsim.io import read_csv

    work = copy_of_run(tiny_run[0], tmp_path)
    folder = work / "results/rollout/tiny_rods/self_supervised/seed0"
    program = folder / "runtime.pt"
    data = bytearray(program.read_bytes())
    with open(program, "rb") as f:
        import torch

        weights = [t for t in torch.export.load(f).state_dict.values() if t.numel() >= 8]
    at = data.find(weights[0].detach().numpy().tobytes()[:32])
    data[at + 1] ^= 0x40
    program.write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match="runtime.pt: corrupt artefact"):
        runtime.load_program(program)
    (folder / "runtime.npz").rename(folder / "runtime.npz.corrupt")  # as runtime.load moves a damaged one aside
    table = work / "results/evaluation/tiny_cloth/metrics.csv"
    text = table.read_text().splitlines()
    table.write_text("\n".join(text[:-1]) + "\n")
    with pytest.raises(ArtefactError, match="metrics.csv: corrupt artefact"):
        read_csv(table)
    assert not program.exists() and not table.exists()
    plan = run("snakemake -n all --configfile config/tiny.yaml", work)
    assert plan.returncode == 0, plan.stderr[-3000:]
    out = plan.stdout
    assert "results/rollout/tiny_rods/self_supervised/seed0/runtime.pt" in out and "results/evaluation/tiny_cloth/metrics.csv" in out
    assert isinstance(pd.read_csv(work / "results/evaluation/summary.csv"), pd.DataFrame)
