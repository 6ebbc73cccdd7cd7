"""The front door: the README stays short and its links resolve, its API tour runs as written, the
command-line page matches the parser, and the docs carry no issue numbers. (The README's layout
table is checked against the import plan by ``tests/test_import_layers.py``.)"""

from __future__ import annotations

import re
import sys

import pytest

from . import regenerate_docs
from .conftest import REPO

README = REPO / "README.md"
DOCS = sorted((REPO / "docs").glob("*.md"))
README_MAX_LINES = 150


def _readme() -> str:
    return README.read_text(encoding="utf-8")


def test_readme_is_short_and_its_links_resolve():
    text = _readme()
    assert len(text.splitlines()) <= README_MAX_LINES
    for page in [README, *DOCS]:
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.relative_to(REPO)}: link to {target} is broken"


def test_readme_api_tour_runs(monkeypatch):
    """The README's Python block runs as written, from the repo root."""
    code = re.findall(r"```python\n(.*?)```", _readme(), re.S)
    assert len(code) == 1
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    exec(compile(code[0], str(README), "exec"), namespace)
    assert namespace["x"].grad is not None and namespace["x"].grad.abs().sum() > 0
    assert int(namespace["frame"].present.sum()) > 100  # features tracked through the sample


@pytest.mark.skipif(not (3, 10) <= sys.version_info[:2] <= (3, 12),
                    reason="argparse's help layout differs on this Python; docs/cli.md shows 3.10-3.12's")
def test_cli_page_matches_the_parser():
    text = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    assert regenerate_docs.OPTIONS in text
    got = text[text.index(regenerate_docs.OPTIONS):]
    assert got == regenerate_docs.options_section(), (
        "docs/cli.md's options differ from the parser: python -m tests.regenerate_docs")


ISSUE_NUMBER = re.compile(r"\bissue\s*#?\d+", re.I)


def test_docs_cite_no_issue_numbers():
    bad = [f"{p.relative_to(REPO)}:{i}" for p in [README, *DOCS]
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if ISSUE_NUMBER.search(line)]
    assert not bad, "issue numbers in the docs: " + ", ".join(bad)
