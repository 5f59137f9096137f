r"""Contact pairs found for a state, kept and taken again for the states near it.

A contact term's broad phase finds, for a state, the pairs of primitives that may lie within a reach r of each other
(:class:`~latentsim.physics.self_contact.SelfContact`'s).  Found at r + 2m for a margin m, they serve every state
whose every vertex lies within m of that state's: two primitives within r of each other there were within r + 2m of
each other in it.  A solver meets nearly the same state at each Newton iteration and line-search trial, a learned loss
the same data states epoch after epoch.  Self-contact's pairs cost the cloth 4-5 ms a state to find when this was
written (0.5-0.6 ms with the compiled grid since); with them kept, cloth_fold's full space took 0.65 of the time
(docs/measurements-archive.md, "Contact, twentieth part").  A mesh collider's candidates are found for
all states at once and cheaply; kept, cloth_drape's training took longer, so they are not.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["KeptPairs"]

#: how many states, and their pairs, a :class:`KeptPairs` keeps at most, and at most how many bytes of states
#: (fewer states of a large mesh, at least one); the oldest is replaced first.  0 states: none kept (a benchmark's
#: comparison, ``benchmarks/contact_cost.py --against unkept``)
KEPT_STATES, KEPT_BYTES = 1024, 64 * 2**20


class KeptPairs:
    """The pairs of up to :data:`KEPT_STATES` states of ``shape`` (points, 3), each found by a term's own search.

    Parameters
    ----------
    shape : a state's shape, (points, 3): the points whose displacement bounds the pairs' (the term's vertices).
    margin : m, as in the module docstring; the search is asked for pairs within its reach plus 2m.
    """

    def __init__(self, shape: tuple[int, int], margin: float):
        self.margin = float(margin)
        most = min(KEPT_STATES, max(1, KEPT_BYTES // (8 * int(np.prod(shape)))))
        self._states = np.zeros((most, *shape))
        self._pairs: list = [None] * most
        self._count = 0
        self._sketch = np.linspace(0, shape[0] - 1, min(shape[0], 16)).astype(np.int64)

    def __call__(self, flat: np.ndarray, search) -> list:
        """The pairs of each state of flat (S, points, 3): a kept state's where every point lies within the margin of
        it, else ``search(states)`` (K, points, 3) -> K pairs for the states left, which are then kept."""
        flat = np.asarray(flat, dtype=np.float64)
        out = [None] * len(flat)
        k, m = min(self._count, len(self._states)), self.margin
        if k and len(flat):  # the kept states near each state: first by a few points (a necessary test), then by all
            sk = self._sketch
            near = torch.cdist(torch.as_tensor(flat[:, sk].reshape(len(flat), -1)), torch.as_tensor(self._states[:k, sk].reshape(k, -1)), p=math.inf)
            for s, j in zip(*np.nonzero((near <= m).numpy())):
                if out[s] is None and np.einsum("ij,ij->i", flat[s] - self._states[j], flat[s] - self._states[j]).max() <= m * m:
                    out[s] = self._pairs[j]
        left = [s for s in range(len(flat)) if out[s] is None]
        if left:
            for s, found in zip(left, search(flat[left])):
                out[s] = found
                if not len(self._states):
                    continue
                self._states[self._count % len(self._states)], self._pairs[self._count % len(self._states)] = flat[s], found
                self._count += 1
        return out
