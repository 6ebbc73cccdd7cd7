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


# ----------------------------------------------------------------------------------------------
# every code block of the README and docs/*.md runs (python) or parses (shell), as written
#
# A block that cannot run has the line ``<!-- not run: <reason> -->`` right above its fence.
# ``text`` blocks are output listings (docs/cli.md's --help pages, checked against the parser
# below), not code.

FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
NOT_RUN = re.compile(r"<!--\s*not run:\s*(.*?)\s*-->\s*$")
SHELL = ("bash", "sh", "shell", "console", "")


def _blocks(page):
    """``[(lang, code, line, not-run reason or None)]`` of the fenced blocks of ``page``."""
    text = page.read_text(encoding="utf-8")
    out = []
    for m in FENCE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        marker = NOT_RUN.search(before)
        out.append((m.group(1), m.group(2), line, marker.group(1) if marker else None))
    return out


PAGES = [README, *DOCS]
PYTHON_PAGES = [p for p in PAGES if any(lang == "python" for lang, *_ in _blocks(p))]


def test_every_block_is_known():
    for page in PAGES:
        for lang, _, line, reason in _blocks(page):
            where = f"{page.relative_to(REPO)}:{line}"
            assert lang in ("python", "text", *SHELL), f"{where}: a ```{lang} block: run it here or mark it"
            assert reason is None or reason.strip(), f"{where}: 'not run:' needs a reason"
    assert README in PYTHON_PAGES and REPO / "docs" / "loop_closure.md" in PYTHON_PAGES


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: p.name)
def test_python_blocks_run(page, monkeypatch):
    """The page's ``python`` blocks run as written, from the repo root (against the sample data in
    the package): the README's each on its own (imports included, as a reader copies one; each sets
    1 thread, as the README tells script users), another page's in order in one namespace."""
    monkeypatch.chdir(REPO)
    namespace: dict = {"__name__": "__docs__"}
    spaces = []
    ran = marked = 0
    for lang, code, line, reason in _blocks(page):
        if lang != "python":
            continue
        if reason is not None:
            marked += 1
            continue
        if page == README:
            namespace = {"__name__": "__docs__"}
            assert "torch.set_num_threads(1)" in code, f"README.md:{line}: the block does not set 1 thread"
        # line numbers of tracebacks point into the page
        exec(compile("\n" * line + code, str(page), "exec"), namespace)
        spaces.append(namespace)
        ran += 1
    assert ran >= 1 or marked  # a page whose every python block says why it is not run
    if page == README:
        tour = spaces[0]
        assert tour["x"].grad is not None and tour["x"].grad.abs().sum() > 0
        assert int(tour["frame"].present.sum()) > 100  # features tracked through the sample
        # the tour ends on a published frame: valid features, a non-empty point cloud
        assert tour["frame"].published.all() and int(tour["frame"].valid.sum()) > 100
        assert tour["cloud"]["points"].shape[0] > 50
        assert tour["f"].valid.any()
        assert tour["rf"].batch_size == 2  # a rig of two configs


def _shell_commands(code: str):
    """The command lines of a shell block (continuations joined, comments dropped)."""
    import shlex

    for cmd in code.replace("\\\n", " ").splitlines():
        words = shlex.split(cmd, comments=True)
        if words:
            yield words


def _cli_args(words):
    """The ``torch-frontend`` arguments of a command line, or None when it is not one."""
    if words[0] == "torch-frontend":
        return words[1:]
    if "-m" in words and words[words.index("-m") + 1] in ("torch_frontend", "torch_frontend.cli"):
        if words[0] in ("python", "python3", "torchrun") or words[0].endswith("python"):
            return words[words.index("-m") + 2:]
    return None


def test_shell_blocks_parse():
    """Every command line of a shell block is a ``make`` target of the Makefile or a
    ``torch-frontend`` command the parser accepts (the paths are examples: they are not run)."""
    from torch_frontend.cli import build_parser

    targets = set(re.findall(r"^([\w-]+):", (REPO / "Makefile").read_text(), re.M))
    checked = 0
    for page in PAGES:
        for lang, code, line, reason in _blocks(page):
            if lang not in SHELL or reason is not None:
                continue
            for words in _shell_commands(code):
                where = f"{page.relative_to(REPO)}:{line}: {' '.join(words)}"
                if words[0] == "make":
                    assert set(words[1:]) <= targets, where
                    checked += 1
                    continue
                args = _cli_args(words)
                assert args is not None, f"{where}: not a torch-frontend or make command (mark the block)"
                try:
                    build_parser().parse_args(args)
                except SystemExit as exc:
                    pytest.fail(f"{where}: the parser refuses it (exit {exc.code})")
                checked += 1
    assert checked >= 15


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
