"""Benchmarks: code that measures the system and prints figures, kept out of the library packages.

`hammer bench ...` runs them (`benchmarks/cli.py`, wired in by `hammer.cli`, the only library module
that imports from here); the bench_*.py scripts also run on their own
(`.venv/bin/python benchmarks/bench_workers.py`).
"""
