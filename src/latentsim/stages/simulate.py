"""Full-space simulation stage: every sequence of a scene into trajectories.h5.

Layout (see docs/artefacts.md): root datasets ``rest_positions (n,3)``,
``masses (n,)``, ``dirichlet (m,)`` and the model's element arrays; root
attributes ``model``, ``dt``, ``gravity`` and the material constants; one group
per sequence ``/sequences/<name>`` with ``positions (T,n,3)``,
``dirichlet_positions (T,m,3)``, ``bc (T,6)``, ``newton_iterations (T,)``,
``gradient_norm (T,)``, ``frame_ms (T,)`` and attribute ``split``; tet scenes add
``min_volume_ratio (T,)`` (the smallest det F = V / V0 over the tets) and
``inverted_tets (T,)`` (how many have det F <= 0) at the end of each frame.
Frame 0 is the initial state (the rest state); frame 1 is solved with x_{-1} = x_0 (at rest) or, for a free
body's sequence with an initial velocity, the rigid motion's x_{-1} (:func:`latentsim.scene.previous_positions`;
the group's attribute ``initial_velocity`` = [v, w] records it).
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from pathlib import Path

import meshio
import numpy as np
import torch

from latentsim.config import ConfigError, check_d_hat
from latentsim.io import atomic_h5, atomic_path, read_mesh_arrays, write_dataset
from latentsim.mesh.geometry import tet_volumes
from latentsim.mesh.validation import MeshError
from latentsim.report.paraview import cells_for, single_block_xdmf
from latentsim.scene import (CONTACT_ATTR, MATERIAL_MODEL_ATTR, bc_parameters, build_potential, contact_settings, dirichlet_trajectory,
                             initial_velocity, load_collider_meshes, own_thickness, previous_positions)
from latentsim.solve.implicit_euler import ImplicitEuler, NewtonFailed, NewtonSettings, StepInfo
from latentsim.utils import progress_bar, working_directory

log = logging.getLogger(__name__)


class SimulationError(RuntimeError):
    """A frame failed to converge (the message names scene, sequence and frame), or the scene cannot be built."""


def volume_ratios(positions: np.ndarray, rest: np.ndarray, tets: np.ndarray):
    """Per frame, the smallest tet volume ratio det F = V / V0 and the count of inverted tets.

    Parameters
    ----------
    positions : (T, n, 3) float, the frames.
    rest : (n, 3) float, the rest positions.
    tets : (e, 4) int, positively oriented at rest.

    Returns
    -------
    min_ratio : (T,) float64, min over tets of det F.
    inverted : (T,) int64, the number of tets with det F <= 0.
    """
    v0 = tet_volumes(rest, tets)
    ratios = np.stack([tet_volumes(x, tets) / v0 for x in positions])
    return ratios.min(axis=1), (ratios <= 0).sum(axis=1).astype(np.int64)


def simulate_sequence(solver: ImplicitEuler, rest, seq: dict, dt: float, label: str, progress=False):
    """Run one sequence; returns a dict of the arrays stored for it."""
    T = int(seq["frames"])
    D = solver.dirichlet
    p = bc_parameters(seq, T)
    xD = dirichlet_trajectory(rest[D], p, dt)
    n = len(rest)
    pos = np.empty((T, n, 3))
    iters = np.zeros(T, dtype=np.int32)
    gnorm = np.full(T, np.nan)
    ms = np.zeros(T)
    pos[0] = rest
    x_prev = rest.copy()
    x_prev2 = previous_positions(rest, solver.masses, initial_velocity(seq), dt)
    timings = dict.fromkeys(StepInfo().timings, 0.0)
    for t in progress_bar(range(1, T), enabled=progress, desc=label, unit="frame"):
        t0 = time.perf_counter()
        try:
            x, info = solver.step(x_prev, x_prev2, xD[t])
        except NewtonFailed as e:
            raise SimulationError(f"{label}, frame {t}: {e} (residual {e.residual:.3e})") from e
        ms[t] = 1e3 * (time.perf_counter() - t0)
        pos[t], iters[t], gnorm[t] = x, info.iterations, info.gradient_norm
        for k in timings:
            timings[k] += info.timings[k]
        x_prev2, x_prev = x_prev, x
    return dict(positions=pos, dirichlet_positions=xD, bc=p, newton_iterations=iters, gradient_norm=gnorm, frame_ms=ms), timings


def simulate_scene(scene: str, mesh_h5, cfg: dict, out_h5, paraview_dir=None, progress=False):
    """Simulate every sequence of ``cfg['sequences']`` and write ``out_h5``.

    cfg holds model, material, dt, gravity, newton, sequences (the rule's params).
    """
    arrays = read_mesh_arrays(mesh_h5)
    model = arrays["model"]
    if model != cfg["model"]:
        raise SimulationError(f"scene '{scene}': {mesh_h5} holds a '{model}' mesh, the config says '{cfg['model']}'")
    if (cfg.get("contact") or {}).get("colliders"):  # a mesh file's size is known from here on
        rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
        try:
            check_d_hat(cfg["contact"].get("d_hat"), float(np.linalg.norm(rest.max(0) - rest.min(0))), scene)
        except ConfigError as e:
            raise SimulationError(f"scene '{scene}' ({mesh_h5}): {e}") from None
    try:
        arrays.update(load_collider_meshes(cfg.get("contact"), cfg.get("mesh_sources") or {}, scene))
    except MeshError as e:
        raise SimulationError(f"scene '{scene}': {e}") from None
    try:
        pot = build_potential(model, arrays, cfg["material"], cfg["dt"], cfg["gravity"], free_only=True, contact=cfg.get("contact"))
    except ValueError as e:  # e.g. a collider attached to a prescribed set that does not fix a pose
        raise SimulationError(f"scene '{scene}': {e}") from None
    contact = None  # the contact block with its defaults resolved, as the trajectories file records it
    if pot.contact is not None:
        _check_initial_penetration(scene, pot.contact, cfg["contact"]["colliders"], arrays)
        contact = contact_settings(cfg["contact"], arrays["rest_positions"], pot.masses.numpy(), np.asarray(cfg["gravity"], dtype=float),
                                   own_thickness(model, cfg["material"]))  # fmt: skip
        log.info("scene %s: %d collider(s), d_hat %.3g m, kappa %.3g", scene, len(pot.contact.colliders) + len(pot.contact.meshes), pot.contact.d_hat,
                 pot.contact.kappa)  # fmt: skip
    solver = ImplicitEuler(pot, NewtonSettings(**cfg["newton"]))
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    log.info("scene %s: %d DoF, %d free, linear solver %s", scene, 3 * len(rest), len(solver.free_dofs), solver.linear.method)
    results = {}
    for seq in cfg["sequences"]:
        label = f"scene {scene}, sequence {seq['name']}"
        data, timings = simulate_sequence(solver, rest, seq, cfg["dt"], label, progress)
        if model == "tets":
            data["min_volume_ratio"], data["inverted_tets"] = volume_ratios(data["positions"], rest, arrays["tets"])
            bad = np.flatnonzero(data["inverted_tets"])
            if bad.size:
                log.warning("%s: %d frames end with an inverted tet (first %d: %d tets, det F down to %.3g)", label,
                            bad.size, bad[0], data["inverted_tets"][bad[0]], data["min_volume_ratio"].min())
            else:
                log.info("%s: no inverted tet at the end of any frame (smallest det F %.3g)", label, data["min_volume_ratio"].min())
        it = data["newton_iterations"][1:]
        log.info(
            "%s: %d frames, %.1f ms/frame, %.2f Newton iterations/frame, timings %s",
            label, len(data["positions"]), data["frame_ms"][1:].mean(), it.mean(), {k: round(v, 3) for k, v in timings.items()},
        )
        if pot.contact is not None:
            data["min_contact_distance"] = pot.contact.clearance(torch.as_tensor(data["positions"]), data["dirichlet_positions"]).numpy()
            inside = np.flatnonzero(data["min_contact_distance"] <= 0)
            if inside.size:
                raise SimulationError(f"{label}, frame {inside[0]}: the surface (a vertex, edge or triangle) lies inside a collider (signed "
                                      f"distance {data['min_contact_distance'][inside[0]]:.3e} m)")  # fmt: skip
            log.info("%s: nearest approach to a collider %.3e m (d_hat %.3e m)", label, data["min_contact_distance"].min(), pot.contact.d_hat)
        results[seq["name"]] = (seq, data)
    with atomic_h5(out_h5, config=cfg) as f:
        f.attrs["scene"] = scene
        f.attrs["model"] = model
        f.attrs["dt"] = float(cfg["dt"])
        f.attrs["gravity"] = np.asarray(cfg["gravity"], dtype=float)
        f.attrs["newton_tolerance"] = float(solver.settings.tolerance)
        f.attrs["force_scale"] = solver.f_ref
        f.attrs["linear_solver"] = solver.linear.method
        if contact is not None:
            f.attrs[CONTACT_ATTR] = json.dumps(contact)
        for k, v in cfg["material"].items():
            if k == "model":  # the material model; the attribute "model" is the scene's (rods, shell, tets)
                f.attrs[MATERIAL_MODEL_ATTR] = str(v)
            elif v is not None:
                f.attrs[k] = float(v)
        write_dataset(f, "rest_positions", rest)
        write_dataset(f, "masses", pot.masses.numpy())
        for k in ("dirichlet", "edges", "triples", "root_of", "triangles", "tets", "surface") + tuple(k for k in arrays if k.startswith("collider")):
            if k in arrays:
                write_dataset(f, k, arrays[k])
        grp = f.create_group("sequences", track_order=True)
        for name, (seq, data) in results.items():
            v0 = initial_velocity(seq)
            _write_sequence(grp, name, data, seq.get("split", "train"), v0)
            if seq.get("train_frames"):
                n = int(seq["train_frames"])
                _write_sequence(grp, f"{name}_train", {k: v[:n] for k, v in data.items()}, "train", v0)
    if paraview_dir is not None:
        write_paraview(paraview_dir, model, arrays, {k: v[1]["positions"] for k, v in results.items()}, cfg["dt"])


def _check_initial_penetration(scene: str, barrier, colliders: list, arrays: dict) -> None:
    """Every sequence starts at the rest state: no vertex, edge or triangle of it may lie inside or on a collider (where
    it stands at rest, grown by the surface's thickness), where the barrier has no finite energy and no step can start.
    Raises a ``SimulationError`` naming the collider (its index in ``contact.colliders`` and its type) and how many
    vertices, edges or triangles it holds; with self-contact, two parts of the surface within its thickness of each other."""
    rest = np.asarray(arrays["rest_positions"], dtype=np.float64)
    dirichlet = np.asarray(arrays.get("dirichlet", ()), dtype=np.int64)
    order = [i for i, q in enumerate(colliders) if q["type"] != "mesh"] + [i for i, q in enumerate(colliders) if q["type"] == "mesh"]
    found = barrier.penetrations(rest, rest[dirichlet] if barrier.moving else None)
    if barrier.self_contact is not None and found[-1][0]:
        raise SimulationError(
            f"scene '{scene}': initial self-contact: two parts of the rest mesh lie {found[-1][1] + barrier.self_contact:.3g} m apart, within "
            f"the thickness {barrier.self_contact:.3g} m they keep (config key 'scenes.{scene}.contact.self_contact'; twice contact.thickness): "
            f"give a rest shape whose parts stand farther apart, a smaller thickness, or leave self-contact off"
        )
    for i, (count, deepest) in zip(order, found):
        if count:
            raise SimulationError(
                f"scene '{scene}': initial penetration: {count} of the rest mesh's vertices, edges or triangles lie inside or on collider {i} "
                f"({colliders[i]['type']}) of contact.colliders (config key 'scenes.{scene}.contact.colliders.{i}'; deepest "
                f"{-deepest:.3g} m inside): move the collider or the mesh so that the rest shape starts outside every collider"
            )


def _write_sequence(grp, name, data, split, initial_velocity=None):
    g = grp.create_group(name)
    g.attrs["split"] = split
    if initial_velocity is not None:
        g.attrs["initial_velocity"] = initial_velocity
    for k, v in data.items():
        write_dataset(g, k, v)


def write_paraview(folder, model, arrays, sequences: dict, dt: float):
    """One XDMF time series per sequence (ParaView opens ``<name>.xdmf``).

    The rest mesh is held by every frame (one block in ParaView: ``single_block_xdmf``); each frame carries the
    point field ``displacement`` (apply ParaView's *Warp By Vector* to see the motion).
    """
    folder = Path(folder)
    with atomic_path(folder) as tmp:
        tmp.mkdir(parents=True)
        # meshio's TimeSeriesWriter puts its .h5 in the current directory
        with working_directory(tmp):
            for name, pos in sequences.items():
                with meshio.xdmf.TimeSeriesWriter(f"{name}.xdmf") as w:
                    w.write_points_cells(pos[0], cells_for(model, arrays))
                    for t in range(len(pos)):
                        w.write_data(t * dt, point_data={"displacement": pos[t] - pos[0]})
                single_block_xdmf(f"{name}.xdmf")
        if folder.exists():
            shutil.rmtree(folder)
