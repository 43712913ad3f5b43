# ccrjax: everything a fresh clone needs, from python3 and make alone.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: install train test lint bench clean

install: $(STAMP)

# Re-runs only when the package metadata changes, so `make install` is idempotent.
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

train: install
	$(PY) -m ccrjax.demo --out runs/demo

test: install
	$(PY) -m pytest

lint: install
	$(PY) -m ruff check ccrjax tests benchmarks experiments

bench: install
	$(PY) benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) runs .pytest_cache
