"""The env a run config asks for. Torch-free: the env host builds its env with it too."""

from __future__ import annotations

import numpy as np
from hammer.envs.base import EnvSpec, VecEnv
from hammer.learning.config import RunConfig


def check_env_fits(cfg: RunConfig, spec: EnvSpec) -> None:
    """What the config asks of the env's observations, checked before any run directory is written."""
    from hammer.envs.description import EnvConfigError

    if cfg.obs_conv and int(np.prod(cfg.obs_conv)) > spec.obs_dim:
        raise EnvConfigError(f"obs_conv: {cfg.obs_conv} is {int(np.prod(cfg.obs_conv))} values but the env's "
                             f"observations have {spec.obs_dim}; fix: the image env_adapters produce (`hammer envs "
                             "check`), e.g. [32, 32, 1] for [gray, resize:32x32, flatten]")


def make_env(cfg: RunConfig) -> VecEnv:
    from hammer.envs.registry import make_vec_env

    return make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs, env_kwargs=cfg.env_kwargs or None,
                        workers=cfg.env_workers, parent_slice=cfg.env_parent_slice,
                        adapters=cfg.env_adapters)
