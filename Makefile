# DRVS: `make test` sets everything up and runs the suite; see README.md.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: setup test test-slow demo lint format clean

setup:
	@bash scripts/setup.sh

test: setup
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS)

# The paper's case study 4.2: leaves out/obstacles/run.png and out/obstacles/summary.json.
demo: setup
	bash scripts/run_scenario.sh worlds/obstacles.yaml --out out/obstacles

test-slow: setup
	$(PY) -m pytest -m slow $(PYTEST_ARGS)

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

clean:
	rm -rf build *.egg-info drvs/msg drvs/srv out .pytest_cache
