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
        self.since = time.monotonic()  # a member never heard of is absent from here on
        self.observer_stalls = 0
        # per member, for the summary: leaves, and the longest absence so far
        self.member_leaves = np.zeros(n, np.int64)
        self.member_longest_s = np.zeros(n)
        self.events: collections.deque[dict] = collections.deque(maxlen=EVENTS_KEPT)

    def seen(self, i: int, t: float) -> None:
        first = not np.isfinite(self.last[i])
        self.last[i] = max(self.last[i], t)
        if self.present[i]:
            return
        self.present[i] = True
        if np.isnan(self.left_at[i]):
            self.joins += 1
            late = t - self.since if first else 0.0
            if late > self.bound:  # it was missing from the start: an absence like any other
                self.member_longest_s[i] = max(self.member_longest_s[i], late)
                self.longest_absence_s = max(self.longest_absence_s, late)
                self.log.warning("%s joined %.1f s late (join %d)", self.names[i], late, self.joins)
            else:
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
            never = not np.isfinite(self.last[i])
            if never:
                out[name] = {"leaves": 0, "longest_absence_s": round(now - self.since, 3), "missing_at_end": True,
                             "never_joined": True}
                continue
            ongoing = 0.0 if self.present[i] or np.isnan(self.left_at[i]) else now - self.left_at[i]
            if self.member_leaves[i] or ongoing or self.member_longest_s[i]:
                out[name] = {"leaves": int(self.member_leaves[i]),
                             "longest_absence_s": round(max(self.member_longest_s[i], ongoing), 3),
                             "missing_at_end": bool(ongoing)}
        return out

    def member_counters(self, now: float | None = None, limit: int = 16) -> dict[str, float]:
        """Per member ever absent (never heard of included), for a heartbeat: `<name>.absent_max_s`
        (its longest absence so far, one still going counted as far as it has gone: never falls) and
        `<name>.joined` (0 until it is first heard of, then 1). At most `limit` members, the longest
        absent first, so a heartbeat's counters stay within their bound however large the team."""
        now = time.monotonic() if now is None else now
        rows = sorted(((a["longest_absence_s"], name, not a.get("never_joined", False))
                       for name, a in self.absences(now).items()), reverse=True)[:limit]
        out: dict[str, float] = {}
        for longest, name, joined in rows:
            key = name.replace("-", "_")
            out[f"{key}.absent_max_s"] = longest
            out[f"{key}.joined"] = int(joined)
        return out

    def present_count(self) -> int:
        return int(self.present.sum())

    def start_clock(self, now: float) -> None:
        """Absences count from `now` (a world's clock starts once its fleet is there, or after its
        start-up wait): a member first heard of before it was not late."""
        self.since = now

    def counters(self) -> dict[str, float]:
        return {"observer_stalls": self.observer_stalls, "robot_joins": self.joins, "robot_leaves": self.leaves, "robot_rejoins": self.rejoins,
                "robot_absent_s": round(self.absent_s, 3), "robot_longest_absence_s": round(self.longest_absence_s, 3)}


def rejections_by_member(by_key: dict[str, dict[str, int]], names: list[str]) -> dict[str, dict[str, int]]:
    """A session's refusals per key (`HammerSession.rejections_by_key`) regrouped per robot: a key
    whose last part is robot i's index (`agent/up/1`, `agent/act/1`) or name counts for robot i. What
    names a flood or a forgery by the keys it came on, so an attack does not read as a link failure."""
    out: dict[str, collections.Counter[str]] = {}
    for key, reasons in by_key.items():
        tail = key.rsplit("/", 1)[-1]
        name = f"local-{tail}" if tail.isdigit() else tail
        if name in names:
            out.setdefault(name, collections.Counter()).update(reasons)
    return {name: dict(c) for name, c in sorted(out.items())}


def flat_member_rejections(per_member: dict[str, dict[str, int]], limit: int = 16) -> dict[str, int]:
    """`rejections_by_member` as heartbeat counters (`local_1.rejected.size`), at most `limit` of them,
    the largest first."""
    rows = sorted(((n, f"{name.replace('-', '_')}.rejected.{reason}") for name, r in per_member.items()
                   for reason, n in r.items() if n), reverse=True)[:limit]
    return {k: int(n) for n, k in rows}
