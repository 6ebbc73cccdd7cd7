# Two commands do all set-up on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
VPY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TRITON_STAMP := $(VENV)/.installed-triton

.PHONY: demo test test-all bench lint clean

$(VPY):
	$(PY) -m venv $(VENV)
	$(VPY) -m pip install -q --upgrade pip

# torch first, pinned, so that nothing later resolves another torch. Which build pip takes is the
# index's choice: the CPU wheel where the machine provides one locally (pip's find-links, as on this
# project's CI), the CUDA build from PyPI on an ordinary Linux machine; for the CPU build there:
# make TORCH_INDEX=https://download.pytorch.org/whl/cpu demo
TORCH_INDEX ?=
$(STAMP): $(VPY) pyproject.toml
	$(VPY) -m pip install -q torch==2.13.0 $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(VPY) -m pip install -q -e ".[dev]"
	$(VPY) -m torch_frontend.fused.selfcheck --warm  # the fused CPU kernels' JIT compile, once (numba's cache)
	touch $(STAMP)

# Triton for the CUDA kernels' tests (interpreted on the CPU, PTX compiled for sm_90): test-all / CI only
$(TRITON_STAMP): $(STAMP)
	$(VPY) -m pip install -q -e ".[dev,triton]"
	touch $(TRITON_STAMP)

demo: $(STAMP)
	$(VENV)/bin/torch-frontend demo
	$(VENV)/bin/torch-frontend demo --flight
	$(VENV)/bin/torch-frontend demo --loop

# the suite on every core (pytest-xdist; each worker runs torch on 1 thread, tests/conftest.py), without
# the slow cases; test-all (what CI runs) adds them and fails where Triton or ROS 1 (tests/test_ros_node.py) is missing
test: $(STAMP)
	$(VPY) -m pytest -q -n auto --dist loadscope -m "not slow"

test-all: $(TRITON_STAMP)
	TORCH_FRONTEND_REQUIRE_TRITON=1 TORCH_FRONTEND_REQUIRE_ROS=1 $(VPY) -m pytest -q -n auto --dist loadscope

bench: $(STAMP)
	$(VPY) benchmarks/bench_pipeline.py --compile --capturable

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) build *.egg-info
