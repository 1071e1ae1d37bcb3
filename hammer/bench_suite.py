"""`hammer bench` without a subcommand: the whole-system figures in one run on this machine.

Raw env stepping (the ceiling), the in-process trainer, the distributed runtime (`hammer up`),
control-loop latency p50/p99 for N=3 and N=5, and peak RSS per role process; printed as a table
with ratios and written as JSON (with the date and the machine) so runs can be compared over time.
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


def run_suite(episodes: int, out_dir: Path | None) -> dict:
    from rich.console import Console
    from rich.table import Table

    from deploy.bench import bench_runtime

    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    rows = bench_runtime(["cn3", "cn5"], episodes)
    t = Table(title=f"hammer bench ({episodes} episodes per runner, hammer/backprop, {os.cpu_count()} cores)")
    for col in ("preset", "raw env", "train", "up", "up lag-1", "train/raw", "up/train", "up lag-1/train",
                "loop p50 ms", "loop p99 ms", "RSS MiB (local/central/env/learner)", "up==train"):
        t.add_column(col, justify="right")
    for r in rows:
        rss = r["rss_mib"]
        t.add_row(r["preset"], f"{r['raw_env_steps_per_s']:,.0f}", f"{r['train_env_steps_per_s']:,.0f}",
                  f"{r['up_env_steps_per_s']:,.0f}", f"{r['up_lag1_env_steps_per_s']:,.0f}",
                  f"{r['ratio_train_over_raw']:.3f}", f"{r['ratio_up_over_train']:.2f}",
                  f"{r['ratio_up_lag1_over_train']:.2f}", f"{r['step_latency_ms_p50']:.2f}",
                  f"{r['step_latency_ms_p99']:.2f}",
                  " / ".join(f"{rss.get(k, float('nan')):.0f}" for k in ("local", "central", "env", "learner")),
                  str(r["same_metrics"]))
    console = Console(width=180)
    console.print(t)
    console.print("env-steps/s = env-copy steps per second, PPO updates included for train and up; "
                    "up lag-1 = `hammer up --runtime max_policy_lag=1`; loop latency = observations out -> every action back, per vector step.")
    result = {"started": started, "machine": machine(), "episodes": episodes, "rows": rows}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / f"bench-{time.strftime('%Y%m%d-%H%M%S')}.json"
        path.write_text(json.dumps(result, indent=1))
        console.print(f"wrote {path}")
    return result
