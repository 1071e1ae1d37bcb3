"""Per-episode link counters: step logs written, read back and summed over episode spans.

The join is checked against a brute-force sum over every logged event; the publisher's per-step
fault attribution against what really arrived over a real Zenoh session on 127.0.0.1.
"""

from __future__ import annotations

import csv
import time

import numpy as np
from hammer.faults.episode_links import (
    BASE_COLUMNS,
    EPISODE_EVENTS,
    episode_columns,
    read_step_logs,
    step_totals,
    write_episode_links,
)
from hammer.faults.links import flat_fault_counters
from hammer.faults.spec import build_plan
from hammer.faults.steplog import STEP_LOG_DIR, LoggedPublisher, StepLog, column
from hammer.protocol.schemas import LocalObs
from hammer.protocol.session import HammerSession, TransportConfig

LINKS = ["env->central", "env->local", "central->local", "local->env"]


def _synthetic_run(run_dir, rng):
    """Two roles log random events (several flushes, events for old steps after their flush, a torn
    last line); the env host's episode file has random spans. Returns the events and episodes."""
    logs = {"env": StepLog(run_dir / STEP_LOG_DIR, "env", [column("env->local", "sent"), column("local->env", "late")],
                           pid=11),
            "local-0": StepLog(run_dir / STEP_LOG_DIR, "local-0",
                               [column("env->local", "delivered"), column("central->local", "dropped"),
                                column("local->env", "sent")], pid=12)}
    events = []
    for step in range(1, 81):
        for log in logs.values():
            for col in log.columns:
                n = int(rng.integers(0, 3))
                at = max(1, step - int(rng.integers(0, 4)))  # late copies: counted for an earlier step
                log.add(at, col, n)
                events.append((at, col, n))
            if rng.random() < 0.2:
                log.flush()
    for log in logs.values():
        log.flush()
    with open(logs["env"].path, "a") as f:
        f.write("81,7,1")  # a SIGKILL in the middle of a write: the line has no newline
    episodes = []
    for e in range(1, 13):
        end = int(rng.integers(5, 90))
        length = int(rng.integers(1, min(end, 25) + 1))
        episodes.append({"episode": e, "env_index": int(rng.integers(0, 4)), "length": length,
                         "start_step": end - length + 1, "end_step": end,
                         "msg_fallbacks": int(rng.integers(0, 9)), "default_actions": int(rng.integers(0, 9))})
    with open(run_dir / "episode_links.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=BASE_COLUMNS, lineterminator="\n")
        w.writeheader()
        w.writerows(episodes)
    return events, episodes


def test_episode_columns_are_the_logged_events_summed_over_each_episode_span(tmp_path):
    events, episodes = _synthetic_run(tmp_path, np.random.default_rng(0))
    rows = write_episode_links(tmp_path, LINKS)
    with open(tmp_path / "episode_links.csv", newline="") as f:
        on_disk = [{k: int(v) for k, v in r.items()} for r in csv.DictReader(f)]
    assert on_disk == rows and len(rows) == len(episodes)
    assert list(on_disk[0]) == [*BASE_COLUMNS, *episode_columns(LINKS)]
    for ep, row in zip(episodes, rows, strict=True):
        assert {c: row[c] for c in BASE_COLUMNS} == ep  # the env host's columns untouched
        for c in episode_columns(LINKS):
            want = sum(n for s, col, n in events if col == c and ep["start_step"] <= s <= ep["end_step"])
            assert row[c] == want, (ep["episode"], c)
    assert sum(r["env_local_sent"] for r in rows) > 0 and sum(r["central_local_dropped"] for r in rows) > 0
    # Events the step logs never carry are 0; `fallbacks` is logged but not a per-episode column.
    assert all(r["env_central_sent"] == 0 for r in rows) and "central_local_fallbacks" not in rows[0]
    # Run totals: every logged event once, the torn line ignored.
    totals = step_totals(read_step_logs(tmp_path / STEP_LOG_DIR))
    for link, per_event in totals.items():
        for event, total in per_event.items():
            assert total == sum(n for _, col, n in events if col == column(link, event)), (link, event)
    # The join can be run again (columns replaced, not appended twice), on fewer links.
    again = write_episode_links(tmp_path, ["env->local"])
    assert list(again[0]) == [*BASE_COLUMNS, *(f"env_local_{e}" for e in EPISODE_EVENTS)]
    assert [r["env_local_sent"] for r in again] == [r["env_local_sent"] for r in rows]


def test_step_log_writes_nothing_without_a_directory_and_rejects_unknown_events(tmp_path):
    log = StepLog(None, "env", [column("env->local", "sent")])
    log.add(3, column("env->local", "sent"))
    log.flush()
    assert log.path is None and not list(tmp_path.iterdir())
    try:
        column("env->local", "lost")
    except ValueError as e:
        assert "lost" in str(e)
    else:
        raise AssertionError("an unknown event was accepted")


def test_logged_publisher_attributes_each_drop_and_duplicate_to_its_message_step(tmp_path):
    """Real sessions on loopback: the steps the log marks dropped are exactly the ones that never
    arrived, duplicated ones arrived twice; a rule of another link is not counted for this one."""
    n = 300
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    plan = build_plan(["env->local:drop=0.3,duplicate=0.2", "local->env:drop=0.5"], seed=4)
    with HammerSession("steplog", t, faults=plan.to_spec()) as pub_s, \
         HammerSession("steplog", TransportConfig.connector(port)) as sub_s:
        sub = sub_s.subscribe(sub_s.keys.obs("*"), LocalObs, maxsize=0)  # read after the whole burst
        time.sleep(0.3)
        log = StepLog(tmp_path, "env", [column("env->local", e) for e in ("sent", "dropped", "duplicated")])
        pub = LoggedPublisher(pub_s.publisher(pub_s.keys.obs(1)), pub_s, log, "env->local")
        obs = np.zeros((2, 4), np.float32)
        for step in range(1, n + 1):
            pub.publish(LocalObs(step=step, env_idx=np.arange(2), agent=1, obs=obs, active=np.ones(2, bool)))
            if step % 50 == 0:
                log.flush()
        log.flush()
        got: list[int] = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            m = sub.get(0.5)
            if m is None and len(got) == pub_s.faults.counters[0].sent:
                break
            if m is not None:
                got.append(m.step)
        report = flat_fault_counters(pub_s.fault_report())
    counts = read_step_logs(tmp_path)
    arrived = np.bincount(got, minlength=n + 1)
    sent = counts["env_local_sent"]
    dropped = np.zeros(n + 1, np.int64)
    dropped[:len(counts["env_local_dropped"])] = counts["env_local_dropped"]
    duplicated = np.zeros(n + 1, np.int64)
    duplicated[:len(counts["env_local_duplicated"])] = counts["env_local_duplicated"]
    assert sent[1:].tolist() == [1] * n
    assert np.array_equal(arrived[1:], (sent - dropped + duplicated)[1:])
    assert 0.2 * n < dropped.sum() < 0.4 * n and duplicated.sum() > 0.1 * (n - dropped.sum())
    assert (dropped.sum(), duplicated.sum()) == (report["fault.env_local.dropped"], report["fault.env_local.duplicated"])
