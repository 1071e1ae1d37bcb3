"""Who of a fleet is there, judged by what arrives from them: joins, leaves and rejoins, each a log
line with the member's name and a counter.

Why from data and not from Zenoh liveliness: a robot whose link is down keeps its liveliness token
until its lease expires (10 s by default), and a robot that is up but silent is no use either. A
member is present while something of its arrived within `missing_after_s`; the world and the
central agent of a fleet each keep one `Presence` of the robots they hear from.
"""

from __future__ import annotations

import collections
import logging
import time

import numpy as np

EVENTS_KEPT = 200  # the latest leave/rejoin events a summary lists (a fleet that runs for days stays flat)


class Presence:
    """Members (by index) seen at times on time.monotonic(); `update(now)` returns who is present."""

    def __init__(self, names: list[str], missing_after_s: float, log: logging.Logger) -> None:
        if not missing_after_s > 0:
            raise ValueError(f"missing_after_s: must be > 0 s, got {missing_after_s}")
        self.names, self.bound, self.log = names, missing_after_s, log
        n = len(names)
        self.last = np.full(n, -np.inf)
        self.present = np.zeros(n, bool)
        self.left_at = np.full(n, np.nan)  # when a missing member was last heard of
        self.joins = self.leaves = self.rejoins = 0
        self.absent_s = 0.0  # total of finished absences
        self.longest_absence_s = 0.0
        self.checked = None  # when `update` last ran
        self.observer_stalls = 0
        # per member, for the summary: leaves, and the longest absence so far
        self.member_leaves = np.zeros(n, np.int64)
        self.member_longest_s = np.zeros(n)
        self.events: collections.deque[dict] = collections.deque(maxlen=EVENTS_KEPT)

    def seen(self, i: int, t: float) -> None:
        self.last[i] = max(self.last[i], t)
        if self.present[i]:
            return
        self.present[i] = True
        if np.isnan(self.left_at[i]):
            self.joins += 1
            self.log.info("%s joined (join %d)", self.names[i], self.joins)
            return
        gone = t - self.left_at[i]
        self.rejoins += 1
        self.absent_s += gone
        self.longest_absence_s = max(self.longest_absence_s, gone)
        self.member_longest_s[i] = max(self.member_longest_s[i], gone)
        self.events.append({"t": round(time.time(), 3), "member": self.names[i], "event": "rejoined",
                            "absent_s": round(gone, 3)})
        self.log.warning("%s rejoined after %.1f s silent (rejoin %d)", self.names[i], gone, self.rejoins)

    def update(self, now: float | None = None) -> np.ndarray:
        """(N,) bool: present now; a member silent beyond the bound leaves (logged, counted)."""
        now = time.monotonic() if now is None else now
        checked, self.checked = self.checked, now
        if checked is not None and now - checked > self.bound:
            # The observer itself was stalled (paused, starved of CPU): what its members sent meanwhile
            # may still be on its way in, so this turn judges no one.
            self.observer_stalls += 1
            self.log.warning("no presence check for %.1f s (this process stalled): judging no one this turn",
                             now - checked)
            return self.present
        gone = self.present & (now - self.last > self.bound)
        for i in np.flatnonzero(gone):
            self.present[i] = False
            self.left_at[i] = self.last[i]
            self.leaves += 1
            self.member_leaves[i] += 1
            self.events.append({"t": round(time.time(), 3), "member": self.names[i], "event": "missing"})
            self.log.warning("%s missing: nothing from it for %.1f s (leave %d)", self.names[i], now - self.last[i],
                             self.leaves)
        return self.present

    def absences(self, now: float | None = None) -> dict[str, dict]:
        """Per member that was ever missing: its leaves, its longest absence (one still going counts
        as far as it has gone), and whether it is missing now. For a summary that names outages."""
        now = time.monotonic() if now is None else now
        out = {}
        for i, name in enumerate(self.names):
            ongoing = 0.0 if self.present[i] or np.isnan(self.left_at[i]) else now - self.left_at[i]
            if self.member_leaves[i] or ongoing:
                out[name] = {"leaves": int(self.member_leaves[i]),
                             "longest_absence_s": round(max(self.member_longest_s[i], ongoing), 3),
                             "missing_at_end": bool(ongoing)}
        return out

    def present_count(self) -> int:
        return int(self.present.sum())

    def counters(self) -> dict[str, float]:
        return {"observer_stalls": self.observer_stalls, "robot_joins": self.joins, "robot_leaves": self.leaves, "robot_rejoins": self.rejoins,
                "robot_absent_s": round(self.absent_s, 3), "robot_longest_absence_s": round(self.longest_absence_s, 3)}
