"""Multiwalker's parallel step without PettingZoo's AEC machinery: the same env, less work.

`pettingzoo.sisl.multiwalker_v9.parallel_env()` is an AEC env (`raw_env` around the Box2D
`MultiWalkerEnv`) inside three wrappers (clip, order enforcing, AEC-to-parallel). A parallel step
walks the agents one by one through all of them: `last()`, the wrapper chain, reward clearing and
accumulation, agent selection. That bookkeeping is a large part of the env step, which is most of a
multiwalker run's time (the profile is in docs/fast-envs.md).

`DirectMultiwalker` wraps the real parallel env and does exactly what that chain does to the Box2D
env, in one loop: each walker's action goes to `MultiWalkerEnv.step(action, i, is_last)` as a
float32 array (the physics and every random draw happen on the last one), then the rewards, dones
and observations are read back the way `raw_env` and the AEC-to-parallel wrapper read them. The
clip wrapper's clip is left out: the walker's `apply_action` uses only sign(a) and min(|a|, 1), so
clipping cannot change the physics. Resets (and seeding) still go through the PettingZoo wrapper,
which re-initialises all of its own state, so nothing it holds can go stale.

It is only used where the result is provably the same: `terminate_on_fall=True` (the paper's
setting), where every episode ends for all walkers at once (a fall, the package dropped or out of
bounds, the terrain's end, or `max_cycles`), so no agent ever leaves mid-episode; and no rendering.
`tests/test_multiwalker_direct.py` checks observations, rewards and flags bit for bit against the
PettingZoo path over whole episodes, resets included. `make_vec_env("mw-pettingzoo", ...)` is the
reference path.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def direct_applies(kwargs: dict[str, Any]) -> bool:
    """Whether the direct step is exact for these multiwalker kwargs."""
    return bool(kwargs.get("terminate_on_fall", True)) and kwargs.get("render_mode") is None


def wrap_if_exact(penv: Any, kwargs: dict[str, Any]) -> Any:
    """The registry's hook for `mw`: the direct step where it is exact, else PettingZoo's env as is."""
    return DirectMultiwalker(penv) if direct_applies(kwargs) else penv


class DirectMultiwalker:
    """A PettingZoo parallel multiwalker env whose `step` bypasses the AEC wrappers (see module doc)."""

    def __init__(self, penv: Any) -> None:
        raw = penv.unwrapped
        base = getattr(raw, "env", None)
        if not (getattr(raw, "metadata", {}).get("name") == "multiwalker_v9" and hasattr(base, "walkers")):
            raise TypeError(f"DirectMultiwalker needs pettingzoo's multiwalker_v9 parallel env, got {type(raw)}")
        if not base.terminate_on_fall or base.render_mode is not None:
            raise ValueError("DirectMultiwalker is exact only with terminate_on_fall=True and no rendering")
        self._penv, self._base = penv, base
        self.possible_agents = list(penv.possible_agents)
        self.agents: list[str] = []
        self.metadata = penv.metadata

    # What the registry, the adapter and the tests read.
    @property
    def unwrapped(self) -> Any:
        return self._penv.unwrapped

    def observation_space(self, agent: str) -> Any:
        return self._penv.observation_space(agent)

    def action_space(self, agent: str) -> Any:
        return self._penv.action_space(agent)

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        obs, infos = self._penv.reset(seed=seed, options=options)
        self.agents = list(self._penv.agents)
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() on a finished multiwalker episode: call reset() first")
        base, agents = self._base, self.agents
        acts = [np.array(actions[a], dtype=np.float32) for a in agents]  # raw_env's cast
        for act in acts:
            if np.isnan(act).any():  # the clip wrapper refuses these too
                raise ValueError("step() cannot take in a nan action")
        last = len(agents) - 1
        for i, act in enumerate(acts):
            # No clip here: the clip wrapper's clip cannot change the physics, because the walker's
            # apply_action uses only sign(a) and min(|a|, 1) (and the adapter clips the batch already).
            base.step(act, i, i == last)
        # raw_env after the last walker: rewards from get_last_rewards (np.float64; the earlier walkers'
        # steps contributed cleared zeros), terminations from get_last_dones, all of them at max_cycles.
        rewards = {a: np.float64(r) for a, r in zip(agents, base.last_rewards, strict=True)}
        if base.frames >= base.max_cycles:
            dones = [True] * len(agents)
        else:
            dones = list(base.last_dones)
        terminations = dict(zip(agents, dones, strict=True))
        truncations = dict.fromkeys(agents, False)
        infos = {a: {} for a in agents}
        observations = {a: np.array(base.last_obs[i], dtype=np.float32) for i, a in enumerate(agents)}
        if any(dones):  # terminate_on_fall: then all are done, and the wrapper would remove them all
            if not all(dones):
                raise RuntimeError("multiwalker ended the episode for some walkers only, which "
                                   "terminate_on_fall=True rules out; use the 'mw-pettingzoo' env")
            self.agents = []
        return observations, rewards, terminations, truncations, infos

    def close(self) -> None:
        self._penv.close()
