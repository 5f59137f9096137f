"""Atomic artefact writes: a killed writer leaves no file that looks complete."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import pytest

from latentsim.io import atomic_h5, read_config_attr


def test_provenance_attributes(tmp_path):
    path = tmp_path / "a.h5"
    with atomic_h5(path, config={"dt": 0.1}, seed=7) as f:
        f["x"] = [1, 2]
    with h5py.File(path) as f:
        assert read_config_attr(f) == {"dt": 0.1}
        assert f.attrs["seed"] == 7 and f.attrs["latentsim_version"]


def test_exception_leaves_nothing(tmp_path):
    path = tmp_path / "a.h5"
    with pytest.raises(RuntimeError):
        with atomic_h5(path) as f:
            f["x"] = [1]
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_sigkill_mid_write_leaves_no_final_file(tmp_path):
    path = tmp_path / "out.h5"
    flag = tmp_path / "writing"
    code = textwrap.dedent(
        f"""
        import time, numpy as np
        from pathlib import Path
        from latentsim.io import atomic_h5
        with atomic_h5({str(path)!r}) as f:
            f["a"] = np.zeros((1000, 1000))
            Path({str(flag)!r}).touch()
            time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code])
    try:
        for _ in range(300):
            if flag.exists():
                break
            time.sleep(0.05)
        assert flag.exists(), "writer never started"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not path.exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "writing"]
    assert leftovers and all(n.startswith(".out.h5.tmp-") for n in leftovers)
