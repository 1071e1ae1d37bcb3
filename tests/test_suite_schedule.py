"""`make test`'s schedule: each module's tests on one xdist worker (tests/conftest.py groups them),
so a module's fixtures (trained teams, reference runs) are built once, not once per worker."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_each_module_runs_on_one_worker(tmp_path):
    """Three quick modules of several tests each on three workers, as `make test` runs them (its xdist
    options, from the Makefile): load alone would spread each module over every worker."""
    record = tmp_path / "cpu.csv"
    modules = ["tests/test_faults_spec.py", "tests/test_settings_structs.py", "tests/test_key_binding.py"]
    xdist = ["-n", "3", "--dist", "loadgroup", "--no-loadscope-reorder"]
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
