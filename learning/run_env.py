"""The env a run config asks for. Torch-free: the env host builds its env with it too."""

from __future__ import annotations

from envs.base import VecEnv
from learning.config import RunConfig


def make_env(cfg: RunConfig) -> VecEnv:
    from envs.registry import make_vec_env

    return make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs, env_kwargs=cfg.env_kwargs or None,
                        workers=cfg.env_workers, parent_slice=cfg.env_parent_slice,
                        adapters=cfg.env_adapters)
