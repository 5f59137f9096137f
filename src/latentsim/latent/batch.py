"""The latent integrator's training rows as typed records: :class:`Triplets`, the rows of a training
set (the ground truth's of :func:`~latentsim.latent.data.build_triplets`, or those of the
integrator's own rollouts), and :class:`Batch`, a minibatch as the loss takes it, with what a
training feature adds to each sample (its condition's time step, elastic factor and weight; its
balancing weight computed beforehand).

A field left ``None`` is a feature not in use; :meth:`Triplets.fields` gives those in use.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Mapping

import torch

from latentsim.latent.data import BATCH_KEYS


@dataclass(frozen=True, eq=False)
class Triplets:
    """Rows of ground-truth or rolled-out triplets, N each.

    Attributes
    ----------
    z, z_prev, z_prev2 : (N, r) the latents of frames t, t-1, t-2 (``z`` the ground truth's; the
        recorded frame's where the row was rolled out at another speed or condition).
    p, p_prev, p_prev2 : (N, k) the frames' boundary-condition vectors.
    xD, xD_prev, xD_prev2 : (N, m, 3) the frames' Dirichlet targets (float64).
    condition : None, or (N, 2) the condition (h, E) a row was rolled out at, its loss to be
        taken there (NaN: none, the minibatch draws one; :mod:`latentsim.latent.conditioning`).
    speed : None, or (N,) the factor on the program a row was rolled out under.
    balance : None, or (N,) each row's balancing weight computed beforehand
        (:func:`~latentsim.latent.loss.fixed_balancing_weights`).
    """

    z: torch.Tensor
    z_prev: torch.Tensor
    z_prev2: torch.Tensor
    p: torch.Tensor
    p_prev: torch.Tensor
    p_prev2: torch.Tensor
    xD: torch.Tensor
    xD_prev: torch.Tensor
    xD_prev2: torch.Tensor
    condition: torch.Tensor | None = None
    speed: torch.Tensor | None = None
    balance: torch.Tensor | None = None

    @classmethod
    def of(cls, rows: "Triplets | Mapping[str, torch.Tensor]"):
        """``rows`` as this type: a record of it as it is, another record's fields or a dict of
        tensors (the keys of :data:`~latentsim.latent.data.BATCH_KEYS` and of the optional fields)
        into it."""
        if isinstance(rows, cls):
            return rows
        return cls(**(rows.fields() if isinstance(rows, Triplets) else dict(rows)))

    def __len__(self) -> int:
        return self.z.shape[0]

    def fields(self) -> dict[str, torch.Tensor]:
        """The fields in use (not None), by name, in declaration order."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]):
        """The record with ``fn`` applied to each field in use."""
        return dataclasses.replace(self, **{k: fn(v) for k, v in self.fields().items()})

    def rows(self, idx):
        """The rows ``idx`` (an index tensor or a slice) of every field in use."""
        return self.map(lambda v: v[idx])

    def replace(self, **changes):
        """The record with ``changes`` to its fields."""
        return dataclasses.replace(self, **changes)

    def cat(self, *others: "Triplets") -> "Triplets":
        """These rows followed by ``others``': the fields all hold, and a ``condition`` that some
        hold with NaN (none) for the others' rows; a field only some hold otherwise is dropped."""
        parts = (self, *others)
        out = {k: torch.cat([getattr(q, k) for q in parts]) for k in BATCH_KEYS}
        for k in ("speed", "balance"):
            if all(getattr(q, k) is not None for q in parts):
                out[k] = torch.cat([getattr(q, k) for q in parts])
        held = [q.condition for q in parts if q.condition is not None]
        if held:
            nan = [torch.full((len(q), 2), float("nan"), dtype=held[0].dtype, device=held[0].device) for q in parts]
            out["condition"] = torch.cat([q.condition if q.condition is not None else n for q, n in zip(parts, nan)])
        return Triplets(**out)


@dataclass(frozen=True, eq=False)
class Batch(Triplets):
    """A minibatch as :func:`~latentsim.latent.loss.integrator_loss` takes it: triplets (B rows)
    and, for a conditioned training (:mod:`latentsim.latent.conditioning`), each sample's
    condition.

    Attributes
    ----------
    dt : None (the potential's), or (B,) each sample's time step.
    stiffness : None (1), or (B,) each sample's factor on the elastic energy.
    scale : None (1), or (B,) a factor on each sample's weight.
    """

    dt: torch.Tensor | None = None
    stiffness: torch.Tensor | None = None
    scale: torch.Tensor | None = None
