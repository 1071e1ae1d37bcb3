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

A served run steps for hours, so a file is bounded (`step_log_max_mb` of runtime.json, per
process): past half of it the file becomes `<role>-<pid>.prev.csv` (the one before is deleted) and
a fresh one starts. The highest step whose rows were deleted goes to `<role>-<pid>.cut`, so
`faults.episode_links` can leave the link columns of the episodes that began by then empty
rather than count them short.

Torch-free: the local-agent client uses it.
"""

from __future__ import annotations

import os
from pathlib import Path

from hammer.faults.links import LINK_IDS, link_of_pattern

EVENTS = ("sent", "dropped", "duplicated", "delivered", "late", "duplicate", "fallbacks", "defaults")
STEP_LOG_DIR = "linksteps"
DEFAULT_MAX_MB = 64.0  # RuntimeSettings.step_log_max_mb's default


def column(link: str, event: str) -> str:
    """`central->local`, `late` -> `central_local_late` (the column name in step logs and episode_links.csv)."""
    if event not in EVENTS:
        raise ValueError(f"unknown link event {event!r}; one of {', '.join(EVENTS)}")
    return f"{LINK_IDS[link]}_{event}"


class StepLog:
    """Counts of link events per global step, appended to this process's CSV by `flush`.

    `directory=None` records nothing (a role started without a run directory to write to).
    `max_bytes`: the disk it may take (None: the run's `step_log_max_mb`, from the runtime.json next
    to `directory`, so every role that writes one obeys the run's cap without passing it along)."""

    def __init__(self, directory: Path | None, role: str, columns: list[str], pid: int | None = None,
                 max_bytes: int | None = None) -> None:
        self.columns = list(columns)
        self._index = {c: j for j, c in enumerate(self.columns)}
        self._pending: dict[int, list[int]] = {}
        self.path: Path | None = None
        self.max_bytes = max_bytes
        self._size = 0  # bytes in the current file
        self._top = -1  # highest step in the current file
        self._prev_top = -1  # ... in the .prev.csv file (-1: none)
        self.cut = -1  # highest step whose rows were deleted
        if directory is not None:
            Path(directory).mkdir(parents=True, exist_ok=True)
            self.path = Path(directory) / f"{role}-{os.getpid() if pid is None else pid}.csv"
            if self.max_bytes is None:
                self.max_bytes = _run_cap(Path(directory).parent)
            self._start_file()

    def _start_file(self) -> None:
        header = ",".join(["step", *self.columns]) + "\n"
        with open(self.path, "w") as f:
            f.write(header)
        self._size, self._top = len(header), -1

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
        self._top = max(self._top, max(self._pending))
        self._pending.clear()
        with open(self.path, "a") as f:
            f.write(text)
        self._size += len(text)
        if self._size > self.max_bytes / 2:
            self._rotate()

    def _rotate(self) -> None:
        """The current file becomes .prev.csv; the one before it is deleted and its top step recorded."""
        prev = self.path.with_name(self.path.stem + ".prev.csv")
        if self._prev_top >= 0:
            prev.unlink(missing_ok=True)
            self.cut = max(self.cut, self._prev_top)
            tmp = self.path.with_suffix(".cut.tmp")
            tmp.write_text(f"{self.cut}\n")
            tmp.replace(self.path.with_suffix(".cut"))
        self.path.replace(prev)
        self._prev_top = self._top
        self._start_file()


def _run_cap(run_dir: Path) -> int:
    """`step_log_max_mb` of the run's runtime.json in bytes (the default without one)."""
    import json

    try:
        mb = float(json.loads((run_dir / "runtime.json").read_text()).get("step_log_max_mb", DEFAULT_MAX_MB))
    except (OSError, ValueError, TypeError):
        mb = DEFAULT_MAX_MB
    return max(1, int(mb * 2**20))


def read_cut(directory: Path) -> int:
    """The highest step any process of the run deleted step-log rows of (-1: none)."""
    top = -1
    for p in Path(directory).glob("*.cut"):
        try:
            top = max(top, int(p.read_text().split()[0]))
        except (OSError, ValueError, IndexError):
            continue
    return top


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
