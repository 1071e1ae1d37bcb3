"""What the learner checks of the env host's rollout chunk before it learns from it."""

from __future__ import annotations

import numpy as np

from envs.base import EnvSpec
from learning.config import RunConfig


class ChunkError(ValueError):
    """An experience chunk whose arrays do not fit this run (named array and what is wrong)."""


def expected_arrays(cfg: RunConfig, spec: EnvSpec, act_dim: int, msg_dim: int) -> dict[str, tuple[tuple, str]]:
    """Name -> (shape, dtype) of the env host's rollout chunk."""
    t, k, n, d = cfg.rollout_steps, cfg.num_envs, cfg.n_agents, spec.obs_dim
    a_shape = spec.action_shape
    return {
        "obs": ((t, k, n, d), "float32"), "prev": ((t, k, n, act_dim), "float32"),
        "msg": ((t, k, n, msg_dim), "float32"),
        "actions": ((t, k, n, *a_shape), "int64" if spec.discrete else "float32"),
        "rewards": ((t, k, n), "float32"), "terminated": ((t, k, n), "bool"), "truncated": ((t, k, n), "bool"),
        "active": ((t, k, n), "bool"), "reset": ((t, k, n), "bool"),
        "final_obs": ((t, k, n, d), "float32"), "final_prev": ((t, k, n, act_dim), "float32"),
        "defaulted": ((t, k, n), "bool"), "steps": ((t,), "int64"),
        "last_obs": ((k, n, d), "float32"), "last_prev": ((k, n, act_dim), "float32"),
    }


def check_chunk(arrays: dict[str, np.ndarray], expected: dict[str, tuple[tuple, str]]) -> None:
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise ChunkError(f"experience chunk lacks arrays {missing}")
    for name, (shape, dtype) in expected.items():
        a = arrays[name]
        if a.shape != shape or a.dtype != np.dtype(dtype):
            raise ChunkError(f"array {name}: got {a.dtype}{a.shape}, expected {dtype}{shape}")
