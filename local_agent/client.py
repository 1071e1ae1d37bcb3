"""The lightweight local-agent client: one per local agent, no torch.

Per vector step it receives its observation (LocalObs) and, for message-using variants, its
message (CentralMsg); it waits for the message up to a deadline, falls back (zeros / last /
last-for-k-steps) when it is late, runs the shared policy in numpy from weights the learner
published, samples from its own random stream (the randomness contract of `learning.sampling`)
and publishes its action. It never talks to other local agents.

Messages are matched to steps by their `step` header: a message for a step already acted on is
counted late and discarded, a second copy of a message is counted as a duplicate, a message for a
future step is kept until that step comes. So nothing is applied to the wrong step or twice.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from safetensors.numpy import load as load_safetensors

from envs.base import EnvSpec
from faults.links import flat_fault_counters
from faults.steplog import LoggedPublisher, StepLog, column
from learning.config import RunConfig
from learning.numpy_policy import NumpyLocalPolicy, softmax
from learning.policy_versions import WeightsInbox
from learning.sampling import LOCAL_STREAM, categorical_inverse_cdf, stream
from protocol.schemas import Action, CentralMsg, Control, Dims, Heartbeat, LocalObs, Weights
from protocol.session import HammerSession

log = logging.getLogger("hammer.local")


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


class MessageFallback:
    """The message a local agent acts on when its central message is missing.

    zeros: a zero vector. last: the last message received for that env copy. last_k: the last one
    for at most k consecutive steps, then zeros (a stale message stops being trusted).
    """

    def __init__(self, mode: str, k_max: int, num_envs: int, msg_dim: int) -> None:
        self.mode, self.k_max = mode, k_max
        self.last = np.zeros((num_envs, msg_dim), np.float32)
        self.age = np.zeros(num_envs, np.int64)

    def received(self, env_idx: np.ndarray, msg: np.ndarray) -> None:
        self.last[env_idx] = msg
        self.age[env_idx] = 0

    def fill(self, env_idx: np.ndarray) -> np.ndarray:
        self.age[env_idx] += 1
        if self.mode == "zeros":
            return np.zeros((len(env_idx), self.last.shape[1]), np.float32)
        out = self.last[env_idx].copy()
        if self.mode == "last_k":
            out[self.age[env_idx] > self.k_max] = 0.0
        return out


@dataclass
class LocalAgent:
    """The acting core, independent of the transport (so it can be tested and reused on a device)."""

    spec: AgentSpec
    policy: NumpyLocalPolicy | None = None
    version: int = -1
    rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self.rng = stream(self.spec.seed, LOCAL_STREAM, self.spec.agent)
        self._onehot = np.eye(self.spec.n_agents, dtype=np.float32)[self.spec.agent]

    def load_weights(self, blob: bytes, version: int) -> None:
        self.policy = NumpyLocalPolicy(load_safetensors(blob))
        self.version = version

    def policy_input(self, obs: np.ndarray, msg: np.ndarray | None) -> np.ndarray:
        parts = [obs]
        if self.spec.onehot:
            parts.append(np.broadcast_to(self._onehot, (obs.shape[0], self.spec.n_agents)))
        if self.spec.msg_dim:
            parts.append(msg)
        return np.concatenate(parts, axis=1).astype(np.float32, copy=False) if len(parts) > 1 else obs

    def act(self, obs: np.ndarray, msg: np.ndarray | None) -> np.ndarray:
        """Sample one action per env copy; draws exactly what the in-process trainer draws."""
        if self.policy is None:
            raise RuntimeError("no policy weights loaded yet")
        out = self.policy.actor_out(self.policy_input(obs, msg))
        k = obs.shape[0]
        if self.spec.discrete:
            return categorical_inverse_cdf(softmax(out), self.rng.random(k))
        z = self.rng.standard_normal((k, self.spec.action_dim))
        return (out + self.policy.std * z).astype(np.float32)


def load_policy_file(path: str) -> tuple[NumpyLocalPolicy, dict]:
    """An exported policy (safetensors) for deployment without a learner; returns (policy, metadata)."""
    from safetensors import safe_open  # numpy framework: no torch

    with safe_open(path, framework="numpy") as f:
        meta = dict(f.metadata() or {})
        params = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open is not a dict
    return NumpyLocalPolicy(params), meta


def run_local_agent(session: HammerSession, spec: AgentSpec, num_envs: int, fallback: str, fallback_k: int,
                    msg_deadline_s: float, weights_timeout_s: float, idle_exit_s: float | None = None,
                    step_log_dir: Path | None = None) -> LocalCounters:
    """Serve one local agent until a stop command (or `idle_exit_s` without observations).
    step_log_dir: where this process logs its link events per step (faults.steplog; None: nowhere)."""
    keys, me = session.keys, spec.agent
    dims = Dims(num_envs=num_envs, n_agents=spec.n_agents, obs_dim=spec.obs_dim,
                msg_dim=spec.msg_dim or None, action_dim=spec.action_dim, discrete=spec.discrete)
    obs_sub = session.subscribe(keys.obs(me), LocalObs, dims)
    msg_sub = session.subscribe(keys.msg(me), CentralMsg, dims) if spec.msg_dim else None
    w_sub = session.subscribe(keys.weights("local"), Weights)
    ctl_sub = session.subscribe(keys.ctl("all"), Control)
    ev = {(link, e): column(link, e) for link, events in (
        ("env->local", ("delivered", "late")), ("central->local", ("delivered", "late", "duplicate", "fallbacks")))
        for e in events}
    slog = StepLog(step_log_dir, f"local-{me}", [*ev.values(), *(column("local->env", e) for e in
                                                                  ("sent", "dropped", "duplicated"))])
    act_pub = LoggedPublisher(session.publisher(keys.act(me), express=True), session, slog, "local->env")
    hb_pub = session.publisher(keys.heartbeat(f"local-{me}"), reliable=False)
    session.declare_alive(f"local-{me}")

    agent = LocalAgent(spec)
    c = LocalCounters()
    fb = MessageFallback(fallback, fallback_k, num_envs, spec.msg_dim)
    pending: dict[int, CentralMsg] = {}  # messages for steps not acted on yet
    last_step = -1
    last_hb = 0.0
    last_obs_t = time.monotonic()

    inbox = WeightsInbox(agent.load_weights)

    def take_weights(block_until: int | None) -> None:
        """Load the policy version the step asks for (never a newer one: see WeightsInbox)."""
        deadline = time.monotonic() + weights_timeout_s
        while True:
            timeout = 0.0 if block_until is None or agent.version >= block_until else deadline - time.monotonic()
            w = w_sub.get(timeout=max(timeout, 0.0))
            if w is not None:
                inbox.offer(w.version, w.blob)
                if inbox.select(block_until):
                    c.weights_loaded += 1
                continue
            if block_until is not None and agent.version < block_until and time.monotonic() < deadline:
                continue
            if block_until is not None and agent.version < block_until:
                c.weights_wait_timeouts += 1
                log.warning("policy version %d not received in %.0fs; acting with %d",
                            block_until, weights_timeout_s, agent.version)
            return

    def preload_first_weights() -> bool:
        """While idle with no policy: load the oldest version held, so the first step is not slowed by
        loading weights (a step never asks for a version older than the learner's first broadcast)."""
        for w in w_sub.drain():
            inbox.offer(w.version, w.blob)
        if inbox.held and inbox.select(min(inbox.held)):
            c.weights_loaded += 1
            return True
        return False

    seen: set[int] = set()  # steps whose message arrived (recent ones): a second copy is a duplicate

    def log_msg(step: int, event: str | None) -> None:
        """A message for `step` is counted (on time: event None; late; duplicate): it was delivered."""
        slog.add(step, ev["central->local", "delivered"])
        if event is not None:
            slog.add(step, ev["central->local", event])

    def absorb(m: CentralMsg) -> None:
        if m.step in seen:
            c.msgs_duplicate += 1
            log_msg(m.step, "duplicate")
        elif m.step <= last_step:
            c.msgs_late += 1
            log_msg(m.step, "late")
        else:
            pending[m.step] = m
            seen.add(m.step)
            if len(seen) > 256:
                seen.difference_update([s for s in seen if s < last_step - 64])

    while True:
        for cmd in ctl_sub.drain():
            if cmd.command in ("stop", "shutdown") and cmd.target in ("*", f"local-{me}"):
                slog.flush()
                return c
        now = time.monotonic()
        if now - last_hb > 1.0:
            hb_pub.publish(Heartbeat(role=f"local-{me}", pid=os.getpid(), status="running",
                                     counters={**c.as_dict(), **flat_fault_counters(session.fault_report()),
                                               "policy_version": agent.version}))
            slog.flush()  # with the heartbeat: a killed agent's step log and last counters agree
            last_hb = now
        o = obs_sub.get(timeout=0.2)
        if o is None:
            if agent.version < 0 and preload_first_weights():
                last_hb = 0.0  # say at once that this agent holds a policy (the env host may wait for it)
            if idle_exit_s is not None and time.monotonic() - last_obs_t > idle_exit_s:
                slog.flush()
                return c
            continue
        last_obs_t = time.monotonic()
        if o.step <= last_step:
            c.obs_stale += 1
            slog.add(o.step, ev["env->local", "delivered"])
            slog.add(o.step, ev["env->local", "late"])
            continue
        take_weights(o.policy_version)
        msg = None
        if msg_sub is not None:
            for m in msg_sub.drain():
                absorb(m)
            deadline = time.monotonic() + msg_deadline_s
            while o.step not in pending:
                m = msg_sub.get(timeout=max(0.0, deadline - time.monotonic()))
                if m is None:
                    break
                absorb(m)
            m = pending.pop(o.step, None)
            for s in [s for s in pending if s < o.step]:  # older than this step: never usable
                del pending[s]
                c.msgs_late += 1
                log_msg(s, "late")
            fallback_mask = np.ones(o.k, dtype=bool)
            msg = np.zeros((o.k, spec.msg_dim), np.float32)
            if m is not None:
                if np.array_equal(m.env_idx, o.env_idx):
                    have = np.ones(o.k, dtype=bool)
                    msg[:] = m.msg
                else:  # a message may carry a different subset of copies: match by env index
                    pos = {int(e): j for j, e in enumerate(m.env_idx)}
                    rows = np.array([pos.get(int(e), -1) for e in o.env_idx])
                    have = rows >= 0
                    msg[have] = m.msg[rows[have]]
                fallback_mask = ~have
                fb.received(o.env_idx[have], msg[have])
                c.msgs_on_time += 1
                log_msg(o.step, None)
            if fallback_mask.any():
                msg[fallback_mask] = fb.fill(o.env_idx[fallback_mask])
                c.fallback_copies += int(fallback_mask.sum())
                slog.add(o.step, ev["central->local", "fallbacks"], int(fallback_mask.sum()))
        else:
            fallback_mask = np.zeros(o.k, dtype=bool)
        action = agent.act(o.obs, msg)
        act_pub.publish(Action(step=o.step, env_idx=o.env_idx, agent=me, action=action,
                               policy_version=max(agent.version, 0), fallback=fallback_mask,
                               msg=msg if msg is not None else None))
        last_step = o.step
        c.steps += 1
        slog.add(o.step, ev["env->local", "delivered"])
