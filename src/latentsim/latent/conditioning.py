"""One latent integrator for a range of time steps and materials (beyond Li et al. 2025, whose
sec. 5 names both as limitations).

A scene's ``conditioning`` block gives a range of time steps h and of Young's moduli E.  The
conditioned integrator takes the condition c = (log h, log E), each mapped to [-1, 1] over its
range, as two more entries of every boundary-condition vector:

    z_t = I(z_{t-1}, z_{t-2}, [p_t, c], [p_{t-1}, c], [p_{t-2}, c]),

so the network, its runtime steppers and its export are those of the unconditioned integrator
with ``bc_dim`` = 6 + 2.  :class:`AtCondition` wraps it back into the 6-entry interface at one
condition, for the rollout and the stress tests.

The loss is the incremental potential at each sample's own condition: the scene's one potential
with a per-sample time step and a per-sample factor E / E_0 on its elastic energy (every elastic
term is linear in E at a fixed Poisson ratio).  Each training sample draws its condition
log-uniformly from the box; the Dirichlet targets of frame t follow from frame t-1's by the
boundary-condition program at that time step (:func:`latentsim.scene.dirichlet_step`).  A box
that is one point trains an unconditioned integrator at that condition: the per-condition
reference the conditioned one is measured against.

Sequences are written at the scene's own time step h_0; at a time step h the same motion in
physical time has ``k = h_0 / h`` times as many frames (:func:`scaled_sequence`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
from torch import nn

from latentsim.config import schema_defaults

#: the entries the condition appends to each boundary-condition vector
CONDITION_DIM = 2


@dataclass(frozen=True)
class Conditioning:
    """The box of conditions an integrator trains over, and the potential's own condition.

    Attributes
    ----------
    time_step : (lo, hi) [s].
    youngs_modulus : (lo, hi) [Pa].
    base_time_step, base_modulus : the time step and modulus the scene's potential is built with;
        a condition (h, E) evaluates it with time step h and elastic factor E / base_modulus.
    time_step_weight_power : a sample's loss is weighted by (h / base_time_step) to this power
        (the schema's ``conditioning.time_step_weight_power``).
    """

    time_step: tuple[float, float]
    youngs_modulus: tuple[float, float]
    base_time_step: float
    base_modulus: float
    time_step_weight_power: float = field(default_factory=lambda: float(schema_defaults("conditioning")["time_step_weight_power"]))

    def __post_init__(self):
        for name in ("time_step", "youngs_modulus"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise ValueError(f"conditioning.{name}: need 0 < lo <= hi, got [{lo}, {hi}]")
            object.__setattr__(self, name, (lo, hi))

    @classmethod
    def at(cls, time_step: float, modulus: float, base_time_step: float, base_modulus: float, **kw) -> "Conditioning":
        """The box of one condition: an unconditioned integrator trained there."""
        return cls((time_step, time_step), (modulus, modulus), base_time_step, base_modulus, **kw)

    @property
    def conditioned(self) -> bool:
        """Whether the integrator takes the condition as input (the box is more than one point)."""
        return self.time_step[0] < self.time_step[1] or self.youngs_modulus[0] < self.youngs_modulus[1]

    def normalise(self, time_step, modulus) -> torch.Tensor:
        """c (..., 2) float32 of conditions (time steps and moduli of one shape): log of each mapped
        to [-1, 1] over its range (0 for a range of one value)."""
        out = []
        for v, (lo, hi) in ((time_step, self.time_step), (modulus, self.youngs_modulus)):
            v = torch.as_tensor(v, dtype=torch.float64)
            span = math.log(hi) - math.log(lo)
            out.append(torch.zeros_like(v) if span == 0 else 2.0 * (torch.log(v) - math.log(lo)) / span - 1.0)
        return torch.stack(out, -1).to(torch.float32)

    def sample(self, n: int, generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """n conditions drawn log-uniformly from the box: time steps (n,) and moduli (n,), float64."""
        u = torch.rand((n, 2), generator=generator, dtype=torch.float64)
        out = []
        for j, (lo, hi) in enumerate((self.time_step, self.youngs_modulus)):
            out.append(torch.exp(math.log(lo) + u[:, j] * (math.log(hi) - math.log(lo))))
        return out[0], out[1]

    def contains(self, time_step: float, modulus: float, rtol: float = 1e-9) -> bool:
        """Whether (h, E) lies in the box."""
        (a, b), (c, d) = self.time_step, self.youngs_modulus
        return a * (1 - rtol) <= time_step <= b * (1 + rtol) and c * (1 - rtol) <= modulus <= d * (1 + rtol)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Conditioning":
        # a file written before the weight's power was a setting was trained with the schema's default
        kw = {"time_step_weight_power": float(d["time_step_weight_power"])} if "time_step_weight_power" in d else {}
        return cls(tuple(d["time_step"]), tuple(d["youngs_modulus"]), float(d["base_time_step"]), float(d["base_modulus"]), **kw)

    def weight(self, time_step: torch.Tensor) -> torch.Tensor:
        """Each sample's loss weight at time steps ``time_step``: (h / base_time_step)^power."""
        return (time_step / self.base_time_step) ** self.time_step_weight_power


def with_condition(p: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """[p, c]: boundary conditions (B, k) with each row's condition (B, 2) or one condition (2,)."""
    c = c.to(p.dtype).to(p.device)
    return torch.cat([p, c.expand(p.shape[0], -1) if c.ndim == 1 else c], -1)


class AtCondition(nn.Module):
    """A conditioned integrator at one condition, in the 6-entry interface of an unconditioned one:
    ``forward(z_prev, z_prev2, p, p_prev, p_prev2)`` appends the condition to each p."""

    def __init__(self, integrator: nn.Module, condition: torch.Tensor):
        super().__init__()
        self.integrator = integrator
        self.register_buffer("condition", torch.as_tensor(condition, dtype=torch.float32).reshape(-1))

    @property
    def out_std(self):
        return self.integrator.out_std

    @property
    def bc_dim(self) -> int:
        return self.integrator.bc_dim - CONDITION_DIM

    def forward(self, z_prev, z_prev2, p, p_prev, p_prev2):
        c = self.condition
        return self.integrator(z_prev, z_prev2, with_condition(p, c), with_condition(p_prev, c), with_condition(p_prev2, c))


def frame_factor(base_time_step: float, time_step: float) -> float:
    """k = h_0 / h: frames at time step h per frame at the scene's own h_0."""
    return float(base_time_step) / float(time_step)


def scaled_frame(frame: int, k: float) -> int:
    """The frame at time step h_0 / k where frame ``frame`` at h_0 begins: its step covers physical
    time from (frame - 1) h_0, which at h_0 / k is frame k (frame - 1) + 1 (rounded to the nearest
    frame; frame 0, the initial state, stays 0)."""
    return 0 if frame <= 0 else max(1, int(round(k * (frame - 1))) + 1)


def scaled_sequence(seq: dict, k: float) -> dict:
    """A sequence of the config written at the scene's time step h_0, as the same motion in physical
    time at h_0 / k: ``frames`` and ``train_frames`` cover the same time, each segment starts at the
    same time and ``reverse_every`` spans the same time (each rounded to the nearest frame)."""
    out = dict(seq)
    out["frames"] = int(round(k * (int(seq["frames"]) - 1))) + 1
    if seq.get("train_frames"):
        out["train_frames"] = int(round(k * (int(seq["train_frames"]) - 1))) + 1
    if seq.get("reverse_every"):
        out["reverse_every"] = max(1, int(round(k * int(seq["reverse_every"]))))
    if seq.get("segments"):
        out["segments"] = [{**s, "start": scaled_frame(int(s.get("start", 0)), k)} for s in seq["segments"]]
    return out
