# softplc: every developer and CI goes through these targets.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
PROGRAM ?= programs/transport.yaml
PLANT ?= transport

.PHONY: setup run test lint bench fuzz clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,bench]'
	touch $(STAMP)

run: setup
	$(VENV)/bin/softplc run $(PROGRAM) --plant $(PLANT) --start

test: setup
	$(PY) -m pytest

lint: setup
	$(VENV)/bin/ruff check softplc tests
	$(VENV)/bin/mypy

bench: setup
	$(VENV)/bin/softplc bench --json bench.json --plots docs/bench --markdown BENCHMARKS.md

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache .hypothesis
