"""Filling a closed surface with tetrahedra (TetGen), to about a target vertex count.

:func:`tetrahedralize` runs TetGen (Si 2015, "TetGen, a Delaunay-based quality
tetrahedral mesh generator") with ``p`` (piecewise linear complex),
``q<ratio>/<dihedral>`` (quality bound), ``O9/7o/<angle>`` (mesh optimisation:
flips, smoothing and vertex insertion/deletion until no dihedral angle exceeds
``angle``, which is what removes slivers; TetGen's refinement bounds the
radius-edge ratio only), ``Y`` (surface kept) and ``a<volume>`` (maximum tet
volume), searching the volume bound for a target vertex count.
TetGen only adds vertices, and keeps the surface it is given, so
:func:`tetrahedralize_to` first remeshes the surface isotropically to an edge
length chosen from the target (:mod:`latentsim.mesh.remesh`), or, with that
off, simplifies a surface that is denser than the target (quadric edge
collapse, Garland & Heckbert 1997, through ``fast_simplification``).
:func:`improve_slivers` then moves interior vertices of the few tets TetGen
leaves under 10 degrees.
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from typing import Any

import numpy as np

from latentsim.mesh.geometry import (
    cells_around_vertices,
    enclosed_volume,
    remove_unreferenced,
    reorient,
    tet_volumes,
)
from latentsim.mesh.quality import dihedral_angles, tet_min_dihedral
from latentsim.mesh.remesh import edge_length_for, remesh_isotropic
from latentsim.mesh.surface import check_closed_surface, surface_of, weld
from latentsim.mesh.validation import (
    MeshError,
    as_cells,
    as_vertices,
    positive_int,
    require_finite,
)
from latentsim.utils import working_directory

logger = logging.getLogger(__name__)


def _tetgen_call(vertices: np.ndarray, triangles: np.ndarray, switches: str):
    """TetGen itself, in this process: (nodes, tets) as it returns them, or a :class:`MeshError`."""
    # tetgen (a compiled extension) is only needed where a surface is filled
    import tetgen

    tg = tetgen.TetGen(vertices, triangles.astype(np.int32))
    try:
        # TetGen writes tetgen-tmpfile_* debris into the cwd when it fails
        with tempfile.TemporaryDirectory() as scratch, working_directory(scratch):
            out = tg.tetrahedralize(switches=switches)
    except RuntimeError as exc:
        hint = "; the surface intersects itself: repair it (e.g. remove self-intersecting faces) first" if "intersect" in str(exc) else ""
        raise MeshError(f"TetGen failed with switches {switches!r}: {exc}{hint}") from exc
    return np.asarray(out[0]), np.asarray(out[1])


def _child(conn, call, args) -> None:
    import faulthandler

    faulthandler.disable()  # a crash here is reported by the parent (in_child_process), not by a dump of every thread
    try:
        conn.send(("ok", call(*args)))
    except BaseException as exc:  # noqa: BLE001 (sent to the parent, which raises it)
        conn.send(("error", exc))
    finally:
        conn.close()


def in_child_process(call, *args):
    """``call(*args)`` in a forked child process, its result or exception passed back: a compiled library that
    aborts the process (TetGen on some damaged surfaces: ``malloc(): invalid size``, SIGABRT) kills the child
    alone, and the caller gets a :class:`MeshError` saying so instead of a process gone without a word."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(child, call, args), daemon=True)
    proc.start()
    child.close()
    try:
        kind, value = parent.recv()
    except EOFError:  # the child died without an answer
        proc.join()
        signal = f"signal {-proc.exitcode}" if proc.exitcode is not None and proc.exitcode < 0 else f"exit code {proc.exitcode}"
        raise MeshError(f"TetGen crashed ({signal}) filling the surface: a surface that intersects itself or is otherwise "
                        "damaged does this; repair it (closed, manifold, not self-intersecting) and run again") from None  # fmt: skip
    finally:
        parent.close()
    proc.join()
    if kind == "error":
        raise value
    return value


def _run_tetgen(vertices: np.ndarray, triangles: np.ndarray, switches: str):
    """One TetGen run, in a child process (:func:`in_child_process`): nodes (m, 3) float64 and tets (e, 4) int64,
    as TetGen orders them."""
    out = in_child_process(_tetgen_call, np.asarray(vertices), np.asarray(triangles), switches)
    nodes = np.asarray(out[0], dtype=np.float64)
    elems = np.asarray(out[1], dtype=np.int64)
    if elems.ndim != 2 or elems.shape[1] != 4 or len(elems) == 0:
        raise MeshError(f"TetGen (switches {switches!r}) returned no tets")
    return nodes, elems


#: TetGen's optimisation target: no dihedral angle above this after optimising [degrees]
MAX_DIHEDRAL_DEG = 150.0


def _base_switches(quality: tuple[float, float] | None, preserve_surface: bool) -> str:
    """TetGen switches without the volume bound: ``p``, ``q<ratio>/<dihedral>O9/7o/<max>``, ``Y``."""
    if quality is not None:
        ratio, dihedral = (float(q) for q in quality)
        if ratio < 1.0 or not (0.0 <= dihedral < 70.0):
            raise MeshError(f"quality (radius-edge ratio >= 1, 0 <= dihedral < 70) got {quality}")
        base = f"pq{ratio:g}/{dihedral:g}O9/7o/{MAX_DIHEDRAL_DEG:g}"
    else:
        base = "p"
    return base + "Y" if preserve_surface else base


class _Runs:
    """TetGen runs on one surface, keeping the one whose vertex count is closest to the target.

    ``runs`` lists ``(max volume or None, vertices, tets, seconds)`` of each run.
    """

    def __init__(self, vertices, triangles, base: str, target: int | None):
        self.vertices, self.triangles, self.base, self.target = vertices, triangles, base, target
        self.runs: list[tuple[float | None, int, int, float]] = []
        self.best: dict[str, Any] = {}

    def __call__(self, max_volume: float | None) -> int:
        """Run TetGen with the volume bound ``max_volume`` (None: none); its vertex count."""
        switches = self.base + (f"a{max_volume:.8e}" if max_volume is not None else "") + "Q"
        t0 = time.perf_counter()
        nodes, elems = _run_tetgen(self.vertices, self.triangles, switches)
        dt = time.perf_counter() - t0
        n = len(nodes)
        self.runs.append((max_volume, n, len(elems), dt))
        logger.info("tetgen %s: %d vertices, %d tets, %.2fs", switches, n, len(elems), dt)
        score = abs(n - self.target) if self.target else 0
        if not self.best or score < self.best["score"]:
            self.best.update(score=score, nodes=nodes, elems=elems, switches=switches)
        return n


def _search_max_volume(run: _Runs, n0: int, total_volume: float, tolerance: float,
                       max_runs: int) -> None:
    """Search the maximum tet volume ``a`` whose run gives ``run.target`` vertices.

    The interior vertex count is modelled as ``n - n0 = C a**-p`` (``n0``: the
    count without a volume bound): starting at ``a = 0.2 V / (target - n0)``
    and ``p = 1``, each step moves ``log a`` by ``(log(n - n0) - log(target -
    n0)) / p`` (at most a factor 10, ``p`` refitted from the last two runs),
    and once the target is bracketed ``log a`` is interpolated linearly in
    ``log(n - n0)``.  Stops within ``tolerance`` or after ``max_runs`` runs in all.
    """
    target = run.target
    runs = run.runs
    a = 0.2 * total_volume / (target - n0)
    lo = hi = None  # (log a, log(n - n0)) with n below / above target
    p = 1.0
    want = math.log(target - n0)
    for _ in range(max_runs - 1):
        n = run(a)
        if abs(n - target) <= tolerance * target:
            break
        la, ln = math.log(a), math.log(max(n - n0, 1))
        if n < target:
            lo = (la, ln)
        else:
            hi = (la, ln)
        if lo is not None and hi is not None and lo[1] != hi[1]:
            # interpolate log a linearly in log(n - n0) between the bracket
            s = (want - lo[1]) / (hi[1] - lo[1])
            la_new = lo[0] + s * (hi[0] - lo[0])
            margin = 0.1 * abs(lo[0] - hi[0])
            la_new = min(max(la_new, min(lo[0], hi[0]) + margin), max(lo[0], hi[0]) - margin)
        else:
            if len(runs) >= 3 and runs[-2][0] is not None and runs[-2][1] > n0 \
                    and runs[-2][1] != n:
                la2, ln2 = math.log(runs[-2][0]), math.log(runs[-2][1] - n0)
                if la2 != la:
                    p = min(max(-(ln - ln2) / (la - la2), 0.3), 3.0)
            step = (ln - want) / p
            la_new = la + min(max(step, -math.log(10.0)), math.log(10.0))
        a = math.exp(la_new)


def _positive_tets(nodes: np.ndarray, elems: np.ndarray):
    """TetGen's output with positively oriented tets and without unreferenced nodes."""
    vol = tet_volumes(nodes, elems)
    neg = vol < 0
    if neg.any():
        elems = reorient(elems, neg)
        logger.info("tetrahedralize: reoriented %d tets", int(neg.sum()))
    if (vol == 0).any():
        raise MeshError(f"TetGen produced a zero-volume tet (index {int(np.argmax(vol == 0))})")
    kept_nodes, elems, kept = remove_unreferenced(nodes, elems)
    if len(kept) != len(nodes):
        logger.info("tetrahedralize: dropped %d unreferenced TetGen nodes", len(nodes) - len(kept))
    return kept_nodes, elems


def improve_slivers(nodes: np.ndarray, tets: np.ndarray, fixed: np.ndarray,
                    below_deg: float = 10.0, rounds: int = 4) -> tuple[np.ndarray, int]:
    """Move free vertices of tets with a dihedral angle below ``below_deg`` to raise it.

    Each round visits the free vertices of such tets once, worst tet first, and
    tries moving the vertex part of the way (1, 1/2, 1/4) to the centroid of
    its neighbours, or away from the bad tet's opposite face by 0.05 to 0.3
    of its mean edge length; the move that raises the smallest dihedral angle
    of the tets around the vertex most, inverting none, is kept (a greedy
    local optimisation, as in Freitag & Ollivier-Gooch 1997).  TetGen's own optimisation
    leaves a few tets near 5 degrees where the surface meets the interior.

    Parameters
    ----------
    nodes : (n, 3) float64
    tets : (e, 4) int64, positively oriented.
    fixed : (n,) bool, vertices that must not move (the surface).
    below_deg : float, the tets worked on.
    rounds : int

    Returns
    -------
    nodes : (n, 3) float64, a copy with the moved vertices.
    moved : int, the number of moves made.
    """
    nodes = nodes.copy()
    start, vt = cells_around_vertices(tets, len(nodes))
    moved = 0
    for _ in range(rounds):
        angle = tet_min_dihedral(nodes, tets)
        bad = np.flatnonzero(angle < below_deg)
        if bad.size == 0:
            break
        before = moved
        visited = fixed.copy()
        for t in bad[np.argsort(angle[bad])]:
            for v in tets[t]:
                if visited[v]:
                    continue
                visited[v] = True
                star = tets[vt[start[v]:start[v + 1]]]
                x = nodes[star]  # (s, 4, 3)
                old = nodes[v]
                ring = np.unique(star)
                others = nodes[ring[ring != v]]
                # away from the opposite face of the bad tet, scaled by the local edge length
                f = nodes[tets[t][tets[t] != v]]
                up = np.cross(f[1] - f[0], f[2] - f[0])
                up *= np.sign(up @ (old - f[0])) / max(np.linalg.norm(up), 1e-300)
                h = np.linalg.norm(others - old, axis=1).mean()
                moves = np.vstack([np.outer([0.0, 1.0, 0.5, 0.25], others.mean(axis=0) - old),
                                   np.outer([0.05, 0.1, 0.2, 0.3], h * up)])
                xs = np.repeat(x[None], len(moves), axis=0)  # (c, s, 4, 3)
                corner = star == v
                xs[:, corner] = (old + moves)[:, None, :]
                xs = xs.reshape(-1, 4, 3)
                e = xs[:, 1:] - xs[:, :1]
                volume_ok = (np.linalg.det(e) > 0).reshape(len(moves), -1).all(axis=1)
                worst = dihedral_angles(xs).min(axis=1).reshape(len(moves), -1).min(axis=1)
                worst[~volume_ok] = -np.inf
                k = int(np.argmax(worst))
                if k > 0 and worst[k] > worst[0]:
                    nodes[v] = old + moves[k]
                    moved += 1
        if moved == before:
            break
    return nodes, moved


def tetrahedralize(
    vertices: np.ndarray,
    triangles: np.ndarray,
    target_vertices: int | None = None,
    quality: tuple[float, float] | None = (2.0, 10.0),
    *,
    tolerance: float = 0.05,
    max_runs: int = 8,
    preserve_surface: bool = True,
    return_info: bool = False,
):
    """Fill a closed triangle surface with tetrahedra using TetGen.

    The surface is first checked with :func:`check_closed_surface`.  TetGen
    runs with ``p`` (piecewise linear complex), ``q<ratio>/<dihedral>``
    (quality bound) when ``quality`` is given, ``Y`` when
    ``preserve_surface`` (no Steiner points on the surface: the boundary of
    the result is exactly the input triangles) and ``a<volume>`` (maximum tet
    volume) while searching for ``target_vertices``.

    Vertex count.  TetGen only adds vertices, so the first run (quality bound,
    no volume bound) gives the fewest vertices reachable: if that is already
    within ``tolerance`` of the target, or above it, it is returned (a count
    far above the target is logged: decimate the surface first, see
    :func:`tetrahedralize_to`).  Otherwise a maximum volume is searched (see
    :func:`_search_max_volume`) for at most ``max_runs`` TetGen runs in all;
    the run closest to the target is returned.  On the Stanford bunny (2,823
    surface vertices) the quality run alone gives 3,543 vertices / 12,037 tets
    in ~0.1 s.

    With ``quality``, the interior vertices of the tets TetGen leaves under 10
    degrees are then moved by :func:`improve_slivers` (the surface stays).

    Parameters
    ----------
    vertices : (n, 3) float
    triangles : (t, 3) int, closed, outward oriented (orientation consistency
        is checked; a surface oriented inward still works since TetGen does
        not care, and the output tets are oriented positively regardless).
    target_vertices : int, optional
    quality : (max radius-edge ratio, min dihedral angle in degrees) or None
        for no quality refinement.  TetGen meets the radius-edge bound; the
        dihedral bound is a goal of its optimisation, not a guarantee (a
        surface kept by ``preserve_surface`` with sliver-shaped triangles
        forces slivers): check the result with :func:`check_mesh`.
    tolerance : float
        Relative distance to ``target_vertices`` that stops the search.
    max_runs : int
        Maximum number of TetGen runs.
    preserve_surface : bool
        Pass ``Y`` so the surface is not refined.
    return_info : bool
        Also return a dict: ``runs`` (list of (max volume or None, vertices,
        tets, seconds)), ``switches`` of the chosen run, ``seconds`` in all.

    Returns
    -------
    vertices : (m, 3) float64; the input surface vertices that are used come
        first, in their input order (unreferenced input vertices are dropped).
    tets : (e, 4) int64, positively oriented.
    info : dict, only if ``return_info``.

    Raises
    ------
    MeshError
        Open / non-manifold / inconsistently oriented surface (naming an
        edge), or a TetGen failure (e.g. self-intersecting surface).
    """
    v, tri = _checked_surface(vertices, triangles)
    base = _base_switches(quality, preserve_surface)
    if target_vertices is not None:
        target_vertices = positive_int(target_vertices, "target_vertices")
    max_runs = positive_int(max_runs, "max_runs")

    run = _Runs(v, tri, base, target_vertices)
    t_start = time.perf_counter()
    _run_to_target(run, v, tri, target_vertices, tolerance, max_runs)
    nodes, elems = _positive_tets(run.best["nodes"], run.best["elems"])
    if quality is not None:
        nodes = _improve_interior(nodes, elems)
    seconds = time.perf_counter() - t_start
    logger.info("tetrahedralize: %d vertices, %d tets (target %s) in %d runs, %.2fs",
                len(nodes), len(elems), target_vertices, len(run.runs), seconds)
    if return_info:
        return nodes, elems, {"runs": run.runs, "switches": run.best["switches"],
                              "seconds": seconds}
    return nodes, elems


def _checked_surface(vertices, triangles) -> tuple[np.ndarray, np.ndarray]:
    """The input of :func:`tetrahedralize` checked (finite (n, 3) vertices, a closed, consistently oriented
    (t, 3) surface) and without unreferenced vertices: (vertices (m, 3) float64, triangles (t, 3) int64)."""
    v = as_vertices(vertices)
    tri = as_cells(triangles, 3, "triangle", len(v))
    require_finite(v, "tetrahedralize")
    check_closed_surface(tri)
    v, tri, _ = remove_unreferenced(v, tri)
    return v, tri


def _run_to_target(run: _Runs, v: np.ndarray, tri: np.ndarray, target_vertices: int | None,
                   tolerance: float, max_runs: int) -> None:
    """The quality run (no volume bound), then, where it gives fewer vertices than ``target_vertices``
    by more than ``tolerance``, the search for a maximum volume (:func:`_search_max_volume`) over the
    surface v (n, 3), tri (t, 3); ``run.best`` holds the run closest to the target."""
    n0 = run(None)
    if target_vertices is not None and n0 > target_vertices * (1 + tolerance):
        logger.info(
            "tetrahedralize: the quality run already gives %d vertices (target %d); TetGen "
            "cannot coarsen (tetrahedralize_to remeshes or decimates the surface)", n0,
            target_vertices)
    if target_vertices is not None and n0 < target_vertices * (1 - tolerance):
        _search_max_volume(run, n0, abs(enclosed_volume(v, tri)), tolerance, max_runs)


def _improve_interior(nodes: np.ndarray, elems: np.ndarray) -> np.ndarray:
    """nodes (n, 3) with the interior vertices of the slivers moved by :func:`improve_slivers` (the
    surface of the tets elems (e, 4) stays), the smallest dihedral angle before and after logged."""
    fixed = np.zeros(len(nodes), dtype=bool)
    fixed[surface_of(elems)] = True
    before = float(tet_min_dihedral(nodes, elems).min())
    nodes, moved = improve_slivers(nodes, elems, fixed)
    logger.info("tetrahedralize: %d interior vertex moves, smallest dihedral angle "
                "%.3g -> %.3g degrees", moved, before,
                float(tet_min_dihedral(nodes, elems).min()))
    return nodes


def _decimated(vertices: np.ndarray, triangles: np.ndarray, reduction: float, name: str):
    """The surface simplified by quadric edge collapse (fraction ``reduction`` of it
    removed), near-coincident vertices welded, checked closed."""
    # fast_simplification is only needed when a surface is denser than the target
    import fast_simplification

    v2, f2 = fast_simplification.simplify(vertices, triangles.astype(np.int32),
                                          target_reduction=reduction)
    v2, f2 = weld(np.asarray(v2, dtype=np.float64), np.asarray(f2, dtype=np.int64),
                  1e-7 * np.ptp(vertices, axis=0).max())
    check_closed_surface(f2.astype(np.int64), name=f"{name} (decimated {reduction:.2f})")
    return v2.astype(np.float64), f2.astype(np.int64)


#: a surface whose fill has a smaller dihedral angle than this [degrees] is remeshed
REMESH_BELOW_DEG = 5.0
#: first guess of the surface's share of a filled mesh's vertices, for the remeshing length
SURFACE_SHARE = 0.55


def _remeshed_fill(vertices, triangles, target: int, name: str, tolerance: float, runs: int,
                   quality):
    """Remesh the surface isotropically, then fill it; shrink the surface while TetGen's
    quality run alone overshoots the target."""
    share = SURFACE_SHARE
    best = None
    for _ in range(runs):
        length = edge_length_for(vertices, triangles, int(round(share * target)))
        v2, f2 = remesh_isotropic(vertices, triangles, length, name=name)
        vv, tt, info = tetrahedralize(v2, f2, target_vertices=target, quality=quality,
                                      return_info=True)
        logger.info("%s: remeshed to edge length %.4g, %d surface vertices: %d vertices",
                    name, length, len(v2), len(vv))
        if best is None or abs(len(vv) - target) < abs(len(best[0]) - target):
            best = (vv, tt)
        n0 = info["runs"][0][1]  # the quality run's count: the fewest this surface allows
        if len(vv) <= target * (1 + tolerance) or n0 <= target * (1 + tolerance):
            break
        share *= 0.97 * target / n0
    return best


def tetrahedralize_to(vertices: np.ndarray, triangles: np.ndarray, target: int, name: str,
                      tolerance: float = 0.05, runs: int = 8,
                      quality: tuple[float, float] | None = (2.0, 10.0), remesh: bool = True):
    """TetGen to about ``target`` vertices, after remeshing or decimating the surface.

    The surface is first filled as it is.  With ``remesh`` (the default), unless
    that fill has at most ``tolerance`` more vertices than the target and no
    dihedral angle under :data:`REMESH_BELOW_DEG` (so a clean CAD surface
    keeps its sharp edges, which the remeshing would round), the surface is
    remeshed isotropically
    (:func:`~latentsim.mesh.remesh.remesh_isotropic`, enclosed volume kept) to
    the edge length of :data:`SURFACE_SHARE` of ``target`` vertices, which
    TetGen then keeps; while TetGen's quality run alone gives more than the
    target, the surface is remeshed coarser (at most ``runs`` times).
    Near-equilateral surface triangles are what let TetGen avoid slivers: a
    decimated surface's needles force them.

    Without ``remesh``, when TetGen's output is above the target, the surface
    is simplified by quadric edge collapse (``fast_simplification``), the
    reduction bisected until TetGen's output lies within ``tolerance`` of the
    target (or the closest run is kept).

    Parameters
    ----------
    vertices : (n, 3) float64
    triangles : (t, 3) int64, a closed outward-oriented surface.
    target : int, the vertex count wanted.
    name : str, used in messages.
    tolerance : float, relative distance to ``target`` that stops the search.
    runs : int, at most this many remeshings or decimations.
    quality : (max radius-edge ratio, min dihedral angle in degrees) or None,
        see :func:`tetrahedralize`.
    remesh : bool, remesh the surface first (else decimate it where needed).

    Returns
    -------
    vertices : (m, 3) float64
    tets : (e, 4) int64, positively oriented.
    """
    V_t, T_t = tetrahedralize(vertices, triangles, target_vertices=target, quality=quality)
    if remesh:
        angle = float(tet_min_dihedral(V_t, T_t).min())
        if len(V_t) <= target * (1 + tolerance) and angle >= REMESH_BELOW_DEG:
            logger.info("%s: the surface as given fills to %d vertices, smallest dihedral angle "
                        "%.3g degrees: not remeshed", name, len(V_t), angle)
            return V_t, T_t
        V_t, T_t = _remeshed_fill(vertices, triangles, target, name, tolerance, runs, quality)
        logger.info("%s: %d vertices for a target of %d", name, len(V_t), target)
        return V_t, T_t
    if len(V_t) <= target * (1 + tolerance):
        return V_t, T_t
    best = (V_t, T_t)
    lo, hi = 0.0, 0.95
    for _ in range(runs):
        r = 0.5 * (lo + hi)
        try:
            v2, f2 = _decimated(vertices, triangles, r, name)
            vv, tt = tetrahedralize(v2, f2, target_vertices=target, quality=quality)
        except MeshError as e:
            logger.info("decimation %.3f of %s rejected: %s", r, name, e)
            hi = r
            continue
        if abs(len(vv) - target) < abs(len(best[0]) - target):
            best = (vv, tt)
        if len(vv) > target * (1 + tolerance):
            lo = r
        elif len(vv) < target * (1 - tolerance):
            hi = r
        else:
            break
    logger.info("%s: %d vertices for a target of %d", name, len(best[0]), target)
    return best
