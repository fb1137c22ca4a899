# minimdm: `make book` builds the HTML book, `make test` runs every test and notebook.
# Both create .venv on first use: torch==2.13.0 (a CPU build) goes in first, so that the
# project's `torch>=2.3` never pulls a multi-GB CUDA build.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.minimdm-installed
export VTK_DEFAULT_OPENGL_WINDOW := vtkEGLRenderWindow
export PYVISTA_OFF_SCREEN := true
export MPLBACKEND := Agg
# matplotlib caches the paths of its fonts, which live in the venv: one cache per venv, so that
# another checkout's venv (a clean clone beside this one) cannot leave paths that no longer exist
export MPLCONFIGDIR ?= $(abspath $(VENV))/mplconfig

# nbval over the chapters. A busy machine must not fail a cell: nbval waits 2000 s for a cell, but
# only 5 s for its output messages (raised in notebooks/conftest.py) and 60 s for a kernel to start.
NBVAL := --nbval-lax --nbval-output-timeout=120 --nbval-kernel-startup-timeout=300
# A second CPU dispatch for `make test-dispatch`: AVX2 kernels in ATen, MKL and oneDNN. On an AVX2
# machine that is its default; there, pass e.g. DISPATCH="ATEN_CPU_CAPABILITY=default
# MKL_ENABLE_INSTRUCTIONS=SSE4_2 MKL_CBWR=SSE4_2 ONEDNN_MAX_CPU_ISA=SSE41".
DISPATCH ?= ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 MKL_CBWR=AVX2 ONEDNN_MAX_CPU_ISA=AVX2

.PHONY: all setup test test-dispatch book lab lint format clean

all: test

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip>=23"
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[dev,book]"
	touch $(STAMP)

setup: $(STAMP)

test: $(STAMP)
	$(PY) -m ruff check minimdm tests benchmarks notebooks
	$(PY) -m ruff format --check minimdm tests benchmarks notebooks
	$(PY) -m pytest -q -p no:cacheprovider -n 2 --dist loadfile tests
	$(PY) -m pytest -q -p no:cacheprovider $(NBVAL) -n 2 --dist loadfile notebooks

# Every chapter's checked outputs under the machine's own CPU dispatch, then under $(DISPATCH):
# a checked output must not depend on which SIMD kernels the CPU runs (about twice `make test`'s
# nbval time).
test-dispatch: $(STAMP)
	$(PY) -m pytest -q -p no:cacheprovider $(NBVAL) -n 2 --dist loadfile notebooks
	env $(DISPATCH) $(PY) -m pytest -q -p no:cacheprovider $(NBVAL) -n 2 --dist loadfile notebooks

book: $(STAMP)
	$(VENV)/bin/jupyter-book build book --warningiserror --keep-going

lab: $(STAMP)
	$(VENV)/bin/jupyter lab notebooks

lint: $(STAMP)
	$(PY) -m ruff check minimdm tests benchmarks notebooks
	$(PY) -m ruff format --check minimdm tests benchmarks notebooks

format: $(STAMP)
	$(PY) -m ruff format minimdm tests benchmarks notebooks
	$(PY) -m ruff check --fix minimdm tests benchmarks notebooks

clean:
	rm -rf book/_build
