# DRVS: `make test` sets everything up and runs the suite; see README.md.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python

.PHONY: setup rviz-setup postgres-setup test test-slow soak reliability-report bench demo lint format docs clean

setup:
	@bash scripts/setup.sh

# Debian's rviz and xvfb too (for run_scenario.sh --rviz and the RViz screenshot test).
rviz-setup:
	@bash scripts/setup.sh --rviz

# PostgreSQL and PostGIS too: the registry's tests run against a private cluster (docs/registry.md).
postgres-setup:
	@bash scripts/setup.sh --postgres

# Two passes: everything but the whole runs on two workers (pytest-xdist; a module stays on one
# worker, so a module's shared master is its own), then the whole runs alone, one at a time: each
# takes most of the machine and its simulated world must keep up.
test: postgres-setup
	$(PY) -m pytest -n 2 --dist loadfile -m "not slow" $(PYTEST_ARGS) test/unit test/project test/live; status=$$?; \
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS) test/scenarios && exit $$status

# The paper's case study 4.2: leaves out/obstacles/run.png and out/obstacles/summary.json.
demo: setup
	bash scripts/run_scenario.sh worlds/obstacles.yaml --out out/obstacles

test-slow: postgres-setup
	$(PY) -m pytest -m slow $(PYTEST_ARGS)

# The reliability suites (faults, load, hostile input, security, master restart) at small sizes:
# writes their figures into docs/reliability.md (between its reliability markers).
reliability-report: setup
	$(PY) scripts/reliability_report.py $(PYTEST_ARGS)

# The slow variants (full sizes: 10 robots x 20 vision systems x 50 requests, repeated
# faults), then the report with them; their lines are kept in $(SOAK_LOG), not run twice.
SOAK_LOG := out/soak-reliability.jsonl
soak: postgres-setup
	@mkdir -p out && rm -f $(SOAK_LOG)
	DRVS_RELIABILITY_LOG=$(CURDIR)/$(SOAK_LOG) $(PY) -m pytest -m slow $(PYTEST_ARGS); status=$$?; \
	$(PY) scripts/reliability_report.py --soak --slow-log $(SOAK_LOG) $(PYTEST_ARGS) && exit $$status

# The benchmarks (bench/, issue 16): bench/results/latest.md, latest.json, the plots,
# docs/performance.md's results and README.md's targets met. QUICK=1: small sizes, about
# 2 minutes, into bench/results/quick/ (the full results and the docs stay as they are).
# BENCH_ARGS='--only wire'.
bench: postgres-setup
	$(PY) -m bench.run $(if $(QUICK),--size quick --out bench/results/quick,--size full --docs) $(BENCH_ARGS)

# ruff, then mypy over the pure packages ([tool.mypy] in pyproject.toml).
lint: postgres-setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m mypy

format: setup
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

# The node pages' parameter tables (docs/nodes/NODE.md), from the nodes' settings dataclasses
# (test/project/test_param_docs.py checks them).
docs: setup
	$(PY) -m drvs.ros.param_docs --write docs/nodes

clean:
	rm -rf build *.egg-info drvs/msg drvs/srv out .pytest_cache
