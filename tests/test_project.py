"""Project set-up: the two README commands, CI entry point, layout, licence files."""

from __future__ import annotations

import re

import pytest

from .conftest import REPO


def test_ci_runs_the_full_suite_command_of_the_readme():
    """CI runs ``make test-all`` (``make test`` plus the slow cases), a command the README gives."""
    run = (REPO / ".ci" / "run").read_text()
    assert run.startswith("#!/usr/bin/env bash")
    assert re.search(r"^make test-all$", run, re.M)
    assert "make test-all" in (REPO / "README.md").read_text()
    mk = (REPO / "Makefile").read_text()
    fast = re.search(r"^test:.*\n\t(.*)$", mk, re.M).group(1)
    full = re.search(r"^test-all:.*\n\t(.*)$", mk, re.M).group(1)
    assert '-m "not slow"' in fast and "-m" not in full.split("pytest", 1)[1]


def test_makefile_installs_cpu_torch_first():
    mk = (REPO / "Makefile").read_text()
    torch_line = mk.index("pip install -q torch==2.13.0")
    editable = mk.index('pip install -q -e ".[dev]"')
    assert torch_line < editable
    for target in ("demo:", "test:", "test-all:", "bench:"):
        assert re.search(rf"^{target}", mk, re.M)


def test_install_says_which_torch_build_and_how_to_get_the_cpu_one():
    """The README does not promise a CPU torch the default index may not give; ``TORCH_INDEX``
    (empty by default: the machine's own index) selects the CPU wheels' index."""
    import shutil
    import subprocess

    readme = (REPO / "README.md").read_text()
    assert "(CPU build)" not in readme and "installs (CPU torch)" not in readme
    assert "TORCH_INDEX=https://download.pytorch.org/whl/cpu" in readme and "CUDA build" in readme
    if shutil.which("make") is None:
        pytest.skip("no make on this machine")
    dry = ["make", "-n", "-B", "-C", str(REPO), ".venv/.installed"]
    plain = subprocess.run(dry, capture_output=True, text=True, check=True).stdout
    cpu = subprocess.run(dry + ["TORCH_INDEX=https://download.pytorch.org/whl/cpu"], capture_output=True, text=True,
                         check=True).stdout
    assert "torch==2.13.0" in plain and "--index-url" not in plain
    assert "torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu" in cpu


def test_license_is_an_spdx_string():
    """``project.license`` as an SPDX string (the TOML-table form makes setuptools >= 77 print a
    deprecation warning on every install), and a setuptools that reads it."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        pytest.skip("tomllib needs Python >= 3.11")
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert meta["project"]["license"] == "Apache-2.0"
    assert set(meta["project"]["license-files"]) == {"LICENSE", "NOTICE"}
    assert "setuptools>=77" in meta["build-system"]["requires"]


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


def _import_everything():
    """Import every submodule of the package (as a long session would) and run a tracker step."""
    import importlib
    import pkgutil

    import torch

    import torch_frontend as tf

    # modules of optional extras (the CUDA kernels, fused/_triton_*.py, need Triton: `pip install -e ".[triton]"`)
    has_triton = importlib.util.find_spec("triton") is not None
    for m in pkgutil.walk_packages(tf.__path__, "torch_frontend."):
        if m.name.startswith("torch_frontend.fused._triton_") and not has_triton:
            continue
        importlib.import_module(m.name)
    tr = tf.FeatureTracker(tf.load_config(REPO / "configs" / "euroc.yaml"))
    tr.track(torch.zeros(1, 1, 480, 752, dtype=torch.uint8), [0.0])
    tr.track(torch.zeros(1, 1, 480, 752, dtype=torch.uint8), [0.05])


def test_public_names_stay_the_documented_objects_after_a_run():
    """``tf.clahe(images)`` must keep working after the tracker (or anything) imported the module
    that defines it: a package attribute is overwritten by a submodule of the same name, so no
    lazily exported name may equal a submodule's name, and every public name is its module's object."""
    import importlib
    import inspect

    import torch

    import torch_frontend as tf

    _import_everything()
    for pkg_name in ("torch_frontend", "torch_frontend.loop", "torch_frontend.io", "torch_frontend.testing",
                     "torch_frontend.pipelines"):
        try:
            pkg = importlib.import_module(pkg_name)
        except ModuleNotFoundError:
            continue
        exports = getattr(pkg, "_EXPORTS", {})
        for name in pkg.__all__:
            obj = getattr(pkg, name)
            assert not inspect.ismodule(obj), f"{pkg_name}.{name} is a module, not the documented object"
            if name in exports:
                src = importlib.import_module(f".{exports[name]}", pkg_name)
                assert obj is getattr(src, name), f"{pkg_name}.{name} is not {src.__name__}.{name}"
    eq = tf.clahe(torch.full((1, 1, 16, 16), 7, dtype=torch.uint8))
    assert eq.shape == (1, 1, 16, 16) and eq.dtype == torch.uint8
