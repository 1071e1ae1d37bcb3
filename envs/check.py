"""`hammer envs check`: can this env run, and with which adapters?

Builds one copy of the env as its factory returns it, lists its agents and spaces, decides which
`envs.adapters` it needs (or why none can help), then builds it the way a run would (`make_vec_env`
with those adapters) and steps it with random actions to measure its speed and episode length.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hammer.envs.description import EnvConfigError, EnvDescription


@dataclass
class CheckReport:
    name: str
    agents: list[str] = field(default_factory=list)
    spaces: list[tuple[str, str, str]] = field(default_factory=list)  # (agents, observation space, action space)
    max_steps: int | None = None
    needed: list[str] = field(default_factory=list)
    adapters: list[str] = field(default_factory=list)  # what the run would use (given, or the needed ones)
    obs_dim: int | None = None
    actions: str | None = None
    steps_per_s: float | None = None
    mean_episode_len: float | None = None
    problem: str | None = None  # why it cannot run (then the fields after `needed` stay empty)

    def fix(self) -> str | None:
        """The config line a run needs (None: runs as it is)."""
        parts = []
        if self.adapters:
            parts.append(f"--set 'env_adapters=[{','.join(self.adapters)}]'")
        parts.append(f"--set n_agents={len(self.agents)}")
        return " ".join(parts)


def check_env(name: str, env_kwargs: dict[str, Any], adapters: list[str] | None, n_agents: int,
              seconds: float = 1.5) -> CheckReport:
    from hammer.envs.adapters import needed_adapters
    from hammer.envs.catalog import parallel_env_factory
    from hammer.envs.registry import make_vec_env
    from hammer.envs.rware_vec import is_rware, settings_from
    from pettingzoo import AECEnv

    rep = CheckReport(name)
    if name == "cn":
        rep.problem = None
        rep.agents = [f"agent_{i}" for i in range(n_agents)]
    elif is_rware(name):  # not PettingZoo: no adapters apply; the settings check names a bad field
        rep.max_steps = settings_from(EnvDescription(name, n_agents, dict(env_kwargs))).max_steps
        rep.agents = [f"robot_{i}" for i in range(n_agents)]
    else:
        factory, _, max_steps = parallel_env_factory(EnvDescription(name, n_agents, dict(env_kwargs)))
        raw = factory()
        try:
            if isinstance(raw, AECEnv) or not hasattr(raw, "possible_agents"):
                rep.problem = (f"the factory returns {type(raw).__name__}, not a PettingZoo parallel env (AEC envs "
                               "step one agent at a time); name the module's parallel_env")
                return rep
            rep.agents = list(raw.possible_agents)
            groups: dict[tuple[str, str], list[str]] = {}
            for a in rep.agents:
                groups.setdefault((str(raw.observation_space(a)), str(raw.action_space(a))), []).append(a)
            rep.spaces = [(", ".join(v), o, s) for (o, s), v in groups.items()]
            u = raw.unwrapped
            rep.max_steps = max_steps or getattr(u, "max_cycles", None) or getattr(getattr(u, "env", None),
                                                                                   "max_cycles", None)
            rep.needed, rep.problem = needed_adapters(raw)
        finally:
            raw.close()
        if rep.problem:
            return rep
    rep.adapters = list(adapters) if adapters is not None else rep.needed
    try:
        venv = make_vec_env(name, len(rep.agents), 1, env_kwargs=env_kwargs or None, adapters=rep.adapters)
    except EnvConfigError as e:
        rep.problem = str(e)
        return rep
    try:
        s = venv.spec
        rep.obs_dim = s.obs_dim
        rep.actions = (f"{s.action_dim} discrete" if s.discrete else
                       f"{s.action_dim} continuous in [{s.action_low:g}, {s.action_high:g}]")
        rng = np.random.default_rng(0)
        venv.reset(0)
        steps, lengths, t0 = 0, [], time.perf_counter()
        while time.perf_counter() - t0 < seconds or not lengths and steps < 10_000:
            a = (rng.integers(0, s.action_dim, (1, s.n_agents)) if s.discrete else
                 rng.uniform(s.action_low, s.action_high, (1, s.n_agents, s.action_dim)).astype(np.float32))
            lengths += [e.length for e in venv.step(a).episodes]
            steps += 1
        rep.steps_per_s = steps / (time.perf_counter() - t0)
        rep.mean_episode_len = float(np.mean(lengths)) if lengths else None
    finally:
        venv.close()
    return rep
