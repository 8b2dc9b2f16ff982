# Two commands on a fresh machine: `make demo` (the main job: train the default CPU config on a local
# Ray cluster, tracked in ./mlflow.db) and `make test` (the test suite).
# Both create ./.venv on first use. torch==2.13.0 is installed first and on its own so that
# anny's torch requirement does not pull a multi-GB CUDA build on CPU-only machines.
VENV ?= .venv
PY := $(VENV)/bin/python

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	touch $@

.PHONY: install demo test lint
install: $(VENV)/.installed

demo: $(VENV)/.installed
	$(PY) jobs/train.py --config configs/default.yaml --out runs/default

test: $(VENV)/.installed
	$(PY) -m pytest

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
