"""`hammer bench soak`: a real `hammer serve` sampled over time, every role process found and measured,
and nothing left running after it (no figure is asserted: speed and memory targets live in the bench)."""

from __future__ import annotations

import json

import pytest
from hammer.benchmarks.soak import growth, role_of, run_soak, write_result

from tests.runtime_helpers import processes_mentioning

ROLES = {"launcher", "policy-server", "central", "local-0", "local-1", "local-2", "env"}


def test_role_names_come_from_the_command_lines_the_launcher_uses():
    py = "/venv/bin/python"
    assert role_of([py, "-P", "-m", "hammer.entry", "local", "--run-dir", "r", "--agent", "2"]) == "local-2"
    assert role_of([py, "-P", "-m", "hammer.cli", "local", "--run-dir", "r", "--agents", "0,1"]) == "locals-0-1"
    assert role_of([py, "-P", "-m", "hammer.entry", "learner", "--run-dir", "r"]) == "policy-server"
    assert role_of([py, "-P", "-m", "hammer.cli", "serve", "b", "--episodes", "9"]) == "launcher"
    assert role_of([py, "-c", "from multiprocessing.spawn import spawn_main"]) is None


def test_growth_is_measured_from_the_first_sample_after_the_warm_up():
    samples = [{"t_s": t, "rss_mib": {"env": rss}, "pids": {"env": pid}, "disk_mib": disk, "episodes": ep}
               for t, rss, pid, disk, ep in [(0, 50.0, 1, 0.0, None), (60, 100.0, 1, 1.0, 1000),
                                             (120, 110.0, 2, 2.0, 2000)]]
    g = growth(samples, warm_s=60)
    assert g["processes"]["env"] == {"first_mib": 100.0, "end_mib": 110.0, "growth_pct": 10.0, "restarted": True}
    assert g["disk"]["growth_mib_per_h"] == 60.0 and g["disk"]["bytes_per_episode"] == round(2**20 / 1000, 1)


@pytest.mark.timeout(240)
def test_a_short_soak_samples_every_process_and_stops_the_run(tmp_path):
    # 6 s, a sample every 1.2 s: what is checked (every process sampled, the disk growing, a clean stop)
    # does not depend on the soak's length, and the served run burns its CPU for as long as it lasts
    r = run_soak(minutes=0.1, every_s=1.2, work=tmp_path / "soak", progress=lambda line: None)
    assert len(r["samples"]) >= 5 and r["samples"][-1]["t_s"] >= 6
    for s in r["samples"]:
        assert set(s["rss_mib"]) == ROLES and all(v > 0 for v in s["rss_mib"].values()), s
    assert r["samples"][-1]["disk_mib"] > r["samples"][0]["disk_mib"]
    assert set(r["growth"]["processes"]) == ROLES
    assert not any(p["restarted"] for p in r["growth"]["processes"].values())
    summary = json.loads((tmp_path / "soak" / "run" / "summary.json").read_text())
    assert summary["stopped_by"] == "SIGINT" and summary["attendance"]["leaves"] == 0  # a clean Ctrl-C
    assert not processes_mentioning(str(tmp_path))
    written = write_result(r, tmp_path / "results")
    assert json.loads(written.read_text())["growth"] == r["growth"]
