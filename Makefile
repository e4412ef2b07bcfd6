# autocal: `make demo` and `make test` set everything up on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
AUTOCAL_DATA_DIR ?= $(abspath ../shared/data)
export AUTOCAL_DATA_DIR
DEMO_OUT ?= demo-output
PYTEST_ARGS ?=

.PHONY: install demo demo-nightly test docs lint format bench bench-night clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev]"
	touch $@

install: $(VENV)/.installed

# The main job end to end: start the API and a worker on SQLite, submit a calibration over
# HTTP (real HERA data when the data folder is present, else a simulated observation), wait,
# print the result summary and the product paths, stop the processes (scripts/demo.py).
demo: install
	$(VENV)/bin/autocal info
	PATH="$(abspath $(VENV))/bin:$$PATH" MPLBACKEND=Agg $(PY) scripts/demo.py

# Monitoring across nights: the API and a worker on SQLite calibrate the real nights JD
# 2458043/44/45 (7 antennas) submitted with POST /nightly, then print each night's outliers
# and the monitoring page's URL; in a terminal the page is served until Ctrl-C
# (scripts/demo_nightly.py; DEMO_SERVE_S=seconds otherwise).
demo-nightly: install
	PATH="$(abspath $(VENV))/bin:$$PATH" MPLBACKEND=Agg $(PY) scripts/demo_nightly.py

test: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest -n 2 -ra $(PYTEST_ARGS)

# The documentation (docs/: Markdown pages, Sphinx with MyST and numpydoc) as HTML in
# docs/_build/html. Warnings are errors; every page is read afresh (-E), and the API, command
# and REST references are generated from the code (docs/conf.py), so they follow it.
SPHINXOPTS ?=
docs: install
	MPLBACKEND=Agg $(VENV)/bin/sphinx-build -E -W --keep-going -q -b html $(SPHINXOPTS) \
		docs docs/_build/html
	@echo "documentation: $(abspath docs/_build/html/index.html)"

lint:
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format:
	$(VENV)/bin/ruff check --fix . && $(VENV)/bin/ruff format .

# Speed targets (benchmarks/README.md); the HERA-size night needs ~25 GB in /tmp and ~1.5 h.
bench: install
	$(PY) benchmarks/tsky.py
	$(PY) benchmarks/fit.py

bench-night: install
	$(PY) benchmarks/night.py

# The engine-vs-croissant-sim speed guard (issue 25; benchmarks/README.md). croissant-sim is
# not a dependency of autocal: it gets its own virtualenv (needs PyPI once, then works
# offline), with a Python older than 3.13 (CROISSANT_PYTHON, default python3).
CROISSANT_VENV ?= .venv-croissant
CROISSANT_PYTHON ?= $(PYTHON)
.PHONY: bench-croissant-env bench-croissant

$(CROISSANT_VENV)/.installed: benchmarks/croissant-requirements.txt
	$(CROISSANT_PYTHON) -m venv $(CROISSANT_VENV)
	$(CROISSANT_VENV)/bin/python -m pip install --quiet --upgrade pip
	$(CROISSANT_VENV)/bin/python -m pip install --quiet -r benchmarks/croissant-requirements.txt
	JAX_ENABLE_X64=1 $(CROISSANT_VENV)/bin/python -c "import croissant; print('croissant-sim', croissant.__version__)"
	touch $@

bench-croissant-env: $(CROISSANT_VENV)/.installed

bench-croissant: install bench-croissant-env
	$(PY) benchmarks/tsky_vs_croissant.py --croissant-python $(CROISSANT_VENV)/bin/python

clean:
	rm -rf $(VENV) $(CROISSANT_VENV) $(DEMO_OUT) .pytest_cache .ruff_cache *.egg-info docs/_build docs/_generated docs/api

# The job service from the repository's venv (settings: AUTOCAL_* variables, deploy/README.md).
SERVE_ARGS ?=
WORKER_ARGS ?=
.PHONY: serve worker

serve: install
	$(VENV)/bin/autocal serve $(SERVE_ARGS)

worker: install
	$(VENV)/bin/autocal worker $(WORKER_ARGS)
