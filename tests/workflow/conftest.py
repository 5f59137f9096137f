"""The tiny run that the workflow tests share: the README's command, in a copy of the repository."""

from __future__ import annotations

import time

import pytest
from workflow_support import TINY_COMMAND, repository_copy, shell


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """One complete run of the tiny config (the README's command) in a fresh copy; (folder, seconds)."""
    work = repository_copy(tmp_path_factory.mktemp("tiny_a"))
    t0 = time.perf_counter()
    shell(TINY_COMMAND, work)
    return work, time.perf_counter() - t0
