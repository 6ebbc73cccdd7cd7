"""Rewrite the generated part of ``docs/cli.md`` (the "Options" section: every command's ``--help``
at 100 columns) after changing the command line:

    .venv/bin/python -m tests.regenerate_docs

``tests/test_docs.py`` fails while the page and the parser disagree.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys

from .conftest import REPO

CLI_DOC = REPO / "docs" / "cli.md"
OPTIONS = "## Options\n"
COMMANDS = ((), ("track",), ("demo",), ("loop",), ("vocabulary",), ("vocabulary", "train"), ("compare",), ("ros",),
            ("config",))
HELP_COLUMNS = "100"


def help_text(command) -> str:
    """``torch-frontend <command> --help`` as printed at 100 columns."""
    from torch_frontend.cli import main

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_COLUMNS
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            try:
                main([*command, "--help"])
            except SystemExit:
                pass
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old
    return out.getvalue().rstrip() + "\n"


def options_section() -> str:
    parts = [OPTIONS]
    for cmd in COMMANDS:
        parts.append(f"\n### `torch-frontend {' '.join(cmd)}`\n\n```text\n{help_text(cmd)}```\n".replace(
            "`torch-frontend `", "`torch-frontend`"))
    return "".join(parts)


def main() -> int:
    text = CLI_DOC.read_text(encoding="utf-8")
    head = text[: text.index(OPTIONS)] if OPTIONS in text else text.rstrip() + "\n\n"
    tmp = CLI_DOC.with_suffix(".tmp")
    tmp.write_text(head + options_section(), encoding="utf-8")
    tmp.replace(CLI_DOC)
    print(f"wrote {CLI_DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
