"""Benchmarks: code that measures the system and prints figures, kept out of the library packages.

`hammer bench ...` runs them (`hammer/commands/bench.py`, the only module that imports from here);
some also run on their own (`.venv/bin/python -m hammer.benchmarks.bench_workers`). What only the tests
use lives in tests/harness/, outside the wheel.
"""
