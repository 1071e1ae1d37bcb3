"""The trainer's rollout buffer rebuilt from what the env host and the central agent sent.

`RemoteRollout` fills a `TeamLearner`'s buffer from a rollout chunk and the central agent's
per-step records exactly as the in-process trainer fills it by acting, recomputing the
acting-time log-probs and values; `BehaviourSnapshots` holds the networks of the last few policy
versions, so a chunk acted by an older version (policy lag) is evaluated with that version.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
from hammer.envs.base import EnvSpec
from hammer.learning.ppo_update import TeamLearner
from hammer.learning.team import Team


class RemoteRollout:
    """Fills a TeamLearner's buffer from a rollout chunk (+ central records) as the trainer would."""

    def __init__(self, learner: TeamLearner, spec: EnvSpec) -> None:
        self.learner, self.spec = learner, spec
        self.team = learner.team

    @torch.no_grad()
    def fill(self, r: dict[str, np.ndarray], central: dict[int, dict[str, np.ndarray]] | None) -> int:
        """Returns how many steps lacked a central record (their messages count as not kept)."""
        team, buf = self.team, self.learner.buf
        missing = 0
        buf.reset[:] = r["reset"]
        buf.actions[:] = r["actions"]
        buf.rewards[:], buf.terminated[:], buf.truncated[:] = r["rewards"], r["terminated"], r["truncated"]
        buf.active[:] = r["active"]
        buf.final_values[:] = 0.0
        buf.c_final_values[:] = 0.0
        for t in range(buf.t):
            obs, msg = r["obs"][t], r["msg"][t]
            buf.obs[t], buf.msg[t] = obs, msg
            buf.state[t] = team.global_state(obs, r["prev"][t], int(r["steps"][t]))
            if central is not None:
                rec = central.get(int(r["steps"][t]))
                if rec is None:  # the central agent never saw this step: agents acted on fallbacks
                    missing += 1
                    buf.msg_raw[t], buf.c_logp[t], buf.c_values[t], buf.keep[t] = msg, 0.0, 0.0, 0.0
                else:
                    buf.msg_raw[t], buf.c_logp[t], buf.c_values[t] = rec["msg_raw"], rec["c_logp"], rec["c_values"]
                    buf.keep[t] = rec["keep"]
            else:
                buf.msg_raw[t], buf.keep[t] = msg, 1.0
                buf.c_logp[t], buf.c_values[t] = 0.0, 0.0
            buf.logp[t], buf.values[t] = team.local_evaluate(obs, msg, r["actions"][t])
            if r["reset"][t].any():
                idx = np.flatnonzero(r["reset"][t].any(axis=1))
                fobs = r["final_obs"][t][idx]
                fstate = team.global_state(fobs, r["final_prev"][t][idx], int(r["steps"][t]), idx)
                buf.final_values[t, idx] = team.local_values(fobs, team.bootstrap_messages(fstate))
                buf.c_final_values[t, idx] = team.central_values(fstate)
        return missing


class BehaviourSnapshots:
    """The network states of the last `max_lag` + 1 policy versions, so experience acted by an
    older version can be evaluated with exactly that version (its log-probs and values)."""

    def __init__(self, team: Team, max_lag: int) -> None:
        self.max_lag = max_lag
        self.nets = [team.local] + ([team.central] if team.central is not None else [])
        self.states: dict[int, list[dict[str, torch.Tensor]]] = {}

    def _state(self) -> list[dict[str, torch.Tensor]]:
        return [{k: v.detach().clone() for k, v in net.state_dict().items()} for net in self.nets]

    def _load(self, states: list[dict[str, torch.Tensor]]) -> None:
        for net, st in zip(self.nets, states, strict=True):
            net.load_state_dict(st)

    def keep(self, version: int) -> None:
        """Remember the current weights as `version` (a no-op when synchronous)."""
        if not self.max_lag:
            return
        self.states[version] = self._state()
        for v in [v for v in self.states if v < version - self.max_lag]:
            del self.states[v]

    @contextmanager
    def acting_as(self, version: int, current: int):
        """Within the block the networks hold `version`; the current weights come back after."""
        if version == current:
            yield
            return
        if version not in self.states:
            raise KeyError(f"no snapshot of policy version {version} (kept: {sorted(self.states)})")
        now = self.states.get(current) or self._state()  # keep(current) ran after its publish
        self._load(self.states[version])
        try:
            yield
        finally:
            self._load(now)
