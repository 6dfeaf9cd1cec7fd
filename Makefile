# softplc: every developer and CI goes through these targets.
#
# Installs are split by what a target needs, each with its own stamp in the venv: `make run`
# installs the runtime dependencies only; `make test`/`make lint` add the dev extra (pytest,
# mypy, ...) and the bench extra (SNAKES, matplotlib: the bench tests import them); `make bench`
# adds the bench extra. `make setup` installs everything (a developer's venv).
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip install --quiet
RUN_STAMP := $(VENV)/.installed-run
DEV_STAMP := $(VENV)/.installed-dev
BENCH_STAMP := $(VENV)/.installed-bench
PROGRAM ?= programs/transport.yaml
PLANT ?= transport
# `make run`'s endpoints (HOST:PORT, IPv6 in brackets: API=[::1]:8080; off turns one off),
# and ARGS for any other `softplc run` flag (ARGS='--tls on --period 1ms').
MODBUS ?= 127.0.0.1:5020
API ?= 127.0.0.1:8080
OPCUA ?= 127.0.0.1:4840
ARGS ?=

.PHONY: setup run test lint bench fuzz mutate shell clean

setup: $(DEV_STAMP) $(BENCH_STAMP)

$(PY):
	python3 -m venv $(VENV)
	$(PIP) --upgrade pip

$(RUN_STAMP): pyproject.toml | $(PY)
	$(PIP) -e .
	touch $@

$(DEV_STAMP): pyproject.toml $(RUN_STAMP)
	$(PIP) -e '.[dev]'
	touch $@

$(BENCH_STAMP): pyproject.toml $(RUN_STAMP)
	$(PIP) -e '.[bench]'
	touch $@

# The simulated plant restarts with the PLC, so the demo resumes warm after a Ctrl-C; a PLC
# next to a real machine keeps the default boot policy, stop (docs/retain.md).
run: $(RUN_STAMP)
	$(VENV)/bin/softplc run $(PROGRAM) --plant $(PLANT) --start --boot-policy warm \
		--modbus '$(MODBUS)' --api '$(API)' --opcua '$(OPCUA)' $(ARGS)

# The suite starts a few hundred interpreters (softplc run: supervisor, scan, service and
# compile processes). Their bytecode compiled once here (incremental: changed files only) is
# read by every one of them, also where PYTHONDONTWRITEBYTECODE keeps Python from caching it:
# measured 15 % of the wall time of the process tests (tests/runtime/test_stop_paths.py and
# test_supervision.py: 55 -> 46 s, user CPU 37 -> 29 s).
test: $(DEV_STAMP) $(BENCH_STAMP)
	$(PY) -m compileall -q softplc tests > /dev/null
	$(PY) -m pytest

lint: $(DEV_STAMP) $(BENCH_STAMP)
	$(VENV)/bin/ruff check softplc tests
	$(VENV)/bin/mypy

bench: $(BENCH_STAMP)
	$(VENV)/bin/softplc bench --json bench.json --plots docs/bench --markdown BENCHMARKS.md

# Long fuzz run (about 10 min here): the same fuzz tests as `make test` at 50x the cases; what
# was tried is appended to fuzz-report.jsonl (figures quoted in RELIABILITY.md).
FUZZ_SCALE ?= 50
fuzz: $(DEV_STAMP) $(BENCH_STAMP)
	rm -f fuzz-report.jsonl
	SOFTPLC_FUZZ_SCALE=$(FUZZ_SCALE) SOFTPLC_FUZZ_REPORT=fuzz-report.jsonl \
		$(PY) -m pytest tests/fuzz tests/system/test_lifecycle_model.py -q -p no:cacheprovider

# Mutation testing (issue 43), not part of `make test`: each module where a bug hurts most
# against its own fast tests (the map: TARGETS in softplc/bench/mutate.py), MUTATE_SAMPLE
# seeded mutants per module, each applied in a private copy of the tree (never the working
# tree), 2 jobs. About 15 min on this 2-core machine; no mutant starts after 14 min
# (--budget-s: the rest count as "not run"). Known equivalent mutants are listed, with why,
# in softplc/bench/equivalent_mutants.txt. Writes build/mutation.json and build/mutation.md
# (RELIABILITY.md, "Mutation testing", quotes them).
MUTATE_SAMPLE ?= 20
mutate: $(DEV_STAMP) $(BENCH_STAMP)
	$(PY) -m softplc.bench.mutate --seed 43 --sample $(MUTATE_SAMPLE) --jobs 2 --budget-s 840 \
		--equivalent softplc/bench/equivalent_mutants.txt \
		--json build/mutation.json --markdown build/mutation.md

# A shell with the venv active: `softplc` is on the PATH there (`exit` leaves it). The same
# without make: `. .venv/bin/activate`.
shell: $(RUN_STAMP)
	@echo "softplc is on the PATH in this shell ($(abspath $(VENV))/bin); exit to leave"
	@VIRTUAL_ENV="$(abspath $(VENV))" PATH="$(abspath $(VENV))/bin:$$PATH" "$${SHELL:-/bin/sh}" -i

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache .hypothesis
