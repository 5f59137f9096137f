"""What contact on the whole surface costs the full space, against the vertices alone, in one process.

For each named contact scene of the config: prepare its mesh, then simulate the first frames of its first sequence
twice, with the contact the scene has now (every vertex, and a strand's edges or a shell's or solid's triangles
against every curved collider, at the surface's thickness) and with the vertices alone at the mid-surface (the
model before the primitives and thickness existed), alternating the two per repeat so that both see the same load
(after two frames of each, untimed, that take the kernels' compilation).  It prints ms per frame and Newton iterations
per frame of each (medians over the repeats), the ratio, and each one's clearance: the least signed distance of any
vertex, edge or triangle from the colliders over the frames, measured on the surface with thickness (negative: the
surface went in).

    python benchmarks/contact_cost.py [--config config/config.yaml] [--scenes cloth_sphere hair_head] [--frames 150]

With ``--against unkept`` the second of the two is the same contact with no pairs kept from one state to the next
(:mod:`latentsim.physics.kept_pairs`), and the last column the largest difference of a vertex's position between the
two runs (they differ only in the order their sums are taken).

    python benchmarks/contact_cost.py --scenes cloth_fold --frames 150 --against unkept

A scene with a mesh collider (cloth_drape) has no vertices-alone model: it is refused without ``--against unkept``.

Run it on an otherwise idle machine, or say what ran beside it; the ratio of one run is the figure to compare.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("KMP_BLOCKTIME", "0")

import numpy as np
import torch

from latentsim.config import load_config
from latentsim.io import read_mesh_arrays
from latentsim.physics import kept_pairs
from latentsim.physics.contact import ContactBarrier
from latentsim.scene import bc_parameters, build_potential, dirichlet_trajectory, load_collider_meshes
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonSettings
from latentsim.stages.mesh import prepare_mesh

ROOT = Path(__file__).resolve().parents[1]


def vertices_only(barrier: ContactBarrier, colliders) -> ContactBarrier:
    """The same barrier over the vertices alone, against the colliders as given (not grown by a thickness)."""
    return ContactBarrier(len(barrier.stencils), colliders, barrier.d_hat, barrier.kappa, barrier.extend_below, barrier.attached,
                          barrier.rest_dirichlet, barrier.friction, barrier.slip)  # fmt: skip


def potentials(name: str, sc: dict, meshes: dict, against: str):
    """The scene's mesh arrays and its two potentials: the surface's, and the vertices alone (``against`` "vertices") or
    a second surface's ("unkept")."""
    with tempfile.TemporaryDirectory() as tmp:
        prepare_mesh(name, sc["model"], sc["mesh"], sc["dirichlet"], meshes, Path(tmp) / "mesh.h5")
        arrays = read_mesh_arrays(Path(tmp) / "mesh.h5")
    arrays.update(load_collider_meshes(sc["contact"], meshes, name))  # a mesh collider's surface, as the simulation reads it
    surface = build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"], free_only=True, contact=sc["contact"])
    if against == "unkept":
        return arrays, surface, build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"], free_only=True, contact=sc["contact"])
    bare = build_potential(sc["model"], arrays, sc["material"], sc["dt"], sc["gravity"], free_only=True, contact={**sc["contact"], "thickness": 0.0})
    bare.contact = vertices_only(bare.contact, bare.contact.colliders)
    return arrays, surface, bare


@contextlib.contextmanager
def pairs_kept(keep: bool):
    """Within it, contact terms that build their kept pairs keep none unless ``keep``."""
    saved = kept_pairs.KEPT_STATES
    kept_pairs.KEPT_STATES = saved if keep else 0
    try:
        yield
    finally:
        kept_pairs.KEPT_STATES = saved


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "config.yaml"))
    ap.add_argument("--scenes", nargs="+", default=["cloth_sphere"])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--against", choices=["vertices", "unkept"], default="vertices")
    args = ap.parse_args(argv)
    cfg = load_config(args.config)
    missing = [s for s in args.scenes if s not in cfg["scenes"] or not cfg["scenes"][s]["contact"]["colliders"]]
    if missing:
        print(f"contact_cost: no contact scene {', '.join(missing)} in {args.config}", file=sys.stderr)
        return 1
    meshed = [s for s in args.scenes if any(q["type"] == "mesh" for q in cfg["scenes"][s]["contact"]["colliders"])]
    if args.against == "vertices" and meshed:
        print(f"contact_cost: {', '.join(meshed)} holds a mesh collider, which has no model of vertices alone to compare "
              f"against (its barrier pairs every vertex, edge and triangle with the mesh); use --against unkept", file=sys.stderr)  # fmt: skip
        return 1
    torch.set_num_threads(1)
    other = "vertices only" if args.against == "vertices" else "no pairs kept"
    last = "clearance vertices only" if args.against == "vertices" else "largest difference"
    print(f"| scene | frames | surface: ms/frame | it/frame | {other}: ms/frame | it/frame | ratio | clearance surface | {last} |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.scenes:
        sc = cfg["scenes"][name]
        rows = {"surface": [], "bare": []}
        arrays, *warm = potentials(name, sc, cfg["meshes"], args.against)
        for pot in warm:  # two frames of each first, untimed: the kernels' compilation and the libraries' first calls
            run_measured(sc, arrays, pot, 2, pot.contact)
        for _ in range(args.repeats):  # (potentials built afresh each repeat: nothing kept from the last)
            arrays, surface, bare = potentials(name, sc, cfg["meshes"], args.against)
            for key, pot in (("surface", surface), ("bare", bare)):
                with pairs_kept(not (key == "bare" and args.against == "unkept")):
                    rows[key].append(run_measured(sc, arrays, pot, args.frames, surface.contact))
        (ms_s, it_s, cl_s), (ms_b, it_b, cl_b) = (np.median(np.asarray([r[:3] for r in rows[k]]), axis=0) for k in ("surface", "bare"))
        tail = f"{cl_b:.2e} m" if args.against == "vertices" else f"{np.abs(rows['surface'][-1][3] - rows['bare'][-1][3]).max():.1e} m"
        print(f"| {name} | {args.frames} | {ms_s:.1f} | {it_s:.2f} | {ms_b:.1f} | {it_b:.2f} | {ms_s / ms_b:.2f} | {cl_s:.2e} m | {tail} |")
    return 0


def run_measured(sc: dict, arrays: dict, pot, frames: int, measure: ContactBarrier) -> tuple[float, float, float, np.ndarray]:
    """Simulate the first ``frames`` frames of the scene's first sequence: (ms per frame, Newton iterations per frame,
    the least clearance over the frames by ``measure``, the surface's barrier, measured apart from the timing, and the
    frames (F, n, 3))."""
    solver = ImplicitEuler(pot, NewtonSettings(**sc["newton"]))
    seq = sc["sequences"][0]
    T = min(int(seq["frames"]), frames + 1)
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    xD = dirichlet_trajectory(rest[solver.dirichlet], bc_parameters(seq, T), sc["dt"])
    x2 = x1 = rest.copy()
    iters, seconds, states = 0, 0.0, []
    for t in range(1, T):
        t0 = time.perf_counter()
        x, info = solver.step(x1, x2, xD[t])
        seconds += time.perf_counter() - t0
        iters += info.iterations
        states.append(x)
        x2, x1 = x1, x
    X = torch.as_tensor(np.asarray(states))
    targets = torch.as_tensor(np.asarray(xD[1:T])) if measure.moving else None
    clearance = float(measure.clearance(X, targets).min())
    return 1e3 * seconds / (T - 1), iters / (T - 1), clearance, X.numpy()


if __name__ == "__main__":
    sys.exit(main())
