"""The lightweight local-agent client: one per local agent, no torch.

Per vector step it receives its observation (LocalObs) and, for message-using variants, its
message (CentralMsg); it waits for the message up to a deadline, falls back (zeros / last /
last-for-k-steps) when it is late, runs the shared policy in numpy from weights the learner
published, samples from its own random stream (the randomness contract of `learning.sampling`)
and publishes its action. It never talks to other local agents.

`LocalAgentClient` (its process, `steps.ClientCore`) reads top to bottom as what it does with each observation (`on_obs`): load
the policy version it names, wait for its message (`on_message` sorts each one that arrives)
or fall back, act, publish the action. `LocalAgent` is the transport-free acting core.

Messages are matched to steps by their `step` header: a message for a step already acted on is
counted late and discarded, a second copy of a message is counted as a duplicate, a message for a
future step is kept until that step comes. So nothing is applied to the wrong step or twice.
An observation or message for a step beyond the step window (runtime.bounds) is rejected and
counted, never adopted: one forged step number cannot make every real step look stale.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from hammer.learning.numpy_policy import NumpyLocalPolicy, params_from_blob
from hammer.learning.sampling import LOCAL_STREAM, categorical_draw, stream
from hammer.local_agent.steps import (  # noqa: F401 - re-exported: the names every driver of an agent imports from here
    MSG_EVENTS,
    OBS_EVENTS,
    AgentSpec,
    ClientCore,
    LocalCounters,
    StepCore,
    step_log_columns,
)
from hammer.protocol.schemas import CentralMsg, LocalObs


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
        self.policy = NumpyLocalPolicy(params_from_blob(blob))
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
        return self.sample(self.policy.actor_out(self.policy_input(obs, msg)))

    def sample(self, out: np.ndarray) -> np.ndarray:
        """Actions from the policy's output (logits or Gaussian means, one row per env copy), drawn
        from this agent's own stream: the part of `act` an agent pool runs per agent after one
        stacked forward for all its agents."""
        k = out.shape[0]
        if self.spec.discrete:
            return categorical_draw(out, self.rng.random(k))[0]
        z = self.rng.standard_normal((k, self.spec.action_dim))
        return (out + self.policy.std * z).astype(np.float32)


class AgentSteps(StepCore):
    """What one local agent does with its inputs, whoever drives it: its own process
    (`LocalAgentClient`) or an agent pool serving many agents from one event loop
    (`local_agent.pool.LocalAgentPool`). Everything here is the agent's own: its counters, its
    fallback state, the messages it holds, its step window, its step log and its action publisher
    (`steps.StepCore`); here its numpy acting core and message fallback.

    A subclass provides `step_log`, `action_pub`, `reject` and `progressed`."""

    def init_steps(self, spec: AgentSpec, num_envs: int, fallback: str, fallback_k: int, step_window: int,
                   start_step: int | None = None) -> None:
        self.init_core(spec, step_window, start_step)
        self.agent = LocalAgent(spec)
        self.fallback = MessageFallback(fallback, fallback_k, num_envs, spec.msg_dim)

    def settle_message(self, obs: LocalObs) -> tuple[np.ndarray, np.ndarray]:
        """Once the message of `obs`'s step is here or its deadline passed: the message of each env
        copy, and the mask of copies that act on a fallback instead."""
        received = self.pending.pop(obs.step, None)
        for step in [s for s in self.pending if s < obs.step]:  # older than this step: never usable
            del self.pending[step]
            self.counts.msgs_late += 1
            self.log_msg(step, "late")
        msg = np.zeros((obs.k, self.spec.msg_dim), np.float32)
        have = np.zeros(obs.k, dtype=bool)
        if received is not None:
            have = self.fill_received(msg, received, obs.env_idx)
            self.fallback.received(obs.env_idx[have], msg[have])
            self.counts.msgs_on_time += 1
            self.log_msg(obs.step, None)
        fallback_mask = ~have
        if fallback_mask.any():
            msg[fallback_mask] = self.fallback.fill(obs.env_idx[fallback_mask])
            self.counts.fallback_copies += int(fallback_mask.sum())
            self.step_log.add(obs.step, MSG_EVENTS["fallbacks"], int(fallback_mask.sum()))
        return msg, fallback_mask

    @staticmethod
    def fill_received(msg: np.ndarray, received: CentralMsg, env_idx: np.ndarray) -> np.ndarray:
        """Copy a message's rows into `msg`; returns which env copies it covered (it may carry a
        different subset of copies than the observation: matched by env index)."""
        if np.array_equal(received.env_idx, env_idx):
            msg[:] = received.msg
            return np.ones(len(env_idx), dtype=bool)
        pos = {int(e): j for j, e in enumerate(received.env_idx)}
        rows = np.array([pos.get(int(e), -1) for e in env_idx])
        have = rows >= 0
        msg[have] = received.msg[rows[have]]
        return have


class LocalAgentClient(AgentSteps, ClientCore):
    """One local agent's process: observation (and message) in, action out, in numpy
    (`steps.ClientCore` is the process; `lite.LiteLocalAgentClient` the same without numpy).

    step_log_dir: where this process logs its link events per step (faults.steplog; None: nowhere)."""

    def no_fallbacks(self, k: int) -> np.ndarray:
        return np.zeros(k, dtype=bool)

    def act_on(self, obs: LocalObs, msg: np.ndarray | None, fallback_mask: np.ndarray) -> None:
        self.publish_action(obs, self.agent.act(obs.obs, msg), msg, fallback_mask)
