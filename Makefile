# Quick start: `make demo` flies a scenario, `make test` runs the checks.
# The venv is made with the first Python >= 3.11 on PATH (python3.13, python3.12, python3.11,
# python3); `make PY=/path/to/python3.12 test` names one. Nothing is installed system-wide.
PYTHONS := python3.13 python3.12 python3.11 python3
ifeq ($(origin PY),undefined)
PY := $(shell for p in $(PYTHONS); do \
  "$$p" -c 'import sys; sys.exit(sys.version_info < (3, 11))' >/dev/null 2>&1 \
  && { command -v "$$p"; break; }; done)
endif
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SCENARIO ?= config/scenarios/paper.yaml
OUT ?= out/paper

SWEEP_SEEDS ?= 0:1000
SWEEP_WORKERS ?= 2
SWEEP_OUT ?= out/sweep

.PHONY: demo simulate test sitl-test lint typecheck pytest bench sweep clean

$(STAMP): pyproject.toml
	@if [ -z "$(PY)" ]; then \
	  echo "error: no Python >= 3.11 found (tried $(PYTHONS))."; \
	  echo "  Debian 12 / Ubuntu 24.04: sudo apt install python3 python3-venv"; \
	  echo "  Ubuntu 22.04: sudo apt install python3.11 python3.11-venv"; \
	  echo "  or name one: make PY=/path/to/python3.11 ..."; exit 1; fi
	@$(PY) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || { \
	  echo "error: PY=$(PY) is $$($(PY) -V 2>&1); the project needs Python >= 3.11"; exit 1; }
	@$(PY) -c 'import ensurepip, venv' 2>/dev/null || { \
	  echo "error: $(PY) cannot make a venv (no ensurepip)."; \
	  echo "  Debian/Ubuntu: sudo apt install $$($(PY) -c 'import os, sys; print(os.path.basename(os.path.realpath(sys.executable)))')-venv"; \
	  echo "  (python3-venv for the system's python3), then run make again."; exit 1; }
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/companion fly $(SCENARIO) --out $(OUT)

simulate: $(STAMP)
	$(BIN)/companion simulate $(SCENARIO) --out $(OUT)

test: $(STAMP) lint typecheck pytest

lint: $(STAMP)
	$(BIN)/ruff check companion tests bench
	$(BIN)/ruff format --check companion tests bench
	$(BIN)/lint-imports

typecheck: $(STAMP)
	$(BIN)/mypy companion bench

pytest: $(STAMP)
	$(BIN)/pytest -q

# The real ArduCopter SITL in the loop (../shared/sitl/); about 4 minutes, flights side by side.
sitl-test: $(STAMP)
	$(BIN)/pytest -m sitl -q --durations=0

# `make bench` writes out/bench-results.json (untracked, the tree stays clean); the published
# bench/results.json is rewritten only on request: `make bench BENCH_OUT=bench/results.json`.
BENCH_OUT ?= out/bench-results.json
bench: $(STAMP)
	@mkdir -p $(dir $(BENCH_OUT))
	$(BIN)/python -m bench --out $(BENCH_OUT)

# The long run: SWEEP_SEEDS random worlds per sensor layout, both vehicle models. Resumable:
# run it again and it skips the runs already in $(SWEEP_OUT)/results.csv.
sweep: $(STAMP)
	$(BIN)/companion sweep --seeds $(SWEEP_SEEDS) --workers $(SWEEP_WORKERS) --out $(SWEEP_OUT) --resume

clean:
	rm -rf $(VENV) out build *.egg-info
