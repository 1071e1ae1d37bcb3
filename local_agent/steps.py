"""The numpy-free core of a local agent: what it knows of its task, its counters, its step
bookkeeping (`StepCore`) and its process (`ClientCore`).

Why apart from client.py: the edge agent of a discrete K=1 team runs without numpy
(`lite.LiteLocalAgentClient`, serve/edge_entry.py: numpy is a large share of its memory budget,
docs/deploy.md "Footprint"), and it must
handle steps, messages, fallbacks, step windows and weights exactly as the numpy agent does. So
both share this code; each brings only its arrays and its acting (`client.AgentSteps` numpy's,
`lite.LiteSteps` plain Python's). Messages are matched to steps as client.py says.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hammer.faults.steplog import LoggedPublisher, StepLog, column
from hammer.protocol.dims import Dims
from hammer.protocol.schemas import Action, CentralMsg, LocalObs
from hammer.protocol.session import HammerSession
from hammer.runtime.bounds import StepWindow
from hammer.runtime.role import Role
from hammer.runtime.weights import WeightsIntake

if TYPE_CHECKING:  # annotations only: the edge agent builds its AgentSpec without the (pydantic) RunConfig
    from hammer.envs.base import EnvSpec
    from hammer.learning.config import RunConfig
    from hammer.runtime.settings import RuntimeSettings

OBS_EVENTS = {e: column("env->local", e) for e in ("delivered", "late")}
MSG_EVENTS = {e: column("central->local", e) for e in ("delivered", "late", "duplicate", "fallbacks")}


@dataclass
class AgentSpec:
    """What a local agent must know of its task (from the run directory's env_spec.json)."""

    agent: int
    n_agents: int
    obs_dim: int  # the observation this agent receives (joint obs for variant centralized)
    msg_dim: int  # 0 when the variant sends no messages
    discrete: bool
    action_dim: int
    seed: int
    onehot: bool = False  # variant centralized: append one-hot(agent) to the joint observation

    @classmethod
    def from_config(cls, cfg: RunConfig, env: EnvSpec, agent: int) -> AgentSpec:
        w = cfg.wiring
        return cls(agent=agent, n_agents=cfg.n_agents, obs_dim=w.local_obs_dim(env.obs_dim), msg_dim=w.msg_dim,
                   discrete=env.discrete, action_dim=env.action_dim, seed=cfg.seed, onehot=w.joint_obs)


@dataclass
class LocalCounters:
    steps: int = 0
    msgs_on_time: int = 0
    msgs_late: int = 0  # arrived after the step was acted on a fallback
    msgs_duplicate: int = 0
    fallback_copies: int = 0  # env copies acted on a fallback message
    obs_stale: int = 0  # observation for a step already acted on (duplicate or reordered)
    weights_loaded: int = 0
    weights_wait_timeouts: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class StepCore:
    """What one local agent does with its inputs, whoever drives it: its own process
    (`LocalAgentClient`) or an agent pool serving many agents from one event loop
    (`local_agent.pool.LocalAgentPool`). Everything here is the agent's own: its counters, its
    fallback state, the messages it holds, its step window, its step log and its action publisher.

    A subclass provides `agent`, `fallback`, `settle_message`, `step_log`, `action_pub`, `reject` and
    `progressed` (`init_core` sets the rest). numpy-free: the numpy agent (`client.AgentSteps`) and
    the lite edge agent (`lite.LiteSteps`, no numpy) share it."""

    def init_core(self, spec: AgentSpec, step_window: int, start_step: int | None = None) -> None:
        """What every driver of an agent sets up, whatever its arrays are (`init_steps` of a subclass adds
        its acting core `agent` and its message `fallback`)."""
        self.spec = spec
        self.counts = LocalCounters()
        self.pending: dict[int, CentralMsg] = {}  # messages for steps not acted on yet
        self.seen: set[int] = set()  # steps whose message arrived (recent ones): a second copy is a duplicate
        self.last_step = -1
        # start_step: where the run is known to be (runtime.bounds.known_step), so a forged first step is refused
        self.window = StepWindow(step_window, start=start_step)
        self.msg_window = StepWindow(step_window, resync_s=None, start=start_step)  # messages follow the observations

    def obs_refused(self, obs: LocalObs) -> bool:
        """An observation for a step already acted on (counted stale) or beyond the step window
        (rejected): not acted on."""
        if obs.step <= self.last_step and self.window.stale(obs.step, self.last_step):
            self.counts.obs_stale += 1
            self.step_log.add(obs.step, OBS_EVENTS["delivered"])
            self.step_log.add(obs.step, OBS_EVENTS["late"])
            return True
        if obs.step <= self.last_step:  # the real stream is below an anchor it never followed
            self.reject("step_resync", f"observations of steps up to {obs.step} came steadily below {self.last_step}: "
                                       "following them")
        if self.window.ahead(obs.step, self.last_step):
            self.reject("step_ahead", f"observation for step {obs.step} while at {self.last_step}")
            return True
        return False

    def publish_action(self, obs: LocalObs, action: Any, msg: Any, fallback_mask: Any,
                       pub: LoggedPublisher | None = None) -> None:
        """Send this step's action (with the message it used) and count the step; `pub`: another
        publisher of the same key (a pool's non-express one, inside a burst)."""
        (pub or self.action_pub).publish(Action(step=obs.step, env_idx=obs.env_idx, agent=self.spec.agent, action=action,
                                       policy_version=max(self.agent.version, 0), fallback=fallback_mask,
                                       msg=msg if obs.echo else None))  # the env host records it
        self.last_step = obs.step
        self.counts.steps += 1
        self.step_log.add(obs.step, OBS_EVENTS["delivered"])
        self.progressed()

    def on_message(self, m: CentralMsg) -> None:
        """Keep a message for a step to come; count a duplicate or a late one; reject one beyond the window."""
        if self.msg_window.ahead(m.step, self.last_step):
            self.reject("step_ahead", f"message for step {m.step} while at {self.last_step}")
            return
        if m.step in self.seen:
            self.counts.msgs_duplicate += 1
            self.log_msg(m.step, "duplicate")
        elif m.step <= self.last_step:
            self.counts.msgs_late += 1
            self.log_msg(m.step, "late")
        else:
            self.pending[m.step] = m
            self.seen.add(m.step)
            if len(self.seen) > 256:
                self.seen.difference_update([s for s in self.seen if s < self.last_step - 64])

    def log_msg(self, step: int, event: str | None) -> None:
        """A message for `step` is counted (on time: event None; late; duplicate): it was delivered."""
        self.step_log.add(step, MSG_EVENTS["delivered"])
        if event is not None:
            self.step_log.add(step, MSG_EVENTS[event])


def step_log_columns() -> list[str]:
    """The link events a local agent logs per step (faults.steplog)."""
    return [*OBS_EVENTS.values(), *MSG_EVENTS.values(),
            *(column("local->env", e) for e in ("sent", "dropped", "duplicated"))]


class ClientCore(StepCore, Role):
    """One local agent's process: observation (and message) in, action out (numpy-free: a subclass
    brings the arrays: `client.LocalAgentClient` numpy's, `lite.LiteLocalAgentClient` plain Python's).

    step_log_dir: where this process logs its link events per step (faults.steplog; None: nowhere)."""

    def __init__(self, session: HammerSession, spec: AgentSpec, num_envs: int, settings: RuntimeSettings, *,
                 idle_exit_s: float | None = None, step_log_dir: Path | None = None, start_step: int | None = None,
                 start_version: int | None = None) -> None:
        name = f"local-{spec.agent}"
        step_log = StepLog(step_log_dir, name, step_log_columns())
        super().__init__(session, name, step_log=step_log, idle_exit_s=idle_exit_s,
                         stall_warn_s=settings.stall_warn_s)
        self.init_steps(spec, num_envs, settings.fallback, settings.fallback_k, settings.step_window, start_step)
        self.msg_deadline_s = settings.msg_deadline_ms / 1e3
        self.stall_what = "observations"
        dims = Dims(num_envs=num_envs, n_agents=spec.n_agents, obs_dim=spec.obs_dim,
                    msg_dim=spec.msg_dim or None, action_dim=spec.action_dim, discrete=spec.discrete)
        self.observations = session.subscribe(self.keys.obs(spec.agent), LocalObs, dims)
        self.handle(self.observations, self.on_obs)  # messages are taken in on_obs, up to their deadline
        self.messages = session.subscribe(self.keys.msg(spec.agent), CentralMsg, dims) if spec.msg_dim else None
        self.weights = WeightsIntake(session, "local", self.agent.load_weights, settings.weights_timeout_s,
                                     reject=self.reject, max_policy_lag=settings.max_policy_lag,
                                     start_version=start_version,
                                     on_held=lambda version: self.heartbeat_soon())
        self.action_pub = LoggedPublisher(session.publisher(self.keys.act(spec.agent), express=True), session,
                                          step_log, "local->env")

    def counters(self) -> dict[str, int]:
        return {**self.counts.as_dict(), **self.weights.counters()}

    def gauges(self) -> dict[str, int]:
        """policy_held: the newest version this agent holds (the env host names a push only once held)."""
        return {"policy_version": self.agent.version, "policy_held": self.weights.known}

    # ----- a step, in the order it flows ---------------------------------------------------------
    def on_obs(self, obs: LocalObs) -> None:
        """Act on one vector step's observation with the version it names and its message (or a fallback)."""
        if self.obs_refused(obs):
            return
        if self.weights.ahead(obs.policy_version):
            self.reject("version_ahead", f"observation names policy version {obs.policy_version}")
            return
        self.weights.take(obs.policy_version)
        self.sync_weight_counters()
        if self.agent.policy is None:  # no version came in time and none is held: no action, the env
            return  # host's default stands in (counted there and as weights_wait_timeouts here)
        if self.messages is not None:
            msg, fallback_mask = self.message_for(obs)
        else:
            msg, fallback_mask = None, self.no_fallbacks(obs.k)
        self.weights.pump()  # a push's next chunk: asked now, it crosses the link while the link has no step traffic
        self.act_on(obs, msg, fallback_mask)

    def message_for(self, obs: LocalObs) -> tuple[Any, Any]:
        """The message of each env copy of this step (waiting for it up to the deadline), and the
        mask of copies that act on a fallback instead."""
        for m in self.messages.drain():
            self.on_message(m)
        deadline = time.monotonic() + self.msg_deadline_s
        while obs.step not in self.pending:
            m = self.messages.get(timeout=max(0.0, deadline - time.monotonic()))
            if m is None:
                break
            self.on_message(m)
        return self.settle_message(obs)

    def on_idle(self) -> None:
        """No policy yet: load the first one now, and say so at once (the env host may wait for it).
        A push being pulled: its next chunk, on the slow idle timer."""
        if self.agent.version < 0 and self.weights.preload_oldest():
            self.sync_weight_counters()
            self.heartbeat_soon()
        self.weights.pump(idle=True)

    def sync_weight_counters(self) -> None:
        self.counts.weights_loaded, self.counts.weights_wait_timeouts = self.weights.loaded, self.weights.wait_timeouts
