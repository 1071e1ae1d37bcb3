"""Who of a run's roles was there, and for how long not: the launcher's record of liveliness tokens.

A role whose process dies, is killed, or hangs past its Zenoh lease drops its liveliness token, and
that is the only sign of the outage a role that can no longer speak gives. Its peers only see late
messages and fallbacks, which a run counts but cannot name; so the launcher records every token
that goes and comes back after start-up as one log line with the role and a running counter, keeps
per role how often and how long it was away, and a run with a role away longer than
`max_absence_s` is degraded with that role named (deploy.launcher `_verdict`).

Only the run's own roles are followed: in the plain profile any peer can declare a token under any
name, and a record that grew with every invented name would be one more thing a long run grows.
The list of events is bounded (the latest `max_events`, and how many were dropped).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

log = logging.getLogger("hammer.up.attendance")
log.setLevel(logging.INFO)  # joins and rejoins are INFO, leaves WARNING: all reach the console and launcher.log


@dataclass
class RoleAttendance:
    joins: int = 0  # its token came up (the first time included)
    leaves: int = 0  # its token went while the run was live
    rejoins: int = 0  # came up again after a leave
    absent_s: float = 0.0  # finished absences, and an open one up to the end
    longest_absence_s: float = 0.0
    away_since: float | None = None  # clock time its token went (None: here, or never seen)
    here: bool = False


class Attendance:
    """Tokens up and down per role, on the `clock` of the caller (time.monotonic by default)."""

    def __init__(self, roles: Iterable[str], max_events: int = 200, clock=time.monotonic) -> None:
        self.clock = clock
        self.t0 = clock()
        self.wall0 = time.time()
        self.roles = {r: RoleAttendance() for r in roles}
        self.events: deque[dict] = deque(maxlen=max_events)
        self.events_total = 0
        self.started = False  # after start-up every change is logged (the launcher logs start-up itself)
        self.ended_at: float | None = None  # the run is ending: tokens going now are the roles stopping

    def start(self) -> None:
        """Every role is up: from now on a token going is an outage, and every change is logged."""
        self.started = True

    def end(self, now: float | None = None) -> None:
        """The run is ending (the env host spent its budget, or the launcher stops everyone): tokens
        going from now on are roles stopping, not leaving. An absence still open ends here."""
        if self.ended_at is not None:
            return
        now = self.clock() if now is None else now
        self.ended_at = now
        for r in self.roles.values():
            if r.away_since is not None:
                self._close_absence(r, now - r.away_since)

    def up(self, role: str, now: float | None = None) -> None:
        r = self.roles.get(role)
        if r is None or r.here or self.ended_at is not None:
            return
        now = self.clock() if now is None else now
        r.here = True
        r.joins += 1
        if r.away_since is None:
            self._event(role, "join", now, f"{role} joined (join {r.joins})", logging.INFO)
            return
        gone = now - r.away_since
        r.away_since = None
        r.rejoins += 1
        self._close_absence(r, gone)
        self._event(role, "rejoin", now, f"{role} rejoined after {gone:.1f} s (rejoin {r.rejoins})", logging.INFO,
                    absent_s=round(gone, 3))

    def down(self, role: str, now: float | None = None) -> None:
        r = self.roles.get(role)
        if r is None or not r.here or self.ended_at is not None:
            return
        now = self.clock() if now is None else now
        r.here = False
        r.leaves += 1
        r.away_since = now
        self._event(role, "leave", now, f"{role} left (leave {r.leaves})", logging.WARNING)

    def _close_absence(self, r: RoleAttendance, gone: float) -> None:
        r.absent_s += gone
        r.longest_absence_s = max(r.longest_absence_s, gone)

    def _event(self, role: str, kind: str, now: float, line: str, level: int, **extra) -> None:
        self.events_total += 1
        self.events.append({"t_s": round(now - self.t0, 3), "at": _iso(self.wall0 + now - self.t0), "role": role,
                            "event": kind, **extra})
        if self.started:  # before that the launcher's "all roles alive" line says it
            log.log(level, line)

    # ----- what it shows ------------------------------------------------------------------------
    def away(self, now: float | None = None) -> dict[str, float]:
        """Roles away right now and for how long (s)."""
        now = self.clock() if now is None else now
        return {n: now - r.away_since for n, r in self.roles.items() if r.away_since is not None}

    def leaves(self) -> int:
        return sum(r.leaves for r in self.roles.values())

    def rejoins(self) -> int:
        return sum(r.rejoins for r in self.roles.values())

    def longest(self, role: str, now: float | None = None) -> float:
        """Its longest absence, an open one included."""
        r = self.roles[role]
        now = self.clock() if now is None else now
        return max(r.longest_absence_s, now - r.away_since if r.away_since is not None else 0.0)

    def summary(self) -> dict:
        """summary.json's `attendance`: per role its counters, then the latest events."""
        roles = {n: {"joins": r.joins, "leaves": r.leaves, "rejoins": r.rejoins, "absent_s": round(r.absent_s, 3),
                     "longest_absence_s": round(r.longest_absence_s, 3),
                     **({"away_at_end": True} if r.away_since is not None else {})}
                 for n, r in sorted(self.roles.items())}
        return {"roles": roles, "leaves": self.leaves(), "rejoins": self.rejoins(), "events": list(self.events),
                "events_dropped": self.events_total - len(self.events)}

    def degraded_reasons(self, max_absence_s: float) -> list[str]:
        """One reason per role that was away longer than `max_absence_s` at a time."""
        out = []
        for n, r in sorted(self.roles.items()):
            if r.longest_absence_s > max_absence_s:
                out.append(f"{n} was away {r.longest_absence_s:.1f} s at most (> max_absence_s {max_absence_s:g} s; "
                           f"{r.leaves} leave{'s' if r.leaves != 1 else ''}, {r.absent_s:.1f} s in all"
                           f"{', still away at the end' if r.away_since is not None else ''})")
        return out


def _iso(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"
