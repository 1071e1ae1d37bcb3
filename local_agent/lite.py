"""The local agent without numpy: the edge agent of a discrete MLP team at K=1 (serve/edge_entry.py).

Why: an edge agent has a small budget of resident memory, and numpy with numpy.random takes more
of it than everything else the agent needs (docs/deploy.md "Footprint" has the figures). So where the task allows (discrete actions, an
MLP policy, one env copy: the usual robot) the edge agent runs this instead of
`client.LocalAgentClient`: the same process core (`steps.ClientCore`: step window, message
deadline and matching, fallbacks, weights intake, counters, step log, heartbeat), the same wire
(protocol/schemas.py, its arrays checked in pure Python as `WireArray`s), and acting in plain
Python: the forward of learning/lite_policy.py, the agent's own stream by learning/pcg64.py,
numpy's PCG64 draw for draw, and the contract's draw (learning/categorical.py, the numpy agent's
for the same logits on every machine). An action differs from the numpy agent's only where a
float32 logit differs in its last bits and the uniform falls within that of a class boundary
(measured: docs/deploy.md "Footprint").

It handles any K correctly (lists of rows), but costs a Python loop per copy: the edge entry picks
it only at K=1 (`serve.edge_entry.lite_choice`).
"""

from __future__ import annotations

from typing import Any

from hammer.learning.categorical import draw
from hammer.learning.lite_policy import LiteLocalPolicy
from hammer.learning.pcg64 import LOCAL_STREAM, lite_stream
from hammer.local_agent.steps import MSG_EVENTS, AgentSpec, ClientCore, StepCore
from hammer.protocol.fields import WireArray
from hammer.protocol.schemas import CentralMsg, LocalObs


class LiteMessageFallback:
    """`client.MessageFallback` on lists: zeros, the last message of a copy, or it for k steps."""

    def __init__(self, mode: str, k_max: int, num_envs: int, msg_dim: int) -> None:
        self.mode, self.k_max, self.msg_dim = mode, k_max, msg_dim
        self.last = [[0.0] * msg_dim for _ in range(num_envs)]
        self.age = [0] * num_envs

    def received(self, env_idx: list[int], rows: list[list[float]]) -> None:
        for e, row in zip(env_idx, rows):
            self.last[e] = list(row)
            self.age[e] = 0

    def fill(self, env_idx: list[int]) -> list[list[float]]:
        for e in env_idx:
            self.age[e] += 1
        if self.mode == "zeros":
            return [[0.0] * self.msg_dim for _ in env_idx]
        if self.mode == "last_k":
            return [[0.0] * self.msg_dim if self.age[e] > self.k_max else list(self.last[e]) for e in env_idx]
        return [list(self.last[e]) for e in env_idx]


class LiteLocalAgent:
    """`client.LocalAgent` of a discrete team in plain Python: the same inputs, stream and draws."""

    def __init__(self, spec: AgentSpec) -> None:
        if not spec.discrete:
            raise ValueError("the lite agent acts only for discrete actions")
        self.spec = spec
        self.policy: LiteLocalPolicy | None = None
        self.version = -1
        self.rng = lite_stream(spec.seed, LOCAL_STREAM, spec.agent)
        self._onehot = [1.0 if i == spec.agent else 0.0 for i in range(spec.n_agents)] if spec.onehot else []

    def load_weights(self, blob: bytes, version: int) -> None:
        self.policy = LiteLocalPolicy(blob)
        self.version = version

    def act(self, obs: list[list[float]], msg: list[list[float]] | None) -> list[int]:
        """One action id per env copy, from the rows of its observation and message (float32 values)."""
        if self.policy is None:
            raise RuntimeError("no policy weights loaded yet")
        logits = [self.policy.logits(row + self._onehot + (msg[j] if self.spec.msg_dim else []))
                  for j, row in enumerate(obs)]
        u = self.rng.random(len(obs))  # after the forward, as the numpy agent draws
        return [draw(z, x) for z, x in zip(logits, u)]


class LiteSteps(StepCore):
    """`client.AgentSteps` on lists: the message of each copy, received or a fallback."""

    def init_steps(self, spec: AgentSpec, num_envs: int, fallback: str, fallback_k: int, step_window: int,
                   start_step: int | None = None) -> None:
        self.init_core(spec, step_window, start_step)
        self.agent = LiteLocalAgent(spec)
        self.fallback = LiteMessageFallback(fallback, fallback_k, num_envs, spec.msg_dim)

    def settle_message(self, obs: LocalObs) -> tuple[list[list[float]], list[bool]]:
        """As `AgentSteps.settle_message`: rows of the message per env copy, and which copies fell back."""
        received = self.pending.pop(obs.step, None)
        for step in [s for s in self.pending if s < obs.step]:  # older than this step: never usable
            del self.pending[step]
            self.counts.msgs_late += 1
            self.log_msg(step, "late")
        env = obs.env_idx.tolist()
        msg = [[0.0] * self.spec.msg_dim for _ in env]
        have = [False] * len(env)
        if received is not None:
            have = self.fill_received(msg, received, env)
            self.fallback.received([e for e, h in zip(env, have) if h], [r for r, h in zip(msg, have) if h])
            self.counts.msgs_on_time += 1
            self.log_msg(obs.step, None)
        missing = [j for j, h in enumerate(have) if not h]
        if missing:
            for j, row in zip(missing, self.fallback.fill([env[j] for j in missing])):
                msg[j] = row
            self.counts.fallback_copies += len(missing)
            self.step_log.add(obs.step, MSG_EVENTS["fallbacks"], len(missing))
        return msg, [not h for h in have]

    @staticmethod
    def fill_received(msg: list[list[float]], received: CentralMsg, env: list[int]) -> list[bool]:
        """The received message's rows into `msg`, matched by env index; which copies it covered."""
        rows, got = received.msg.tolist(), received.env_idx.tolist()
        if got == env:
            msg[:] = rows
            return [True] * len(env)
        pos = {e: j for j, e in enumerate(got)}
        have = []
        for i, e in enumerate(env):
            j = pos.get(e)
            if j is not None:
                msg[i] = rows[j]
            have.append(j is not None)
        return have


class LiteLocalAgentClient(LiteSteps, ClientCore):
    """One local agent's process without numpy (see the module docstring): `client.LocalAgentClient`'s
    arguments and behaviour."""

    def no_fallbacks(self, k: int) -> list[bool]:
        return [False] * k

    def act_on(self, obs: LocalObs, msg: list[list[float]] | None, fallback_mask: list[bool]) -> None:
        k, m = obs.k, self.spec.msg_dim
        actions = self.agent.act(obs.obs.tolist(), msg)
        wire_msg: Any = None
        if msg is not None and obs.echo:  # the env host records it (training, a trace)
            wire_msg = WireArray.of("float32", (k, m), [x for row in msg for x in row])
        self.publish_action(obs, WireArray.of("int64", (k,), actions), wire_msg,
                            WireArray.of("bool", (k,), fallback_mask))
