"""DRVS benchmarks: ``make bench`` (``.venv/bin/python -m bench.run``); see bench/README.md."""
