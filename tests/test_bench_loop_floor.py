"""The loop-floor benchmark runs the real topology over real Zenoh and times every step."""

from __future__ import annotations

import pytest
from hammer.benchmarks.loop_floor import measure


@pytest.mark.parametrize(("topology", "typed"), [("split", False), ("grouped", True)])
def test_loop_floor_times_every_step_of_the_topology(topology, typed):
    row = measure(topology, typed, k=4, n=2, d=12, m=4, steps=60, warmup=10, timeout=30)
    assert row.steps == 60
    assert row.processes == (4 if topology == "split" else 3)
    assert 0 < row.p50_us <= row.p99_us
