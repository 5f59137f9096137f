"""Print the analytic benchmarks that tests/physics/test_physics.py asserts, with the measured ratios.

    python benchmarks/physics_validation.py
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "physics"))
from test_physics import BETA, rod_cantilever, static_solve, tet_cantilever  # noqa: E402

from latentsim.solve.modes import lowest_modes  # noqa: E402

print("| model | DoF | tip deflection / Euler-Bernoulli | omega_1 / analytic | omega_2 / analytic |")
print("|---|---|---|---|---|")
for name, build in (("rod (40 segments)", rod_cantilever), ("tets (120x8x8 cells, 5-tet split)", tet_cantilever)):
    pot, V, EI, q, rho_a = build()
    L = V[:, 0].max()
    x = static_solve(pot, V)
    tip = V[:, 0] > L - 1e-9
    ratio = -(x[tip, 1] - V[tip, 1]).mean() / (q * L**4 / (8 * EI))
    w2, _, _ = lowest_modes(pot, 6, V)
    w = np.sqrt(np.abs(w2))
    an = [b**2 * np.sqrt(EI / (rho_a * L**4)) for b in BETA]
    second = min(w[2:], key=lambda v: abs(v / an[1] - 1))
    print(f"| {name} | {V.size:,} | {ratio:.4f} | {w[0] / an[0]:.4f} | {second / an[1]:.4f} |")
