"""Preallocated, contiguous rollout buffers (T, K, N, ...), reused every update."""

from __future__ import annotations

import numpy as np


class RolloutBuffer:
    """Everything one update needs, time-major; `flat(name)` views it as (T*K, N, ...) rows."""

    def __init__(self, t: int, k: int, n: int, obs_dim: int, state_dim: int, msg_dim: int,
                 action_shape: tuple[int, ...], discrete: bool) -> None:
        self.t, self.k, self.n = t, k, n
        f32 = np.float32
        self.obs = np.zeros((t, k, n, obs_dim), f32)
        self.state = np.zeros((t, k, state_dim), f32)
        self.msg = np.zeros((t, k, n, msg_dim), f32)  # what the local agents received
        self.msg_raw = np.zeros((t, k, n, msg_dim), f32)  # central Gaussian sample (rl)
        self.keep = np.ones((t, k, n), f32)  # message not dropped
        self.actions = np.zeros((t, k, n, *action_shape), np.int64 if discrete else f32)
        self.logp = np.zeros((t, k, n), f32)
        self.values = np.zeros((t, k, n), f32)
        self.c_logp = np.zeros((t, k, n), f32)
        self.c_values = np.zeros((t, k, n), f32)
        self.rewards = np.zeros((t, k, n), f32)
        self.terminated = np.zeros((t, k, n), bool)
        self.truncated = np.zeros((t, k, n), bool)
        self.active = np.zeros((t, k, n), bool)
        self.reset = np.zeros((t, k, n), bool)  # the copy was reset after this step
        self.final_values = np.zeros((t, k, n), f32)  # V(final_obs) where reset
        self.c_final_values = np.zeros((t, k, n), f32)

    def flat(self, name: str) -> np.ndarray:
        a = getattr(self, name)
        return a.reshape(self.t * self.k, *a.shape[2:])
