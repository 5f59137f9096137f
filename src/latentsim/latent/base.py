"""What the latent modules share: the device a network trains on, the error a diverged
training raises, the minibatch order, and a potential moved to a device.

Li et al. 2025 train two networks (the autoencoder, sec. 3.2, and the latent integrator,
sec. 3.3) by the same minibatch loop; these are its common parts.
"""

from __future__ import annotations

import copy
import math

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
    """A training diverged: a loss or gradient became NaN/inf, or the training failed the health
    rule of :class:`LossHealth` (an epoch's loss far above its start or above a configured bound,
    or the integrator's predicted latents far outside the training range).

    Attributes
    ----------
    epoch : 1-based epoch in which it happened.
    batch : 0-based minibatch index within that epoch (-1: the epoch as a whole).
    value : the offending value (the epoch's mean loss, the largest latent distance), or None.
    label : what trained (e.g. "scene tiny_rods, method self_supervised"), set by the training
        function that knows it; it opens the message.
    """

    def __init__(self, epoch: int, batch: int = -1, what: str = "loss", value: float | None = None, detail: str = "", label: str = ""):
        self.epoch = int(epoch)
        self.batch = int(batch)
        self.value = None if value is None else float(value)
        self.label = label
        if detail:
            self.reason = f"training diverged in epoch {self.epoch}: {detail}"
        else:
            self.reason = f"training diverged: non-finite {what} in epoch {self.epoch}" + (f", batch {self.batch}" if self.batch >= 0 else "")
        super().__init__(self.reason)

    def __str__(self) -> str:
        return (f"{self.label}: " if self.label else "") + self.reason + " (last good checkpoint, if any, left intact; nothing else written)"


class PlateauStop:
    """The end of a training whose loss has stopped falling (``plateau_stop``; supervised trainings only).

    After epoch e (losses L_0 .. L_e, e + 1 >= 2 w), the training ends when the least loss of the last
    w epochs is not ``tolerance`` (relative) below the least before them:

        min(L_{e-w+1} .. L_e) > min(L_0 .. L_{e-w}) - tolerance |min(L_0 .. L_{e-w})|.

    The rule reads the loss history alone, so a training resumed from a checkpoint ends at the same
    epoch as one that ran through.  Not for the energy losses: the cantilever's self-supervised loss
    flattens within 25 epochs while its test error keeps falling tenfold.

    Parameters
    ----------
    window : w (>= 1).
    tolerance : the relative fall that counts as progress (>= 0).
    """

    def __init__(self, window: int, tolerance: float):
        self.window, self.tolerance = int(window), float(tolerance)

    @classmethod
    def of(cls, setting: dict | None) -> "PlateauStop | None":
        """The rule of a ``plateau_stop`` setting, or None for null."""
        return None if setting is None else cls(setting["window"], setting["tolerance"])

    def reached(self, losses) -> bool:
        """Whether the training whose epoch losses are ``losses`` (in order) ends here."""
        w = self.window
        if len(losses) < 2 * w:
            return False
        before, recent = min(losses[:-w]), min(losses[-w:])
        return recent > before - self.tolerance * abs(before)


class LossHealth:
    """The health rule of a training loss, checked after every epoch; an epoch that breaks it raises
    :class:`TrainingDiverged` (before the epoch's checkpoint is written, so the one on disk is the
    last good one).

    The loss may be an energy (the self-supervised integrator's loss is the incremental potential,
    negative on a healthy run), so it is judged against its own start and scale, measured on the
    first minibatch before any update (the untrained network's loss ``start``, and ``scale`` = the
    largest of |start|, the standard deviation of that minibatch's per-sample losses, and
    ``floor``).  An epoch diverged when its mean loss L satisfies

        L > start + factor * scale      (``factor``: the settings' ``divergence_factor``)
        or L > max_loss                 (``max_loss``: an absolute bound, None: none).

    A healthy training lowers its loss from the start, and no epoch's mean strays far above it (the
    tiny config's integrators: at most 0.18 of a scale above their start), while a training that
    blows up without a NaN ends many orders of magnitude above it (learning rate 1e3: 1e20 in the
    first epoch).  The autoencoder's normalised loss starts near zero at its PCA initialisation and
    may rise under SGD noise (the tiny config: to 0.014); its ``floor`` 0.01 puts the bound at no
    less than start + 1 at the default factor, the loss of decoding every frame to the data's mean
    being at most 1 (the loss is normalised by the largest principal standard deviation).

    Parameters
    ----------
    factor : divergence_factor (> 0).
    max_loss : the absolute bound, or None.
    floor : the least scale (a loss with a natural unit, e.g. the autoencoder's normalised MSE).
    key : the settings block named in the message ("integrator", "autoencoder").
    """

    def __init__(self, factor: float, max_loss: float | None = None, floor: float = 0.0, key: str = "integrator"):
        self.factor, self.max_loss, self.floor, self.key = float(factor), max_loss, float(floor), key
        self.start: float | None = None
        self.scale: float | None = None

    def first_batch(self, loss: float, per_sample: torch.Tensor) -> None:
        """Record the start and scale from the first minibatch (only once: a resumed training keeps
        those of its first run, :meth:`state`)."""
        if self.start is not None:
            return
        spread = float(per_sample.detach().double().std(unbiased=False)) if per_sample.numel() > 1 else 0.0
        self.start = float(loss)
        self.scale = max(abs(self.start), spread if math.isfinite(spread) else 0.0, self.floor)

    def state(self) -> dict:
        """{"loss_start", "loss_scale"} for a checkpoint or the history."""
        return {"loss_start": self.start, "loss_scale": self.scale}

    def load(self, state: dict) -> None:
        self.start, self.scale = state.get("loss_start"), state.get("loss_scale")

    def bound(self) -> float:
        """The largest healthy epoch loss (inf before the first minibatch)."""
        b = math.inf if self.start is None else self.start + self.factor * self.scale
        return min(b, float(self.max_loss)) if self.max_loss is not None else b

    def check(self, epoch: int, loss: float) -> None:
        """Raise TrainingDiverged when the 0-based ``epoch``'s mean loss breaks the rule."""
        if self.max_loss is not None and loss > float(self.max_loss):
            raise TrainingDiverged(epoch + 1, value=loss, detail=f"loss {loss:.4g} above {self.key}.max_loss = {float(self.max_loss):.4g}")
        if self.start is not None and loss > self.start + self.factor * self.scale:
            raise TrainingDiverged(
                epoch + 1, value=loss,
                detail=(f"loss {loss:.4g} far above its start {self.start:.4g} (more than {self.key}.divergence_factor = {self.factor:g} "
                        f"times the loss's scale {self.scale:.4g}: bound {self.start + self.factor * self.scale:.4g})"),
            )  # fmt: skip


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

