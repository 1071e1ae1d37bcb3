"""`hammer view` without a browser: the launcher's live picture (deploy/live.py), its alerts, the
token that guards the view beyond loopback, and /metrics' names (the ones docs/view.md lists).
The view is a real `hammer view` process on loopback, asked over real HTTP."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest
from hammer.deploy.live import LIVE_FILE, SILENT_AFTER_S, Alerts, LiveStatus
from hammer.protocol.schemas import Heartbeat

from tests.runtime_helpers import ENV, ROOT, hammer

pytestmark = pytest.mark.timeout(120)


def test_a_flapping_condition_raises_one_alert_and_a_repeat_within_the_cooldown_is_only_counted():
    a = Alerts(raise_after_s=2.0, clear_after_s=3.0, cooldown_s=60.0)
    out = []
    t = 0.0
    for _ in range(30):  # bad 1 s, good 1 s: never bad long enough to raise
        out += a.observe("missing:local-1", True, t, "local-1 silent")
        out += a.observe("missing:local-1", False, t + 1.0)
        t += 2.0
    assert out == [] and a.firing() == []
    for k in range(6):  # bad for 5 s: raised once, with its reason
        out += a.observe("missing:local-1", True, t + k, "local-1 missing: no heartbeat for 1.6 s")
    assert [e["event"] for e in out] == ["alert"] and "no heartbeat" in out[0]["reason"]
    t += 6
    out += a.observe("missing:local-1", False, t)  # good 1 s, then bad again: still the same alert
    out += a.observe("missing:local-1", True, t + 1.0)
    assert len(out) == 1 and len(a.firing()) == 1
    for k in range(5):  # good for 4 s: resolved
        out += a.observe("missing:local-1", False, t + 2.0 + k)
    assert [e["event"] for e in out] == ["alert", "resolved"] and a.firing() == []
    t += 10
    for k in range(4):  # raised again within the cooldown: counted, not announced
        out += a.observe("missing:local-1", True, t + k, "again")
    assert [e["event"] for e in out] == ["alert", "resolved"] and a.firing()[0]["repeats"] == 1
    for k in range(5):
        out += a.observe("missing:local-1", False, t + 5 + k)
    t += 100
    for k in range(4):  # after the cooldown: announced again
        out += a.observe("missing:local-1", True, t + k, "once more")
    assert [e["event"] for e in out] == ["alert", "resolved", "resolved", "alert"]


def _beat(role: str, pid: int, **counters) -> Heartbeat:
    return Heartbeat(role=role, pid=pid, status="running", counters=counters,
                     gauges={"policy_version": 0, "policy_held": 0, "msg_age_p50_ms": 20.0, "msg_age_p99_ms": 40.0})


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _fleet_board(tmp_path: Path) -> tuple[LiveStatus, SimpleNamespace, Clock]:
    """A fleet launcher's board (deploy/fleet_launch.py: heartbeats by role, restarts, chaos log) and the
    live picture of it on a clock the test moves."""
    clock = Clock()
    live = LiveStatus(tmp_path, "fleet", "cn3 at 20 Hz", robots=3, roles=("env", "central"), clock=clock)
    board = SimpleNamespace(heartbeats={}, restarts={"env": 0, "local-0": 0, "local-1": 0}, chaos_log=[])
    return live, board, clock


def _step(live, board, clock, dt: float, beats: dict[str, int]) -> dict:
    """`dt` seconds on, with a new heartbeat from each role in `beats` (its acts so far)."""
    clock.t += dt
    for role, n in beats.items():
        board.heartbeats[role] = _beat(role, 100 + len(role), acts=n)
    live.tick(board)
    return json.loads((live.run_dir / LIVE_FILE).read_text())


def test_a_silent_robot_stays_in_the_list_with_its_last_seen_age_and_comes_back(tmp_path):
    live, board, clock = _fleet_board(tmp_path)
    d = _step(live, board, clock, 0.3, {"local-0": 10, "local-1": 10})
    rows = {r["name"]: r for r in d["rows"]}
    assert [r["name"] for r in d["rows"]] == ["central", "env", "local-0", "local-1", "local-2"]
    assert rows["local-0"]["state"] == rows["local-1"]["state"] == "ok" and rows["local-2"]["state"] == "never"
    for k in range(4):  # local-1 silent from here on; local-0 keeps beating once a second
        # the world's report: local-0's fresh actions at 20 Hz, local-1 on its default action
        board.heartbeats["env"] = _beat("env", 7, ticks=20 * k, **{"local_0.fresh": 20 * k, "local_0.defaults": 0,
                                                                   "local_1.fresh": 5, "local_1.defaults": 20 * k})
        d = _step(live, board, clock, 1.0, {"local-0": 30 + 20 * k})
    rows = {r["name"]: r for r in d["rows"]}
    assert rows["local-1"]["state"] == "missing" and rows["local-1"]["last_seen_age_s"] == pytest.approx(4.0)
    assert rows["local-0"]["state"] == "ok" and rows["local-0"]["rate_hz"] == pytest.approx(20.0)
    assert d["counts"]["robots_missing"] == 1 and d["counts"]["robots_never"] == 1
    assert [a["key"] for a in d["alerts"]] == ["missing:local-1"], d["alerts"]
    assert f"no heartbeat for {4.0:.1f} s" in d["alerts"][0]["reason"] and 4.0 > SILENT_AFTER_S
    board.heartbeats["env"] = _beat("env", 7, ticks=80, **{"local_0.fresh": 80, "local_0.defaults": 0,
                                                           "local_1.fresh": 20, "local_1.defaults": 65})
    d = _step(live, board, clock, 1.0, {"local-0": 110, "local-1": 11})
    rows = {r["name"]: r for r in d["rows"]}
    assert rows["local-1"]["state"] == "late"  # heard again, on its default part of the world's latest second
    board.heartbeats["env"] = _beat("env", 7, ticks=100, **{"local_0.fresh": 100, "local_0.defaults": 0,
                                                            "local_1.fresh": 40, "local_1.defaults": 65})
    d = _step(live, board, clock, 1.0, {"local-0": 130, "local-1": 31})
    assert {r["name"]: r for r in d["rows"]}["local-1"]["state"] == "ok"
    board.restarts["local-0"] = 1
    _step(live, board, clock, 1.0, {"local-0": 5})
    events = [json.loads(x) for x in (tmp_path / "events.jsonl").read_text().splitlines()]
    kinds = [(e["event"], e.get("role")) for e in events]
    for want in (("missing", "local-1"), ("alert", "local-1"), ("back", "local-1"), ("restart", "local-0")):
        assert want in kinds, kinds
    (tmp_path / "summary.json").write_text(json.dumps({"degraded_reasons": ["local-1 was missing 4.0 s at most"]}))
    live.close(board, "completed")  # the launcher's verdict, written just before, as events
    d = json.loads((tmp_path / LIVE_FILE).read_text())
    assert d["ended"] == "completed"
    assert [(e["event"], e["reason"]) for e in d["events"][-2:]] == [
        ("degraded", "local-1 was missing 4.0 s at most"), ("ended", "completed")]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class View:
    def __init__(self, runs: Path, token: str | None = None) -> None:
        self.port = _free_port()
        env = {k: v for k, v in ENV.items() if k != "HAMMER_VIEW_TOKEN"}
        if token:
            env["HAMMER_VIEW_TOKEN"] = token
        self.proc = subprocess.Popen([sys.executable, "-m", "hammer.cli", "view", str(runs), "--addr",
                                      f"127.0.0.1:{self.port}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        end = time.monotonic() + 30
        while time.monotonic() < end:
            try:
                with socket.create_connection(("127.0.0.1", self.port), 0.2):
                    return
            except OSError:
                assert self.proc.poll() is None, self.proc.stderr.read()
                time.sleep(0.1)
        raise AssertionError("hammer view did not answer")

    def get(self, path: str, headers: dict | None = None, method: str = "GET") -> tuple[int, str, dict]:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}{path}", headers=headers or {}, method=method)
        try:
            with urllib.request.urlopen(req, timeout=5) as r:
                return r.status, r.read().decode(), dict(r.headers)
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode(), dict(e.headers)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


def test_beyond_loopback_the_view_is_refused_in_one_line_without_a_token(tmp_path):
    env = {"HAMMER_VIEW_TOKEN": ""}
    r = hammer("view", str(tmp_path), "--addr", "0.0.0.0:8050", env=env, timeout=60)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "beyond loopback the view needs a token" in r.stderr and "--view-token" in r.stderr
    r = hammer("view", str(tmp_path), "--addr", "0.0.0.0:8050", "--view-token", "short", env=env, timeout=60)
    assert r.returncode == 2 and "at least 16 characters" in r.stderr, r.stderr
    # a launcher refuses before any role starts or any run directory is made
    r = hammer("up", "--episodes", "1", "--out", str(tmp_path / "runs"), "--view", "0.0.0.0:8050", "--no-dashboard",
               env=env, timeout=60)
    assert r.returncode == 2 and "error: --view 0.0.0.0: beyond loopback the view needs a token" in r.stderr, r.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())


def test_with_a_token_the_view_answers_only_its_holders_and_only_reads(tmp_path):
    live, board, clock = _fleet_board(tmp_path / "runs" / "fleet-a")
    _step(live, board, clock, 0.3, {"local-0": 1})
    token = "t0ken-for-the-test-0123456789"
    view = View(tmp_path / "runs", token)
    try:
        assert view.get("/metrics")[0] == 401
        assert view.get("/api/runs", {"Authorization": "Bearer wrong-token-0123456789"})[0] == 401
        status, body, _ = view.get("/metrics", {"Authorization": f"Bearer {token}"})
        assert status == 200 and 'hammer_role_up{robot="0",role="local-0",run="fleet-a"} 1.0' in body
        status, _, headers = view.get(f"/?token={token}")  # a browser: the token once, then a cookie
        assert status == 200 and "HttpOnly" in headers.get("set-cookie", "")
        cookie = headers["set-cookie"].split(";")[0]
        status, body, _ = view.get("/api/runs", {"Cookie": cookie})
        assert status == 200 and [r["run"] for r in json.loads(body)["runs"]] == ["fleet-a"]
        for method in ("POST", "PUT", "DELETE"):
            assert view.get("/api/runs/fleet-a", {"Cookie": cookie}, method=method)[0] == 405
        for bad in ("/api/runs/..%2F..%2Fetc", "/api/runs/../fleet-a", "/api/runs/nope"):
            assert view.get(bad, {"Cookie": cookie})[0] == 404, bad
    finally:
        view.close()


def documented_metrics() -> dict[str, set[str]]:
    """docs/view.md's table: each metric's name and its labels."""
    text = (ROOT / "docs" / "view.md").read_text()
    out = {}
    for name, labels in re.findall(r"^\| `(hammer_[a-z_]+)` \| ([a-z_, ]+) \|", text, re.MULTILINE):
        out[name] = {x.strip() for x in labels.split(",")}
    return out


def test_metrics_have_the_documented_names_and_labels(tmp_path):
    from prometheus_client.parser import text_string_to_metric_families

    live, board, clock = _fleet_board(tmp_path / "runs" / "fleet-b")
    board.heartbeats["env"] = _beat("env", 7, ticks=40, episodes=2)
    _step(live, board, clock, 0.3, {"local-0": 1, "local-1": 1, "central": 3})
    _step(live, board, clock, 1.2, {"local-0": 2, "local-1": 2, "central": 27})  # a rate needs a second of beats
    view = View(tmp_path / "runs")
    try:
        status, body, headers = view.get("/metrics")
    finally:
        view.close()
    assert status == 200 and headers["content-type"].startswith("text/plain")
    seen: dict[str, set[str]] = {}
    for fam in text_string_to_metric_families(body):
        for s in fam.samples:
            if s.name.startswith("hammer_"):
                seen.setdefault(s.name, set()).update(s.labels)
    documented = documented_metrics()
    assert documented and set(seen) <= set(documented), set(seen) - set(documented)
    for name, labels in seen.items():
        assert labels == documented[name], (name, labels, documented[name])
    must = {"hammer_role_up", "hammer_role_last_seen_seconds", "hammer_role_rate_hz", "hammer_role_policy_version",
            "hammer_run_live", "hammer_run_robots"}
    assert must <= set(seen), must - set(seen)


def test_in_hammer_up_a_paused_role_with_its_token_up_is_late_and_one_whose_token_went_is_missing(tmp_path):
    """`hammer up`'s board (deploy.launcher.Board, with the launcher's attendance of liveliness tokens): a
    learner in a long update still holds its token (late, no alert), a local agent whose token went is
    missing, with the attendance's leave as an event."""
    from hammer.deploy.attendance import Attendance
    from hammer.deploy.launcher import Board

    clock = Clock()
    roles = {"env", "learner", "local-0"}
    board = Board(alive=set(roles), attendance=Attendance(roles, clock=clock))
    for r in sorted(roles):
        board.attendance.up(r)
    board.attendance.start()
    live = LiveStatus(tmp_path, "up", "cn3", robots=1, roles=("env", "learner"), clock=clock)
    d = _step(live, board, clock, 0.3, {"env": 1, "learner": 1, "local-0": 1})
    assert {r["name"]: r["state"] for r in d["rows"]} == {"env": "ok", "learner": "ok", "local-0": "ok"}
    for k in range(3):  # the learner's heartbeats pause for 3 s; its token stays
        d = _step(live, board, clock, 1.0, {"env": 2 + k, "local-0": 2 + k})
    assert {r["name"]: r["state"] for r in d["rows"]}["learner"] == "late" and d["alerts"] == []
    board.alive.discard("local-0")
    board.attendance.down("local-0")
    d = _step(live, board, clock, 0.3, {"env": 9, "learner": 9})
    rows = {r["name"]: r["state"] for r in d["rows"]}
    assert rows["local-0"] == "missing" and rows["learner"] == "ok"
    assert ("leave", "local-0") in [(e["event"], e.get("role")) for e in d["events"]]
    assert ("missing", "local-0") in [(e["event"], e.get("role")) for e in d["events"]]
