"""The Neural Modes map at run time: the NumPy transcription against the torch module, per call and per reduced step.

    python benchmarks/neural_modes_map_runtime.py nm_giraffe [--results results] [--repeats 2000]

The subspace dynamics (Eq. 15, ``latentsim.neural_modes.dynamics``) evaluate the map n(z) and its Jacobian
dn/dz at every Newton or L-BFGS iteration.  They do it with ``latentsim.neural_modes.numpy_map.NumpyNeuralModes``
(float64 NumPy, forward mode through the GELU MLP); this script times that against the torch module itself
(``NeuralModes.correction``, its Jacobian by ``torch.func.jacfwd`` and by ``torch.autograd.functional.jacobian``)
on the scene's trained map, checks that they agree, and times the reduced implicit-Euler step of the scene's first
test sequence with either.  Needs results/neural_modes/{scene}/neural_modes.pt (rule nm_train) and
results/sim/{scene}/trajectories.h5.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the step timings are meant (set before numpy loads)

import argparse
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from latentsim.neural_modes import load_neural_modes
from latentsim.neural_modes.dynamics import NeuralModesSubspace, first_test_sequence
from latentsim.scene import potential_from_artefact
from latentsim.solve.reduced import ReducedSettings, reduced_rollout

ROOT = Path(__file__).resolve().parents[1]


class TorchSubspace(NeuralModesSubspace):
    """The same subspace with y and dy/dz from the torch module (``torch.func.jacfwd``, y as its aux output)."""

    def __init__(self, model, dirichlet):
        super().__init__(model, dirichlet)
        self.model = model
        self._jacobian = torch.func.jacfwd(lambda q: (lambda y: (y, y))(model.correction(q)), has_aux=True)

    def _correction(self, q, jac):
        qt = torch.from_numpy(q)
        if not jac:
            with torch.no_grad():
                return self.model.correction(qt).numpy(), None
        J, y = self._jacobian(qt)
        return y.detach().numpy(), J.detach().numpy()


def per_call_us(fn, repeats: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t0) / repeats * 1e6


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--results", default=str(ROOT / "results"))
    ap.add_argument("--repeats", type=int, default=2000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = Path(args.results)
    model = load_neural_modes(results / "neural_modes" / args.scene / "neural_modes.pt")
    with h5py.File(results / "sim" / args.scene / "trajectories.h5", "r") as f:
        pot = potential_from_artefact(f)
        xD = f["sequences"][first_test_sequence(f)]["dirichlet_positions"][()]
    D = pot.dirichlet.numpy()
    subs = {"NumPy (numpy_map)": NeuralModesSubspace(model, D), "torch module, jacfwd": TorchSubspace(model, D)}
    q = np.linspace(-0.5, 0.5, model.m) * 0.1
    qt = torch.from_numpy(q)
    (x0, J0), (x1, J1) = (s.jacobian(q, xD[-1]) for s in subs.values())
    print(f"{args.scene}: {model.n} vertices, {model.m} modes; NumPy against torch: |dx| {np.abs(x0 - x1).max():.1e}, |dJ| {np.abs(J0 - J1).max():.1e}")
    net = subs["NumPy (numpy_map)"].net
    with torch.no_grad():
        rows = {
            "y, NumPy": per_call_us(lambda: net.correction(q), args.repeats),
            "y, torch module": per_call_us(lambda: model.correction(qt), args.repeats),
        }
    rows["y and dy/dz, NumPy"] = per_call_us(lambda: net.correction(q, True), args.repeats)
    rows["y and dy/dz, torch.func.jacfwd"] = per_call_us(lambda: subs["torch module, jacfwd"]._correction(q, True), max(args.repeats // 20, 1))
    rows["dy/dz, torch.autograd.functional.jacobian"] = per_call_us(
        lambda: torch.autograd.functional.jacobian(model.correction, qt, vectorize=True), max(args.repeats // 20, 1)
    )
    for name, us in rows.items():
        print(f"| {name} | {us:.1f} us |")
    for name, sub in subs.items():
        for method in ("newton", "lbfgs"):
            out = reduced_rollout(sub, pot, np.zeros(model.m), np.zeros(model.m), xD, ReducedSettings(method=method, max_iterations=100))
            print(f"| reduced step, {method}, {name} | {np.nanmedian(out['step_ms'][2:]):.3f} ms median | {out['iterations'][2:].mean():.2f} iterations |")


if __name__ == "__main__":
    main()
