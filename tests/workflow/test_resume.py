"""A training killed by SIGKILL resumes, through Snakemake, to the uninterrupted result; a training
that diverges writes nothing a later run takes as complete.

The scene is the tiny config's ``tiny_rods`` alone, its integrator trained for 600 epochs (a few
seconds) so that the kill lands between its first checkpoint (every 10 epochs) and its end.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
import torch
import yaml
from workflow_support import HANG_SECONDS, ROOT

TINY = ROOT / "config" / "tiny.yaml"
INTEGRATOR = "results/integrator/tiny_rods/self_supervised/seed0"


def snakemake(work, *args, check=True):
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--configfile", str(work / "config.yaml"), "--directory", str(work), *args]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=HANG_SECONDS, env=dict(os.environ, CI="1"), check=False)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def rods(tmp_path_factory):
    """A folder with a one-scene config (tiny_rods, integrator 600 epochs) and its simulation and
    autoencoder already run."""
    work = tmp_path_factory.mktemp("resume")
    config = yaml.safe_load(TINY.read_text())
    scene = config["scenes"]["tiny_rods"]
    scene["variants"] = []
    scene["integrator"]["epochs"] = 600
    config.update(scenes={"tiny_rods": scene}, integrator_variants={}, progress=False)
    (work / "config.yaml").write_text(yaml.safe_dump(config))
    snakemake(work, "results/autoencoder/tiny_rods/seed0/autoencoder.pt")
    return work


def weights(path):
    return torch.load(path, map_location="cpu", weights_only=True)["state_dict"]


def test_a_killed_training_resumes_to_the_uninterrupted_result(rods):
    """SIGKILL to the whole Snakemake process group after the first checkpoint: no output is left,
    the checkpoint is; the next run is refused until ``--unlock`` (Snakemake says so), then resumes
    from the checkpoint (the profile's ``rerun-incomplete``) and ends with the weights of an
    uninterrupted training (bitwise: the CPU training is deterministic on one machine), recording
    the killed run's training time up to its checkpoint plus its own."""
    work, out = rods, rods / INTEGRATOR
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--configfile", str(work / "config.yaml"),
           "--directory", str(work), f"{INTEGRATOR}/integrator.pt"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True, env=dict(os.environ, CI="1"))
    try:
        deadline = time.time() + 900  # only bounds a hang
        while time.time() < deadline and proc.poll() is None and not (out / "checkpoint.pt").exists():
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert (out / "checkpoint.pt").exists(), "the training never wrote its checkpoint"
    assert not (out / "integrator.pt").exists() and not (out / "history.h5").exists(), "the training ended before the kill"
    killed = torch.load(out / "checkpoint.pt", weights_only=True)
    assert 10 <= killed["epoch"] < 600 and killed["train_seconds"] > 0

    refused = snakemake(work, f"{INTEGRATOR}/integrator.pt", check=False)
    assert refused.returncode != 0 and "--unlock" in refused.stdout + refused.stderr
    snakemake(work, "--unlock")
    resumed = snakemake(work, f"{INTEGRATOR}/integrator.pt")
    log = (work / "logs/integrator/tiny_rods/self_supervised/seed0.log").read_text()
    assert f"at epoch {killed['epoch']} (" in log
    assert not (out / "checkpoint.pt").exists()  # served its purpose
    with h5py.File(out / "history.h5") as f:
        start, seconds, loss = int(f.attrs["start_epoch"]), float(f.attrs["train_seconds"]), f["loss"][()]
    assert start == killed["epoch"] and len(loss) == 600
    assert seconds > killed["train_seconds"]  # the killed part and the resumed part, not the latter alone
    w_resumed = weights(out / "integrator.pt")

    snakemake(work, f"{INTEGRATOR}/integrator.pt", "--forcerun", "train_integrator")
    with h5py.File(out / "history.h5") as f:
        assert int(f.attrs["start_epoch"]) == 0
        assert np.array_equal(f["loss"][()], loss)
    w_fresh = weights(out / "integrator.pt")
    assert w_fresh.keys() == w_resumed.keys() and all(torch.equal(w_fresh[k], w_resumed[k]) for k in w_fresh)
    assert resumed.returncode == 0


def test_a_diverged_training_writes_no_output(rods, tmp_path):
    """Learning rate 1e3 on the stage: TrainingDiverged names scene, method, epoch and loss; neither
    output nor a checkpoint of the diverged epoch exists (the unit tests show an earlier good
    checkpoint left as it was)."""
    from latentsim.latent.base import TrainingDiverged
    from latentsim.stages.integrator import train_integrator

    config = yaml.safe_load((rods / "config.yaml").read_text())
    settings = {**config["scenes"]["tiny_rods"]["integrator"], "lr": 1e3}
    args = (rods / "results/sim/tiny_rods/trajectories.h5", rods / "results/autoencoder/tiny_rods/seed0/autoencoder.pt", settings, 0, "cpu")
    with pytest.raises(TrainingDiverged, match=r"^scene tiny_rods, method self_supervised: training diverged in epoch 1: loss \S+ far above its start"):
        train_integrator(*args, tmp_path / "integrator.pt", tmp_path / "history.h5", checkpoint=tmp_path / "checkpoint.pt", label="scene tiny_rods, method self_supervised")
    assert not any(tmp_path.iterdir())
