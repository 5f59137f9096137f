"""Draw latentsim's packages and their imports from the code, into docs/architecture.md.

    python tools/architecture.py           # rewrite the diagram and the module table in the doc
    python tools/architecture.py --check   # exit 1 if the doc is not what the code says

The diagram is a Mermaid graph (GitHub and most Markdown viewers draw it): one node per package of
``src/latentsim`` (a top-level module is its own node), one arrow per package that imports another.
Only imports at module level count as arrows; imports inside function bodies are listed separately,
since they are the places where a cycle could hide.  ``tests/unit/test_architecture.py`` runs the check
and asserts that the modules import one another without a cycle.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "src" / "latentsim"
DOC = ROOT / "docs" / "architecture.md"
BEGIN, END = "<!-- BEGIN GENERATED: tools/architecture.py -->", "<!-- END GENERATED -->"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def imports(path: Path, known: set[str]) -> tuple[set[str], set[str]]:
    """(module-level, in-function) latentsim modules that ``path`` imports."""
    tree = ast.parse(path.read_text())
    top, inner = set(), set()

    def targets(node) -> set[str]:
        found = set()
        if isinstance(node, ast.Import):
            found = {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found = {node.module} | {f"{node.module}.{a.name}" for a in node.names}
        return {m for m in found if m in known}

    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            (top if node.col_offset == 0 else inner).update(targets(node))
    return top, inner


def package_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def graph():
    mods = modules()
    known = set(mods)
    edges, hidden = defaultdict(set), {}
    for name, path in mods.items():
        top, inner = imports(path, known)
        edges[name] = top - {name, "latentsim"}  # the root package holds only __version__ and thread settings
        if inner:
            hidden[name] = sorted(inner)
    return mods, edges, hidden


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), i.e. import cycles.

    A package's ``__init__`` that re-exports its submodules is not a cycle with them: a submodule
    that imports its own package's ``__init__`` is."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def render() -> str:
    mods, edges, hidden = graph()
    pkg_edges = sorted({(package_of(a), package_of(b)) for a, bs in edges.items() for b in bs if package_of(a) != package_of(b)})
    lines = ["```mermaid", "flowchart TD"]
    for pkg in sorted({package_of(m) for m in mods} - {"latentsim"}):
        lines.append(f"    {pkg}")
    lines += [f"    {a} --> {b}" for a, b in pkg_edges]
    lines.append("```")
    # structure only (no line counts), so the doc changes when the imports do, not with every edit
    lines += ["", "| module | imports (latentsim, module level) |", "|---|---|"]
    for name in mods:
        deps = ", ".join(sorted(d.removeprefix("latentsim.") for d in edges[name])) or "-"
        lines.append(f"| `{name}` | {deps} |")
    if hidden:
        lines += ["", "Imports inside function bodies (each with a comment saying why):", ""]
        lines += [f"- `{m}`: {', '.join(f'`{d}`' for d in ds)}" for m, ds in sorted(hidden.items())]
    found = cycles(edges)
    lines += ["", "Import cycles: " + ("none." if not found else "; ".join(" -> ".join(c) for c in found))]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/architecture.md is out of date")
    args = parser.parse_args(argv)
    text = DOC.read_text()
    if BEGIN not in text or END not in text:
        print(f"{DOC}: the markers {BEGIN} ... {END} are missing", file=sys.stderr)
        return 1
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    new = f"{head}{BEGIN}\n{render()}\n{END}{tail}"
    if args.check:
        if new != text:
            print(f"{DOC.relative_to(ROOT)} is out of date: run python tools/architecture.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
