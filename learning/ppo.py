"""PPO maths, written once and free of trainer state.

The in-process trainer and (later) the distributed learner processes both call these pure
functions; `PPOUpdater` only wraps one optimiser with its learning rate and grad-norm clip.

Shapes: time first, then any batch shape, e.g. (T, K, N). `mask` is 1 where the agent was present
and acted; absent entries get zero advantage and are left out of every mean. The torch losses also
take mask=None for "all present" (cooperative navigation), which saves the masking ops.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch.optim.adam import adam as functional_adam


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
    """(loss, approx_kl, clipfrac) as tensors (the statistics None unless `stats`): the minibatch
    loop keeps its statistics as tensors and converts them once per update (a float() per
    statistic per minibatch costs more than the maths)."""
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


def clipped_policy_loss(new_logp: torch.Tensor, old_logp: torch.Tensor, adv: torch.Tensor, clip: float,
                        mask: torch.Tensor | None) -> tuple[torch.Tensor, dict[str, float]]:
    """-E[min(r A, clip(r, 1-eps, 1+eps) A)] with r = exp(new - old); also KL and clip-fraction stats."""
    loss, approx_kl, clipfrac = clipped_surrogate(new_logp, old_logp, adv, clip, mask)
    return loss, {"approx_kl": float(approx_kl), "clipfrac": float(clipfrac)}


def value_loss(new_values: torch.Tensor, returns: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """0.5 * E[(V - R)^2] over present entries."""
    return 0.5 * masked_mean((new_values - returns) ** 2, mask)


def clip_by_total_norm(grads: list[torch.Tensor], max_norm: float) -> tuple[list[torch.Tensor], torch.Tensor]:
    """`PPOUpdater.clip_and_step`'s clip (clip_grad_norm_'s rule: scale by min(1, max/(norm + 1e-6)))
    for a torch.compile graph; returns the clipped gradients and the norm before clipping.

    The norm is a sum of squares instead of `_foreach_norm`: inductor fuses the sums into its own
    kernels, while `_foreach_norm` stays a loop of one library call per tensor inside the graph.
    """
    norm = torch.stack([g.pow(2).sum() for g in grads]).sum().sqrt()
    coef = (max_norm / (norm + 1e-6)).clamp(max=1.0)
    return [g * coef for g in grads], norm


def minibatch_indices(n_rows: int, minibatches: int, rng: np.random.Generator) -> list[np.ndarray]:
    """One epoch's shuffled split of rows 0..n_rows-1 into `minibatches` near-equal parts."""
    return np.array_split(rng.permutation(n_rows), minibatches)


class PPOUpdater:
    """One network's Adam optimiser with its own learning rate and grad-norm clip.

    The networks are tiny and an update makes epochs × minibatches optimiser steps per network, so
    per-call overhead, not arithmetic, is the cost. Hence the clip is three foreach ops and the
    step calls the fused CPU Adam kernel directly (the same kernel `Adam(fused=True).step()` runs,
    without ~0.25 ms of Python bookkeeping per call). The `torch.optim.Adam` object still owns
    the state, so checkpoints (`state_dict`/`load_state_dict`) are unchanged; its own `step()`
    makes the first step (it creates the state) and any step where a parameter has no state yet.
    """

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, max_grad_norm: float) -> None:
        self.params = list(params)
        self.optimizer = torch.optim.Adam(self.params, lr=lr, eps=1e-5, fused=True)
        self.max_grad_norm = max_grad_norm

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def clip_and_step(self) -> torch.Tensor:
        """Clip this network's gradient norm, step; returns the norm before clipping as a 0-d tensor."""
        params = [p for p in self.params if p.grad is not None]
        if not params:
            return torch.zeros(())
        grads = [p.grad for p in params]
        norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))
        torch._foreach_mul_(grads, (self.max_grad_norm / (norm + 1e-6)).clamp_(max=1.0))
        self._adam_step(params, grads)
        return norm

    def _adam_step(self, params: list[torch.nn.Parameter], grads: list[torch.Tensor]) -> None:
        group = self.optimizer.param_groups[0]
        states = [self.optimizer.state.get(p) for p in params]
        if (len(self.optimizer.param_groups) != 1 or not group.get("fused") or group["amsgrad"]
                or group["weight_decay"] or group["maximize"] or not all(states)):
            self.optimizer.step()  # first step, or a configuration the direct call does not cover
            return
        steps = [s["step"] for s in states]
        torch._foreach_add_(steps, 1)
        beta1, beta2 = group["betas"]
        torch._fused_adam_(params, grads, [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [],
                           steps, amsgrad=False, lr=float(group["lr"]), beta1=beta1, beta2=beta2, weight_decay=0.0,
                           eps=group["eps"], maximize=False)

    def adam_state(self) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """(exp_avgs, exp_avg_sqs, steps) of every parameter, created as Adam's first step creates
        them (zeros, a float32 0-d step) where missing. The compiled update steps these tensors in
        place, so the `torch.optim.Adam` object keeps owning the state (checkpoints unchanged)."""
        group = self.optimizer.param_groups[0]
        for p in self.params:
            if p not in self.optimizer.state:
                self.optimizer.state[p] = {"step": torch.zeros((), dtype=torch.float32),
                                           "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                           "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        if (len(self.optimizer.param_groups) != 1 or group["amsgrad"] or group["weight_decay"]
                or group["maximize"]):
            raise ValueError("compile=true supports plain Adam only (no amsgrad, weight decay, maximize)")
        states = [self.optimizer.state[p] for p in self.params]
        return [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [s["step"] for s in states]

    def traced_clip_and_step(self, params: list[torch.Tensor], grads: list[torch.Tensor],
                             exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
                             steps: list[torch.Tensor]) -> torch.Tensor:
        """`clip_and_step` written to be traced into a torch.compile graph (compile=true): the
        clip as `clip_by_total_norm`, then torch's own Adam maths in its foreach/capturable form
        (what torch traces when it compiles an Adam optimiser), stepping the state from
        `adam_state` in place. Returns the norm before clipping."""
        group = self.optimizer.param_groups[0]
        grads, norm = clip_by_total_norm(grads, self.max_grad_norm)
        beta1, beta2 = group["betas"]
        # capturable: the step count stays a tensor inside the graph (torch allows it on CPU only
        # while compiling; run eagerly, e.g. under set_stance("force_eager"), the plain form runs).
        functional_adam(params, grads, exp_avgs, exp_avg_sqs, [], steps, foreach=True,
                        capturable=torch.compiler.is_compiling(), amsgrad=False, beta1=beta1, beta2=beta2,
                        lr=group["lr"], weight_decay=0.0, eps=group["eps"], maximize=False)
        return norm

    def step(self) -> float:
        """Clip this network's gradient norm, step; returns the norm before clipping."""
        return float(self.clip_and_step())
