"""Adapters that let any PettingZoo parallel env fit the VecEnv contract (flat float observations,
one observation and action space shared by every agent), selected by the run config's
`env_adapters` and built from SuperSuit, the PettingZoo ecosystem's own wrapper library.

    gray            images to one grey channel (supersuit.color_reduction_v0)
    resize:WxH      images to W x H pixels (supersuit.resize_v1), e.g. resize:32x32
    flatten         any Box observation to a flat float32 vector; bounded integer observations
                    (uint8 images) are scaled to [0, 1] first (dtype_v0, normalize_obs_v0, flatten_v0)
    one_hot         Discrete observations to a one-hot float vector
    pad             observation and action spaces of different sizes padded to the largest
                    (pad_observations_v0, pad_action_space_v0; a padded Discrete action beyond an
                    agent's own space acts as action 0)
    agent_id        a one-hot agent index appended to each observation (agent_indicator_v0), so one
                    shared policy can tell the agents apart

They are applied in the order above whatever order the config lists them in. `needed_adapters`
says which ones an env needs (`hammer envs check`).
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np
from hammer.envs.description import EnvConfigError

ORDER = ("gray", "resize", "flatten", "one_hot", "pad", "agent_id")
_RESIZE = re.compile(r"^resize:(\d+)x(\d+)$")


def parse_adapters(items: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """The adapters in application order; a name that is not one raises with the valid ones."""
    out = []
    for item in items:
        name = "resize" if _RESIZE.match(str(item)) else str(item)
        if name not in ORDER:
            raise EnvConfigError(f"env_adapters: unknown adapter {item!r}; valid: gray, resize:WxH (e.g. resize:32x32), "
                                 "flatten, one_hot, pad, agent_id")
        out.append(str(item))
    if len({_name(a) for a in out}) != len(out):
        raise EnvConfigError(f"env_adapters: {list(items)} lists an adapter twice; fix: list each once")
    return tuple(sorted(out, key=lambda a: ORDER.index(_name(a))))


def _name(adapter: str) -> str:
    return "resize" if _RESIZE.match(adapter) else adapter


def apply_adapters(env: Any, adapters: tuple[str, ...]) -> Any:
    """`env` (a parallel env) wrapped by the adapters, in `ORDER`."""
    if not adapters:
        return env
    import supersuit as ss
    from gymnasium import spaces

    for a in parse_adapters(adapters):
        if a == "gray":
            env = ss.color_reduction_v0(env, mode="full")
        elif _RESIZE.match(a):
            w, h = (int(v) for v in _RESIZE.match(a).groups())
            env = ss.resize_v1(env, x_size=w, y_size=h)
        elif a == "flatten":
            space = env.observation_space(env.possible_agents[0])
            if np.issubdtype(space.dtype, np.integer) and np.isfinite(space.low).all() and np.isfinite(space.high).all():
                env = ss.normalize_obs_v0(ss.dtype_v0(env, np.float32), env_min=0.0, env_max=1.0)
            elif space.dtype != np.float32:
                env = ss.dtype_v0(env, np.float32)
            env = ss.flatten_v0(env)
        elif a == "one_hot":
            def one_hot(obs: Any, space: Any) -> np.ndarray:
                v = np.zeros(space.n, dtype=np.float32)
                v[int(obs) - int(space.start)] = 1.0
                return v

            env = ss.observation_lambda_v0(
                env, one_hot,
                lambda space: spaces.Box(0.0, 1.0, (space.n,), np.float32) if isinstance(space, spaces.Discrete)
                else _refuse("one_hot", f"observation space {space} is not Discrete"))
        elif a == "pad":
            env = ss.pad_action_space_v0(ss.pad_observations_v0(env))
        elif a == "agent_id":
            env = ss.agent_indicator_v0(env, type_only=False)
    return env


def _refuse(adapter: str, why: str) -> Any:
    raise EnvConfigError(f"env_adapters: {adapter}: {why}")


def needed_adapters(env: Any) -> tuple[list[str], str | None]:
    """(the adapters this parallel env needs, or why none can make it run)."""
    from gymnasium import spaces

    agents = list(env.possible_agents)
    obs = [env.observation_space(a) for a in agents]
    act = [env.action_space(a) for a in agents]
    need: list[str] = []
    for s in obs + act:
        if not isinstance(s, (spaces.Box, spaces.Discrete)):
            return [], f"{type(s).__name__} spaces (agent spaces must be Box or Discrete)"
    if any(type(s) is not type(obs[0]) for s in obs) or any(type(s) is not type(act[0]) for s in act):
        return [], "agents mix Box and Discrete spaces"
    if isinstance(obs[0], spaces.Discrete):
        need.append("one_hot")
    elif len(obs[0].shape) >= 2:
        if len(obs[0].shape) == 3 and obs[0].shape[2] == 3:
            need.append("gray")
        if int(np.prod(obs[0].shape[:2])) > 64 * 64:
            need.append("resize:32x32")
        need.append("flatten")
    elif obs[0].dtype != np.float32:
        need.append("flatten")
    hetero = any(repr(s) != repr(obs[0]) for s in obs) or any(repr(s) != repr(act[0]) for s in act)
    if hetero:
        if any(len(s.shape) != len(obs[0].shape) for s in obs if isinstance(s, spaces.Box)):
            return [], "observations of different ranks cannot be padded together"
        need += ["pad", "agent_id"]
    return need, None
