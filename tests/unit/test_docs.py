"""The docs keep up with the project.

docs/scenes.md with config/config.yaml: a section and a table row for every scene.  docs/measurements.md (what holds
now) stays short, and every link into it or into docs/measurements-archive.md (the dated record) names a heading
that is there.
"""

import re
from pathlib import Path

import pytest
import yaml

from latentsim.config import load_config
from latentsim.mesh.build import build_mesh

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "config.yaml"
SCENES_DOC = ROOT / "docs" / "scenes.md"
README = ROOT / "README.md"
MEASUREMENTS = ROOT / "docs" / "measurements.md"
MEASUREMENTS_ARCHIVE = ROOT / "docs" / "measurements-archive.md"
MEASUREMENTS_MAX_LINES = 400


def _slug(heading: str) -> str:
    """The anchor a Markdown renderer (GitHub's rule) gives a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _doc() -> str:
    return SCENES_DOC.read_text()


def _anchors(text: str) -> set[str]:
    """The anchors of a page's headings (a ``#`` line inside a fenced code block is no heading)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)
    return {_slug(m) for m in re.findall(r"^#{1,6} (.+)$", text, flags=re.MULTILINE)}


def _table_rows(text: str) -> dict[str, list[str]]:
    """The scene table's rows by scene (the first table whose header starts with ``| scene |``)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| scene | paper |"))
    rows = {}
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = cells
    return rows


def _scene_names() -> list[str]:
    return list(yaml.safe_load(CONFIG.read_text())["scenes"])


@pytest.mark.parametrize("scene", _scene_names())
def test_every_scene_has_a_section_and_a_row(scene):
    text = _doc()
    assert scene in _anchors(text), f"{SCENES_DOC}: no '## {scene}' section for scene '{scene}' of {CONFIG}"
    assert scene in _table_rows(text), f"{SCENES_DOC}: no row for scene '{scene}' in the scene table"


def test_doc_lists_no_scene_the_config_lacks():
    extra = set(_table_rows(_doc())) - set(_scene_names())
    assert not extra, f"{SCENES_DOC}: table rows for scenes not in {CONFIG}: {sorted(extra)}"


def test_config_and_doc_links_resolve():
    anchors = _anchors(_doc())
    config_links = re.findall(r"docs/scenes\.md#([\w\-]+)", CONFIG.read_text())
    doc_links = re.findall(r"\]\(#([\w\-]+)\)", _doc())
    assert config_links, f"{CONFIG}: no link to docs/scenes.md"
    missing = sorted(set(config_links + doc_links) - anchors)
    assert not missing, f"{SCENES_DOC}: no section for the anchors {missing}"


def test_table_dof_of_generated_meshes_matches_the_config():
    # The generated meshes are cheap to build; the file meshes need TetGen and are left out.
    cfg = load_config(CONFIG)
    rows = _table_rows(_doc())
    checked = 0
    for name, scene in cfg["scenes"].items():
        if scene["mesh"]["generator"] == "file":
            continue
        arrays = build_mesh(scene["model"], scene["mesh"], cfg["meshes"])
        dof = 3 * len(arrays["rest_positions"])
        assert rows[name][4] == f"{dof:,}", f"{SCENES_DOC}: scene '{name}' DoF (ours) {rows[name][4]}, mesh {dof:,}"
        checked += 1
    assert checked >= 4


def _files_that_may_link() -> list[Path]:
    """The README, the docs, and the config, code and tests whose comments may point into the docs."""
    files = [README, *sorted((ROOT / "docs").glob("*.md"))]
    for folder, pattern in (("config", "*.yaml"), ("src", "*.py"), ("tests", "*.py"), ("benchmarks", "*.py"),
                            ("tools", "*.py"), ("workflow", "*.smk")):
        files += sorted((ROOT / folder).rglob(pattern))
    return files


def _links_into(page: Path) -> dict[str, set[str]]:
    """Every anchor a file links to on ``page``, by file: ``docs/<page>#anchor`` anywhere, ``(<page>#anchor)`` from a
    page beside it in docs/, and ``(#anchor)`` on the page itself."""
    name = re.escape(page.name)
    links = {}
    for path in _files_that_may_link():
        text = path.read_text(errors="replace")
        found = set(re.findall(rf"docs/{name}#([\w\-]+)", text))
        if path.parent == page.parent:
            found |= set(re.findall(rf"\]\({name}#([\w\-]+)\)", text))
        if path == page:
            found |= set(re.findall(r"\]\(#([\w\-]+)\)", text))
        if found:
            links[str(path.relative_to(ROOT))] = found
    return links


def test_measurements_page_holds_what_holds_now_in_under_400_lines():
    lines = len(MEASUREMENTS.read_text().splitlines())
    assert lines < MEASUREMENTS_MAX_LINES, (
        f"{MEASUREMENTS}: {lines} lines; it holds each figure once, at its latest value: move what a newer figure "
        f"replaced into {MEASUREMENTS_ARCHIVE.name}"
    )


def test_readme_links_its_measured_figures_to_the_measurements_page():
    assert _links_into(MEASUREMENTS).get("README.md"), f"{README}: no link to a section of {MEASUREMENTS}"


@pytest.mark.parametrize("page", [MEASUREMENTS, MEASUREMENTS_ARCHIVE], ids=lambda page: page.name)
def test_links_into_the_measurements_pages_resolve(page):
    anchors = _anchors(page.read_text())
    missing = {path: sorted(found - anchors) for path, found in _links_into(page).items() if found - anchors}
    assert not missing, f"links to {page.name} whose anchor is no heading of it: {missing}"
