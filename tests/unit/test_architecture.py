"""The package's structure as docs/architecture.md draws it: current, and without import cycles."""

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def load_tool():
    spec = importlib.util.spec_from_file_location("architecture", ROOT / "tools" / "architecture.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cycle_finder_finds_a_cycle_and_only_a_cycle():
    tool = load_tool()
    assert tool.cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert tool.cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_modules_import_one_another_without_a_cycle():
    """Counting imports inside function bodies too: a cycle hidden there is still a cycle."""
    tool = load_tool()
    mods, edges, hidden = tool.graph()
    assert len(mods) > 20
    every = {m: edges[m] | set(hidden.get(m, ())) - {m, "latentsim"} for m in mods}
    assert tool.cycles(every) == []


def test_architecture_doc_is_what_the_code_says():
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "architecture.py"), "--check"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
