"""What one time step knows, handed to every term of the incremental potential.

A term of E_total is ``energy(x, frame)``: most terms (the elastic ones) ignore the frame, a term that
depends on the step reads it - the contact barrier's attached colliders stand where the frame's targets put
them and its lagged friction starts from the frame's previous positions; a damping term measures the
velocity from them.  A solver builds one :class:`Frame` per step and asks each term for itself as it stands
over that step (:meth:`~latentsim.physics.base.EnergyTerm.at`): an explicit per-step object, its energy
and derivatives functions of x alone, rather than state the term keeps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["Frame"]


@dataclass(frozen=True)
class Frame:
    """One step's data (numpy arrays or tensors; leading batch axes as x's).

    targets : x*_D(t) (..., m, 3), the prescribed vertices' positions at the step's end; None without.
    x_prev, x_prev2 : x_{t-1} and x_{t-2} (..., n, 3).
    targets_prev : the prescribed positions at the step's start (..., m, 3) (normally x_{t-1}'s own).
    dt : the time step [s] (a float, or a tensor of the batch shape).
    stiffness : a factor on the elastic energy (a state's Young's modulus over the terms'), or None.
    """

    targets: Any = None
    x_prev: Any = None
    x_prev2: Any = None
    targets_prev: Any = None
    dt: Any = None
    stiffness: Any = None
