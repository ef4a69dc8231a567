"""DRVS benchmarks: ``make bench`` (``.venv/bin/python -m bench.run``); results: docs/performance.md."""
