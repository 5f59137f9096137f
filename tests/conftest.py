"""Shared test fixtures and markers.

Tests live in three folders: ``unit`` (functions and classes on tiny inputs), ``physics`` (energies,
solvers and analytic benchmarks) and ``workflow`` (Snakemake end to end, the benchmark scripts' smoke
runs).  Everything under ``workflow`` is marked ``slow``: ``pytest -m "not slow" tests`` is the quick loop.
"""

from pathlib import Path

import pytest
import torch

WORKFLOW = Path(__file__).resolve().parent / "workflow"


def pytest_collection_modifyitems(config, items):
    for item in items:
        if WORKFLOW in Path(str(item.fspath)).resolve().parents:
            item.add_marker(pytest.mark.slow)


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
