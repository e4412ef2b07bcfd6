# autocal: `make demo` and `make test` set everything up on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
AUTOCAL_DATA_DIR ?= $(abspath ../shared/data)
export AUTOCAL_DATA_DIR
DEMO_OUT ?= demo-output
PYTEST_ARGS ?=

.PHONY: install demo test lint format bench clean

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[dev]"
	touch $@

install: $(VENV)/.installed

# The main job that exists today: a Tsky(nu, LST) table and its plot for a HERA dipole.
demo: install
	$(VENV)/bin/autocal info
	$(VENV)/bin/autocal tsky --sky gsm2008 --beam hera --pol ee --site hera \
		--freqs 100e6:200e6:101 --lsts 0:24:145 --nside 64 --tgnd 300 \
		--out $(DEMO_OUT)/tsky_hera_gsm2008.h5 --plot $(DEMO_OUT)/tsky_hera_gsm2008.png
	@echo "demo results: $(abspath $(DEMO_OUT))/tsky_hera_gsm2008.h5 and .png"

test: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest -n 2 -ra $(PYTEST_ARGS)

lint:
	$(VENV)/bin/ruff check . && $(VENV)/bin/ruff format --check .

format:
	$(VENV)/bin/ruff check --fix . && $(VENV)/bin/ruff format .

bench: install
	$(PY) benchmarks/tsky.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .ruff_cache *.egg-info
