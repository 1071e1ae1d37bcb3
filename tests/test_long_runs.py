"""Outages you can see and runs that last hours: every role's leaves and rejoins are
logged, counted and degrade a run when too long; what a served run writes is bounded (step logs,
trace, role logs) and what the env host keeps is not every episode.

The end-to-end test serves a cn3 team as real processes over Zenoh on 127.0.0.1 and kills one
local agent with the chaos schedule; the others check each bounded file on its own.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hammer.deploy.attendance import Attendance
from hammer.deploy.launcher import Board, launch
from hammer.env_host.checkpoint import EPISODE_ROW_COLUMNS, EpisodeRows
from hammer.env_host.trace import TRACE_ARRAYS, TraceWriter
from hammer.envs.registry import make_vec_env
from hammer.faults.episode_links import BASE_COLUMNS, read_step_logs, write_episode_links
from hammer.faults.steplog import STEP_LOG_DIR, StepLog, column, read_cut
from hammer.learning.config import merge_config
from hammer.runtime.settings import RuntimeSettings
from safetensors.numpy import save_file

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    """An exported (untrained) cn3 HAMMER policy: what it does does not matter here, that it runs does."""
    from hammer.learning.team import Team

    cfg = merge_config("cn3", overrides=["variant=hammer", "central_mode=rl", "seed=1", "num_envs=16"])
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    spec = env.spec
    env.close()
    t = Team(cfg, spec)
    d = tmp_path_factory.mktemp("policy")
    save_file(t.local.export_numpy(), str(d / "local.safetensors"))
    save_file(t.central.export_numpy(), str(d / "central.safetensors"))
    return d, cfg


@pytest.mark.timeout(300)
def test_a_killed_agent_is_logged_counted_and_degrades_the_run_and_served_files_stay_bounded(tmp_path, team):
    policy, base = team
    # 2,000 vector steps: the agent is back long before the end (the outage slows only the steps
    # from the kill to its return; the env host steps the rest as fast as the roles go)
    cfg = base.model_copy(update={"episodes": 1280})
    run = tmp_path / "served"
    settings = RuntimeSettings(
        run_id="long-run", mode="eval", policy_dir=str(policy), agents_per_process=1,
        chaos=["kill:local-1@step=100,for=3s"],  # SIGKILL, and started again 3 s later
        act_deadline_ms=20,  # while local-1 is away each step waits this long for its action
        max_absence_s=1.0, step_log_max_mb=0.02, trace=True, trace_max_mb=0.05)
    res = launch(cfg, settings, run)
    s = res.summary
    assert s["completed"] and s["episodes"] == 1280

    # 1. the outage: one leave and one rejoin of local-1, logged with counters; nobody else left,
    # and the roles stopping at the end of the run are no leaves
    att = s["attendance"]
    assert att["roles"]["local-1"]["leaves"] == 1 and att["roles"]["local-1"]["rejoins"] == 1
    assert att["roles"]["local-1"]["joins"] == 2
    # away from the kill to its restart 3 s later and beyond (less the launcher's 0.25 s tick at most)
    assert att["roles"]["local-1"]["longest_absence_s"] >= 2.5
    assert {n: r["leaves"] for n, r in att["roles"].items() if n != "local-1"} == dict.fromkeys(
        ["central", "env", "policy", "local-0", "local-2"], 0)
    assert [(e["role"], e["event"]) for e in att["events"] if e["event"] != "join"] == [("local-1", "leave"),
                                                                                         ("local-1", "rejoin")]
    launcher_log = (run / "logs" / "launcher.log").read_text()
    assert "local-1 left (leave 1)" in launcher_log and "local-1 rejoined after " in launcher_log
    assert "(rejoin 1)" in launcher_log
    assert s["degraded"] is True
    assert any(r.startswith("local-1 was away ") and "max_absence_s 1 s" in r for r in s["degraded_reasons"])
    on_disk = json.loads((run / "summary.json").read_text())
    assert on_disk["attendance"] == att and on_disk["degraded_reasons"] == s["degraded_reasons"]

    # 2. step logs: rotated, each process's files within the cap (plus one flush), the dropped steps named,
    # and the episodes that began before them have unknown (empty) link columns, the later ones counts
    steps = run / STEP_LOG_DIR
    cut = read_cut(steps)
    assert cut > 0
    for f in steps.glob("*.csv"):
        assert f.stat().st_size < 0.02 * 2**20, f
    with open(run / "episode_links.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["episode"]) for r in rows] == list(range(1, 1281))
    early = [r for r in rows if int(r["start_step"]) <= cut]
    late = [r for r in rows if int(r["start_step"]) > cut]
    assert early and late
    assert all(r["env_local_sent"] == "" for r in early)
    assert all(int(r["env_local_sent"]) == 3 * int(r["length"]) for r in late)  # one obs per agent and step

    # 3. trace: the latest steps only, in order up to the last one, within the cap; no segments left
    tr = np.load(run / "trace.npz")
    assert sorted(tr.files) == sorted(TRACE_ARRAYS)
    assert tr["steps"][-1] == s["step"] and np.array_equal(np.diff(tr["steps"]), np.ones(len(tr["steps"]) - 1))
    assert 0 < len(tr["steps"]) < s["step"] and (run / "trace.npz").stat().st_size < 2 * 0.05 * 2**20
    assert tr["obs"].shape[:3] == (len(tr["steps"]), 16, 3) and tr["versions"].shape == tr["steps"].shape
    assert not (run / "trace").exists()


def test_attendance_counts_leaves_and_rejoins_after_startup_and_ignores_the_run_ending():
    t = [0.0]
    att = Attendance(["env", "local-0", "local-1"], max_events=4, clock=lambda: t[0])
    for r in ("env", "local-0", "local-1", "local-7"):  # local-7 is no role of this run: not followed
        att.up(r)
    att.start()
    t[0] = 10.0
    att.down("local-1")
    att.down("local-1")  # the same token twice: one leave
    t[0] = 14.5
    assert att.away() == {"local-1": 4.5}
    att.up("local-1")
    t[0] = 20.0
    att.down("local-0")
    t[0] = 50.0
    att.end()  # the run ends with local-0 still away: its absence ends here
    att.down("env")  # roles stopping after that are no leaves
    att.up("local-0")
    summary = att.summary()
    assert summary["roles"]["local-1"] == {"joins": 2, "leaves": 1, "rejoins": 1, "absent_s": 4.5,
                                           "longest_absence_s": 4.5}
    assert summary["roles"]["local-0"] == {"joins": 1, "leaves": 1, "rejoins": 0, "absent_s": 30.0,
                                           "longest_absence_s": 30.0, "away_at_end": True}
    assert summary["roles"]["env"]["leaves"] == 0 and "local-7" not in summary["roles"]
    assert [(e["role"], e["event"]) for e in summary["events"]] == [
        ("local-1", "join"), ("local-1", "leave"), ("local-1", "rejoin"), ("local-0", "leave")]
    assert summary["events_dropped"] == 2 and summary["events"][2]["absent_s"] == 4.5
    reasons = att.degraded_reasons(max_absence_s=10.0)
    assert len(reasons) == 1 and reasons[0].startswith("local-0 was away 30.0 s at most (> max_absence_s 10 s")
    assert att.degraded_reasons(max_absence_s=60.0) == []


def test_the_dashboard_shows_who_left_and_who_is_away():
    from hammer.deploy.dashboard import attendance_text, dashboard_table
    from rich.console import Console

    t = [0.0]
    att = Attendance(["local-0", "local-1"], clock=lambda: t[0])
    board = Board(attendance=att)
    att.up("local-0")
    att.up("local-1")
    att.start()
    assert attendance_text(board) == ""
    t[0] = 3.0
    att.down("local-1")
    t[0] = 7.0
    assert attendance_text(board) == "local-1 left 1, rejoined 0; away now: local-1 4 s"
    console = Console(record=True, width=240, color_system=None)
    console.print(dashboard_table(board, merge_config("cn3"), time.monotonic()))
    assert "local-1 left 1, rejoined 0; away now: local-1 4 s" in console.export_text()


def test_episode_rows_go_to_disk_as_they_come_and_resume_cuts_them_back(tmp_path):
    class Ep:  # an envs.base.EpisodeStats as far as the rows need it
        def __init__(self, i: int) -> None:
            self.env_index, self.length = i % 4, 25

    rows = EpisodeRows(tmp_path, num_envs=4)
    rows.start()
    for n in range(1, 1001):
        rows.count(np.ones((4, 3), bool), np.zeros((4, 3), bool))
        rows.add(n, Ep(n), end_step=25 * n)
        assert len(rows.pending) < EpisodeRows.write_every  # never more than a batch in memory
    rows.write_all()
    lines = (tmp_path / "episode_links.csv").read_text().splitlines()
    assert lines[0] == ",".join(EPISODE_ROW_COLUMNS) and len(lines) == 1001 and rows.total == 1000
    assert lines[1] == "1,1,25,1,25,3,0"
    # a session killed mid-write: the torn line and everything after the checkpoint go
    with open(tmp_path / "episode_links.csv", "a") as f:
        f.write("1001,2,25,250")
    rows.cut(700)
    assert (tmp_path / "episode_links.csv").read_text().splitlines() == lines[:701]
    with pytest.raises(ValueError, match="expected episodes 1..900"):
        rows.cut(900)


def test_the_trace_keeps_its_latest_steps_within_its_cap(tmp_path):
    rng = np.random.default_rng(0)
    added = []
    cap = 64 * 1024
    tw = TraceWriter(tmp_path, cap, segment_bytes=8 * 1024)
    for step in range(1, 301):
        v = (step, rng.standard_normal((4, 3, 5)).astype(np.float32), rng.standard_normal((4, 3, 2)).astype(np.float32),
             rng.integers(0, 5, (4, 3)), rng.random((4, 3)) < 0.1, rng.random((4, 3)) < 0.1, step // 100)
        added.append(v)
        tw.add(*v)
        assert tw.disk <= cap + 8 * 1024  # one segment over the cap at most, until the oldest goes
    assert tw.dropped_steps > 0
    tw.close()
    tr = np.load(tmp_path / "trace.npz")
    kept = len(tr["steps"])
    assert kept == 300 - tw.dropped_steps and tr["steps"][0] == tw.dropped_steps + 1
    for j, name in enumerate(TRACE_ARRAYS):
        want = np.stack([np.asarray(v[j]) for v in added[-kept:]])
        assert tr[name].dtype == want.dtype and np.array_equal(tr[name], want), name
    assert not (tmp_path / "trace").exists()


def test_step_logs_rotate_and_the_episodes_they_no_longer_cover_get_empty_link_columns(tmp_path):
    cols = [column("env->local", "sent"), column("local->env", "late")]
    log = StepLog(tmp_path / STEP_LOG_DIR, "env", cols, pid=5, max_bytes=2000)
    for step in range(1, 401):
        log.add(step, cols[0], 3)
        if step % 20 == 0:
            log.flush()
    log.flush()
    files = sorted(p.name for p in (tmp_path / STEP_LOG_DIR).iterdir())
    assert files == ["env-5.csv", "env-5.cut", "env-5.prev.csv"]
    cut = read_cut(tmp_path / STEP_LOG_DIR)
    counts = read_step_logs(tmp_path / STEP_LOG_DIR)["env_local_sent"]
    assert 0 < cut < 400 and not counts[:cut + 1].any()  # the deleted rows are gone from the sums
    assert (counts[cut + 1:] == 3).all()  # every step after the cut is all there
    with open(tmp_path / "episode_links.csv", "w") as f:
        f.write(",".join(BASE_COLUMNS) + "\n")
        f.writelines(f"{e},0,25,{25 * e - 24},{25 * e},0,0\n" for e in range(1, 17))
    rows = write_episode_links(tmp_path, ["env->local"])
    for r in rows:
        if r["start_step"] <= cut:
            assert r["env_local_sent"] == ""
        else:
            assert r["env_local_sent"] == 75


def test_a_role_log_rotates_at_its_cap_with_stderr_following_it(tmp_path):
    """A real role process set up as `hammer up` sets one up: stderr a file under RUN/logs."""
    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)
    (run / "runtime.json").write_text(json.dumps({"run_id": "x", "log_max_mb": 0.01}))  # 10 kB
    code = ("import logging, os, sys\n"
            "from pathlib import Path\n"
            "from hammer.runtime.process import setup_process\n"
            "setup_process('local-0', Path(sys.argv[1]))\n"
            "for i in range(600):\n"
            "    logging.getLogger('hammer.local').info('line %d %s', i, 'x' * 40)\n"
            "print('stdout after', flush=True)\n"
            "os.write(2, b'raw fd 2 after\\n')\n")
    log = run / "logs" / "local-0.log"
    with open(log, "ab") as f:
        env = {k: v for k, v in os.environ.items() if k != "HAMMER_PARENT_PID"}
        subprocess.run([sys.executable, "-P", "-c", code, str(run)], stdout=f, stderr=subprocess.STDOUT,
                       check=True, timeout=60, cwd=ROOT, env=env)
    names = sorted(p.name for p in (run / "logs").iterdir())
    assert names == ["local-0.log", "local-0.log.1", "local-0.log.2"]
    for p in (run / "logs").iterdir():
        assert p.stat().st_size < 0.01 * 2**20 + 200, p  # the cap, plus the line that crossed it
    current = log.read_text()
    assert current.endswith("stdout after\nraw fd 2 after\n")  # print and the raw fd follow the rotation
    assert "line 599 " in (run / "logs" / "local-0.log.1").read_text() + current
