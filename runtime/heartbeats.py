"""The launcher's ledger of every role's counters: what a heartbeat may change, and what it may not.

The run's verdict (`degraded`, its reasons, the rejections per role) is summed from the counters
each role reports about itself, so those reports must be ones no other peer could have written or
rewritten. The key a heartbeat came on names its role (protocol.binding, and in a secure run only
that role may publish there); this ledger adds what the key cannot say:

- a role the launcher started itself is heard only from the processes it started (their pids): a
  heartbeat of `env` from any other pid is refused (`heartbeat_pid`);
- a role started elsewhere (an external agent, a hand-started role) may come and go, but at most
  `max_processes` processes of it are counted (`heartbeat_processes` beyond that), so one identity
  cannot multiply its own counts by inventing pids;
- counters are totals since a process started: a heartbeat in which one of them falls is refused
  (`counters_fell`) and the process keeps its previous figures; a counter a heartbeat leaves out
  keeps its last value (the schema already refuses negative and non-finite ones).
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable

from hammer.protocol.schemas import Heartbeat

log = logging.getLogger("hammer.launcher")


class HeartbeatLedger:
    def __init__(self, started_pids: Callable[[str], set[int] | None], max_processes: int = 8) -> None:
        """started_pids(role): the pids the launcher started for `role` (None: not started here)."""
        self.started_pids = started_pids
        self.max_processes = max_processes
        self.last: dict[tuple[str, int], dict[str, int | float]] = {}
        self.rejected: collections.Counter[str] = collections.Counter()

    def offer(self, h: Heartbeat) -> bool:
        """Record `h` if it may be believed; False (counted, logged) if it is refused."""
        key = (h.role, h.pid)
        reason = self._refusal(h)
        if reason is not None:
            self.rejected[reason] += 1
            n = self.rejected[reason]
            if n <= 10 or n % 1000 == 0:
                log.warning("heartbeat of %s (pid %d) refused #%d (%s)", h.role, h.pid, n, reason)
            return False
        self.last[key] = {**self.last.get(key, {}), **h.counters}
        return True

    def _refusal(self, h: Heartbeat) -> str | None:
        started = self.started_pids(h.role)
        key = (h.role, h.pid)
        if started is not None:
            if h.pid not in started:
                return "heartbeat_pid"
        elif key not in self.last and sum(r == h.role for r, _ in self.last) >= self.max_processes:
            return "heartbeat_processes"
        prev = self.last.get(key)
        if prev is not None and any(v < prev.get(k, 0) for k, v in h.counters.items()):
            return "counters_fell"
        return None
