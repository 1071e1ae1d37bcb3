"""PPO maths, written once and free of trainer state.

`TeamLearner.learn` (the in-process trainer's and the learner process's update) calls these pure
functions; `PPOUpdater` only wraps one optimiser with its learning rate and grad-norm clip.

Shapes: time first, then any batch shape, e.g. (T, K, N). `mask` is 1 where the agent was present
and acted; absent entries get zero advantage and are left out of every mean. The torch losses also
take mask=None for "all present" (cooperative navigation), which saves the masking ops.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import numpy as np
import torch
from hammer.learning.fused_adam import fused_adam_step


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


def masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean over the entries where mask is 1; mask None means every entry is present (one op)."""
    if mask is None:
        return x.mean()
    return (x * mask).sum() / mask.sum().clamp_min(1.0)


def normalize_advantages(adv: torch.Tensor, mask: torch.Tensor | None, eps: float = 1e-8) -> torch.Tensor:
    """Zero mean, unit std over the present entries (absent ones stay 0)."""
    mean = masked_mean(adv, mask)
    var = masked_mean((adv - mean) ** 2, mask)
    out = (adv - mean) / (var.sqrt() + eps)
    return out if mask is None else out * mask


def clipped_surrogate(new_logp: torch.Tensor, old_logp: torch.Tensor, adv: torch.Tensor, clip: float,
                      mask: torch.Tensor | None, stats: bool = True
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """PPO's clipped policy loss -E[min(r A, clip(r, 1-eps, 1+eps) A)] with r = exp(new - old).

    Returns (loss, approx_kl, clipfrac) as tensors (the statistics None unless `stats`): the
    minibatch loop keeps its statistics as tensors and converts them once per update (a float()
    per statistic per minibatch costs more than the maths)."""
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip))
    approx_kl = clipfrac = None
    if stats:
        with torch.no_grad():
            r = ratio.detach()
            approx_kl = masked_mean((r - 1) - log_ratio.detach(), mask)
            clipfrac = masked_mean(((r - 1).abs() > clip).float(), mask)
    return masked_mean(loss, mask), approx_kl, clipfrac


def value_loss(new_values: torch.Tensor, returns: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """0.5 * E[(V - R)^2] over present entries."""
    return 0.5 * masked_mean((new_values - returns) ** 2, mask)


def minibatch_indices(n_rows: int, minibatches: int, rng: np.random.Generator) -> list[np.ndarray]:
    """One epoch's shuffled split of rows 0..n_rows-1 into `minibatches` near-equal parts."""
    return np.array_split(rng.permutation(n_rows), minibatches)


def minibatch_slices(shuffled: dict[str, torch.Tensor], sizes: list[int], dim: int = 0
                     ) -> Iterator[dict[str, torch.Tensor]]:
    """The minibatches of one epoch whose rows are already in the epoch's shuffled order along `dim`:
    consecutive slices of `sizes` rows (views, no gather per minibatch). The one minibatch iterator
    of the eager, compiled (dim 0) and seed-batched (dim 1: the seeds lead) updates."""
    start = 0
    for n in sizes:
        yield {k: v.narrow(dim, start, n) for k, v in shuffled.items()}
        start += n


def clip_coefficient(norm: torch.Tensor, max_norm: float) -> torch.Tensor:
    """The grad-norm clip rule of every update (eager, compiled, seed-batched):
    `torch.nn.utils.clip_grad_norm_`'s scale min(1, max_norm / (norm + 1e-6))."""
    return (max_norm / (norm + 1e-6)).clamp(max=1.0)


def clip_grad_norm(grads: list[torch.Tensor], max_norm: float, stacked: bool = False) -> torch.Tensor:
    """Scale `grads` in place by `clip_coefficient` of their total L2 norm; returns the norm before
    clipping (0-d). `stacked`: every tensor is (S, ...), slice s being network s's gradient (a seed
    batch), and each slice is clipped by its own norm; returns the (S,) norms."""
    if not stacked:
        # three foreach ops, without clip_grad_norm_'s per-call grouping of the tensors
        norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))
        torch._foreach_mul_(grads, clip_coefficient(norm, max_norm))
        return norm
    s = grads[0].shape[0]
    per_tensor = torch.stack([torch.linalg.vector_norm(g.reshape(s, -1), dim=1) for g in grads], dim=1)
    norm = torch.linalg.vector_norm(per_tensor, dim=1)
    scale = clip_coefficient(norm, max_norm)
    for g in grads:
        g.mul_(scale.reshape(s, *([1] * (g.dim() - 1))))
    return norm


def clip_and_step(optimizer: torch.optim.Adam, params: list[torch.Tensor], grads: list[torch.Tensor],
                  max_norm: float, stacked: bool = False) -> torch.Tensor:
    """The optimiser step of the eager and the seed-batched updates: clip `grads` (`clip_grad_norm`),
    then one Adam step of `params` through torch's fused kernel (`fused_adam_step`). Returns the
    norm(s) before clipping. The compiled update traces the same rule and torch's own Adam maths
    instead (`compiled_update.traced_clip_and_step`): the fused kernel mutates its state in a way
    torch.compile cannot functionalize."""
    norm = clip_grad_norm(grads, max_norm, stacked)
    fused_adam_step(optimizer, params, grads)
    return norm


class PPOUpdater:
    """One network's Adam optimiser with its own learning rate and grad-norm clip.

    The `torch.optim.Adam` object owns the state, so a checkpoint is its `state_dict`. The step
    runs through `fused_adam_step`: the same fused kernel as `optimizer.step()`, with less
    per-call overhead, which is what an update of these small networks spends its time on.
    """

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, max_grad_norm: float,
                 name: str = "local") -> None:
        self.name = name  # the network: its statistics are `<name>/...` (local, central)
        self.params = list(params)
        self.optimizer = torch.optim.Adam(self.params, lr=lr, eps=1e-5, fused=True)
        self.max_grad_norm = max_grad_norm

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def clip_and_step(self) -> torch.Tensor:
        """Clip this network's gradient norm, take one Adam step; returns the norm before clipping
        as a 0-d tensor."""
        params = [p for p in self.params if p.grad is not None]
        if not params:
            return torch.zeros((), device=self.params[0].device)
        return clip_and_step(self.optimizer, params, [p.grad for p in params], self.max_grad_norm)


class UpdateStats:
    """The statistics of an update's last epoch by name, summed over its minibatches as tensors
    (no host sync per minibatch) and turned into floats once: their means (a statistic that is a
    vector, one value per seed of a seed batch, gives a list)."""

    def __init__(self) -> None:
        self.names: list[str] = []
        self.total: torch.Tensor | None = None
        self.n = 0

    def add(self, stats: dict[str, torch.Tensor]) -> None:
        st = torch.stack(list(stats.values()))
        if self.total is None:
            self.names, self.total = list(stats), st
        else:
            self.total = self.total + st
        self.n += 1

    def means(self) -> dict[str, float]:
        assert self.total is not None, "an update with no minibatch"
        return dict(zip(self.names, (self.total / self.n).tolist(), strict=True))
