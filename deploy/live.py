"""A run's live picture for `hammer view`, written by the launcher that already holds it.

The launcher of `hammer up`, `hammer serve` and `hammer serve --realtime` already gathers every
role's heartbeats, tokens, restarts and chaos events into its board. `LiveStatus.tick(board)`
(called from the launcher's own tick, ~4-10 times a second) turns that board into three files
in the run directory, which is all the web view reads:

- `live.json`: the current picture, replaced atomically (write + rename) every `WRITE_EVERY_S`:
  one row per role or robot ever seen (a silent one stays, with its last-seen age), the fleet's
  counts, the open alerts and the latest events;
- `events.jsonl`: every event once (leaves, rejoins, missing and back, restarts, pushes and canary
  steps, version switches, rejections by reason, alerts raised and resolved), bounded;
- `series.jsonl`: one sample a second (then sparser as the run grows old: a run of days keeps a few
  thousand lines) of the paper metric, the rates and the message ages, for the plots.

Why files and not a socket to the view: the view is its own process and must be read-only. It
never holds a Zenoh session, so nothing a browser sends can reach the run's keys; it may die or be
restarted without the run noticing; `hammer view RUNS_DIR` shows finished runs from the same files.

A row's state: `ok`; `late` (the world held or defaulted it part of its latest second); `missing`
(no heartbeat for `SILENT_AFTER_S`, its token gone, or the world applied its default action for the
whole of its latest report); `never` (not heard of yet); `stopped` (its last heartbeat said so).
Alerts (`Alerts`) have a reason, hysteresis (raised after `raise_after_s` bad, cleared after
`clear_after_s` good) and a cooldown (a repeat within `cooldown_s` is counted, not announced), so a
flapping link does not flood.
"""

from __future__ import annotations

import json
import logging
import os
import re
import socket
import subprocess
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("hammer.live")

LIVE_FILE = "live.json"
EVENTS_FILE = "events.jsonl"
SERIES_FILE = "series.jsonl"
LIVE_VERSION = 1
WRITE_EVERY_S = 0.2  # live.json at 5 Hz: a page sees a change within ~0.3 s
SILENT_AFTER_S = 1.5  # heartbeats come every 1 s: one and a half missed is silence
EVENTS_KEPT = 50  # the latest events in live.json (events.jsonl holds them all, up to MAX_EVENT_LINES)
MAX_EVENT_LINES = 20_000
VIEW_TOKEN_ENV = "HAMMER_VIEW_TOKEN"


def _robot_index(name: str) -> int | None:
    m = re.fullmatch(r"local-(\d+)", name)
    return int(m.group(1)) if m else None


# ----- alerts ---------------------------------------------------------------------------------------
@dataclass
class _Alert:
    bad_since: float | None = None
    good_since: float | None = None
    firing: bool = False
    notified_at: float = float("-inf")
    repeats: int = 0  # raised again within the cooldown: counted, not announced
    reason: str = ""


class Alerts:
    """Conditions by key, each judged with hysteresis and announced at most once per cooldown."""

    def __init__(self, raise_after_s: float = 2.0, clear_after_s: float = 3.0, cooldown_s: float = 60.0) -> None:
        self.raise_after_s, self.clear_after_s, self.cooldown_s = raise_after_s, clear_after_s, cooldown_s
        self.state: dict[str, _Alert] = {}

    def observe(self, key: str, bad: bool, now: float, reason: str = "") -> list[dict]:
        """The condition `key` is `bad` (with `reason`) or not at `now`: the events it makes (raised,
        resolved), none while it only flaps inside the hysteresis or repeats within the cooldown."""
        a = self.state.setdefault(key, _Alert())
        out: list[dict] = []
        if bad:
            a.good_since = None
            a.reason = reason or a.reason
            a.bad_since = now if a.bad_since is None else a.bad_since
            if not a.firing and now - a.bad_since >= self.raise_after_s:
                a.firing = True
                if now - a.notified_at >= self.cooldown_s:
                    a.notified_at = now
                    out.append({"event": "alert", "key": key, "reason": a.reason})
                else:
                    a.repeats += 1
        else:
            a.bad_since = None
            if a.firing:
                a.good_since = now if a.good_since is None else a.good_since
                if now - a.good_since >= self.clear_after_s:
                    a.firing = False
                    out.append({"event": "resolved", "key": key, "reason": a.reason})
        return out

    def firing(self) -> list[dict]:
        return [{"key": k, "reason": a.reason, "repeats": a.repeats} for k, a in sorted(self.state.items()) if a.firing]


# ----- the picture ----------------------------------------------------------------------------------
@dataclass
class _Row:
    name: str
    first_seen: float | None = None  # wall time
    last_seen: float | None = None  # monotonic, the latest heartbeat
    hb: object = None  # the latest heartbeat object (a new one is a new arrival)
    marks: deque = None  # (time, counter) of the latest heartbeats, for the rate over RATE_WINDOW_S
    rate: float | None = None
    world: tuple[int, int] | None = None  # robot: (fresh, defaults) at the world's previous report
    world_delta: tuple[int, int] | None = None  # ... and their growth in its latest one
    state: str = "never"
    since: float | None = None  # when the state began (monotonic)
    version: int | None = None


RATE_COUNTERS = ("env_steps", "acts", "ticks", "steps", "msgs_sent")
RATE_WINDOW_S = 3.0  # a rate over heartbeats a second apart, dated by arrival: a few of them smooth the jitter


class LiveStatus:
    """The launcher's board as RUN/live.json, RUN/events.jsonl and RUN/series.jsonl (module doc)."""

    def __init__(self, run_dir: Path, kind: str, title: str, robots: int = 0, roles: tuple[str, ...] = (),
                 clock=time.monotonic, wall=time.time, alerts: Alerts | None = None) -> None:
        self.run_dir, self.kind, self.title = Path(run_dir), kind, title
        self.clock, self.wall = clock, wall
        self.t0, self.wall0 = clock(), wall()
        self.rows: dict[str, _Row] = {}
        for name in (*roles, *(f"local-{i}" for i in range(robots))):
            self.rows[name] = _Row(name)
        self.robots = robots
        self.alerts = alerts or Alerts()
        self.events: deque[dict] = deque(maxlen=EVENTS_KEPT)
        self.event_lines = 0
        self.events_dropped = 0
        self._written = float("-inf")
        self._series_at = float("-inf")
        self._attendance_seen = 0
        self._chaos_seen = 0
        self._restarts: dict[str, int] = {}
        self._rejected: dict[str, dict[str, int]] = {}
        self._pushes_mtime = None
        self._pushes_seen = 0
        self.rollout: dict = {}
        self._world_hb = None
        self._rejection_marks: dict[str, tuple[float, int]] = {}
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for name in (LIVE_FILE, EVENTS_FILE, SERIES_FILE):  # a new session in the same directory starts afresh
            (self.run_dir / name).unlink(missing_ok=True)
        self._event({"event": "started", "reason": f"{kind} {title}"})

    # ----- events -------------------------------------------------------------------------------
    def _event(self, e: dict) -> None:
        now = self.wall()
        e = {"t": round(now, 3), "t_s": round(self.clock() - self.t0, 3), **e}
        self.events.append(e)
        if self.event_lines >= MAX_EVENT_LINES:
            self.events_dropped += 1
            return
        self.event_lines += 1
        with open(self.run_dir / EVENTS_FILE, "a") as f:
            f.write(json.dumps(e) + "\n")

    # ----- one tick -----------------------------------------------------------------------------
    def tick(self, board, now: float | None = None) -> None:
        """Take the board in; write live.json at most every WRITE_EVERY_S. Never raises: the view is
        a side show, a launcher must not fail for it (a failure is logged once)."""
        try:
            self._tick(board, self.clock() if now is None else now)
        except Exception as e:  # noqa: BLE001 - see the docstring
            if not getattr(self, "_failed", False):
                self._failed = True
                log.warning("live status not written (%s: %s); the run goes on", type(e).__name__, e)

    def _tick(self, board, now: float) -> None:
        if now - self._written < WRITE_EVERY_S:
            return
        self._written = now
        self._take_heartbeats(board, now)
        self._take_board_events(board)
        self._take_pushes()
        self._judge(board, now)
        self._write(board, now)
        age = now - self.t0
        if now - self._series_at >= max(1.0, age / 3600.0):
            self._series_at = now
            self._sample(board, now)

    def _row(self, name: str) -> _Row:
        r = self.rows.get(name)
        if r is None:
            r = self.rows[name] = _Row(name)
        return r

    def _take_heartbeats(self, board, now: float) -> None:
        for name, h in list(board.heartbeats.items()):
            r = self._row(name)
            if h is r.hb:
                continue
            r.hb, r.last_seen = h, now
            if r.first_seen is None:
                r.first_seen = self.wall()
            c = h.counters
            key = next((k for k in RATE_COUNTERS if k in c), None)
            if key is not None and not (self.kind == "fleet" and _robot_index(name) is not None):
                r.rate = _rate(r, now, c[key])
            v = h.gauges.get("policy_version")
            if v is not None and r.version is not None and int(v) != r.version:
                self._event({"event": "switch", "role": name, "reason": f"{name} acts with policy version {int(v)} "
                                                                         f"(was {r.version})"})
            if v is not None:
                r.version = int(v)
            rejected = {k.split(".", 1)[1]: int(n) for k, n in c.items() if k.startswith("rejected.") and n}
            before = self._rejected.get(name, {})
            grown = {k: n - before.get(k, 0) for k, n in rejected.items() if n > before.get(k, 0)}
            if grown:
                self._rejected[name] = rejected
                self._event({"event": "rejected", "role": name,
                             "reason": f"{name} refused " + ", ".join(f"{n:,} {k}" for k, n in sorted(grown.items()))})
        world = board.heartbeats.get("env") if self.kind == "fleet" else None
        if world is not None and world is not self._world_hb:
            self._world_hb = world
            for i in range(self.robots):
                r = self._row(f"local-{i}")
                key = f"local_{i}"
                cur = (int(world.counters.get(f"{key}.fresh", 0)), int(world.counters.get(f"{key}.defaults", 0)))
                if r.world is not None:
                    r.world_delta = (cur[0] - r.world[0], cur[1] - r.world[1])
                r.world = cur
                r.rate = _rate(r, now, cur[0])  # a robot's control rate: its fresh actions the world applied

    def _take_board_events(self, board) -> None:
        att = getattr(board, "attendance", None)
        if att is not None and att.events_total > self._attendance_seen:
            new = list(att.events)[-(att.events_total - self._attendance_seen):]
            self._attendance_seen = att.events_total
            for e in new:
                if e["event"] != "join" or att.started:
                    self._event({"event": e["event"], "role": e["role"],
                                 "reason": f"{e['role']} {e['event']}" + (f" after {e['absent_s']:.1f} s"
                                                                          if "absent_s" in e else "")})
        chaos = getattr(board, "chaos_log", [])
        for e in chaos[self._chaos_seen:]:
            self._event({"event": "chaos", "reason": json.dumps(e, default=str)[:200]})
        self._chaos_seen = len(chaos)
        for name, n in getattr(board, "restarts", {}).items():
            if n > self._restarts.get(name, 0):
                self._event({"event": "restart", "role": name, "reason": f"{name} died and was restarted ({n})"})
            self._restarts[name] = n

    def _take_pushes(self) -> None:
        from hammer.runtime.pushes import HistoryError, assignment, read_pushes

        path = self.run_dir / "pushes.json"
        try:
            mtime = path.stat().st_mtime_ns
        except FileNotFoundError:
            return
        if mtime == self._pushes_mtime:
            return
        self._pushes_mtime = mtime
        try:
            entries = read_pushes(self.run_dir)
        except HistoryError as e:
            self._event({"event": "pushes_unreadable", "reason": str(e)[:300]})
            return
        for e in entries[self._pushes_seen:]:
            action = e.get("action", "push")
            decision = e.get("decision") if isinstance(e.get("decision"), dict) else {}
            what = f"{action} v{e['version']}" + (f" (restores v{e['restores_version']})" if "restores_version" in e else "")
            if e.get("agents"):
                what += f" agents {','.join(str(a) for a in e['agents'])}"
            if "stage" in decision:
                what += f" stage {decision['stage']}"
            if e.get("reason"):
                what += f": {e['reason']}"
            self._event({"event": action, "reason": what})
        self._pushes_seen = len(entries)
        a = assignment(entries)
        last = entries[-1] if entries else {}
        decision = last.get("decision") if isinstance(last.get("decision"), dict) else {}
        self.rollout = {"base": a.base, "canary": a.canary, "canary_agents": sorted(a.canary_agents),
                        "stage": decision.get("stage"), "last": last.get("action"), "pushes": len(entries)}

    # ----- judging ------------------------------------------------------------------------------
    def _judge(self, board, now: float) -> None:
        alive = getattr(board, "alive", None) or set()  # `hammer up`'s tokens (a fleet's launcher follows none)
        att = getattr(board, "attendance", None)
        followed = set(att.roles) if att is not None and att.started else set()
        for name, r in self.rows.items():
            h = r.hb
            silent = r.last_seen is None or now - r.last_seen > SILENT_AFTER_S
            if getattr(h, "status", None) == "stopped":
                state = "stopped"
            elif r.last_seen is None and not (r.world and r.world[0]):
                state = "never"
            elif name in followed and name not in alive:
                state = "missing"  # its liveliness token went (`hammer up`: the launcher follows them)
            elif silent:
                # a token still up while the heartbeats pause (a learner in a long update): late, not gone
                state = "late" if name in followed else "missing"
            elif r.world_delta is not None and r.world_delta[1] > 0:
                state = "missing" if r.world_delta[0] == 0 else "late"
            else:
                state = "ok"
            if state != r.state:
                if r.state in ("ok", "late") and state == "missing":
                    self._event({"event": "missing", "role": name, "reason": self._silence(r, now)})
                elif r.state == "missing" and state in ("ok", "late"):
                    self._event({"event": "back", "role": name,
                                 "reason": f"{name} back after {now - (r.since or now):.1f} s"})
                r.state, r.since = state, now
            for e in self.alerts.observe(f"missing:{name}", state == "missing", now, self._silence(r, now)):
                self._event({**e, "role": name})
        for name, reasons in self._rejected.items():
            recent = self._recent_rejections(name, now, sum(reasons.values()))
            for e in self.alerts.observe(f"rejections:{name}", recent, now,
                                         f"{name} refuses payloads: " + ", ".join(f"{k} {v:,}" for k, v in
                                                                                  sorted(reasons.items()))):
                self._event({**e, "role": name})

    def _recent_rejections(self, name: str, now: float, total: int) -> bool:
        """Refusals grew within the last 5 s (the alert clears once they stop growing)."""
        marks = self._rejection_marks
        t, n = marks.get(name, (float("-inf"), 0))
        if total > n:
            marks[name] = t, n = now, total
        return now - t < 5.0

    def _silence(self, r: _Row, now: float) -> str:
        if r.last_seen is None:
            return f"{r.name}: never heard of"
        why = f"no heartbeat for {now - r.last_seen:.1f} s" if now - r.last_seen > SILENT_AFTER_S else \
            "the world applied its default action" if r.world_delta and r.world_delta[1] else "its liveliness token is gone"
        return f"{r.name} missing: {why}"

    # ----- writing ------------------------------------------------------------------------------
    def _rows(self, now: float) -> list[dict]:
        out = []
        canary = set(self.rollout.get("canary_agents") or ())
        for name, r in sorted(self.rows.items(), key=lambda x: _order(x[0])):
            h = r.hb
            c = dict(getattr(h, "counters", {}) or {})
            g = dict(getattr(h, "gauges", {}) or {})
            i = _robot_index(name)
            world_defaults = r.world[1] if r.world else None
            row = {"name": name, "robot": i, "state": r.state,
                   "last_seen_age_s": None if r.last_seen is None else round(now - r.last_seen, 2),
                   "state_for_s": None if r.since is None else round(now - r.since, 1),
                   "status": getattr(h, "status", None), "pid": getattr(h, "pid", None),
                   "detail": getattr(h, "detail", "") or "",
                   "rate_hz": None if r.rate is None else round(r.rate, 2),
                   "msg_age_p50_ms": g.get("msg_age_p50_ms", g.get("step_p50_ms")),
                   "msg_age_p99_ms": g.get("msg_age_p99_ms", g.get("step_p99_ms")),
                   "defaults": world_defaults if world_defaults is not None else c.get("default_actions"),
                   "fallbacks": (c.get("msg_stale", 0) + c.get("msg_none", 0)) if "msg_none" in c  # a robot
                   else c.get("fallback_copies", c.get("msg_fallback_copies")),  # a local agent, the env host
                   "policy_acted": g.get("policy_version"), "policy_held": g.get("policy_held"),
                   "cohort": None if i is None or not self.rollout else ("canary" if i in canary else "base"),
                   "restarts": self._restarts.get(name, 0),
                   "rejected": sum(self._rejected.get(name, {}).values())}
            if self.kind == "fleet" and i is not None and r.world_delta is not None and self._world_hb is not None:
                row["world_fresh"] = r.world[0]
            out.append(row)
        return out

    def _counts(self, board, rows: list[dict]) -> dict:
        env = board.heartbeats.get("env")
        c = {**getattr(env, "counters", {}), **getattr(env, "gauges", {})} if env is not None else {}
        robots = [r for r in rows if r["robot"] is not None]
        states = {s: sum(r["state"] == s for r in robots) for s in ("ok", "late", "missing", "never", "stopped")}
        out = {"robots": len(robots), **{f"robots_{s}": n for s, n in states.items()},
               "roles": len(rows), "roles_missing": sum(r["state"] == "missing" for r in rows),
               "episodes": c.get("episodes"), "paper_metric_100": c.get("paper_metric_100"),
               "ticks": c.get("ticks"), "env_steps": c.get("env_steps"),
               "restarts": sum(self._restarts.values())}
        rate = getattr(board, "env_rate", None)
        if callable(rate):
            out["env_steps_per_s"] = round(rate(), 1)
        return out

    def _write(self, board, now: float, ended: str | None = None) -> None:
        rows = self._rows(now)
        live = {"version": LIVE_VERSION, "kind": self.kind, "title": self.title, "run": self.run_dir.name,
                "written_at": round(self.wall(), 3), "started_at": round(self.wall0, 3),
                "elapsed_s": round(now - self.t0, 1), "ended": ended, "counts": self._counts(board, rows),
                "rows": rows, "alerts": self.alerts.firing(), "rollout": self.rollout,
                "events": list(self.events), "events_dropped": self.events_dropped}
        tmp = self.run_dir / f".{LIVE_FILE}.tmp"
        tmp.write_text(json.dumps(live))
        os.replace(tmp, self.run_dir / LIVE_FILE)
        self.last = live

    def _sample(self, board, now: float) -> None:
        live = getattr(self, "last", None)
        if live is None:
            return
        c = live["counts"]
        s = {"t": round(self.wall(), 2), "t_s": round(now - self.t0, 1), "paper_metric_100": c.get("paper_metric_100"),
             "episodes": c.get("episodes"), "env_steps_per_s": c.get("env_steps_per_s"),
             "robots_ok": c.get("robots_ok"),
             "rows": {r["name"]: [r["rate_hz"], r["msg_age_p50_ms"], r["msg_age_p99_ms"]] for r in live["rows"]}}
        with open(self.run_dir / SERIES_FILE, "a") as f:
            f.write(json.dumps(s) + "\n")

    def close(self, board, ended: str) -> None:
        """The run is over (`ended`: how): a last picture that says so."""
        try:
            now = self.clock()
            self._take_heartbeats(board, now)
            self._take_board_events(board)
            self._take_pushes()
            try:  # the launcher's verdict, written just before: each degraded reason as an event
                summary = json.loads((self.run_dir / "summary.json").read_text())
            except (OSError, ValueError):
                summary = {}
            for reason in summary.get("degraded_reasons") or []:
                self._event({"event": "degraded", "reason": str(reason)[:500]})
            self._event({"event": "ended", "reason": ended})
            self._write(board, now, ended=ended)
        except Exception as e:  # noqa: BLE001 - the run's own end must not fail for the view
            log.warning("live status: last picture not written (%s)", e)


def _rate(r: _Row, now: float, count: float) -> float | None:
    if r.marks is None:
        r.marks = deque()
    r.marks.append((now, count))
    while len(r.marks) > 2 and now - r.marks[1][0] >= RATE_WINDOW_S:
        r.marks.popleft()
    (t0, c0), (t1, c1) = r.marks[0], r.marks[-1]
    if c1 < c0:  # a restarted process counts from zero again
        r.marks.clear()
        return None
    return (c1 - c0) / (t1 - t0) if t1 - t0 >= 1.0 else r.rate


def _order(name: str) -> tuple:
    i = _robot_index(name)
    return (1, i, "") if i is not None else (0, 0, name)


# ----- the view process, started beside a launcher ---------------------------------------------------
def parse_view_addr(text: str) -> tuple[str, int]:
    """`[ADDR:]PORT` (an IPv6 address in brackets) -> (host, port); ValueError naming the fix."""
    host, sep, port = str(text).rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        p = int(port)
        if not 0 <= p <= 65535:
            raise ValueError
    except ValueError:
        raise ValueError(f"--view {text!r}: expected [ADDR:]PORT, e.g. 8050 or 127.0.0.1:8050") from None
    return host or "127.0.0.1", p


def is_loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def view_token(token: str | None) -> str | None:
    """The token given, else the environment's (HAMMER_VIEW_TOKEN), else None."""
    return token or os.environ.get(VIEW_TOKEN_ENV) or None


def check_view_addr(host: str, token: str | None, flag: str = "--view") -> None:
    """Beyond loopback the view answers only with a token: ValueError (one line) without one."""
    if not is_loopback(host) and not token:
        raise ValueError(f"{flag} {host}: beyond loopback the view needs a token; fix: --view-token TOKEN (or "
                         f"{VIEW_TOKEN_ENV}=TOKEN), or bind 127.0.0.1")
    if token is not None and len(token) < 16:
        raise ValueError("--view-token: at least 16 characters (e.g. python -c 'import secrets; "
                         "print(secrets.token_urlsafe())')")


class ViewProcess:
    """`hammer view RUNS_DIR` as a child of a launcher: started before the run, stopped after it."""

    def __init__(self, runs_dir: Path, addr: str, token: str | None = None, log_path: Path | None = None) -> None:
        from hammer.runtime.process import PARENT_ENV

        self.host, port = parse_view_addr(addr)
        self.token = view_token(token)
        check_view_addr(self.host, self.token)
        if port == 0:  # chosen here, so the URL can be printed before the child answers
            fam = socket.AF_INET6 if ":" in self.host else socket.AF_INET
            with socket.socket(fam) as s:
                s.bind((self.host, 0))
                port = s.getsockname()[1]
        self.port = port
        env = {**os.environ, PARENT_ENV: str(os.getpid())}
        if self.token:
            env[VIEW_TOKEN_ENV] = self.token  # never on the command line (ps shows it)
        else:
            env.pop(VIEW_TOKEN_ENV, None)
        Path(runs_dir).mkdir(parents=True, exist_ok=True)
        self.log_path = Path(log_path) if log_path is not None else Path(runs_dir) / ".view.log"
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-P", "-m", "hammer.cli", "view", str(runs_dir),
                                      "--addr", f"[{self.host}]:{port}" if ":" in self.host else f"{self.host}:{port}"],
                                     env=env, stdout=self._log, stderr=subprocess.STDOUT)

    def url(self, run: str | None = None) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/" + (f"#/run/{run}" if run else "")

    def wait_ready(self, timeout: float = 20.0) -> None:
        """Until it answers; ValueError with its last log line if it exits or stays silent."""
        deadline = time.monotonic() + timeout
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else "::1" if self.host == "::" else self.host
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise ValueError(f"--view: the view exited ({self.proc.returncode}): {self._tail()}")
            try:
                with socket.create_connection((host, self.port), timeout=0.2):
                    return
            except OSError:
                time.sleep(0.1)
        self.stop()
        raise ValueError(f"--view: the view did not answer on port {self.port} in {timeout:.0f} s: {self._tail()}")

    def _tail(self) -> str:
        try:
            lines = [x for x in self.log_path.read_text(errors="replace").splitlines() if x.strip()]
        except OSError:
            return "no log"
        return lines[-1] if lines else "nothing in its log"

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


class LiveRun:
    """What a launcher command adds for the view, in one object: the live files of `run_dir`
    (`tick(board)` from the launcher's tick, `close(how)` at the end) and, with `view`, the view
    process on the folder holding the run (started now, stopped by `close`). ValueError (one line)
    for a bad `view` address, a missing token beyond loopback, or a view that does not start."""

    def __init__(self, run_dir: Path, kind: str, title: str, robots: int = 0, roles: tuple[str, ...] = (),
                 view: str | None = None, token: str | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.args = (kind, title, robots, roles)
        self.status: LiveStatus | None = None
        self.board = None
        self.view = None
        if view is not None:
            self.view = ViewProcess(self.run_dir.resolve().parent, view, token, self.run_dir / "logs" / "view.log")
            self.view.wait_ready()

    @property
    def url(self) -> str | None:
        return None if self.view is None else self.view.url(self.run_dir.name)

    def tick(self, board) -> None:
        self.board = board
        if self.status is None:  # at the first tick: the launcher has prepared the run directory by now
            self.status = LiveStatus(self.run_dir, *self.args)
        self.status.tick(board)

    def close(self, how: str) -> None:
        try:
            if self.status is not None and self.board is not None:
                self.status.close(self.board, how)
        finally:
            if self.view is not None:
                self.view.stop()
