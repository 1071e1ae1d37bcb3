"""An Adam step that calls torch's fused Adam kernel directly (the CPU one, or the CUDA one for
parameters on a GPU: `RunConfig.device`).

The networks are tiny and a PPO update makes epochs × minibatches optimiser steps per network, so
per-call overhead, not arithmetic, is the cost, and most of `Adam(fused=True).step()` is Python
bookkeeping around one kernel. `fused_adam_step` calls that same kernel (`torch._fused_adam_`, a
private op) on the state the `torch.optim.Adam` object owns: the result is bit-identical to
`optimizer.step()` (tests/test_learning_ppo.py checks) and checkpoints (`state_dict`) are unchanged.
"""

from __future__ import annotations

import torch


def fused_adam_step(optimizer: torch.optim.Adam, params: list[torch.nn.Parameter],
                    grads: list[torch.Tensor]) -> None:
    """`optimizer.step()` for `params` (the parameters that have a gradient, `grads`).

    Falls back to `optimizer.step()` itself where the direct call does not apply: the first step
    (it creates the state), a parameter without state yet, or a configuration other than one
    fused group of plain Adam.
    """
    group = optimizer.param_groups[0]
    states = [optimizer.state.get(p) for p in params]
    if (len(optimizer.param_groups) != 1 or not group.get("fused") or group["amsgrad"]
            or group["weight_decay"] or group["maximize"] or not all(states)):
        optimizer.step()
        return
    steps = [s["step"] for s in states]
    torch._foreach_add_(steps, 1)
    beta1, beta2 = group["betas"]
    torch._fused_adam_(params, grads, [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [],
                       steps, amsgrad=False, lr=float(group["lr"]), beta1=beta1, beta2=beta2, weight_decay=0.0,
                       eps=group["eps"], maximize=False)
