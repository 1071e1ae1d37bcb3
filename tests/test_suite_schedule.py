"""`make test`'s schedule: each module's tests on one xdist worker (tests/conftest.py groups them),
so a module's fixtures (trained teams, reference runs) are built once, not once per worker."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_each_module_runs_on_one_worker(tmp_path):
    """Three quick modules of several tests each on two workers with `make test`'s xdist options (from the
    Makefile; it runs three workers): load alone would spread each module over both workers, and one
    worker must take two modules whole. Modules whose imports are light: each worker collects all three."""
    record = tmp_path / "cpu.csv"
    modules = ["tests/test_protocol_experience.py", "tests/test_settings_structs.py", "tests/test_key_binding.py"]
    xdist = ["-n", "2", "--dist", "loadgroup", "--no-loadscope-reorder"]
    assert " ".join(xdist[2:]) in (ROOT / "Makefile").read_text()  # the options make test uses
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *xdist, *modules],
                       cwd=ROOT, env=dict(os.environ, HAMMER_TEST_CPU=str(record)), capture_output=True, text=True,
                       timeout=300, check=False)
    assert r.returncode == 0, r.stdout[-2000:]
    workers: dict[str, set[str]] = {}
    for line in record.read_text().splitlines():
        nodeid, _cpu, _wall, worker, _start = line.rsplit(",", 4)
        workers.setdefault(nodeid.split("::")[0], set()).add(worker)
    assert sorted(workers) == sorted(modules)
    assert all(len(w) == 1 for w in workers.values()), f"a module's tests ran on several workers: {workers}"
