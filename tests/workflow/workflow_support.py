"""What the workflow tests share: a copy of the repository, commands run as a user types them.

The tiny run (``conftest.tiny_run``) runs the README's command in such a copy.  The copy holds the
repository's files (no results, logs or .git) with ``../shared`` beside it pointing at the real one, so
the tiny config's ``meshes.local_dir: ../shared/meshes`` reads the same meshes and the repository's own
``results/`` is never touched.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# Only catches a hang: the tiny run takes about 2 min on a quiet 2-core machine and several times that
# with other work beside it; a correct run must never hit this.
HANG_SECONDS = 3 * 3600
TINY_COMMAND = "snakemake --cores 2 all --configfile config/tiny.yaml"
_NOT_COPIED = shutil.ignore_patterns(".git", "results", "logs", ".snakemake", "__pycache__", "*.egg-info",
                                     ".pytest_cache", "report.html", "report.zip")


def repository_copy(dest: Path) -> Path:
    """A copy of the repository at ``dest/latentsim`` with ``dest/shared`` linked to ``../shared``."""
    work = dest / "latentsim"
    shutil.copytree(ROOT, work, ignore=_NOT_COPIED, symlinks=True)
    shared = ROOT.parent / "shared"
    if shared.is_dir():
        (dest / "shared").symlink_to(shared.resolve(), target_is_directory=True)
    return work


def shell(command: str, cwd: Path, timeout: float = HANG_SECONDS, check: bool = True) -> subprocess.CompletedProcess:
    """Run ``command`` as a user types it, with this interpreter's scripts (snakemake, ...) first on PATH.

    ``check``: raise unless it exits 0."""
    env = dict(os.environ, CI="1", PATH=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    proc = subprocess.run(["bash", "-c", command], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"`{command}` in {cwd} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc


def snakemake(*args, cwd=ROOT, check=True, timeout=HANG_SECONDS):
    """``python -m snakemake`` on the repository's Snakefile (from ``cwd``, e.g. with ``--directory``)."""
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), *args]
    env = dict(os.environ, CI="1")
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}")
    return proc
