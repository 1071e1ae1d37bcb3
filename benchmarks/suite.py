"""`hammer bench` without a subcommand: the whole-system figures in one run on this machine.

Raw env stepping (the ceiling), the in-process trainer, the distributed runtime (`hammer up`),
control-loop latency p50/p99 for N=3 and N=5 next to the loop's floor on this machine (the same
topology with no work in any role, `hammer bench loop-floor`), and peak RSS per role process;
printed as a table with ratios and written as JSON (with the date and the machine) so runs can be
compared over time.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import psutil


def machine() -> dict:
    return {"hostname": platform.node(), "cpu_count": os.cpu_count(), "cpu": platform.processor() or platform.machine(),
            "memory_gib": round(psutil.virtual_memory().total / 2**30, 1), "python": platform.python_version(),
            "platform": platform.platform()}


def _floor(preset: str, steps: int = 300) -> dict:
    """The loop-floor p50 (ms) for this preset's N, K, observation and message sizes."""
    from hammer.benchmarks.loop_floor import measure
    from hammer.envs.registry import make_vec_env
    from hammer.learning.config import merge_config

    cfg = merge_config(preset, None, [], {"variant": "hammer", "central_mode": "backprop"})
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    d = env.spec.obs_dim
    env.close()
    kw = {"k": cfg.num_envs, "n": cfg.n_agents, "d": d, "m": cfg.effective_msg_dim, "steps": steps}
    typed, raw = measure("split", True, **kw), measure("split", False, **kw)
    return {"floor_ms_p50_typed": typed.p50_us / 1e3, "floor_ms_p99_typed": typed.p99_us / 1e3,
            "floor_ms_p50_raw": raw.p50_us / 1e3, "floor_ms_p99_raw": raw.p99_us / 1e3}


def run_suite(episodes: int, out_dir: Path | None) -> dict:
    from hammer.benchmarks.runtime import bench_runtime, same_label
    from rich.console import Console
    from rich.table import Table

    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    rows = bench_runtime(["cn3", "cn5"], episodes)
    for r in rows:
        r.update(_floor(r["preset"]))
    t = Table(title=f"hammer bench ({episodes} episodes per runner, hammer/backprop, {os.cpu_count()} cores)")
    for col in ("preset", "raw env", "train", "up", "up lag-1", "train/raw", "up/train", "up lag-1/train",
                "loop p50 ms", "loop p99 ms", "floor p50 ms typed/raw", "RSS MiB (local/central/env/learner)", "up==train"):
        t.add_column(col, justify="right")
    for r in rows:
        rss = r["rss_mib"]
        t.add_row(r["preset"], f"{r['raw_env_steps_per_s']:,.0f}", f"{r['train_env_steps_per_s']:,.0f}",
                  f"{r['up_env_steps_per_s']:,.0f}", f"{r['up_lag1_env_steps_per_s']:,.0f}",
                  f"{r['ratio_train_over_raw']:.3f}", f"{r['ratio_up_over_train']:.2f}",
                  f"{r['ratio_up_lag1_over_train']:.2f}", f"{r['step_latency_ms_p50']:.2f}",
                  f"{r['step_latency_ms_p99']:.2f}",
                  f"{r['floor_ms_p50_typed']:.2f} / {r['floor_ms_p50_raw']:.2f}",
                  " / ".join(f"{rss.get(k, float('nan')):.0f}" for k in ("local", "central", "env", "learner")),
                  same_label(r))
    console = Console(width=180)
    console.print(t)
    console.print("env-steps/s = env-copy steps per second, PPO updates included for train and up; "
                    "up lag-1 = `hammer up --runtime max_policy_lag=1`; loop latency = observations out -> every action back, per vector step; "
                  "floor = the same loop with no work in any role (`hammer bench loop-floor`): no code in the roles can go below it.")
    result = {"started": started, "machine": machine(), "episodes": episodes, "rows": rows}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / f"bench-{time.strftime('%Y%m%d-%H%M%S')}.json"
        path.write_text(json.dumps(result, indent=1))
        console.print(f"wrote {path}")
    return result
