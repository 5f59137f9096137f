"""Small shared helpers: progress bars, logging, threads."""

from __future__ import annotations

import contextlib
import logging
import os
import sys

from tqdm.auto import tqdm


def progress_enabled(requested: bool | None = None) -> bool:
    """Progress bars are on unless CI is set or the caller turns them off."""
    if os.environ.get("CI"):
        return False
    return True if requested is None else bool(requested)


def progress_bar(iterable, enabled=False, **kwargs):
    """tqdm over ``iterable`` when enabled (written to stderr), else the iterable."""
    if not enabled:
        return iterable
    return tqdm(iterable, file=sys.stderr, dynamic_ncols=True, **kwargs)


def configure_threads(n: int | None = None):
    """Use ``n`` torch threads (the rule's ``threads``).

    The OpenMP/MKL wait policy is set when ``latentsim`` is imported.
    """
    if n:
        import torch  # here, not at the top: torch is slow to import and utils serves code that may not need it

        torch.set_num_threads(int(n))


def setup_logging(path=None, level=logging.INFO):
    """Log to ``path`` (the rule's log file) and to stderr."""
    handlers = [logging.StreamHandler(sys.stderr)]
    if path:
        handlers.append(logging.FileHandler(path, mode="w"))
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", handlers=handlers, force=True)


def run_stage(snakemake, main):
    """Run a stage script's ``main(snakemake)`` with logging to the rule's log file.

    Exceptions are written to the log (with traceback) and re-raised, so the
    job fails with the message in both places.
    """
    configure_threads(getattr(snakemake, "threads", None))
    log_path = snakemake.log[0] if len(snakemake.log) else None
    setup_logging(log_path)
    try:
        return main(snakemake)
    except Exception:
        logging.getLogger("latentsim").exception("stage failed")
        raise


@contextlib.contextmanager
def working_directory(path):
    """Run a block in another working directory (for libraries that write to the cwd)."""
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)
