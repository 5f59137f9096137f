"""A config's ``device: cuda`` on a machine without a GPU: the job that trains stops at once, saying so.

The config is validated where the workflow starts (``device`` is one of auto, cpu, cuda), but
whether CUDA is present is a property of the machine a training job runs on (a cluster's GPU node,
not the login node), so it is checked there: at the start of training, before any output is written.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from latentsim.stages.autoencoder import train_autoencoder

pytestmark = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU: device cuda is valid here")


def _trajectories(path):
    """A scene's trajectories.h5 as far as the autoencoder stage reads it: 5 vertices, one prescribed, one training sequence."""
    g = np.random.default_rng(0)
    rest = g.normal(size=(5, 3))
    with h5py.File(path, "w") as f:
        f.attrs["model"] = "shell"
        f["rest_positions"], f["dirichlet"] = rest, np.array([0])
        s = f.create_group("sequences/walk")
        s.attrs["split"] = "train"
        x = rest + 0.01 * g.normal(size=(8, 5, 3))
        s["positions"], s["dirichlet_positions"], s["bc"] = x, x[:, :1], np.zeros((8, 6))
    return path


@pytest.mark.parametrize("device", ["cuda", "cuda:0"])
def test_device_cuda_without_a_gpu_stops_training_with_a_clear_message(device, tmp_path):
    settings = {"latent_dim": 2, "widths": [4], "epochs": 1, "batch_size": 4}
    model, latents = tmp_path / "autoencoder.pt", tmp_path / "latents.h5"
    with pytest.raises(ValueError, match=rf"device '{device}' requested but CUDA is not available"):
        train_autoencoder(_trajectories(tmp_path / "trajectories.h5"), settings, 0, device, model, latents)
    assert not model.exists() and not latents.exists()
    # the same settings on the CPU train: the message is about the device, nothing else
    train_autoencoder(tmp_path / "trajectories.h5", settings, 0, "cpu", model, latents)
    assert model.exists() and latents.exists()
