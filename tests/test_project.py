"""Project set-up (issue 3): the two README commands, CI entry point, layout, licence files."""

from __future__ import annotations

import re

from .conftest import REPO


def test_ci_runs_make_test():
    run = (REPO / ".ci" / "run").read_text()
    assert run.startswith("#!/usr/bin/env bash")
    assert re.search(r"^make test$", run, re.M)


def test_makefile_installs_cpu_torch_first():
    mk = (REPO / "Makefile").read_text()
    torch_line = mk.index("pip install -q torch==2.13.0")
    editable = mk.index('pip install -q -e ".[dev]"')
    assert torch_line < editable
    for target in ("demo:", "test:", "bench:"):
        assert re.search(rf"^{target}", mk, re.M)


def test_readme_opens_with_what_and_two_commands():
    readme = (REPO / "README.md").read_text()
    head = readme[:3000]
    assert "make demo" in head and "make test" in head
    assert head.index("VINS-Mono") < head.index("make demo")


def test_layout_and_licences():
    for d in ("torch_frontend", "tests", "notebooks", "configs", "benchmarks"):
        assert (REPO / d).is_dir(), d
    assert "Apache License" in (REPO / "LICENSE").read_text()
    assert (REPO / "torch_frontend" / "data" / "euroc_mini" / "LICENSE.md").is_file()
    assert (REPO / "tests" / "data" / "motorcycle" / "README.md").is_file()
    py = (REPO / "pyproject.toml").read_text()
    assert 'name = "torch-frontend"' in py and "torch>=2.3" in py
    assert 'torch-frontend = "torch_frontend.cli:main"' in py


def test_sample_data_is_light():
    total = sum(p.stat().st_size for p in (REPO / "torch_frontend" / "data").rglob("*") if p.is_file())
    assert total < 8 * 2**20


def test_public_names_resolve():
    import torch_frontend as tf
    import torch_frontend.loop as loop

    for name in tf.__all__:
        assert getattr(tf, name) is not None, name
    for name in loop.__all__:
        assert getattr(loop, name) is not None, name
