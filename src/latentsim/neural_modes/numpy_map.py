r"""The Neural Modes map in float64 NumPy, with its Jacobian: the deployable runtime of ``network.NeuralModes``.

    n(z) = X + E z + y(z),      dn/dz = E + dy/dz,

y the GELU MLP with everything ``NeuralModes.correction`` builds in (n(0) = X, zero on fixed DoFs,
M-orthogonal to the rigid modes, the exact orthogonality l^T W y = 0, the half-turn symmetry),
evaluated layer by layer with the Jacobian carried forward (forward mode, all m tangents at once;
GELU'(s) = Phi(s) + s phi(s)).  The subspace dynamics (``dynamics.NeuralModesSubspace``, Eq. 15)
step with it: on the tiny config's 25-vertex, 2-mode map (``benchmarks/neural_modes_map_runtime.py``,
one busy CPU core) y costs 71 us against 359 us through the torch module, y with dy/dz 180 us against
8.4 ms by ``torch.func.jacfwd`` (4.1 ms by ``torch.autograd.functional.jacobian``), and the reduced
Gauss-Newton step 1.2 ms against 35 ms (150 ms in a busier run): PyTorch's per-operation overhead
dominates maps this small.  The torch module stays the definition: the tests check this
transcription and its Jacobian against it and autograd.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erf

__all__ = ["NumpyNeuralModes", "gelu"]


def gelu(s: np.ndarray, derivative: bool = False):
    """GELU(s) = s Phi(s) (the exact, erf form of ``torch.nn.GELU``), and its derivative
    Phi(s) + s phi(s) when ``derivative`` (else None)."""
    c = 1.0 + erf(s / math.sqrt(2.0))
    value = 0.5 * s * c
    return value, (0.5 * c + s * np.exp(-0.5 * s * s) / math.sqrt(2.0 * math.pi) if derivative else None)


class NumpyNeuralModes:
    """The correction y(z) of a trained :class:`~latentsim.neural_modes.network.NeuralModes` and its
    Jacobian, copied into float64 NumPy arrays (no auxiliary inputs).

    Attributes
    ----------
    X : (3n,) rest positions.   E : (3n, m) linear modes.   m : modal coordinates.
    """

    def __init__(self, model):
        if model.aux_dim:
            raise ValueError(f"NumpyNeuralModes evaluates maps without auxiliary inputs; this one has {model.aux_dim}")
        self.m = int(model.m)
        self.X = model.X.detach().numpy().copy()
        self.E = model.E.detach().numpy().copy()
        lin = [m for m in model.mlp if hasattr(m, "weight")]
        self.layers = [(m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in lin]
        self.mask = model.mask.detach().numpy().copy()
        self.R = None if model.R is None else model.R.detach().numpy().copy()
        self.MR = None if model.MR is None else model.MR.detach().numpy().copy()
        # l^T W y = 0 built into the map (orthogonality 'exact'): W the vertex masses (metric 'mass') or 1
        self.exact_orthogonality = model.exact_orthogonality is not None
        self.w3 = np.ones(len(self.X)) if model.w3 is None else model.w3.detach().numpy().copy()
        self.symmetry = None  # (source (n,), R (3,3), parity (m,)) when built into the map
        if model.sym_R is not None:
            self.symmetry = tuple(b.detach().numpy().copy() for b in (model.sym_source, model.sym_R, model.sym_parity))
        self.y0 = self._mlp(np.zeros(self.m))[0] if model.exact_origin else np.zeros_like(self.X)

    def _mlp(self, q, jac=False):
        """The MLP's output (3n,) at q (m,) and, with ``jac``, its Jacobian (3n, m)."""
        a, J = q, (np.eye(self.m) if jac else None)
        for W, b in self.layers[:-1]:
            a, d = gelu(W @ a + b, jac)
            if jac:
                J = d[:, None] * (W @ J)
        W, b = self.layers[-1]
        return W @ a + b, (W @ J if jac else None)

    def correction(self, q, jac: bool = False):
        """y(q) (3n,) as ``NeuralModes.correction`` and, with ``jac``, dy/dq (3n, m) (else None)."""
        y, Jy = self._mlp(q, jac)
        y = y - self.y0
        if self.symmetry is not None:  # y <- (y(q) + T y(S q)) / 2, as NeuralModes.correction
            source, Rs, parity = self.symmetry
            if np.all(parity > 0):  # S q = q
                ys, Jys = y, Jy
            else:
                ys, Jys = self._mlp(parity * q, jac)
                ys = ys - self.y0
            y = 0.5 * (y + (ys.reshape(-1, 3) @ Rs.T)[source].reshape(-1))
            if jac:
                Jt = np.einsum("ij,njr->nir", Rs, Jys.reshape(-1, 3, self.m))[source].reshape(-1, self.m)
                Jy = 0.5 * (Jy + Jt * parity)
        y = y * self.mask
        if jac:
            Jy = Jy * self.mask[:, None]
        if self.R is not None:
            y = y - self.R @ (self.MR.T @ y)
            if jac:
                Jy = Jy - self.R @ (self.MR.T @ Jy)
        if self.exact_orthogonality:  # y <- y - l c, c = (l^T W y) / (l^T W l), as NeuralModes.correction
            l = self.E @ q
            wl = self.w3 * l
            b = float(wl @ l)
            if b > 0:
                c = float(wl @ y) / b
                if jac:
                    dc = ((self.w3 * y) @ self.E + wl @ Jy - 2.0 * c * (wl @ self.E)) / b
                    Jy = Jy - self.E * c - np.outer(l, dc)
                y = y - l * c
        return y, Jy
