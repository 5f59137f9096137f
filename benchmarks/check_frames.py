"""Check every stored frame of a run's full simulations against its equations of motion, independently of the
solver: the incremental potential is rebuilt from each trajectories.h5 (its model and material.model), its
gradient recomputed at every frame by autograd of the PyTorch energies (not the solver's compiled kernels), and
the largest free-DoF residual compared with the solver's tolerance (a scene with colliders: the barrier's
gradient included).  Tet scenes also report the frames that end with an inverted tet; scenes with colliders the
nearest approach of any vertex, edge or triangle to one over every frame (negative: inside); scenes with a mesh
collider, by the IPC Toolkit as a second implementation, the frames where the surface crosses it (its intersection
test) and the least distance between them less the thickness (its distances over the pairs within 1 cm); scenes with
self-contact, the same of the surface against itself (less its thickness there, twice the colliders').

    python benchmarks/check_frames.py [results/sim]

It exits with status 1, naming the folder, when it finds no trajectories.h5 to check (a mistyped folder, or a run
whose simulate stage has not run): a check of nothing is no pass.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np
import torch

from latentsim.scene import MATERIAL_MODEL_ATTR, potential_from_artefact, previous_positions


def check(path: Path) -> dict:
    with h5py.File(path) as f:
        pot = potential_from_artefact(f)
        tol = float(f.attrs["newton_tolerance"] * f.attrs["force_scale"])
        free = np.setdiff1d(np.arange(len(f["rest_positions"])), f["dirichlet"][()])
        law = str(f.attrs.get(MATERIAL_MODEL_ATTR, "stvk"))
        worst, frames, inverted, nearest = 0.0, 0, 0, float("inf")
        crossing, mesh_nearest, self_crossing, self_nearest = 0, float("inf"), 0, float("inf")
        for name, grp in f["sequences"].items():
            if name.endswith("_train") and name[: -len("_train")] in f["sequences"]:
                continue  # the first frames of a sequence stored whole
            X = torch.as_tensor(grp["positions"][()])
            XD = torch.as_tensor(grp["dirichlet_positions"][()])  # where the colliders attached to them stand
            # x_{-1}: x_0 at rest, else a free body's initial rigid motion (the sequence's initial_velocity)
            x_before = torch.as_tensor(previous_positions(X[0].numpy(), f["masses"][()], grp.attrs.get("initial_velocity"), float(f.attrs["dt"])))
            for t in range(1, len(X)):
                x = X[t].clone().requires_grad_(True)
                (g,) = torch.autograd.grad(pot(x, X[t - 1], X[t - 2] if t >= 2 else x_before, targets=XD[t], penalty=False), x)
                worst = max(worst, float(g[free].norm()) / tol)
            frames += len(X) - 1
            if pot.contact is not None:
                nearest = min(nearest, float(pot.contact.clearance(X, XD).min()))
                for mesh in pot.contact.meshes:
                    c, d = _toolkit_check(pot.contact.primitives.numpy(), X.numpy(), mesh)
                    crossing, mesh_nearest = crossing + c, min(mesh_nearest, d)
                if pot.contact.self_contact is not None:
                    c, d = _toolkit_check(pot.contact.primitives.numpy(), X.numpy(), None, pot.contact.self_contact)
                    self_crossing, self_nearest = self_crossing + c, min(self_nearest, d)
            if "inverted_tets" in grp:
                inverted += int((grp["inverted_tets"][1:] > 0).sum())
    return dict(law=law, frames=frames, worst=worst, inverted=inverted, nearest=nearest, crossing=crossing, mesh_nearest=mesh_nearest,
                self_crossing=self_crossing, self_nearest=self_nearest)  # fmt: skip


def _toolkit_check(primitives, X, mesh=None, thickness: float = 0.0) -> tuple[int, float]:
    """The frames of X (T, n, 3) whose surface (``primitives``, edges or triangles) crosses ``mesh`` (None: itself), and
    the least distance between them less the mesh's thickness (itself: less ``thickness``), by the IPC Toolkit."""
    import ipctk

    from latentsim.physics.mesh_contact import unique_edges

    n = X.shape[1]
    tris = primitives if primitives.shape[1] == 3 else np.zeros((0, 3), np.int64)
    edges = primitives if primitives.shape[1] == 2 else unique_edges(primitives)
    V = np.zeros((0, 3)) if mesh is None else mesh.vertices
    if mesh is not None:
        edges, tris, thickness = np.vstack([edges, mesh.edges + n]), np.vstack([tris, mesh.faces + n]), mesh.thickness
    cm = ipctk.CollisionMesh(np.asfortranarray(np.vstack([X[0], V])), np.asfortranarray(edges.astype(np.int32)), np.asfortranarray(tris.astype(np.int32)))
    if mesh is not None:
        cm.can_collide = ipctk.make_static_obstacle_filter(n)
    crossing, nearest = 0, float("inf")
    for x in X:
        W = np.asfortranarray(np.vstack([x, V]))
        crossing += bool(ipctk.has_intersections(cm, W))
        pairs = ipctk.NormalCollisions()
        pairs.build(cm, W, 0.01)
        if len(pairs):
            nearest = min(nearest, float(np.sqrt(pairs.compute_minimum_distance(cm, W))) - thickness)
    return crossing, nearest


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", nargs="?", default="results/sim",
                        help="the run's folder of full simulations, one <scene>/trajectories.h5 each (default: %(default)s)")
    root = Path(parser.parse_args(argv).root)
    paths = sorted(root.glob("*/trajectories.h5"))
    if not paths:
        found = "no such folder" if not root.is_dir() else "no <scene>/trajectories.h5 in it"
        parser.exit(1, f"check_frames: {root}: {found}; nothing to check (a run's simulations are in results/sim)\n")
    print("| scene | material | frames | max residual / tolerance (autograd) | frames ending with an inverted tet | nearest approach to a collider [m] "
          "| mesh collider (IPC Toolkit): frames crossing, nearest [m] | self-contact (IPC Toolkit): frames crossing, nearest [m] |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for path in paths:
        r = check(path)
        near = "-" if r["nearest"] == float("inf") else f"{r['nearest']:.3g}"
        mesh = "-" if r["mesh_nearest"] == float("inf") else f"{r['crossing']}, {r['mesh_nearest']:.3g}"
        own = "-" if r["self_nearest"] == float("inf") else f"{r['self_crossing']}, {r['self_nearest']:.3g}"
        print(f"| {path.parent.name} | {r['law']} | {r['frames']} | {r['worst']:.2f} | {r['inverted']} | {near} | {mesh} | {own} |", flush=True)


if __name__ == "__main__":
    main()
