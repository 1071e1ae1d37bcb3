"""Env names -> `VecEnv`: the one entry point (`make_vec_env`) the trainer and the env host call.

Names:
  cn        vectorised cooperative navigation (`envs.spread.VecSimpleSpread`, numpy, all K copies
            in one array program); local_ratio 0.5, 25 steps; observe_others=False hides the
            other agents from each local observation (not in mpe2); obs_radius=r masks, in the
            local agents' inputs only, landmarks and agents at distance >= r (`envs.local_view`).
  cn-mpe2   the same task through PettingZoo: mpe2 simple_spread_v3, discrete actions, 25 steps,
            local_ratio 0.5 (the reference the vectorised version is checked against).
  mw        SISL multiwalker_v9 with the paper's settings (individual rewards, fallen walkers
            removed, terrain 200, 500 steps), stepped without PettingZoo's AEC wrappers where that
            is exact (`envs.multiwalker_direct`: terminate_on_fall=True, the paper's setting).
  mw-pettingzoo
            the same env through PettingZoo's parallel wrapper all the way (the reference).
  rware     the multi-robot warehouse (rware 2.0, Gymnasium with tuple spaces, `envs.rware_vec`): each
            robot's partial view is its local observation, the whole warehouse goes to the central
            agent only (`EnvSpec.local_obs_dim`); env_kwargs size (tiny|small|medium|large),
            difficulty (easy|normal|hard), sensor_range, max_steps (500), column_height,
            request_queue_size, reward_type, impl (rware: rware's objects, the default and the
            reference; numpy: `envs.rware_numpy`, the same env on all copies at once).
            `rware-tiny-2ag` etc. name rware's own presets.
  module:factory
            any PettingZoo parallel env, e.g. `pettingzoo.sisl.multiwalker_v9:parallel_env`
            or `mpe2.simple_reference_v3:parallel_env`; env_kwargs
            are passed to the factory and n_agents must match its possible_agents.

`env_adapters` (`envs.adapters`: flatten, one_hot, pad, agent_id, gray, resize:WxH) make envs
with image or Discrete observations or with different spaces per agent fit; `hammer envs check
module:factory` says which an env needs. A `module:factory` module is imported from the current
folder too (as `python -m` does), so a wrapper module next to the config needs no PYTHONPATH.

`env_kwargs` override the defaults field by field; unknown fields are refused with the list of valid
ones. `workers=0` steps the K copies in this process; `workers>=1` splits them over that many
subprocesses (`envs.workers.SubprocVecEnv`), which rebuild the env from the picklable
`EnvDescription`, never from a pickled env.
"""

from __future__ import annotations

from typing import Any

from hammer.envs.adapters import parse_adapters
from hammer.envs.base import VecEnv
from hammer.envs.catalog import build_cn, build_local, parallel_env_factory, valid_names
from hammer.envs.description import EnvConfigError, EnvDescription
from hammer.envs.rware_vec import is_rware, settings_from
from hammer.envs.workers import SubprocVecEnv


def make_vec_env(env: str, n_agents: int, num_envs: int, *, env_kwargs: dict[str, Any] | None = None,
                 workers: int = 0, parent_slice: bool = False, adapters: list[str] | tuple[str, ...] = ()) -> VecEnv:
    """Build K = num_envs copies of the N = n_agents env `env` (see module docstring for the names).

    Seeding happens in `reset(seed)` (copy k gets seed + k). `workers=0` runs in-process;
    `workers>=1` splits the copies into that many slices stepped in parallel subprocesses, with
    identical results; `parent_slice=True` steps slice 0 in this process instead (W-1 subprocesses;
    workers=1 is then simply in-process). `adapters` (`envs.adapters`) wrap each PettingZoo env.
    """
    if not isinstance(env, str) or not env:
        raise EnvConfigError(f"env: expected a name, got {env!r}; valid names: {valid_names()}")
    if not isinstance(n_agents, int) or n_agents < 1:
        raise EnvConfigError(f"n_agents: must be an int >= 1, got {n_agents!r}")
    if not isinstance(num_envs, int) or num_envs < 1:
        raise EnvConfigError(f"num_envs: must be an int >= 1, got {num_envs!r}")
    if not isinstance(workers, int) or workers < 0 or workers > num_envs:
        raise EnvConfigError(f"workers: must be an int in [0, num_envs={num_envs}], got {workers!r} "
                             "(0 = in-process)")
    kwargs = dict(env_kwargs or {})
    adapters = parse_adapters(adapters)
    if env == "cn":
        if adapters:
            raise EnvConfigError("env_adapters: env 'cn' is vectorised numpy, not PettingZoo, and needs none; fix: "
                                 "remove env_adapters")
        return build_cn(n_agents, num_envs, kwargs, workers)
    desc = EnvDescription(env, n_agents, kwargs, adapters)
    if is_rware(env):
        settings_from(desc)  # validate the name and kwargs here, before any process starts
    else:
        parallel_env_factory(desc)  # validate the name and kwargs here, before any process starts
    if workers == 0 or (workers == 1 and parent_slice):
        return build_local(desc, num_envs)
    return SubprocVecEnv(desc, num_envs, workers, parent_slice=parent_slice)
