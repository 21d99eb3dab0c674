# Two commands on a fresh Debian machine:
#   make demo   installs everything and runs the demo job on the embedded default
#   make test   runs the test suite (fast and slow tiers)
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
LLVM := /usr/lib/x86_64-linux-gnu/libLLVM-19.so
export DRJIT_LIBLLVM_PATH ?= $(LLVM)

.PHONY: install install-cuda system-deps demo check test test-fast docs bench-docs bench clean

system-deps:
	@if [ ! -e "$(LLVM)" ]; then \
	  echo "installing Debian's libllvm19 (Dr.Jit crashes with the default LLVM 15)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get install -y libllvm19 || { $$SUDO apt-get update && $$SUDO apt-get install -y libllvm19; }; \
	fi

$(BIN)/ndrf: pyproject.toml
	$(MAKE) system-deps
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	# The CPU wheel of torch first: an unpinned torch would pull several GB of CUDA packages.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev]'
	touch $(BIN)/ndrf

install: $(BIN)/ndrf

# A GPU machine: torch's CUDA build (PyPI's default wheel; several GB of CUDA libraries as pip
# packages) over the CPU wheel. Mitsuba's and Dr.Jit's wheels hold their CUDA variants already.
# NDRF_DEVICE=auto (the default) then runs on the GPU (docs/guide/deployment.md#gpus).
install-cuda: install
	$(BIN)/pip install --force-reinstall --index-url https://pypi.org/simple torch==2.13.0

demo: install
	$(BIN)/ndrf -v run examples/demo.json --out runs/demo

check: install
	$(BIN)/lint-imports
	$(BIN)/ruff check .
	$(BIN)/mypy

test: install
	$(BIN)/python -m pytest

test-fast: install
	$(BIN)/python -m pytest -m "not slow"

# the docs site into site/: the job-file reference regenerated from the schemas, warnings are errors
docs: install
	$(BIN)/python -m schemas.reference
	$(BIN)/mkdocs build --strict

# the benchmark pages of the docs, from bench/results (after a benchmark wrote new results); the index
# opens with bench/overview.md, written by hand
bench-docs: install
	$(BIN)/python -m bench.docs

bench: install
	$(BIN)/pip install -q -e '.[dev,bench]'
	$(BIN)/python -m bench --quick

clean:
	rm -rf $(VENV) runs site .pytest_cache
