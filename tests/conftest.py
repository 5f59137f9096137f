"""Shared test fixtures and markers.

Tests live in three folders: ``unit`` (functions and classes on tiny inputs), ``physics`` (energies,
solvers and analytic benchmarks) and ``workflow`` (Snakemake end to end, the benchmark scripts' smoke
runs).  Everything under ``workflow`` is marked ``slow``: ``pytest -m "not slow" tests`` is the quick loop.
"""

from pathlib import Path

import pytest
import torch

WORKFLOW = Path(__file__).resolve().parent / "workflow"


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own, which reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    for item in items:
        if WORKFLOW in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.slow)
        item.add_marker(pytest.mark.xdist_group(xdist_group(item)))


def xdist_group(item) -> str:
    """The worker group of a test when the suite runs on several processes (``-n auto --dist loadgroup``):
    every test of the shared tiny run together (it runs once per worker that needs it), every other test with
    the rest of its module (a module's fixtures are built once per worker too)."""
    return "tiny_run" if "tiny_run" in getattr(item, "fixturenames", ()) else item.nodeid.split("::", 1)[0]


@pytest.fixture(autouse=True, scope="module")
def _module_default_dtype(request):
    """Modules that set ``FLOAT64 = True`` run with float64 as torch's default dtype.

    Module scope and autouse, so the default is set before the module's own
    fixtures build tensors, and restored for the modules that follow.
    """
    if not getattr(request.module, "FLOAT64", False):
        yield
        return
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


@pytest.fixture(autouse=True, scope="module")
def _module_torch_threads(request):
    """Modules that set ``ONE_THREAD = True`` run torch on one thread.

    Their networks are tiny: threading only adds overhead on shared CI cores.
    """
    if not getattr(request.module, "ONE_THREAD", False):
        yield
        return
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _icosphere(levels: int = 2):
    """A unit icosphere's closed outward surface about the origin: vertices (on the sphere) and 20 * 4**levels faces."""
    import numpy as np

    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
         [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]  # fmt: skip
    v = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(levels):
        mid, f2 = {}, []

        def m(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                p = v[a] + v[b]
                v.append(p / np.linalg.norm(p))
                mid[key] = len(v) - 1
            return mid[key]

        for a, b, c in f:
            ab, bc, ca = m(a, b), m(b, c), m(c, a)
            f2 += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = f2
    return np.array(v), np.array(f, dtype=np.int64)


@pytest.fixture
def icosphere():
    """``icosphere(levels)``: a unit icosphere's closed outward surface (vertices, faces), 20 * 4**levels faces."""
    return _icosphere

