"""The documentation works in a clone of the repository alone: README.md opens with exactly its two
set-up commands, and every relative link (and every `../path` it quotes) resolves inside the repo."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from .conftest import ROOT

DOCS = [ROOT / "README.md", ROOT / "systemd" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|!\[[^\]]*\]\(([^)\s]+)\)")
QUOTED_PARENT = re.compile(r"`(\.\./[^`\s]+)`")
SETUP = ["pip install . && crtk-bridge --profile profiles/so101.yaml --sim",
         "pip install '.[test]' && python -m pytest -q"]


def _inside_repo(target: Path) -> bool:
    try:
        target.resolve().relative_to(ROOT)
    except ValueError:
        return False
    return target.exists()


def test_docs_found():
    assert len(DOCS) >= 4 and all(d.is_file() for d in DOCS)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves_inside_the_repo(doc):
    text = doc.read_text()
    broken = []
    for m in LINK.finditer(text):
        target = m.group(1) or m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (http:, https:, mailto:) or an anchor in the same page
        path = target.split("#", 1)[0]
        if not _inside_repo(doc.parent / path):
            broken.append(target)
    for m in QUOTED_PARENT.finditer(text):
        if not _inside_repo(doc.parent / m.group(1)):
            broken.append(m.group(1))
    assert not broken, f"{doc.relative_to(ROOT)}: links that do not resolve inside the repository: {broken}"


def test_link_check_catches_a_link_outside_the_repo(tmp_path):
    # the checker itself: the README's old link to ../shared/ would fail it
    assert not _inside_repo(ROOT / "README.md" / ".." / ".." / "shared" / "crtk-spec.txt")
    assert LINK.findall("see [CRTK](../shared/crtk-spec.txt) and ![x](img.png)") == [
        ("../shared/crtk-spec.txt", ""), ("", "img.png")]


def test_readme_opens_with_exactly_its_two_setup_commands():
    text = (ROOT / "README.md").read_text()
    head = text.split("\n---\n", 1)[0]  # the part before the first horizontal rule
    assert head.startswith("# crtk-bridge\n")
    blocks = re.findall(r"```(\w*)\n(.*?)```", head, re.S)
    assert blocks == [("sh", SETUP[0] + "\n"), ("sh", SETUP[1] + "\n")]
    assert "\n## " not in head  # no section before them
    # CI runs the second command verbatim
    assert SETUP[1] in (ROOT / ".ci" / "run").read_text().splitlines()


def test_architecture_is_described_inside_the_repo():
    arch = ROOT / "docs" / "architecture.md"
    assert "(docs/architecture.md)" in (ROOT / "README.md").read_text()
    text = arch.read_text()
    for must in ("front process", "control process", "## Layers", "## The seam"):
        assert must in text
