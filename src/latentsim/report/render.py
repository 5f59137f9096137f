"""Looking at motions: rendered frames and clips of any trajectory file.

Every function reads the trajectory layout of ``docs/artefacts.md`` (ground
truth ``trajectories.h5`` and rollouts ``rollout.h5`` alike, through
:func:`latentsim.report.motion.load_motion`) or an already loaded
:class:`~latentsim.report.motion.Motion`, and writes one file atomically
(:func:`latentsim.io.atomic_path`).  The ParaView series of the same files
are :func:`latentsim.report.paraview.write_xdmf_series`.

- :func:`render_frames`: ground truth against each method, side by side, at
  chosen frames (matplotlib 3D: rods as polylines, shells and the boundary
  faces of tets as shaded triangles, Dirichlet vertices in red); every panel
  shares the same axes; a method that has diverged by a frame gets an empty
  panel naming its divergence frame;
- :func:`render_clip`: the same side by side as an animated GIF (Pillow), or
  MP4 where ffmpeg exists.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import animation
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from latentsim.io import atomic_path
from latentsim.report.motion import Motion, load_motion
from latentsim.report.plots import save_figure

__all__ = ["Motion", "have_ffmpeg", "load_motion", "render_clip", "render_frames"]

_LIGHT = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])


def _as_motion(obj, sequence, frames, label) -> Motion:
    if isinstance(obj, Motion):
        if obj.sequence != sequence:
            raise ValueError(f"motion {obj.label!r} holds sequence {obj.sequence!r}, not {sequence!r}")
        return obj
    return load_motion(obj, sequence, frames=frames, label=label)


def _load_all(truth, methods, sequence, frames):
    gt = _as_motion(truth, sequence, frames, "ground truth")
    if isinstance(methods, (str, os.PathLike, Motion)):
        methods = {None: methods}
    out = [gt]
    for name, m in (methods or {}).items():
        mo = _as_motion(m, sequence, frames, name)
        if mo.rest.shape != gt.rest.shape:
            raise ValueError(
                f"method {mo.label!r}, sequence {sequence!r}: {mo.rest.shape[0]} vertices, ground truth has {gt.rest.shape[0]}"
            )
        out.append(mo)
    return out


def _limits(motions, frames, bounds: str) -> np.ndarray:
    """(3,2) axis limits: the ground truth's (``truth``) or every motion's (``all``) finite
    positions at ``frames``; the rest shape when none is finite."""
    use = motions[:1] if bounds == "truth" else motions
    pts = []
    for m in use:
        for fr in frames:
            x = m.at(fr)
            if x is not None:
                pts.append(x[np.isfinite(x).all(axis=1)])
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    if not len(P):
        P = motions[0].rest
    lo, hi = P.min(axis=0), P.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    # flat objects (a cloth at rest) get depth, so out-of-plane motion stays in view
    half = np.maximum(half * 1.08, 0.15 * half.max() + 1e-9)
    return np.stack([centre - half, centre + half], axis=1)


def _shade(x: np.ndarray, tris: np.ndarray, rgb) -> np.ndarray:
    """(F,4) face colours, Lambert shading two-sided (cloth is seen from both sides).

    ``rgb`` is one colour (3,) or one per face (F,3).
    """
    a, b, c = x[tris[:, 0]], x[tris[:, 1]], x[tris[:, 2]]
    nrm = np.cross(b - a, c - a)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    k = 0.35 + 0.65 * np.abs(nrm @ _LIGHT)
    base = np.broadcast_to(np.asarray(rgb, dtype=float)[..., :3], (len(tris), 3))
    col = np.empty((len(tris), 4))
    col[:, :3] = np.clip(base * k[:, None], 0, 1)
    col[:, 3] = 1.0
    return col


def _setup_axes(ax, limits, vertical: int, elev, azim):
    ax.set_xlim(*limits[0])
    ax.set_ylim(*limits[1])
    ax.set_zlim(*limits[2])
    ax.view_init(elev=elev, azim=azim, vertical_axis="xyz"[vertical])
    # after view_init: matplotlib stores the aspect relative to the current vertical axis
    ax.set_box_aspect(np.maximum(limits[:, 1] - limits[:, 0], 1e-9))
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])


def _circle(centre, e1, e2, radius, n=24, arc=2 * np.pi) -> np.ndarray:
    """(n-1, 2, 3) segments of a circle (or an arc of ``arc`` radians from e1) in the plane of e1, e2."""
    t = np.linspace(0.0, arc, n)
    p = np.asarray(centre, float) + radius * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    return np.stack([p[:-1], p[1:]], axis=1)


def _frame_of(axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit vector along ``axis`` and two unit vectors perpendicular to it and to each other."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return u, e1, np.cross(u, e1)


def collider_segments(colliders, limits) -> np.ndarray:
    """(S, 2, 3) line segments of a wireframe of each collider (a scene's ``contact.colliders`` entries:
    dicts of ``type`` half_space, sphere, capsule or mesh and their parameters, a mesh's with its surface's ``vertices``
    and ``triangles``); a half-space's plane as a grid across the axis ``limits`` (3, 2), a mesh's edges."""
    segs = []
    span = float(np.max(limits[:, 1] - limits[:, 0]))
    for c in colliders:
        kind = c["type"]
        if kind == "sphere":
            o, r = np.asarray(c["centre"], float), float(c["radius"])
            z = np.eye(3)
            for k in range(6):  # meridians through the poles on the y axis, and parallels
                a = np.pi * k / 6
                segs.append(_circle(o, np.cos(a) * z[0] + np.sin(a) * z[2], z[1], r))
            for h in (-0.7, -0.35, 0.0, 0.35, 0.7):
                segs.append(_circle(o + h * r * z[1], z[0], z[2], r * np.sqrt(1 - h * h)))
        elif kind == "capsule":
            a, b, r = np.asarray(c["a"], float), np.asarray(c["b"], float), float(c["radius"])
            u, e1, e2 = _frame_of(b - a)
            for k in range(8):
                d = r * (np.cos(np.pi * k / 4) * e1 + np.sin(np.pi * k / 4) * e2)
                segs.append(np.array([[a + d, b + d]]))
            for end, s in ((a, -1.0), (b, 1.0)):
                segs.append(_circle(end, e1, e2, r))
                for k in range(4):  # the end cap's half meridians
                    w = np.cos(np.pi * k / 4) * e1 + np.sin(np.pi * k / 4) * e2
                    segs.append(_circle(end, w, s * u, r, n=12, arc=np.pi))
        elif kind == "half_space":
            p, (n, e1, e2) = np.asarray(c["point"], float), _frame_of(c["normal"])
            centre = limits.mean(axis=1)
            base = centre - np.dot(centre - p, n) * n  # the view's centre projected onto the plane
            for t in np.linspace(-span, span, 9):
                segs.append(np.array([[base + t * e1 - span * e2, base + t * e1 + span * e2]]))
                segs.append(np.array([[base + t * e2 - span * e1, base + t * e2 + span * e1]]))
        elif kind == "mesh":  # its edges (the entry carries its surface, ``vertices`` and ``triangles``)
            V, F = np.asarray(c["vertices"], float), np.asarray(c["triangles"], np.int64)
            e = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
            segs.append(V[e])
        else:
            raise ValueError(f"collider_segments: unknown collider type {kind!r}")
    return np.concatenate(segs) if segs else np.zeros((0, 2, 3))


def _at_frame(colliders, frame: int):
    """The collider entries to draw at ``frame``: ``colliders`` itself (static ones), or what it gives for
    the frame when it is a function of the frame (colliders that move with the boundary-condition program)."""
    return colliders(frame) if callable(colliders) else colliders


def _draw_panel(ax, motion: Motion, frame: int, limits, vertical, elev, azim, colour, title=True, values=None, cmap=None, colliders=()):
    """Draw one motion at one frame on a 3D axis; returns the panel's status.

    ``values`` (n,) in [0, 1], optional, colour the elements through ``cmap``
    (mean over each element's vertices) instead of the flat ``colour``; ``colliders`` (a scene's
    ``contact.colliders``) are drawn as grey wireframes.
    """
    ax.cla()
    _setup_axes(ax, limits, vertical, elev, azim)
    if len(colliders):
        ax.add_collection3d(Line3DCollection(collider_segments(colliders, limits), colors="0.55", linewidths=0.4), autolim=False, axlim_clip=True)
    status = motion.status(frame)
    head = f"{motion.label}\nframe {frame}" if title else None
    if status != "ok":
        for a in (ax.xaxis, ax.yaxis, ax.zaxis):
            a.pane.set_alpha(0.0)
        ax.grid(False)
        if status == "diverged":
            f0 = motion.diverged_frame if motion.diverged_frame >= 0 else frame
            msg = f"diverged at frame {f0}"
        else:
            msg = f"no frame {frame}\n(sequence has {motion.n_frames})"
        ax.text2D(0.5, 0.5, msg, transform=ax.transAxes, ha="center", va="center", color="firebrick", fontsize=10)
    else:
        x = motion.at(frame)
        if motion.segments is not None:
            seg = motion.segments
            cols = [colour] if values is None else cmap(values[seg].mean(axis=1))
            ax.add_collection3d(
                Line3DCollection(x[seg], colors=cols, linewidths=0.8), autolim=False, axlim_clip=True
            )
        if motion.triangles is not None:
            tris = motion.triangles
            rgb = colour if values is None else cmap(values[tris].mean(axis=1))
            fc = _shade(x, tris, rgb)
            ax.add_collection3d(
                # edges in the face colours hide the antialiasing seams between triangles
                Poly3DCollection(x[tris], facecolors=fc, edgecolors=fc, linewidths=0.3),
                autolim=False,
                axlim_clip=True,
            )
        if len(motion.dirichlet):
            d = x[motion.dirichlet]
            ax.scatter(d[:, 0], d[:, 1], d[:, 2], s=4, c="red", depthshade=False, axlim_clip=True)
        outside = ~((x >= limits[:, 0]) & (x <= limits[:, 1])).all(axis=1)
        if outside.any() and head:
            head += f"\n{outside.mean():.0%} of vertices outside view"
    if head:
        ax.set_title(head, fontsize=9)
    return status


def _colours(n):
    cmap = plt.get_cmap("tab10")
    return [(0.45, 0.5, 0.6)] + [cmap(i % 10)[:3] for i in range(n - 1)]


_ERROR_CMAP = plt.get_cmap("viridis")  # no red in it: red marks the Dirichlet vertices


def _vertex_errors(motions, frames):
    """Per-vertex distance to the ground truth (motions[0]) of every ``ok`` panel.

    Returns ``per_vertex`` {(row, column): (n,) float} and ``errors``
    (len(frames), len(motions)) float, each panel's largest distance (NaN
    where the panel is not ``ok``).
    """
    gt = motions[0]
    errors = np.full((len(frames), len(motions)), np.nan)
    per_vertex = {}
    for i, fr in enumerate(frames):
        for j, m in enumerate(motions):
            if m.status(fr) == "ok" and gt.status(fr) == "ok":
                per_vertex[i, j] = np.linalg.norm(m.at(fr) - gt.at(fr), axis=1)
                errors[i, j] = per_vertex[i, j].max()
    return per_vertex, errors


def _error_scale(errors, error_max=None) -> float:
    """Top of the error colour scale: ``error_max`` or the largest method error shown."""
    top = error_max if error_max is not None else np.nanmax(errors[:, 1:], initial=0.0)
    return float(top) if np.isfinite(top) and top > 0 else 1.0


def _error_values(per_vertex, i, j, top):
    """Colour-map input (n,) in [0, 1] of a method panel, None for the ground truth or an empty panel."""
    return np.clip(per_vertex[i, j] / top, 0, 1) if j > 0 and (i, j) in per_vertex else None


def _error_colorbar(fig, top, bottom, height):
    cax = fig.add_axes((0.25, bottom, 0.5, height))
    sm = plt.cm.ScalarMappable(norm=plt.Normalize(0.0, top), cmap=_ERROR_CMAP)
    fig.colorbar(sm, cax=cax, orientation="horizontal", label="vertex distance to ground truth [m]")


def render_frames(
    truth,
    methods,
    sequence: str,
    frames,
    path,
    *,
    bounds="truth",
    elev=15.0,
    azim=-60.0,
    panel_size=2.8,
    dpi=100,
    title=None,
    color_by_error=False,
    error_max=None,
    wrap=None,
    colliders=(),
) -> dict:
    """Ground truth against each method, side by side, at chosen frames.

    Rows are frames, columns ground truth then the methods in the order given
    (or, with ``wrap``, a grid of frames, each a column of the motions).
    Every panel has the same axis limits and aspect, so positions compare.

    Parameters
    ----------
    truth : path of the ground-truth trajectory file, or a :class:`Motion`.
    methods : mapping method name -> path of a trajectory-layout file (a
        rollout) or :class:`Motion`; may be empty.
    sequence : str, a sequence present in every file.
    frames : sequence of int, frames to show (within the ground truth).
    path : output image (PNG unless the suffix says otherwise).
    bounds : ``"truth"`` (default) fits the axes to the ground truth at these
        frames, so a method that flies off is seen leaving the view (the panel
        says how many vertices are outside); ``"all"`` fits every finite point;
        ``"row"`` fits each row (frame) to the ground truth at that frame, for
        motions that travel far (the panels of a row still share their axes).
    elev, azim : float, view angles [degrees]; the vertical axis is y (gravity).
    colliders : a scene's ``contact.colliders`` (dicts), drawn as grey wireframes in every panel; or a
        function of the frame giving them where they stand then (attached ones move).
    color_by_error : bool
        Colour each method's elements by the distance of their vertices to the
        ground truth at the same frame (viridis, one scale for the whole
        figure, colour bar at the bottom) instead of a flat colour.
    error_max : float or None
        Top of that scale [m]; default the largest error shown.
    wrap : int or None
        Lay many frames out as a grid: the frames run left to right, ``wrap``
        to a line, each frame a column of the motions (ground truth on top),
        the lines one under the other.  None: one row per frame.

    Returns
    -------
    dict with ``status`` ((len(frames), 1 + len(methods)) array of str:
    ``ok``, ``diverged`` or ``missing``), ``labels`` (column labels),
    ``limits`` ((len(frames), 3, 2) axis limits of each row) and
    ``max_error`` ((len(frames), 1 + len(methods)) float: largest vertex
    distance to the ground truth in each panel [m], 0 for the ground truth,
    NaN where a panel is not ``ok``).
    """
    frames = _checked_frames(frames, bounds)
    motions = _load_all(truth, methods, sequence, frames)
    gt = motions[0]
    bad = [f for f in frames if not 0 <= f < gt.n_frames]
    if bad:
        raise ValueError(f"render_frames: frames {bad} outside sequence {sequence!r} of the ground truth ({gt.n_frames} frames)")
    limits = _row_limits(motions, frames, bounds)
    R, C = len(frames), len(motions)
    per_vertex, errors = _vertex_errors(motions, frames)
    per_line, shape, place = _panel_grid(R, C, wrap)
    header, footer = 0.9, (0.8 if color_by_error else 0.0)  # inches for the title and the colour bar
    height = panel_size * shape[0] + header + footer
    fig = plt.figure(figsize=(panel_size * shape[1], height))
    top = _error_scale(errors, error_max)
    panel = lambda i, j: fig.add_subplot(shape[0], shape[1], place(i, j), projection="3d")  # noqa: E731
    status = _draw_panels(panel, motions, frames, limits, per_vertex if color_by_error else None, top, elev, azim, colliders)
    fig.suptitle(title or f"{sequence}: ground truth vs methods (red: Dirichlet vertices)", fontsize=10)
    fig.subplots_adjust(
        left=0.01, right=0.99, bottom=(footer + 0.05) / height, top=1 - header / height, wspace=0.02, hspace=0.2 if per_line is None else 0.3
    )
    if color_by_error:
        _error_colorbar(fig, top, 0.45 / height, 0.12 / height)
    save_figure(fig, path, dpi)
    return {"status": status.astype(str), "labels": [m.label for m in motions], "limits": limits, "max_error": errors}


def _checked_frames(frames, bounds: str) -> list[int]:
    """``frames`` as ints, refused when there are none or ``bounds`` is not one :func:`render_frames` knows."""
    frames = [int(f) for f in frames]
    if not frames:
        raise ValueError("render_frames: no frames given")
    if bounds not in ("truth", "all", "row"):
        raise ValueError(f"render_frames: bounds must be 'truth', 'all' or 'row', got {bounds!r}")
    return frames


def _row_limits(motions, frames, bounds: str) -> np.ndarray:
    """(len(frames), 3, 2) axis limits of each row: each frame's own ground truth (``bounds`` row), else the
    limits of ``bounds`` over every frame, repeated."""
    if bounds == "row":
        return np.stack([_limits(motions, [fr], "truth") for fr in frames])
    return np.repeat(_limits(motions, frames, bounds)[None], len(frames), axis=0)


def _panel_grid(R: int, C: int, wrap):
    """(frames a line or None, grid shape (rows, columns), place(i, j)): the subplot number of frame i,
    motion j among R frames of C motions, one row per frame, or ``wrap`` frames to a line."""
    if wrap is not None and int(wrap) < 1:
        raise ValueError(f"render_frames: wrap must be a positive number of frames, got {wrap}")
    per_line = None if wrap is None else min(int(wrap), R)
    shape = (R, C) if per_line is None else (-(-R // per_line) * C, per_line)
    place = (lambda i, j: i * C + j + 1) if per_line is None else (lambda i, j: ((i // per_line) * C + j) * per_line + i % per_line + 1)
    return per_line, shape, place


def _draw_panels(panel, motions, frames, limits, per_vertex, top, elev, azim, colliders) -> np.ndarray:
    """Draw motion j at frame i on new 3D axes ``panel(i, j)``, coloured by error where ``per_vertex`` (from
    :func:`_vertex_errors`) is given, on the scale's ``top``; returns the (len(frames), len(motions)) status."""
    colours = _colours(len(motions))
    status = np.empty((len(frames), len(motions)), dtype=object)
    for i, fr in enumerate(frames):
        for j, m in enumerate(motions):
            values = None if per_vertex is None else _error_values(per_vertex, i, j, top)
            status[i, j] = _draw_panel(panel(i, j), m, fr, limits[i], m.vertical, elev, azim, colours[j], values=values, cmap=_ERROR_CMAP, colliders=_at_frame(colliders, fr))
    return status


def have_ffmpeg() -> bool:
    """Whether matplotlib can write MP4 (an ``ffmpeg`` executable is on the PATH)."""
    return animation.writers.is_available("ffmpeg")


def render_clip(
    truth,
    methods,
    sequence: str,
    path,
    *,
    start=0,
    stride=5,
    max_frames=60,
    fps=12,
    bounds="truth",
    elev=15.0,
    azim=-60.0,
    panel_size=2.6,
    dpi=90,
    title=None,
    color_by_error=False,
    error_max=None,
    wrap=None,
    colliders=(),
) -> dict:
    """Animated clip of ground truth and methods side by side (GIF, or MP4 with ffmpeg).

    Frames ``start, start + stride, ...`` up to ``max_frames`` of them and the
    ground truth's end; only those frames are read from the files.  With the
    defaults (90 dpi, 60 frames) a two-panel clip is a few hundred kB.

    Parameters
    ----------
    truth, methods, sequence : as in :func:`render_frames` (``methods`` may
        also be a single path: one rollout against the ground truth).
    bounds : ``"truth"`` or ``"all"``, as in :func:`render_frames`, over all
        the clip's frames (the camera never moves).
    path : ``.gif`` (Pillow) or ``.mp4`` (needs ffmpeg; see :func:`have_ffmpeg`).
    start, stride, max_frames : int, which frames to show.
    fps : int, frames per second of the clip.
    color_by_error, error_max : as in :func:`render_frames`; the scale is
        fixed over the whole clip (default: the largest error in any frame).
    colliders : as in :func:`render_frames`.

    Returns
    -------
    dict with ``frames`` (list of frame indices shown) and ``bytes`` (file size).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        writer = animation.PillowWriter(fps=fps)
    elif suffix == ".mp4":
        if not have_ffmpeg():
            raise RuntimeError(f"render_clip: {path} needs ffmpeg, which is not installed; write a .gif instead")
        writer = animation.FFMpegWriter(fps=fps)
    else:
        raise ValueError(f"render_clip: unsupported clip format {suffix!r} ({path}); use .gif or .mp4")
    if bounds not in ("truth", "all"):
        raise ValueError(f"render_clip: bounds must be 'truth' or 'all', got {bounds!r}")
    if stride < 1 or max_frames < 1:
        raise ValueError(f"render_clip: stride ({stride}) and max_frames ({max_frames}) must be >= 1")
    T = _as_motion(truth, sequence, [], "ground truth").n_frames  # reads no frames
    frames = list(range(start, T, stride))[:max_frames]
    if not frames:
        raise ValueError(f"render_clip: start {start} is past the end of sequence {sequence!r} ({T} frames)")
    motions = _load_all(truth, methods, sequence, frames)
    limits = _limits(motions, frames, bounds)
    C = len(motions)
    per_vertex, errors = _vertex_errors(motions, frames) if color_by_error else ({}, None)
    top = _error_scale(errors, error_max) if color_by_error else 1.0
    footer = 0.85 if color_by_error else 0.0
    height = panel_size + 0.5 + footer
    fig = plt.figure(figsize=(panel_size * C, height))
    axes = [fig.add_subplot(1, C, j + 1, projection="3d") for j in range(C)]
    colours = _colours(C)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=footer / height, top=1 - 0.5 / height, wspace=0.02)
    if color_by_error:
        _error_colorbar(fig, top, 0.5 / height, 0.1 / height)
    head = fig.suptitle("", fontsize=9)

    def update(i, fr):
        for j, (ax, m, c) in enumerate(zip(axes, motions, colours)):
            values = _error_values(per_vertex, i, j, top) if color_by_error else None
            _draw_panel(ax, m, fr, limits, m.vertical, elev, azim, c, title=False, values=values, cmap=_ERROR_CMAP, colliders=_at_frame(colliders, fr))
            ax.set_title(m.label, fontsize=8)
        head.set_text(f"{title or sequence}   frame {fr}   t = {fr * motions[0].dt:.2f} s")

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, tempfile.TemporaryDirectory(dir=path.parent, prefix=".clip-") as d:
        # the writers choose the container from the file's suffix, which the atomic temporary name lacks
        inner = Path(d) / f"clip{suffix}"
        # driving the writer directly draws each frame once (FuncAnimation.save draws it twice)
        with writer.saving(fig, inner, dpi):
            for i, fr in enumerate(frames):
                update(i, fr)
                writer.grab_frame()
        os.replace(inner, tmp)
    plt.close(fig)
    return {"frames": frames, "bytes": path.stat().st_size}
