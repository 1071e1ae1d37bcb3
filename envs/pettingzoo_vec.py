"""K copies of any PettingZoo *parallel* env, stepped in-process as one `VecEnv` batch.

PettingZoo speaks dicts keyed by agent name whose key set changes as agents leave (multiwalker
removes fallen walkers mid-episode). The learners want fixed-shape arrays, so this adapter fixes the
agent order once from `possible_agents`, pads absent agents with zeros and reports who was present
through the `active` / `next_active` masks. Per-agent terminated/truncated flags are passed through
exactly as the env reports them; a copy is reset automatically once it has no agents left.

This is on the trainer's hot path: all per-step buffers are preallocated and reused, the agent index
of every name is looked up once, and actions are clipped for the whole batch in one numpy call.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import numpy as np
from hammer.envs.base import EnvSpec, EpisodeTracker, VecEnv, VecStep
from hammer.envs.description import EnvConfigError

ParallelEnvFactory = Callable[[], Any]


class EnvSpaceError(EnvConfigError):
    """The env's spaces cannot be expressed as the fixed (K, N, D) arrays of the VecEnv contract.

    A subclass of `EnvConfigError`, so callers that catch configuration mistakes catch this too.
    """


def spec_from_parallel_env(env: Any, name: str, max_steps: int | None = None) -> EnvSpec:
    """Describe one copy of `env` as an `EnvSpec`, or raise `EnvSpaceError` saying what does not fit.

    Requires flat Box observations and Discrete or flat Box actions, identical for every agent (one
    shared policy acts for all of them, so their spaces must match).
    """
    from gymnasium import spaces

    agents = tuple(env.possible_agents)
    if not agents:
        raise EnvSpaceError(f"env {name!r}: possible_agents is empty; a multi-agent env needs agents")
    obs_spaces = [env.observation_space(a) for a in agents]
    act_spaces = [env.action_space(a) for a in agents]
    o0, a0 = obs_spaces[0], act_spaces[0]
    if not isinstance(o0, spaces.Box) or len(o0.shape) != 1:
        raise EnvSpaceError(
            f"env {name!r}: observation_space of {agents[0]!r} is {o0}; hammer needs a flat Box (1-D vector); "
            f"fix: {_adapter_fix(o0)} (`hammer envs check {name}` says what the env needs)"
        )
    for a, o in zip(agents, obs_spaces):
        if not isinstance(o, spaces.Box) or o.shape != o0.shape:
            raise EnvSpaceError(
                f"env {name!r}: observation_space of {a!r} is {o} but {agents[0]!r} has {o0}; agents must "
                "be homogeneous (same observation shape) because they share one policy; fix: --set "
                "env_adapters=[pad,agent_id] (pads every space to the largest and tells the agents apart)"
            )
    for a, s in zip(agents, act_spaces):
        if s != a0:
            raise EnvSpaceError(
                f"env {name!r}: action_space of {a!r} is {s} but {agents[0]!r} has {a0}; agents must be "
                "homogeneous (same action space) because they share one policy; fix: --set "
                "env_adapters=[pad,agent_id] (pads every space to the largest and tells the agents apart)"
            )
    if max_steps is None:  # PettingZoo envs keep it as max_cycles, some one level down (multiwalker)
        raw = env.unwrapped
        max_steps = int(getattr(raw, "max_cycles", None) or getattr(getattr(raw, "env", None), "max_cycles", 0) or 0)
    if isinstance(a0, spaces.Discrete):
        if int(a0.start) != 0:
            raise EnvSpaceError(f"env {name!r}: Discrete action_space must start at 0, got start={a0.start}")
        return EnvSpec(name=name, n_agents=len(agents), obs_dim=int(o0.shape[0]), discrete=True,
                       action_dim=int(a0.n), max_steps=max_steps, agent_ids=agents)
    if isinstance(a0, spaces.Box) and len(a0.shape) == 1:
        low, high = np.unique(a0.low), np.unique(a0.high)
        if len(low) != 1 or len(high) != 1 or not np.isfinite(low[0]) or not np.isfinite(high[0]):
            raise EnvSpaceError(
                f"env {name!r}: continuous action_space {a0} must have one finite low and one finite high "
                "for every component (EnvSpec.action_low/action_high are scalars); rescale the actions "
                "(e.g. gymnasium RescaleAction on each agent)."
            )
        return EnvSpec(name=name, n_agents=len(agents), obs_dim=int(o0.shape[0]), discrete=False,
                       action_dim=int(a0.shape[0]), max_steps=max_steps, agent_ids=agents,
                       action_low=float(low[0]), action_high=float(high[0]))
    raise EnvSpaceError(
        f"env {name!r}: action_space {a0} is neither Discrete nor a flat Box; hammer supports those two only."
    )


def _adapter_fix(space: Any) -> str:
    from gymnasium import spaces

    if isinstance(space, spaces.Discrete):
        return "--set env_adapters=[one_hot]"
    if isinstance(space, spaces.Box) and len(space.shape) == 3:
        return "--set env_adapters=[gray,resize:32x32,flatten] (an image: grey, small, flat)"
    if isinstance(space, spaces.Box):
        return "--set env_adapters=[flatten]"
    return "no adapter fits this space (Box or Discrete only)"


class PettingZooVecEnv(VecEnv):
    """K in-process copies of a PettingZoo parallel env behind the `VecEnv` contract.

    `factory()` must return a fresh parallel env each call. `index_offset` shifts both the seeds
    (copy k is seeded with seed + index_offset + k) and the `EpisodeStats.env_index`, so a worker
    process running a slice of a larger batch behaves exactly like that slice run in-process.
    """

    def __init__(self, factory: ParallelEnvFactory, num_envs: int, *, name: str = "pettingzoo",
                 max_steps: int | None = None, index_offset: int = 0) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = num_envs
        self.index_offset = index_offset
        self.envs = [factory() for _ in range(num_envs)]
        from pettingzoo import AECEnv

        for e in self.envs:
            if isinstance(e, AECEnv) or not hasattr(e, "possible_agents"):
                raise EnvSpaceError(
                    f"env {name!r}: the factory returned {type(e).__name__}, which is not a PettingZoo "
                    "parallel env (AEC envs step one agent at a time); use the module's parallel_env()."
                )
        self.spec = spec_from_parallel_env(self.envs[0], name, max_steps)
        K, N, D = num_envs, self.spec.n_agents, self.spec.obs_dim
        self._names = self.spec.agent_ids
        self._index = {a: i for i, a in enumerate(self._names)}
        if self.spec.discrete:
            self._low = self._high = None
        else:
            box = self.envs[0].action_space(self._names[0])
            self._low = box.low.astype(np.float32)
            self._high = box.high.astype(np.float32)
            self._act_buf = np.zeros((K, N, self.spec.action_dim), dtype=np.float32)
        # Which agents are present in each copy right now, as (index, name) pairs in fixed order.
        self._present: list[list[tuple[int, str]]] = [[] for _ in range(K)]
        self._obs = np.zeros((K, N, D), dtype=np.float32)
        self._next_active = np.zeros((K, N), dtype=bool)
        self.tracker = EpisodeTracker(K)
        self._seeded = False

    # -- helpers ---------------------------------------------------------------------------------
    def _take_obs(self, k: int, env: Any, obs: dict[str, Any]) -> None:
        """Write the observations of the agents now present in copy k into self._obs / _next_active."""
        row, act = self._obs[k], self._next_active[k]
        row.fill(0.0)
        act.fill(False)
        index = self._index
        present = []
        for a in env.agents:
            i = index[a]
            present.append((i, a))
            act[i] = True
            o = obs.get(a)
            if o is not None:
                row[i] = o
        present.sort()
        self._present[k] = present

    # -- VecEnv ----------------------------------------------------------------------------------
    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Reset every copy with seed + index_offset + k; returns copies of (obs, active)."""
        base = int(seed) + self.index_offset
        for k, env in enumerate(self.envs):
            obs, _ = env.reset(seed=base + k)
            if not env.agents:
                raise RuntimeError(f"env {self.spec.name!r} copy {k + self.index_offset} has no agents "
                                   "right after reset()")
            self._take_obs(k, env, obs)
        self.tracker = EpisodeTracker(self.num_envs)
        self._seeded = True
        return self._obs.copy(), self._next_active.copy()

    def step(self, actions: np.ndarray) -> VecStep:
        if not self._seeded:
            raise RuntimeError("call reset(seed) before step(): the copies have not been seeded yet")
        spec = self.spec
        K, N = self.num_envs, spec.n_agents
        if spec.discrete:
            acts = np.asarray(actions)
            if acts.shape != (K, N):
                raise ValueError(f"actions must have shape (K, N) = {(K, N)} for a discrete env, got {acts.shape}")
            acts = acts.astype(np.int64, copy=False).tolist()  # python ints: what PettingZoo envs expect
        else:
            acts = np.asarray(actions, dtype=np.float32)
            if acts.shape != (K, N, spec.action_dim):
                raise ValueError(f"actions must have shape (K, N, A) = {(K, N, spec.action_dim)} for a "
                                 f"continuous env, got {acts.shape}")
            acts = np.clip(acts, self._low, self._high, out=self._act_buf)

        active = self._next_active.copy()
        reward = np.zeros((K, N), dtype=np.float32)
        terminated = np.zeros((K, N), dtype=bool)
        truncated = np.zeros((K, N), dtype=bool)
        final_obs = np.empty_like(self._obs)
        done = np.zeros(K, dtype=bool)
        index = self._index

        for k, env in enumerate(self.envs):
            ak = acts[k]
            obs, rew, term, trunc, _ = env.step({a: ak[i] for i, a in self._present[k]})
            for a, r in rew.items():
                reward[k, index[a]] = r
            for a, t in term.items():
                if t:
                    terminated[k, index[a]] = True
            for a, t in trunc.items():
                if t:
                    truncated[k, index[a]] = True
            if env.agents:
                self._take_obs(k, env, obs)
                final_obs[k] = self._obs[k]
                # Agents that left at this step keep their last observation in final_obs.
                for a in obs:
                    i = index[a]
                    if not self._next_active[k, i]:
                        final_obs[k, i] = obs[a]
            else:
                fo = final_obs[k]
                fo.fill(0.0)
                for a, o in obs.items():
                    fo[index[a]] = o
                done[k] = True
                obs, _ = env.reset()  # unseeded: continue this copy's own random stream
                self._take_obs(k, env, obs)
                # An env that comes back from reset with no agents cannot be stepped.
                if not env.agents:
                    raise RuntimeError(f"env {spec.name!r} copy {k + self.index_offset} has no agents "
                                       "right after reset()")

        if spec.max_steps:
            # Some envs (multiwalker) report their time limit as a termination; PPO must bootstrap
            # there, so an episode that ends exactly at max_steps counts as truncated.
            at_limit = done & (self.tracker.length + 1 >= spec.max_steps)
            if at_limit.any():
                truncated[at_limit] |= terminated[at_limit]
                terminated[at_limit] = False
        episodes = self.tracker.record(reward, active, done)
        if self.index_offset:
            episodes = [type(e)(e.env_index + self.index_offset, e.paper_metric, e.team_return, e.length)
                        for e in episodes]
        return VecStep(obs=self._obs.copy(), reward=reward, terminated=terminated, truncated=truncated,
                       active=active, next_active=self._next_active.copy(), final_obs=final_obs,
                       done=done, episodes=episodes)

    def close(self) -> None:
        for env in self.envs:
            with contextlib.suppress(Exception):  # best effort: a half-built env may fail to close
                env.close()
