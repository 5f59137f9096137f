"""What the latent modules share: the device a network trains on, the error a diverged
training raises, the minibatch order, and a potential moved to a device.

Li et al. 2025 train two networks (the autoencoder, sec. 3.2, and the latent integrator,
sec. 3.3) by the same minibatch loop; these are its common parts.
"""

from __future__ import annotations

import copy

import torch


def resolve_device(spec: str | torch.device = "auto") -> torch.device:
    """Turn ``"auto" | "cpu" | "cuda" | "cuda:N"`` into a :class:`torch.device`.

    ``"auto"`` picks CUDA when available, else the CPU.  Raises ``ValueError``
    for unknown strings and when CUDA is requested but not available.
    """
    if isinstance(spec, torch.device):
        spec = str(spec)
    if not isinstance(spec, str):
        raise ValueError(f"device must be a string such as 'auto', 'cpu', 'cuda'; got {spec!r}")
    s = spec.strip().lower()
    if s == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if s == "cpu":
        return torch.device("cpu")
    if s == "cuda" or (s.startswith("cuda:") and s[5:].isdigit()):
        if not torch.cuda.is_available():
            raise ValueError(f"device {spec!r} requested but CUDA is not available")
        dev = torch.device(s)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {spec!r} requested but only {torch.cuda.device_count()} CUDA device(s) exist")
        return dev
    raise ValueError(f"unknown device {spec!r}: use 'auto', 'cpu', 'cuda' or 'cuda:N'")


class TrainingDiverged(RuntimeError):
    """A training loss (or gradient) became NaN/inf.

    Attributes
    ----------
    epoch : 1-based epoch in which the non-finite value appeared.
    batch : 0-based minibatch index within that epoch.
    """

    def __init__(self, epoch: int, batch: int = -1, what: str = "loss"):
        self.epoch = int(epoch)
        self.batch = int(batch)
        super().__init__(
            f"training diverged: non-finite {what} in epoch {self.epoch}"
            + (f", batch {self.batch}" if self.batch >= 0 else "")
            + " (last good checkpoint, if any, left intact)"
        )


def minibatches(N: int, batch_size: int, gen: torch.Generator, min_size: int = 1) -> list[torch.Tensor]:
    """A random permutation of ``range(N)`` drawn from ``gen``, cut into minibatches of
    ``batch_size`` rows; a last batch of fewer than ``min_size`` rows is dropped."""
    perm = torch.randperm(N, generator=gen)
    out = [perm[i : i + batch_size] for i in range(0, N, batch_size)]
    if len(out) > 1 and out[-1].numel() < min_size:
        out = out[:-1]  # BatchNorm cannot train on a single sample
    return out


def potential_on(potential, device: torch.device):
    """A copy of the potential with every tensor attribute on ``device`` (the potential itself
    when it is there already)."""
    if potential.masses.device == device:
        return potential
    if hasattr(potential, "to"):
        return potential.to(device)

    def moved(obj):
        new = copy.copy(obj)
        for k, v in vars(obj).items():
            if torch.is_tensor(v):
                setattr(new, k, v.to(device))
        return new

    pot = moved(potential)
    if hasattr(pot, "terms"):
        pot.terms = [moved(t) for t in potential.terms]
    return pot

