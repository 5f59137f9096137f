"""docs/scenes.md keeps up with config/config.yaml: a section and a table row for every scene."""

import re
from pathlib import Path

import pytest
import yaml

from latentsim.config import load_config
from latentsim.mesh.build import build_mesh

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "config.yaml"
SCENES_DOC = ROOT / "docs" / "scenes.md"


def _slug(heading: str) -> str:
    """The anchor a Markdown renderer (GitHub's rule) gives a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _doc() -> str:
    return SCENES_DOC.read_text()


def _anchors(text: str) -> set[str]:
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
