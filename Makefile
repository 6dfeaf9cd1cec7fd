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

# Long fuzz run (about 10 min here): the same fuzz tests as `make test` at 50x the cases; what
# was tried is appended to fuzz-report.jsonl (figures quoted in RELIABILITY.md).
FUZZ_SCALE ?= 50
fuzz: setup
	rm -f fuzz-report.jsonl
	SOFTPLC_FUZZ_SCALE=$(FUZZ_SCALE) SOFTPLC_FUZZ_REPORT=fuzz-report.jsonl \
		$(PY) -m pytest tests/fuzz -q -p no:cacheprovider

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache .hypothesis
