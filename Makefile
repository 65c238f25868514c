# Quick start: `make demo` flies a scenario, `make test` runs the checks.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SCENARIO ?= config/scenarios/paper.yaml
OUT ?= out/paper

.PHONY: demo simulate test sitl-test lint typecheck pytest bench clean

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

# The real ArduCopter SITL in the loop (../shared/sitl/); about 4 minutes, flights side by side.
sitl-test: $(STAMP)
	$(BIN)/pytest -m sitl -q --durations=0

bench: $(STAMP)
	$(BIN)/python -m bench

clean:
	rm -rf $(VENV) out build *.egg-info
