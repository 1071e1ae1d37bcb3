"""compile=true: one vector step of the whole team's acting as one compiled graph.

Eager acting is a dozen torch calls per vector step (the central network, the local actor, the
local critic, each a few layers) and then the sampling in numpy, which costs more than the env step
itself (docs/fast-envs.md, "The floor under those targets"). Each call is cheap; their count, the
numpy round trips between them and torch's tanh kernel are not. Here the stream draws come
first, in the order and amounts the randomness contract fixes (`learning.sampling`: central,
dropout, local), and everything after them is one `torch.compile` graph: the central message means
and values, the Gaussian message sample and its log-density, dropout, the local input, the local
actor and critic and the categorical (or Gaussian) action sample with its log-probability.

The maths is `Team.central_messages` + `Team.local_act` (`CentralActing.messages`,
`Team.sample_local`), transcribed into torch with the same dtypes (float64 where the contract says
so); only float rounding differs: the hidden layers' tanh is the graph's 2σ(2x) − 1 (what the
compiled update computes, `networks._traced_tanh`), the float64 softmax runs in the graph's exp.
So a compiled run's trajectory is not bit-identical to an eager run's (its update was not either);
tests/test_fused_acting.py checks the two agree step by step for every variant.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from hammer.learning.central_acting import CentralOut
from hammer.learning.compiled_update import COMPILE_OPTIONS, allow_many_graphs, skip_guards
from hammer.learning.numpy_policy import LOG_2PI
from hammer.learning.sampling import ActingStreams

if TYPE_CHECKING:
    from hammer.learning.team import Team


class FusedActing:
    """`Team.act` for compile=true: the draws in numpy, the rest one compiled call."""

    def __init__(self, team: Team) -> None:
        self.team = team
        w = team.wiring
        self.m, self.rl, self.random = team.msg_dim, w.central_rl, w.random_messages
        self.net = w.has_central_network
        self.log_msg_std = math.log(team.acting.msg_std)
        allow_many_graphs()
        self.graph = torch.compile(self._act, fullgraph=True, dynamic=False, options=COMPILE_OPTIONS)
        self.seen: set[tuple] = set()

    def act(self, obs: np.ndarray, state: np.ndarray, streams: ActingStreams, dropout: float
            ) -> tuple[CentralOut, np.ndarray, np.ndarray, np.ndarray]:
        team = self.team
        inputs = self.inputs(obs, state, streams, dropout)
        args = [team.tensor(np.ascontiguousarray(a)) for a in inputs]
        key = tuple((a.shape, a.dtype) for a in args)
        with torch.no_grad(), skip_guards(key in self.seen):
            out = self.graph(*args)
        self.seen.add(key)
        return self.outputs([team.host(t) for t in out], inputs[3])

    def inputs(self, obs: np.ndarray, state: np.ndarray, streams: ActingStreams, dropout: float
               ) -> list[np.ndarray]:
        """The graph's inputs for one vector step: what the local agents see, the global state and
        the randomness contract's draws, in its order (central, dropout, local). A seed batch draws
        each seed's inputs from its own streams and runs `_act` over them all (`learning.seed_batch`)."""
        team, m = self.team, self.m
        k, n = obs.shape[:2]
        if self.random:
            c_draw = streams.central_uniform_messages(k, n, m)
        elif self.rl:
            c_draw = streams.central_normals(k, n, m)
        else:
            c_draw = np.zeros((k, n, m), dtype=np.float32)
        keep = streams.dropout_keep(k, n, dropout) if m else np.ones((k, n), dtype=bool)
        l_draw = streams.local_uniforms(k) if team.discrete else streams.local_normals(k, team.act_dim)
        return [team.local_view(obs), state, c_draw, keep, l_draw]

    @staticmethod
    def outputs(out: list[np.ndarray], keep: np.ndarray) -> tuple[CentralOut, np.ndarray, np.ndarray, np.ndarray]:
        """`Team.act`'s result from the graph's outputs on the host and the dropout draw `keep`."""
        sent, mean, raw, c_logp, c_value, action, logp, value = out
        return CentralOut(sent, mean, raw, c_logp, c_value, keep), action, logp, value

    def _act(self, obs: torch.Tensor, state: torch.Tensor, c_draw: torch.Tensor, keep: torch.Tensor,
             l_draw: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """One vector step after the draws, written to be traced into one graph."""
        team = self.team
        k, n = obs.shape[:2]
        zeros = torch.zeros(k, n, device=obs.device)
        c_logp = c_value = zeros
        if self.random:
            mean = raw = sent = c_draw
        elif self.net:
            mean = team.central.message_mean(state)
            if self.rl:  # CentralActing.messages: the sample in float64, logp from the draw
                raw = (mean.double() + team.acting.msg_std * c_draw).float()
                c_logp = (-0.5 * c_draw.pow(2) - self.log_msg_std - 0.5 * LOG_2PI).sum(-1).float()
                sent = raw.clamp(-1.0, 1.0)
                c_value = team.central.values(state)
            else:
                raw = sent = mean
        else:
            mean = raw = sent = c_draw  # (K, N, 0)
        if self.m:
            sent = sent * keep.unsqueeze(-1)
        x = team.local_input(obs, sent)
        out, value = team.local.actor_out(x), team.local.value(x)
        if team.discrete:  # Team.sample_local: float64 softmax, inverse CDF, log of the probability
            z = out.double()
            e = (z - z.amax(-1, keepdim=True)).exp()
            probs = e / e.sum(-1, keepdim=True)
            idx = (probs.cumsum(-1) <= l_draw.unsqueeze(-1)).sum(-1).clamp(max=probs.shape[-1] - 1)
            logp = probs.gather(-1, idx.unsqueeze(-1)).squeeze(-1).log().float()
            action = idx.long()
        else:
            log_std = team.local.log_std
            action = (out.double() + log_std.exp().double() * l_draw).float()
            logp = (-0.5 * l_draw.pow(2) - log_std.double() - 0.5 * LOG_2PI).sum(-1).float()
        return sent, mean, raw, c_logp, c_value, action, logp, value

