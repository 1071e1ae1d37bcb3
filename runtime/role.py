"""The event loop every distributed role runs: control, heartbeat, step-log flush, idle exit.

Each role process (env host, central agent, local agent, learner, policy server) does the same
housekeeping around its real work: it obeys a stop command addressed to it, says it is alive with
its counters about once a second, flushes its per-step link log in the heartbeat's rhythm (so a
killed process's step log and its last heartbeat agree), and, where asked, exits after a spell
with no input. `Role` owns that housekeeping once; a role subclass says only what it does with
its messages: `poll` waits for the role's main input and hands each message to an `on_*`
handler, `on_idle` runs when nothing came, `counters` is what its heartbeat reports.

What a role refuses is counted by reason (`reject`), next to what its subscriptions rejected as
malformed (`HammerSession.rejection_counts`): both go into every heartbeat and the role's final
counters as `rejected.<reason>`, so a degraded run is visible in the run directory. A stop command
is obeyed only from the launcher (`LAUNCHER`) and from the env host, which ends the run when its
budget is spent (in a secure run the access rules let only the launcher publish control). A role that has made progress once and then makes
none for `stall_warn_s` says so: a WARNING in its log and `stalled: ...` in its heartbeat's detail.

A role that drives the loop itself instead of reacting to input (the env host) does not call
`run`; it calls `stop_requested` and `heartbeat` from its own loop.

The process shell (session, run directory, exit status) stays in `hammer/commands/roles.py`, the
algorithm (acting, learning) in `learning/` and the acting cores; this module is only the loop.
"""

from __future__ import annotations

import collections
import logging
import os
import time
from collections.abc import Callable
from typing import Any

from hammer.faults.links import flat_fault_counters
from hammer.faults.steplog import StepLog
from hammer.protocol.access import LAUNCHER
from hammer.protocol.schemas import Control, Heartbeat, HeartbeatStatus
from hammer.protocol.session import HammerSession, Subscription

STOP_COMMANDS = ("stop",)
STOP_SENDERS = (LAUNCHER, "env")  # the senders (stamped by their sessions) whose stop ends a role
DEFAULT_STALL_WARN_S = 30.0


class Role:
    """One role's event loop. A subclass declares its inputs with `handle` (one main input the loop
    waits on) and `handle_queued` (inputs taken whenever they are there, before each wait), each
    with the `on_*` handler that takes a message; or overrides `poll` for any other kind of wait."""

    heartbeat_every_s = 1.0
    progress_every_s = 30.0  # a progress line in the role's log (its counters): enough to follow, not a flood
    poll_s = 0.2  # how long `poll` may block: the loop's reaction time to control and heartbeats

    def __init__(self, session: HammerSession, name: str, *, step_log: StepLog | None = None,
                 idle_exit_s: float | None = None, report_faults: bool = True,
                 stall_warn_s: float | None = DEFAULT_STALL_WARN_S) -> None:
        self.session, self.keys, self.name = session, session.keys, name
        self.log = logging.getLogger(f"hammer.{name.split('-')[0]}")
        self.step_log = step_log
        self.idle_exit_s = idle_exit_s
        self.report_faults = report_faults
        self.stop_reason: str | None = None
        self._control = session.subscribe(self.keys.ctl("all"), Control)
        self._heartbeat_pub = session.publisher(self.keys.heartbeat(name), reliable=False)
        self._last_heartbeat = 0.0  # the first loop turn says at once that this role is up
        self._last_input = time.monotonic()
        self._main: tuple[Subscription, Callable[[Any], None]] | None = None
        self._queued: list[tuple[Subscription, Callable[[Any], None]]] = []
        self._last_progress_log = time.monotonic()
        t = session.transport
        self.log.info("%s started: %s, pid %d, run %s, %s listen %s connect %s%s", name, type(self).__name__,
                      os.getpid(), session.run_id, t.mode or "peer", t.listen or "-", t.connect or "-",
                      f", zenoh config {t.zenoh_config_file}" if t.zenoh_config_file else "")
        self.rejected: collections.Counter[str] = collections.Counter()  # refused by this role, by reason
        self.stall_warn_s = stall_warn_s
        self.stall_what = "input"  # what a stalled role is waiting for (its heartbeat says)
        self._progress_t: float | None = None  # None until the role's first progress
        self.cpu_at_start: float | None = None  # process CPU seconds when the role started work (run)
        self._stalled = False

    def handle(self, subscription: Subscription, handler: Callable[[Any], None]) -> None:
        """The role's main input: the loop waits up to `poll_s` on it and gives each message to `handler`."""
        self._main = (subscription, handler)

    def handle_queued(self, subscription: Subscription, handler: Callable[[Any], None]) -> None:
        """An input drained into `handler` before each wait on the main input (it never blocks the loop)."""
        self._queued.append((subscription, handler))

    # ----- what a role declares -----------------------------------------------------------------
    def poll(self, timeout: float) -> bool:
        """Wait up to `timeout` s for the role's main input and handle what came; True if anything did."""
        for subscription, handler in self._queued:
            for msg in subscription.drain():
                handler(msg)
        if self._main is None:
            raise NotImplementedError(f"{type(self).__name__}: declare an input with handle() or override poll()")
        subscription, handler = self._main
        msg = subscription.get(timeout=timeout)
        if msg is None:
            return False
        handler(msg)
        return True

    def on_start(self) -> None:
        """The role is declared alive and about to take input (e.g. publish the first weights)."""

    def on_idle(self) -> None:
        """Nothing arrived within `poll_s` (e.g. preload weights, republish)."""

    def on_stop(self) -> None:
        """The loop has ended (stop command or idle exit): final files, summaries."""

    def alive_names(self) -> list[str]:
        """The liveliness tokens this process declares: its name (an agent pool: each agent's)."""
        return [self.name]

    def counters(self) -> dict[str, int | float]:
        """Totals the heartbeat reports (fault-layer counters are added when `report_faults`): each
        >= 0 and never falling while the process lives (the launcher refuses a heartbeat whose
        counters fall, and sums them over a role's processes)."""
        return {}

    def gauges(self) -> dict[str, int | float]:
        """Current values the heartbeat reports that may move either way (policy version, latency)."""
        return {}

    # ----- the shell ----------------------------------------------------------------------------
    def reject(self, reason: str, what: str) -> None:
        """Count a message this role refused (valid on the wire, not acceptable here) and log the first ones."""
        self.rejected[reason] += 1
        n = self.rejected[reason]
        if n <= 10 or n % 1000 == 0:
            self.log.warning("%s rejected #%d (%s): %s", self.name, n, reason, what)

    def rejection_counters(self) -> dict[str, int]:
        """Every rejection of this process by reason: the role's own and its subscriptions'."""
        from hammer.protocol.transport_log import refused_counts

        return {**rejection_counters(self.session.rejection_counts(), self.rejected),
                **{f"refused.{r}": n for r, n in refused_counts().items()}}  # strangers Zenoh turned away

    def fault_report(self) -> dict[str, dict[str, int]]:
        """What the fault layer did to this role's publishes (an agent pool: each agent's own)."""
        return self.session.fault_report()

    def traffic(self) -> dict[str, int]:
        """Messages and bytes this role published (`hammer bench scale`: messages and bytes per step)."""
        return self.session.traffic()

    def final_counters(self) -> dict[str, int | float]:
        """What the process writes at exit (faults.links.write_role_counters): counters, rejections,
        faults, traffic."""
        return {**self.counters(), **self.gauges(), **self.rejection_counters(),
                **flat_fault_counters(self.fault_report()), **self.traffic(), **process_usage(self.cpu_at_start)}

    def progressed(self) -> None:
        """The role did its work once more (acted on a step, learned from a chunk)."""
        self._progress_t = time.monotonic()
        if self._stalled:
            self._stalled = False
            self.log.warning("%s progressing again", self.name)

    def stall_detail(self) -> str:
        """'stalled: ...' once the role made progress and then none for `stall_warn_s` (logged once per stall)."""
        if self._progress_t is None or self.stall_warn_s is None:
            return ""
        idle = time.monotonic() - self._progress_t
        if idle <= self.stall_warn_s:
            return ""
        if not self._stalled:
            self._stalled = True
            self.log.warning("%s STALLED: no progress for %.0f s (waiting for %s)", self.name, idle, self.stall_what)
        return f"stalled: no progress for {idle:.0f} s (waiting for {self.stall_what})"

    def stop_requested(self) -> bool:
        """True once a stop command for everyone or for this role has arrived from the launcher or the
        env host (a command from any other sender is counted, logged with its sender and ignored)."""
        for cmd in self._control.drain():
            if cmd.command not in STOP_COMMANDS or cmd.target not in ("*", self.name):
                continue
            if cmd.sender not in STOP_SENDERS:
                self.reject("control_sender", f"{cmd.command} command from {cmd.sender or 'an unnamed sender'}")
            elif self.stop_reason is None:
                self.stop_reason = f"{cmd.command} command from {cmd.sender}"
        return self.stop_reason is not None

    def heartbeat(self, status: HeartbeatStatus = "running") -> None:
        """Publish the counters if `heartbeat_every_s` has passed since the last heartbeat (status
        `stopped`: at once, the last one)."""
        now = time.monotonic()
        if status != "stopped" and now - self._last_heartbeat <= self.heartbeat_every_s:
            return
        self._last_heartbeat = now
        counters = {**self.counters(), **self.rejection_counters()}
        if self.report_faults:
            counters = {**counters, **flat_fault_counters(self.fault_report())}
        final_heartbeat_publisher(self.session, self.name, self._heartbeat_pub, status).publish(
            Heartbeat(role=self.name, pid=os.getpid(), status=status, counters=dict(list(counters.items())[:64]),
                      gauges=self.gauges(), detail=self.stall_detail()))
        if self.step_log is not None:
            self.step_log.flush()
        if now - self._last_progress_log >= self.progress_every_s:
            self._last_progress_log = now
            self.log.info("%s progress: %s", self.name, _brief({**counters, **self.gauges()}))

    def heartbeat_soon(self) -> None:
        """Make the next loop turn publish a heartbeat (something the launcher waits for changed)."""
        self._last_heartbeat = 0.0

    def run(self) -> None:
        """Declare this role alive (its subscriptions are in place), then handle input until a
        stop command, or `idle_exit_s` without input."""
        self.cpu_at_start = process_cpu_s()
        for name in self.alive_names():
            self.session.declare_alive(name)
        self.log.info("%s alive (pid %d)", self.name, os.getpid())  # a log's tail tells how far a dead role got
        self.on_start()
        self._last_input = time.monotonic()
        while not self.stop_requested():
            self.heartbeat()
            if self.poll(self.poll_s):
                self._last_input = time.monotonic()
                continue
            self.on_idle()
            if self.idle_exit_s is not None and time.monotonic() - self._last_input > self.idle_exit_s:
                self.stop_reason = f"no input for {self.idle_exit_s:g} s"
                break
        if self.step_log is not None:
            self.step_log.flush()
        self.on_stop()
        self.heartbeat("stopped")
        self.log.info("%s stopped: %s", self.name, self.stop_reason)


def final_heartbeat_publisher(session: HammerSession, name: str, periodic, status: str):
    """Where a heartbeat goes: the periodic ones best effort (telemetry), the last one (`stopped`, the
    role's final counters, which a launcher keeps for a role started elsewhere) reliably, so that
    closing the session right after it does not lose it."""
    if status != "stopped":
        return periodic
    return session.publisher(session.keys.heartbeat(name), reliable=True, block=False, express=True)


def rejection_counters(*counts: dict[str, int]) -> dict[str, int]:
    """Refusals by reason, summed over `counts`, as the counters a process reports: `rejected.<reason>`."""
    total: collections.Counter[str] = collections.Counter()
    for c in counts:
        total.update(c)
    return {f"rejected.{r}": int(n) for r, n in sorted(total.items()) if n}


def process_cpu_s() -> float:
    """CPU seconds of this process so far, every thread (Zenoh's included)."""
    import resource

    u = resource.getrusage(resource.RUSAGE_SELF)
    return u.ru_utime + u.ru_stime


def process_usage(cpu_at_start: float | None = None) -> dict[str, float]:
    """This process's CPU seconds, those since its role started work (`cpu_at_start`: imports and
    set-up left out, which dominate a short run), and its peak RSS, for its final counters
    (`hammer bench scale`: CPU and memory per role)."""
    import resource

    cpu = process_cpu_s()
    out = {"cpu_s": round(cpu, 3), "rss_peak_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}
    if cpu_at_start is not None:
        out["cpu_run_s"] = round(cpu - cpu_at_start, 3)
    return out


def _brief(counters: dict[str, int | float]) -> str:
    """Counters for a log line: the non-zero ones, floats rounded."""
    return ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in counters.items() if v) or "-"
