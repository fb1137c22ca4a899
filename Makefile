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

# nbval over the chapters. A busy machine must not fail a cell: nbval waits 2000 s for a cell, but
# only 5 s for its output messages (raised in notebooks/conftest.py) and 60 s for a kernel to start.
NBVAL := --nbval-lax --nbval-output-timeout=120 --nbval-kernel-startup-timeout=300

.PHONY: all setup test book lab lint format clean

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
	$(PY) -m pytest -q -p no:cacheprovider tests
	$(PY) -m pytest -q -p no:cacheprovider $(NBVAL) -n 2 --dist loadfile notebooks

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
