# Quick start: `make demo` flies a scenario, `make test` runs the checks.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SCENARIO ?= config/scenarios/paper.yaml
OUT ?= out/paper

SWEEP_SEEDS ?= 0:1000
SWEEP_WORKERS ?= 2
SWEEP_OUT ?= out/sweep

.PHONY: demo simulate test lint typecheck pytest bench sweep clean

$(STAMP): pyproject.toml
	@$(PY) -c 'import ensurepip' 2>/dev/null || { \
	  echo "$(PY) has no venv support: installing Debian's $(PY)-venv"; \
	  if [ "$$(id -u)" = 0 ]; then apt-get install -y $(PY)-venv; \
	  else sudo apt-get install -y $(PY)-venv; fi; }
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
	$(BIN)/ruff check companion sim tests bench
	$(BIN)/ruff format --check companion sim tests bench

typecheck: $(STAMP)
	$(BIN)/mypy companion sim bench

pytest: $(STAMP)
	$(BIN)/pytest -q

bench: $(STAMP)
	$(BIN)/python -m bench

# The long run: SWEEP_SEEDS random worlds per sensor layout, both vehicle models. Resumable:
# run it again and it skips the runs already in $(SWEEP_OUT)/results.csv.
sweep: $(STAMP)
	$(BIN)/companion sweep --seeds $(SWEEP_SEEDS) --workers $(SWEEP_WORKERS) --out $(SWEEP_OUT) --resume

clean:
	rm -rf $(VENV) out build *.egg-info
