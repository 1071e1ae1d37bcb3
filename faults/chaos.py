"""Process-level chaos on a schedule: kill, pause/resume, restart a role at a step or a time.

    kill:central@step=2000            SIGKILL; the launcher does NOT restart it (it stays dead)
    kill:central@step=2000,for=5s     ... and it is started again 5 s later
    restart:central@step=3000         start it again (SIGKILL first if it is still running)
    pause:local-1@t=10s,for=3s        SIGSTOP at 10 s, SIGCONT 3 s later
    resume:local-1@t=20s              SIGCONT

`step=N` is the env host's vector step (as its heartbeat reports it, about twice a second, so an
event fires within ~0.5 s of that step); `t=Ns` counts from the moment every role was alive.
A role killed by chaos is "held": the launcher's automatic restart of dead agents leaves it alone
until a `restart` (or the `for=` duration) brings it back, so an experiment sees a real outage.

Agent pools (`agents_per_process` > 1): chaos acts on processes, so an event naming `local-3`
acts on the pool process serving it (e.g. `locals-0-6`): killing or pausing it takes down every
agent of that pool, as a crash of that process would. The chaos log says which process it hit.
Name the pool itself (`kill:locals-0-6@...`) to say so explicitly; `agents_per_process=1` keeps
one process per agent when an experiment needs a single agent's outage.
"""

from __future__ import annotations

import re
import signal
import time
from dataclasses import dataclass, field, replace

from hammer.protocol.access import LEARNER, POLICY

ACTIONS = ("kill", "pause", "resume", "restart")
_EVENT_RE = re.compile(r"^(?P<action>[a-z]+):(?P<role>[A-Za-z0-9_\-]+)@(?P<when>[a-z]+)=(?P<at>[0-9.]+)s?"
                       r"(?:,for=(?P<for>[0-9.]+)s?)?$")


class ChaosSpecError(ValueError):
    """A chaos event that cannot be parsed; the message shows the expected form."""


@dataclass(frozen=True)
class ChaosEvent:
    action: str
    role: str
    at_step: int | None = None
    at_t: float | None = None
    duration_s: float | None = None

    def describe(self) -> str:
        if self.at_step is None and self.at_t is None:
            return f"{self.action} {self.role}"
        when = f"step {self.at_step}" if self.at_step is not None else f"t={self.at_t:g}s"
        dur = f" for {self.duration_s:g}s" if self.duration_s is not None else ""
        return f"{self.action} {self.role} at {when}{dur}"


def parse_chaos(text: str) -> ChaosEvent:
    """`kill:central@step=2000` / `pause:local-1@t=10s,for=3s` -> ChaosEvent."""
    m = _EVENT_RE.match(text.strip())
    if not m:
        raise ChaosSpecError(f"--chaos {text!r}: expected ACTION:ROLE@step=N or ACTION:ROLE@t=SECONDS[,for=SECONDS], "
                             "e.g. 'kill:central@step=2000' or 'pause:local-1@t=10s,for=3s'")
    action, role, when = m["action"], m["role"], m["when"]
    if action not in ACTIONS:
        raise ChaosSpecError(f"--chaos {text!r}: action {action!r} unknown; fix: use one of {', '.join(ACTIONS)}")
    if when not in ("step", "t"):
        raise ChaosSpecError(f"--chaos {text!r}: {when}= unknown; fix: use step=N or t=SECONDS")
    if m["for"] is not None and action not in ("kill", "pause"):
        raise ChaosSpecError(f"--chaos {text!r}: for= only applies to kill and pause")
    if role in ("env", LEARNER, POLICY) and action != "pause":
        raise ChaosSpecError(f"--chaos {text!r}: only central and local-i can be killed or restarted "
                             "(the env host, the learner and the policy server hold the run's state); pause them instead")
    return ChaosEvent(action, role, at_step=int(float(m["at"])) if when == "step" else None,
                      at_t=float(m["at"]) if when == "t" else None,
                      duration_s=float(m["for"]) if m["for"] is not None else None)


@dataclass
class ChaosScheduler:
    """The launcher's `chaos(sup, board)` hook: fires due events, records what it did in board.chaos_log."""

    events: list[ChaosEvent]
    _t0: float | None = None
    _done: set[int] = field(default_factory=set)
    _followups: list[tuple[float, ChaosEvent]] = field(default_factory=list)

    @classmethod
    def from_strings(cls, items: list[str]) -> ChaosScheduler:
        return cls([parse_chaos(x) for x in items])

    def bind_pools(self, specs) -> None:
        """Events naming an agent served by a pool act on that pool's process (module docstring)."""
        owner = {m: s.name for s in specs for m in getattr(s, "members", ())}
        self.events = [replace(ev, role=owner.get(ev.role, ev.role)) for ev in self.events]

    def validate_roles(self, names: set[str]) -> None:
        for ev in self.events:
            if ev.role not in names:
                raise ChaosSpecError(f"--chaos {ev.describe()}: no role {ev.role!r} in this run; "
                                     f"roles: {', '.join(sorted(names))}")

    def __call__(self, sup, board) -> None:
        now = time.monotonic()
        if self._t0 is None:
            self._t0 = now
        env = board.heartbeats.get("env")
        step = int(env.counters.get("step", 0)) if env is not None else 0
        for i, ev in enumerate(self.events):
            if i in self._done:
                continue
            due = (ev.at_step is not None and step >= ev.at_step) or (ev.at_t is not None and now - self._t0 >= ev.at_t)
            if due:
                self._done.add(i)
                self._fire(sup, board, ev, step, now)
                if ev.duration_s is not None:
                    back = ChaosEvent("restart" if ev.action == "kill" else "resume", ev.role)  # "after for="
                    self._followups.append((now + ev.duration_s, back))
        for item in [f for f in self._followups if f[0] <= now]:
            self._followups.remove(item)
            self._fire(sup, board, item[1], step, now)

    def _fire(self, sup, board, ev: ChaosEvent, step: int, now: float) -> None:
        name = ev.role
        if ev.action == "kill":
            board.held.add(name)
            sup.signal(name, signal.SIGKILL)
        elif ev.action == "pause":
            sup.signal(name, signal.SIGSTOP)
        elif ev.action == "resume":
            sup.signal(name, signal.SIGCONT)
        elif ev.action == "restart":
            board.held.add(name)  # the launcher must not restart it as well
            rp = sup.roles.get(name)
            if rp is not None and rp.proc is not None:
                rp.proc.send_signal(signal.SIGCONT)
                rp.proc.kill()
                rp.proc.wait(5.0)
                rp.exit_codes.append(rp.proc.returncode)
                rp.proc = None
            sup.start(rp.spec if rp is not None else None)
            board.held.discard(name)
        board.chaos_log.append({"t": round(now - (self._t0 or now), 3), "step": step, "event": ev.describe()})
