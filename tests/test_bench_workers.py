"""`benchmarks/bench_workers.py` runs end to end on a tiny budget: every design, including the
ceiling of independent processes, steps real multiwalker copies and reports a finite speed."""

from __future__ import annotations

import math
import runpy
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_workers.py"


def test_every_design_steps_and_reports_a_speed():
    mod = runpy.run_path(str(BENCH), run_name="bench_workers")
    r = mod["run"](num_envs=2, workers=2, n_agents=3, steps=5, repeats=1)
    assert set(r["phases"]) == {"in-process", "2 workers", "2 slices, parent steps one", mod["CEIL"], mod["FREE"],
                                mod["LOCK"]}
    for name, phases in r["phases"].items():
        assert len(phases) == 1 and phases[0][0] > 0, name
    for key in ("speedup", "speedup_parent_slice", "speedup_ceiling"):
        assert math.isfinite(r[key]) and r[key] > 0, key
    assert set(r["median_paired_speedup"]) == set(r["phases"]) - {"in-process"}
    # Charging each step its slower slice can only cost time: lockstep is never faster than free.
    (free,), (lock,) = r["phases"][mod["FREE"]], r["phases"][mod["LOCK"]]
    assert 0 < lock[0] <= free[0] * (1 + 1e-9)


def test_slices_match_the_worker_split():
    from hammer.envs.workers import slice_counts

    assert slice_counts(8, 2) == [(0, 4), (4, 4)]
    assert slice_counts(7, 3) == [(0, 3), (3, 2), (5, 2)]
    assert sum(c for _, c in slice_counts(5, 5)) == 5
