"""PPO maths, written once and free of trainer state.

The in-process trainer and (later) the distributed learner processes both call these pure
functions; `PPOUpdater` only wraps one optimiser with its learning rate and grad-norm clip.

Shapes: time first, then any batch shape, e.g. (T, K, N). `mask` is 1 where the agent was present
and acted; absent entries get zero advantage and are left out of every mean.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch


def next_values(values: np.ndarray, last_values: np.ndarray, final_values: np.ndarray,
                reset: np.ndarray) -> np.ndarray:
    """V(s_{t+1}) for every step of a rollout.

    values (T, ...) are V(s_t); last_values (...) is V of the observation after the rollout;
    where the env copy was reset after step t (`reset[t]`), s_{t+1} is a new episode's first
    observation, so use final_values[t] = V(final_obs_t) instead (needed for truncation bootstraps).
    """
    nxt = np.concatenate([values[1:], last_values[None]], axis=0)
    return np.where(reset, final_values, nxt)


def gae(rewards: np.ndarray, values: np.ndarray, next_vals: np.ndarray, terminated: np.ndarray,
        dones: np.ndarray, gamma: float, lam: float, mask: np.ndarray | None = None
        ) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation with time-limit bootstrapping.

        delta_t = r_t + gamma * V(s_{t+1}) * (1 - terminated_t) - V(s_t)
        A_t     = delta_t + gamma * lam * (1 - done_t) * A_{t+1}

    terminated: the task ended the agent's episode (no future value). done = terminated or
    truncated: the agent's episode ended, so the recursion does not leak into the next episode;
    a truncated step still bootstraps from V(final_obs) through next_vals.
    Returns (advantages, returns = advantages + values), both zero where mask is 0.
    """
    t_len = rewards.shape[0]
    m = np.ones_like(rewards, dtype=np.float32) if mask is None else mask.astype(np.float32)
    not_term = 1.0 - terminated.astype(np.float32)
    not_done = 1.0 - dones.astype(np.float32)
    adv = np.zeros_like(rewards, dtype=np.float32)
    last = np.zeros(rewards.shape[1:], dtype=np.float32)
    for t in reversed(range(t_len)):
        delta = rewards[t] + gamma * next_vals[t] * not_term[t] - values[t]
        last = (delta + gamma * lam * not_done[t] * last) * m[t]
        adv[t] = last
    return adv, (adv + values) * m


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


def normalize_advantages(adv: torch.Tensor, mask: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Zero mean, unit std over the present entries (absent ones stay 0)."""
    mean = masked_mean(adv, mask)
    var = masked_mean((adv - mean) ** 2, mask)
    return (adv - mean) / (var.sqrt() + eps) * mask


def clipped_policy_loss(new_logp: torch.Tensor, old_logp: torch.Tensor, adv: torch.Tensor, clip: float,
                        mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """-E[min(r A, clip(r, 1-eps, 1+eps) A)] with r = exp(new - old); also KL and clip-fraction stats."""
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip))
    with torch.no_grad():
        stats = {
            "approx_kl": float(masked_mean((ratio - 1) - log_ratio, mask)),
            "clipfrac": float(masked_mean(((ratio - 1).abs() > clip).float(), mask)),
        }
    return masked_mean(loss, mask), stats


def value_loss(new_values: torch.Tensor, returns: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """0.5 * E[(V - R)^2] over present entries."""
    return 0.5 * masked_mean((new_values - returns) ** 2, mask)


def minibatch_indices(n_rows: int, minibatches: int, rng: np.random.Generator) -> list[np.ndarray]:
    """One epoch's shuffled split of rows 0..n_rows-1 into `minibatches` near-equal parts."""
    return np.array_split(rng.permutation(n_rows), minibatches)


class PPOUpdater:
    """One network's Adam optimiser with its own learning rate and grad-norm clip."""

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, max_grad_norm: float) -> None:
        self.params = list(params)
        self.optimizer = torch.optim.Adam(self.params, lr=lr, eps=1e-5, foreach=True)
        self.max_grad_norm = max_grad_norm

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> float:
        """Clip this network's gradient norm, step; returns the norm before clipping."""
        norm = torch.nn.utils.clip_grad_norm_(self.params, self.max_grad_norm)
        self.optimizer.step()
        return float(norm)
