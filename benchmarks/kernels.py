"""`hammer bench kernels`: how fast one training update could be with torch's own CPU kernels.

The target for `hammer train --set compile=true` is a multiple of JaxMARL's rate at the matched cn3
schedule (docs/fast-envs.md). Before chasing Python overhead, this asks what the arithmetic alone costs: it times, one core, at
the exact shapes of a run (a minibatch's rows through every Linear layer of the local policy and
critic, and of the central network where there is one), the matmuls of a forward and a backward
(forward x W^T, then dY W and dY^T x), each hidden layer's tanh as the trainer computes it (torch's
tanh below `networks._FAST_TANH_MIN` elements, 2 sigmoid(2x) - 1 above) and its backward; the same
for acting (K x N rows per vector step). Summed over an update's minibatch steps and vector steps,
that is a floor: no Python, no optimiser, no loss, no sampling, no copying; only the layers.

Next to it, measured in the same run: the real update (`TeamLearner.learn`) and collection
(`Trainer._collect`, the env step timed apart), eager or compiled. If even the floor's rate is
below a target, no removal of overhead reaches it with these kernels (see docs/fast-envs.md).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from hammer.learning.config import merge_config
from hammer.learning.networks import _FAST_TANH_MIN
from hammer.learning.rundir import RunDir
from hammer.learning.sampling import env_reset_seed
from hammer.learning.trainer import Trainer
from torch import nn


def _time(fn, repeats: int) -> float:
    """Seconds per call, the best of three timed loops (the machine is shared)."""
    for _ in range(max(repeats // 10, 5)):
        fn()
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = min(best, (time.perf_counter() - t) / repeats)
    return best


def _tanh(x: torch.Tensor) -> torch.Tensor:
    if x.numel() < _FAST_TANH_MIN:
        return torch.tanh(x)
    return (x * 2.0).sigmoid_().mul_(2.0).sub_(1.0)


def layer_costs(linears: list[nn.Linear], rows: int, backward: bool, repeats: int,
                dtype: torch.dtype = torch.float32) -> dict[str, float]:
    """Seconds of one pass of `rows` rows through these layers (tanh after every layer but the
    last): forward matmuls, forward tanh, and with `backward` the two backward matmuls per layer
    and tanh's backward; all in `dtype` (bfloat16: what autocast runs under precision=bf16)."""
    out = {"matmul": 0.0, "tanh": 0.0}
    for i, lin in enumerate(linears):
        w, b = lin.weight.detach().to(dtype), lin.bias.detach().to(dtype)
        x = torch.randn(rows, w.shape[1], dtype=dtype)
        dy = torch.randn(rows, w.shape[0], dtype=dtype)
        out["matmul"] += _time(lambda w=w, b=b, x=x: torch.addmm(b, x, w.t()), repeats)
        if backward:
            out["matmul"] += _time(lambda w=w, dy=dy: dy @ w, repeats)  # dL/dx
            out["matmul"] += _time(lambda x=x, dy=dy: dy.t() @ x, repeats)  # dL/dW
        if i < len(linears) - 1:
            h = torch.randn(rows, w.shape[0], dtype=dtype)
            out["tanh"] += _time(lambda h=h: _tanh(h), repeats)
            if backward:
                y = torch.tanh(h)
                out["tanh"] += _time(lambda y=y, dy=dy: torch.ops.aten.tanh_backward(dy, y), repeats)
    return out


def _nets(team) -> list[tuple[str, list[nn.Linear], int]]:
    """(name, its Linear layers, rows per sample) of every network an update trains: the local
    policy's (one row per agent) and the central network's (one row per env copy)."""
    nets = []
    for name, net, per in (("local", team.local, team.n), ("central", team.central, 1)):
        if net is None:
            continue
        for sub, mod in net.named_children():
            lins = [m for m in mod.modules() if isinstance(m, nn.Linear)]
            if lins:
                nets.append((f"{name}.{sub}", lins, per))
    return nets


def measure(variant: str = "il", compile_: bool = False, updates: int = 30, repeats: int = 300,
            central_mode: str = "rl", precision: str = "fp32") -> dict[str, Any]:
    """The floor and the real thing for one cn3 config, one core. precision=bf16: the update's
    layers in bfloat16 (the acting floor stays float32, as acting does)."""
    torch.set_num_threads(1)
    extra = {"variant": variant} | ({"central_mode": central_mode} if variant == "hammer" else {})
    cfg = merge_config("cn3", extra=extra, overrides=["episodes=1000000", "torch_threads=1",
                                                      f"compile={str(compile_).lower()}", f"precision={precision}"])
    update_dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, RunDir.create(Path(tmp) / "run", cfg), tensorboard=False)
        samples = cfg.num_envs * cfg.rollout_steps
        mb_samples = samples // cfg.minibatches
        steps_per_update = cfg.epochs * cfg.minibatches
        floor_update = floor_act = 0.0
        parts: dict[str, float] = {}
        for name, lins, per in _nets(tr.team):
            upd = layer_costs(lins, mb_samples * per, backward=True, repeats=repeats, dtype=update_dtype)
            act = layer_costs(lins, cfg.num_envs * per, backward=False, repeats=repeats)
            for what, s in upd.items():
                parts[f"update.{name}.{what}"] = round(s * steps_per_update * 1e3, 3)
            for what, s in act.items():
                parts[f"act.{name}.{what}"] = round(s * cfg.rollout_steps * 1e3, 3)
            floor_update += sum(upd.values()) * steps_per_update
            floor_act += sum(act.values()) * cfg.rollout_steps
        # the real loop: collection (env step apart) and the update
        env_s = [0.0]
        step = tr.env.step

        def timed_step(a):
            t = time.perf_counter()
            r = step(a)
            env_s[0] += time.perf_counter() - t
            return r

        tr.env.step = timed_step
        tr.start()
        obs, _ = tr.env.reset(env_reset_seed(cfg.seed, 0))
        prev = tr.team.zero_prev_actions(cfg.num_envs)
        collect = learn = 0.0
        warm = 3
        for u in range(warm + updates):
            if u == warm:
                collect = learn = env_s[0] = 0.0
            t0 = time.perf_counter()
            obs, prev, _ = tr._collect(obs, prev)
            t1 = time.perf_counter()
            tr.learner.learn(obs, prev, tr.update, tr.vector_step)
            tr.update += 1
            collect, learn = collect + t1 - t0, learn + time.perf_counter() - t1
        tr.env.close()
    ms = 1e3 / updates
    env_ms = env_s[0] * ms
    real = collect * ms + learn * ms
    floor = env_ms + (floor_act + floor_update) * 1e3
    return {
        "variant": variant + (f"-{central_mode}" if variant == "hammer" else ""), "compile": compile_,
        "precision": precision,
        "schedule": f"{cfg.num_envs} envs x {cfg.rollout_steps} steps, {cfg.epochs} epochs x {cfg.minibatches} "
                    f"minibatches of {mb_samples} samples",
        "update_ms": round(learn * ms, 2), "update_floor_ms": round(floor_update * 1e3, 2),
        "collect_ms": round(collect * ms, 2), "env_ms": round(env_ms, 2),
        "act_floor_ms": round(floor_act * 1e3, 2),
        "env_steps_per_s": round(samples / real * 1e3), "floor_env_steps_per_s": round(samples / floor * 1e3),
        "parts_ms": parts, "load_1min": round(os.getloadavg()[0], 2),
    }
