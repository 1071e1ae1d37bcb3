"""An agent pool: one process serving many local agents, each keeping its own identity on the wire.

Why: on a machine with fewer cores than local agents, one process per agent means 2N+ runnable
processes per vector step competing for the cores; every wake-up costs a context switch and cold
caches (docs/runtime.md, "Performance"). A pool serves agents `--agents 0-19` from one process and
one event loop: one thread waits on one queue (`protocol.session.Inbox`) that every agent's
observation and message subscription feeds, and the agents that are ready act together, with one
stacked numpy forward for all of them (bit-identical to one forward per agent: see `_forward`);
their actions go out as one burst (`protocol.session.BATCH_MIN`: Zenoh may send them in one batch).

What stays each agent's own (so a pool is indistinguishable from N single-agent processes on the
wire and in the run directory):
- its keys: it subscribes to `env/obs/<i>` and `central/msg/<i>` and publishes `agent/act/<i>`;
- its random stream `[seed, 1, i]` (`LocalAgent.rng`), its fallback state, the messages it holds,
  its step windows and counters (`AgentSteps`, shared with `LocalAgentClient`);
- its fault layer: a `FaultInjector` of its own on its publishers, so the seeded fault streams and
  the fault counters are the ones a single-agent process would have;
- its heartbeat (`ctl/hb/local-<i>`), its liveliness token (`alive/local-<i>`), its step log
  (`RUN/linksteps/local-<i>-<pid>.csv`) and its final counters (`RUN/counters/local-<i>-<pid>.json`).

What the agents share: the process (killing the pool kills all its agents: chaos and restarts act
on the pool, docs/runtime.md), the Zenoh session (in a secure run one identity whose grants are
exactly its agents' keys, `protocol.access.grants`), the control subscription and the weights
intake (every local agent runs the same shared policy, so it is loaded once). Rejections made at
the pool level (control from a wrong sender, weights beyond the bound) are reported by its first
agent.
"""

from __future__ import annotations

import collections
import os
import time
from pathlib import Path

import numpy as np
from hammer.faults.links import flat_fault_counters
from hammer.faults.steplog import LoggedPublisher, StepLog
from hammer.learning.numpy_policy import NumpyLocalPolicy, params_from_blob
from hammer.local_agent.client import AgentSpec, AgentSteps, step_log_columns
from hammer.protocol.access import pool_name
from hammer.protocol.dims import Dims
from hammer.protocol.fault_injection import FaultInjector, FaultSpec
from hammer.protocol.ranges import parse_indices
from hammer.protocol.schemas import CentralMsg, Heartbeat, LocalObs
from hammer.protocol.session import HammerSession, Inbox, burst_express, io_counters
from hammer.runtime.role import Role, final_heartbeat_publisher
from hammer.runtime.settings import RuntimeSettings
from hammer.runtime.weights import WeightsIntake


def parse_agents(text: str, n_agents: int | None = None) -> list[int]:
    """`0-19`, `0,2,5-7` -> sorted agent indices; a ValueError names the field and the fix."""
    return parse_indices(text, "--agents", n_agents, "agent")


class PooledAgent(AgentSteps):
    """One agent of a pool: its own subscriptions, publishers, fault layer, counters and step log."""

    def __init__(self, pool: LocalAgentPool, spec: AgentSpec, num_envs: int, fallback: str, fallback_k: int,
                 step_window: int, step_log_dir: Path | None, faults: FaultSpec | None,
                 start_step: int | None = None) -> None:
        self.init_steps(spec, num_envs, fallback, fallback_k, step_window, start_step)
        self.pool, self.name = pool, f"local-{spec.agent}"
        self.rejected: collections.Counter[str] = collections.Counter()
        self.faults = FaultInjector(faults) if faults is not None and faults.enabled else None
        self.step_log = StepLog(step_log_dir, self.name, step_log_columns())
        session, keys = pool.session, pool.keys
        dims = Dims(num_envs=num_envs, n_agents=spec.n_agents, obs_dim=spec.obs_dim,
                    msg_dim=spec.msg_dim or None, action_dim=spec.action_dim, discrete=spec.discrete)
        self.observations = session.subscribe(keys.obs(spec.agent), LocalObs, dims, inbox=pool.inbox)
        self.messages = (session.subscribe(keys.msg(spec.agent), CentralMsg, dims, inbox=pool.inbox)
                         if spec.msg_dim else None)
        act = session.publisher(keys.act(spec.agent), express=True)
        batched = session.publisher(keys.act(spec.agent), express=False)  # inside a burst (BATCH_MIN)
        self.heartbeat_pub = session.publisher(keys.heartbeat(self.name), reliable=False)
        self.publishers = (act, batched, self.heartbeat_pub)
        for p in self.publishers:
            p.faults = self.faults
        self.action_pub = LoggedPublisher(act, session, self.step_log, "local->env")
        self.action_pub_batched = LoggedPublisher(batched, session, self.step_log, "local->env")
        self.waiting: LocalObs | None = None  # the observation to act on once its message is here
        self.deadline = 0.0

    def reject(self, reason: str, what: str) -> None:
        self.rejected[reason] += 1
        n = self.rejected[reason]
        if n <= 10 or n % 1000 == 0:
            self.pool.log.warning("%s rejected #%d (%s): %s", self.name, n, reason, what)

    def progressed(self) -> None:
        self.pool.progressed()

    def ready(self, now: float) -> bool:
        """Its observation is here and so is its message (or it needs none, or the deadline passed)."""
        w = self.waiting
        return w is not None and (self.messages is None or w.step in self.pending or now >= self.deadline)

    def counters(self) -> dict[str, int | float]:
        weights = self.pool.weights
        self.counts.weights_loaded, self.counts.weights_wait_timeouts = weights.loaded, weights.wait_timeouts
        # the shared intake's pull counters: reported once, by the first agent
        return {**self.counts.as_dict(), **(weights.counters() if self is self.pool.members[0] else {})}

    def gauges(self) -> dict[str, int]:
        """policy_held: the newest version the pool holds (the env host names a push only once held)."""
        return {"policy_version": self.agent.version, "policy_held": self.pool.weights.known}

    def rejection_counters(self) -> dict[str, int]:
        """This agent's rejections: its subscriptions' and its own (the first agent: the pool's too)."""
        total: collections.Counter[str] = collections.Counter(self.rejected)
        subs = [s for s in (self.observations, self.messages) if s is not None]
        if self is self.pool.members[0]:
            total.update(self.pool.rejected)
            subs += self.pool.shared_subscriptions()
        for sub in subs:
            total.update(sub.stats.rejected)
            if sub.stats.overflow:
                total["overflow"] += sub.stats.overflow
        return {f"rejected.{r}": int(n) for r, n in sorted(total.items()) if n}

    def fault_counters(self) -> dict[str, int]:
        return flat_fault_counters(self.faults.report()) if self.faults is not None else {}

    def final_counters(self) -> dict[str, int | float]:
        """What a single-agent process would write at exit for this agent (faults.links.write_role_counters)."""
        subs = [s for s in (self.observations, self.messages) if s is not None]
        return {**self.counters(), **self.gauges(), **self.rejection_counters(), **self.fault_counters(),
                **io_counters(list(self.publishers), subs)}


class LocalAgentPool(Role):
    """Many local agents served by one process and one event loop (see the module docstring)."""

    def __init__(self, session: HammerSession, specs: list[AgentSpec], num_envs: int, settings: RuntimeSettings, *,
                 idle_exit_s: float | None = None, step_log_dir: Path | None = None, start_step: int | None = None,
                 start_version: int | None = None) -> None:
        if session.faults is not None:
            raise ValueError("an agent pool's session must not have a fault layer: the settings' faults are "
                             "applied per agent (each agent gets its own injector)")
        super().__init__(session, pool_name([s.agent for s in specs]), idle_exit_s=idle_exit_s,
                         stall_warn_s=settings.stall_warn_s)
        self.msg_deadline_s = settings.msg_deadline_ms / 1e3
        self.stall_what = "observations"
        self.inbox = Inbox()
        self.members = [PooledAgent(self, spec, num_envs, settings.fallback, settings.fallback_k, settings.step_window,
                                    step_log_dir, settings.faults, start_step) for spec in specs]
        self._route = {}
        for m in self.members:
            self._route[m.observations] = (m, self.on_obs)
            if m.messages is not None:
                self._route[m.messages] = (m, self.on_message)
        self.policies: dict[int, NumpyLocalPolicy] = {}  # version -> policy (the last few: a canary and its base)
        self.weights = WeightsIntake(session, "local", self._load_weights, settings.weights_timeout_s,
                                     reject=self.reject, max_policy_lag=settings.max_policy_lag,
                                     start_version=start_version,
                                     on_held=lambda version: self.heartbeat_soon())
        self.forwards = self.stacked_forwards = 0  # forward calls, and those that served several agents at once

    def alive_names(self) -> list[str]:
        return [m.name for m in self.members]

    def shared_subscriptions(self) -> list:
        return [self._control, self.weights._sub]

    def _load_weights(self, blob: bytes, version: int) -> None:
        """One policy object for every agent of the pool (they all run the shared local policy). The
        last few versions stay: during a staged rollout (serve/canary.py) a pool may hold canary
        agents and others, whose steps name two versions, and the intake only ever loads forward."""
        policy = NumpyLocalPolicy(params_from_blob(blob))
        self.policies[version] = policy
        for v in sorted(self.policies)[:-4]:
            del self.policies[v]
        for m in self.members:
            m.agent.policy, m.agent.version = policy, version

    # ----- the loop --------------------------------------------------------------------------------
    def poll(self, timeout: float) -> bool:
        """Wait on every agent's inputs at once (up to the nearest message deadline), take all that
        came, then act for every agent that is ready."""
        waiting = [m.deadline for m in self.members if m.waiting is not None]
        if waiting:
            timeout = min(timeout, max(0.0, min(waiting) - time.monotonic()))
        got = self.inbox.get(timeout=timeout)
        n = 0
        while got is not None:
            member, handler = self._route[got[0]]
            handler(member, got[1])
            n += 1
            got = self.inbox.get(timeout=0)
        return self.act_ready() > 0 or n > 0

    def on_obs(self, member: PooledAgent, obs: LocalObs) -> None:
        """Hold an agent's observation until its message is here (or the deadline passes)."""
        if member.waiting is not None and obs.step > member.waiting.step:
            self.act([member])  # a newer step is here: the held one acts on its fallback now
        if member.obs_refused(obs):
            return
        if self.weights.ahead(obs.policy_version):
            member.reject("version_ahead", f"observation names policy version {obs.policy_version}")
            return
        member.waiting, member.deadline = obs, time.monotonic() + self.msg_deadline_s

    def on_message(self, member: PooledAgent, m: CentralMsg) -> None:
        member.on_message(m)

    def act_ready(self) -> int:
        now = time.monotonic()
        ready = [m for m in self.members if m.ready(now)]
        if ready:
            self.act(ready)
        return len(ready)

    def act(self, members: list[PooledAgent]) -> None:
        """Act for `members` (their observations held): the version each step names, their messages
        or fallbacks, one stacked forward per group of equal shape, each agent's own draws."""
        groups: dict[int, list[PooledAgent]] = {}
        for m in members:  # grouped first: acting a group clears its members' held observations
            groups.setdefault(m.waiting.policy_version, []).append(m)
        for version, group in sorted(groups.items()):
            self.weights.take(version)
            if self.members[0].agent.policy is None:  # none came in time, none held: no action, the env
                for m in group:  # host's default stands in (counted there and as weights_wait_timeouts)
                    m.waiting = None
                continue
            kept = [v for v in self.policies if v <= version]  # an older version's step after a newer load
            if kept and max(kept) != self.members[0].agent.version:
                for m in self.members:
                    m.agent.policy, m.agent.version = self.policies[max(kept)], max(kept)
            inputs = []
            for m in group:
                obs = m.waiting
                msg, mask = m.settle_message(obs) if m.messages is not None else (None, np.zeros(obs.k, dtype=bool))
                inputs.append((m, obs, msg, mask, m.agent.policy_input(obs.obs, msg)))
            self.weights.pump()  # a push's next chunk: asked now, it crosses the link while it has no step traffic
            outs = self._forward([x[4] for x in inputs])
            for j, ((m, obs, msg, mask, _), out) in enumerate(zip(inputs, outs, strict=True)):
                m.waiting = None
                pub = None if burst_express(j, len(inputs)) else m.action_pub_batched
                m.publish_action(obs, m.agent.sample(out), msg, mask, pub)

    def _forward(self, xs: list[np.ndarray]) -> list[np.ndarray]:
        """The shared policy's output for each agent's input. Inputs of equal shape go through one
        stacked (agents, K, d) forward: numpy's matmul runs the same BLAS call on each (K, d) slice
        as a forward per agent would, so the outputs are bit-identical (tests/test_local_pool.py),
        unlike one (agents*K, d) matmul, whose BLAS blocking differs from K rows at a time. A conv
        encoder reshapes its batch, so such a policy runs one forward per agent."""
        policy = self.members[0].agent.policy
        if policy is None:
            raise RuntimeError("no policy weights loaded yet")
        self.forwards += 1
        if len(xs) == 1 or policy.actor_enc is not None or len({x.shape for x in xs}) != 1:
            return [policy.actor_out(x) for x in xs]
        self.stacked_forwards += 1
        return list(policy.actor_out(np.stack(xs)))

    # ----- housekeeping, per agent ------------------------------------------------------------------
    def on_idle(self) -> None:
        """No policy yet: load the first one now, and say so at once (the env host may wait for it)."""
        if self.members[0].agent.version < 0 and self.weights.preload_oldest():
            self.heartbeat_soon()
        self.weights.pump(idle=True)  # a push being pulled: its next chunk, on the slow idle timer

    def counters(self) -> dict[str, int]:
        return {"agents": len(self.members), "forwards": self.forwards, "stacked_forwards": self.stacked_forwards}

    def heartbeat(self, status: str = "running") -> None:
        """One heartbeat per agent, as a single-agent process sends it (the launcher, the env host's
        eval start and the link table read `local-<i>`), and each agent's step log flushed."""
        now = time.monotonic()
        if status != "stopped" and now - self._last_heartbeat <= self.heartbeat_every_s:
            return
        self._last_heartbeat = now
        detail = self.stall_detail()
        for m in self.members:
            counters = {**m.counters(), **m.rejection_counters(), **m.fault_counters()}
            final_heartbeat_publisher(self.session, m.name, m.heartbeat_pub, status).publish(Heartbeat(role=m.name, pid=os.getpid(), status=status,
                                              counters=dict(list(counters.items())[:64]), gauges=m.gauges(),
                                              detail=detail))
            m.step_log.flush()
        if now - self._last_progress_log >= self.progress_every_s:
            self._last_progress_log = now
            steps = [m.counts.steps for m in self.members]
            self.log.info("%s progress: %d agents, steps %d..%d, forwards %d (%d stacked)", self.name,
                          len(self.members), min(steps), max(steps), self.forwards, self.stacked_forwards)

    def on_stop(self) -> None:
        for m in self.members:
            m.step_log.flush()
            if m.faults is not None:
                m.faults.close()
