"""The package's structure as docs/architecture.md draws it: current, without import cycles, and no function over 100 lines."""

import ast
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


def test_packages_depend_on_one_another_in_layers():
    """No two packages import each other, even through different modules: physics below solve, the
    methods above both, stages on top (docs/architecture.md)."""
    tool = load_tool()
    mods, edges, hidden = tool.graph()
    packages = {}
    for m in mods:
        for d in edges[m] | set(hidden.get(m, ())):
            a, b = tool.package_of(m), tool.package_of(d)
            if a != b and "latentsim" not in (a, b):
                packages.setdefault(a, set()).add(b)
    assert tool.cycles(packages) == []
    assert "physics" in packages.get("solve", set()) and not packages.get("physics")


def test_architecture_doc_is_what_the_code_says():
    proc = subprocess.run([sys.executable, str(ROOT / "tools" / "architecture.py"), "--check"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


MAX_FUNCTION_LINES = 100
#: the training loop's own limit: a feature beyond the paper is a piece that feeds it data (latent/features.py)
MAX_FIT_INTEGRATOR_LINES = 60


def test_no_function_in_the_package_is_longer_than_the_limit():
    """Every function and method of src/ (docstring included) is at most MAX_FUNCTION_LINES lines long."""
    long, fit = {}, None
    for path in sorted((ROOT / "src").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long[f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"] = lines
                if node.name == "fit_integrator":
                    fit = lines
    assert long == {}, f"functions over {MAX_FUNCTION_LINES} lines (split them into helpers): {long}"
    assert fit is not None and fit < MAX_FIT_INTEGRATOR_LINES, f"fit_integrator is {fit} lines"
