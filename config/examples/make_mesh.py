"""Write the example scene's mesh, a ring (torus) in millimetres, as a binary STL.

    python config/examples/make_mesh.py            # writes config/examples/ring.stl

The ring stands upright in the xy plane (its axis along z), centred on the origin: major radius
``MAJOR_RADIUS`` (centre of the tube to the axis), tube radius ``TUBE_RADIUS``, ``MAJOR_SEGMENTS``
x ``TUBE_SEGMENTS`` vertices.  Units are millimetres, as CAD programs export them; the example config
scales them to metres (mesh.scale: 0.001).  The output is byte-for-byte the same on every run.

Only NumPy is needed, so this file is also a template for a mesh of one's own: any closed, consistently
oriented triangle surface in a format meshio reads (STL, OBJ, PLY, ...) will do.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

MAJOR_RADIUS = 40.0  # mm, axis to tube centre
TUBE_RADIUS = 10.0  # mm
MAJOR_SEGMENTS = 24
TUBE_SEGMENTS = 10
OUT = Path(__file__).resolve().with_name("ring.stl")


def ring_surface(R: float = MAJOR_RADIUS, r: float = TUBE_RADIUS, n: int = MAJOR_SEGMENTS,
                 m: int = TUBE_SEGMENTS) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus surface about the z axis.

    Returns
    -------
    vertices : (n * m, 3) float64
    triangles : (2 * n * m, 3) int64, counter-clockwise seen from outside (outward normals).
    """
    theta = 2 * np.pi * np.arange(n) / n  # around the axis
    phi = 2 * np.pi * np.arange(m) / m  # around the tube
    rho = R + r * np.cos(phi)  # (m,) distance from the axis
    vertices = np.stack([np.outer(np.cos(theta), rho), np.outer(np.sin(theta), rho),
                         np.broadcast_to(r * np.sin(phi), (n, m))], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + j, ((i + 1) % n) * m + j  # (theta_i, phi_j), (theta_i+1, phi_j)
    c, d = ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                                np.stack([a, c, d], -1).reshape(-1, 3)])
    return vertices, triangles


def polyhedron_volume(R: float = MAJOR_RADIUS, r: float = TUBE_RADIUS, n: int = MAJOR_SEGMENTS,
                      m: int = TUBE_SEGMENTS) -> float:
    """Exact volume of :func:`ring_surface` (mm^3): n sin(2 pi/n) R times the m-gon's area.

    (Each of the n pieces between two meridian planes is swept by the tube's m-gon along a chord;
    the smooth torus, 2 pi^2 R r^2, is the limit of large n and m.)
    """
    return n * math.sin(2 * math.pi / n) * R * 0.5 * m * r * r * math.sin(2 * math.pi / m)


def write_binary_stl(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """A binary STL (float32 facet normals and corners), written whole to a temporary file and renamed."""
    tri = vertices[triangles]  # (t, 3, 3)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    record = np.zeros(len(tri), dtype=[("normal", "<f4", 3), ("corners", "<f4", (3, 3)),
                                       ("attribute", "<u2")])
    record["normal"], record["corners"] = normal, tri
    header = b"latentsim example ring (torus), millimetres".ljust(80, b" ")
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(header)
        f.write(np.uint32(len(tri)).tobytes())
        f.write(record.tobytes())
    tmp.replace(path)


def main(argv: list[str]) -> None:
    out = Path(argv[1]) if len(argv) > 1 else OUT
    vertices, triangles = ring_surface()
    write_binary_stl(out, vertices, triangles)
    print(f"{out}: {len(vertices)} vertices, {len(triangles)} triangles, "
          f"volume {polyhedron_volume():.1f} mm^3")


if __name__ == "__main__":
    main(sys.argv)
