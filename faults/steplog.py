"""Per-step link events of one role process: the raw material of the per-episode link counters.

An episode of an env copy is a range of global vector steps, and every step-loop message carries
the step it is for in its header. No role sees a whole link (see `faults.links`), so each role
writes what it saw, per step: the sender its messages and what its fault layer did to them
(attributed to the message's step), the receiver what arrived (attributed to the step the
message was for, even when it arrives later). `faults.episode_links` sums these over each
episode's steps at the end of `hammer up`.

One file per process, `RUN/linksteps/<role>-<pid>.csv`: a header `step,<link_id>_<event>,...`
and one row per step with events since the previous flush. A step can appear in several rows
(a late copy arrives after its step was flushed): readers sum them. Rows are appended about once
a second, in the heartbeat's rhythm, so a SIGKILLed process loses roughly what its last heartbeat
also missed; a torn last line is skipped by the reader. Plain CSV: nothing read back can run code.

Torch-free: the local-agent client uses it.
"""

from __future__ import annotations

import os
from pathlib import Path

from hammer.faults.links import LINK_IDS, link_of_pattern

EVENTS = ("sent", "dropped", "duplicated", "delivered", "late", "duplicate", "fallbacks", "defaults")
STEP_LOG_DIR = "linksteps"


def column(link: str, event: str) -> str:
    """`central->local`, `late` -> `central_local_late` (the column name in step logs and episode_links.csv)."""
    if event not in EVENTS:
        raise ValueError(f"unknown link event {event!r}; one of {', '.join(EVENTS)}")
    return f"{LINK_IDS[link]}_{event}"


class StepLog:
    """Counts of link events per global step, appended to this process's CSV by `flush`.

    `directory=None` records nothing (a role started without a run directory to write to)."""

    def __init__(self, directory: Path | None, role: str, columns: list[str], pid: int | None = None) -> None:
        self.columns = list(columns)
        self._index = {c: j for j, c in enumerate(self.columns)}
        self._pending: dict[int, list[int]] = {}
        self.path: Path | None = None
        if directory is not None:
            Path(directory).mkdir(parents=True, exist_ok=True)
            self.path = Path(directory) / f"{role}-{os.getpid() if pid is None else pid}.csv"
            with open(self.path, "w") as f:
                f.write(",".join(["step", *self.columns]) + "\n")

    def add(self, step: int, col: str, n: int = 1) -> None:
        if self.path is None or not n:
            return
        row = self._pending.get(step)
        if row is None:
            row = self._pending[step] = [0] * len(self.columns)
        row[self._index[col]] += n

    def flush(self) -> None:
        """Append the pending rows (one write, so a kill tears at most the last line)."""
        if self.path is None or not self._pending:
            return
        text = "".join(f"{s},{','.join(map(str, row))}\n" for s, row in sorted(self._pending.items()))
        self._pending.clear()
        with open(self.path, "a") as f:
            f.write(text)


class LoggedPublisher:
    """A step-loop publisher that logs, at each message's step: one `sent`, and the `dropped` /
    `duplicated` its session's fault layer decided for it.

    Those two decisions are made synchronously inside `publish` (`protocol.fault_injection.FaultInjector.
    submit`), so the change of the fault counters across the call belongs to this message, as long
    as one thread publishes this role's step-loop messages (true for every role). Only rules whose
    key pattern belongs to `link` count, as in `faults.links.flat_fault_counters`, so the step logs
    add up to the link table. `delayed` is not logged: a reordered message's delay is counted when
    it is released, during another message's publish or on the fault layer's timer thread."""

    def __init__(self, pub, session, log: StepLog, link: str) -> None:
        self.pub, self.log = pub, log
        self.link = link
        faults = getattr(pub, "faults", session.faults)  # an agent pool's agent: its own fault layer
        self._counters = [] if faults is None else [
            faults.counters[i] for i, r in enumerate(faults.spec.rules) if link_of_pattern(r.match) == link]
        self._sent, self._dropped, self._duplicated = (column(link, e) for e in ("sent", "dropped", "duplicated"))

    def publish(self, msg) -> int:
        if not self._counters:
            seq = self.pub.publish(msg)
            self.log.add(msg.step, self._sent)
            return seq
        dropped = sum(c.dropped for c in self._counters)
        duplicated = sum(c.duplicated for c in self._counters)
        seq = self.pub.publish(msg)
        self.log.add(msg.step, self._sent)
        self.log.add(msg.step, self._dropped, sum(c.dropped for c in self._counters) - dropped)
        self.log.add(msg.step, self._duplicated, sum(c.duplicated for c in self._counters) - duplicated)
        return seq

    def close(self) -> None:
        self.pub.close()
