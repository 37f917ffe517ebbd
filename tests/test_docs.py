"""The README stays short and its links resolve; the docs' relative links resolve."""

from __future__ import annotations

import re

import pytest

from tests.conftest import REPO

DOCS = sorted((REPO / "docs").rglob("*.md"))


def test_the_readme_is_at_most_150_lines_with_the_two_set_up_commands():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    assert "bash scripts/demo.sh" in text and "bash scripts/test.sh" in text


@pytest.mark.parametrize("path", [REPO / "README.md", *DOCS], ids=lambda p: p.name)
def test_relative_links_resolve(path):
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text())
    files = [link for link in links if ("." in link or "/" in link)  # a file, not a formula's "](u)"
             and not link.startswith(("http://", "https://", "mailto:"))]
    missing = [link for link in files if not (path.parent / link).exists()]
    assert not missing, missing
