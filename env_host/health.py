"""Each agent's health in a served run, for a staged rollout's gates: RUN/health.json.

A canary is judged by comparing its agents with the rest over the same window (serve/canary.py),
so the signals must be per agent and cumulative (the judge takes differences between two reads).
The env host is where most of them are measured: it sees every agent's action arrive (or not) at
the deadline, and it always runs beside the run directory (in the hub namespace when the agents
are elsewhere). It also keeps each agent's heartbeat (the same Zenoh messages the launcher reads,
validated on receipt) for what only the agent knows: the messages it rejected, and its process id,
which changes when the agent crashed and was restarted. Written atomically about twice a second.

Per agent: the version its steps named, actions in time, default actions (env copies), fallback
copies (it acted on a fallback message), the summed arrival latency of its actions (ms from the
observations going out), its rejected messages, its restarts (process ids seen - 1) and its
leaves (heartbeat silences over `LEAVE_S`). Team-wide: episodes finished and the sums (and sums of
squares, for a window's standard error) of their paper metric and team return: a cooperative team's reward cannot be split per agent, so the judge can
compare it only over time (the canary window against the window before the push).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
from hammer.protocol.schemas import Heartbeat
from hammer.protocol.session import HammerSession
from hammer.runtime.pushes import HEALTH

WRITE_EVERY_S = 0.5
LEAVE_S = 5.0  # a heartbeat silence this long counts as a leave (agents beat every second)


class AgentHealth:
    """Per-agent counters of a served run, written to RUN/health.json."""

    def __init__(self, session: HammerSession, run_dir: Path, n_agents: int) -> None:
        self.path = Path(run_dir) / HEALTH
        self.n = n_agents
        self.actions = np.zeros(n_agents, np.int64)  # actions in time
        self.defaults = np.zeros(n_agents, np.int64)  # env copies acted with the declared default
        self.fallbacks = np.zeros(n_agents, np.int64)  # env copies acted on a fallback message
        self.latency_ms = np.zeros(n_agents, np.float64)  # summed over `actions`
        self.copies = np.zeros(n_agents, np.int64)  # env copies stepped
        self.episodes, self.metric_sum, self.return_sum = 0, 0.0, 0.0
        self.metric_sq_sum = self.return_sq_sum = 0.0  # for the judge's standard error of a window's mean
        self.rejected: list[dict[int, int]] = [{} for _ in range(n_agents)]  # pid -> its rejected total
        self.leaves = np.zeros(n_agents, np.int64)
        self.last_beat = [0.0] * n_agents
        self.silent = [False] * n_agents
        self.held = np.full(n_agents, -1, np.int64)  # the newest policy version each agent holds (heartbeats)
        self.subs = [session.subscribe(session.keys.heartbeat(f"local-{i}"), Heartbeat) for i in range(n_agents)]
        self.last_write = 0.0

    def step(self, got, arrived_ms: np.ndarray) -> None:
        """One vector step's actions (env_host.actions.StepActions) and each agent's arrival time
        (ms; NaN: not in time)."""
        on_time = ~np.isnan(arrived_ms)
        self.actions += on_time
        self.latency_ms += np.where(on_time, arrived_ms, 0.0)
        self.defaults += got.defaulted.sum(axis=0)
        self.fallbacks += got.fallback.sum(axis=0)
        self.copies += got.defaulted.shape[0]

    def episode(self, paper_metric: float, team_return: float) -> None:
        self.episodes += 1
        self.metric_sum += float(paper_metric)
        self.return_sum += float(team_return)
        self.metric_sq_sum += float(paper_metric) ** 2
        self.return_sq_sum += float(team_return) ** 2

    def poll(self, step: int, versions: list[int], central_version: int) -> None:
        """Take the agents' heartbeats; write the file every WRITE_EVERY_S."""
        now = time.monotonic()
        if now - self.last_write < WRITE_EVERY_S:
            return
        self.last_write = now
        self.beats(now)
        for i in range(self.n):
            if self.last_beat[i] and not self.silent[i] and now - self.last_beat[i] > LEAVE_S:
                self.leaves[i] += 1  # counted once per silence
                self.silent[i] = True
        self.write(step, versions, central_version)

    def beats(self, now: float | None = None) -> None:
        """Take the agents' heartbeats that came: alive, rejections, and the version each holds
        (`held`: its `policy_held` gauge, or for an agent without one the version it loaded)."""
        now = time.monotonic() if now is None else now
        for i, sub in enumerate(self.subs):
            for hb in sub.drain():
                self.last_beat[i], self.silent[i] = now, False
                self.rejected[i][hb.pid] = sum(int(v) for k, v in hb.counters.items() if k.startswith("rejected."))
                g = hb.gauges
                self.held[i] = int(g.get("policy_held", g.get("policy_version", -1)))

    def write(self, step: int, versions: list[int], central_version: int) -> None:
        agents = [{"agent": i, "version": int(versions[i]), "actions": int(self.actions[i]),
                   "copies": int(self.copies[i]), "defaults": int(self.defaults[i]),
                   "fallbacks": int(self.fallbacks[i]), "latency_ms_sum": round(float(self.latency_ms[i]), 3),
                   "rejected": sum(self.rejected[i].values()), "restarts": max(0, len(self.rejected[i]) - 1),
                   "leaves": int(self.leaves[i])} for i in range(self.n)]
        data = {"step": step, "time": time.time(), "central_version": int(central_version),
                "episodes": self.episodes, "metric_sum": self.metric_sum, "return_sum": self.return_sum,
                "metric_sq_sum": self.metric_sq_sum, "return_sq_sum": self.return_sq_sum,
                "agents": agents}
        tmp = self.path.with_name(HEALTH + f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(data))
        os.replace(tmp, self.path)

    def close(self) -> None:
        for sub in self.subs:
            sub.close()
