"""`hammer bench runtime`: the distributed runtime against the in-process trainer, same config, same run.

For each preset it trains the same number of episodes twice: in-process (`learning.trainer`) and
as separate processes over Zenoh (`deploy.up.launch`), and reports env-steps/s of both (PPO updates
included in both), their ratio, and the control-loop latency of the distributed step (env host
publishes observations -> every action is back), p50 and p99.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import psutil


def _train(cfg, path: Path) -> dict:
    from learning.rundir import RunDir
    from learning.trainer import train

    return train(cfg, RunDir.create(path, cfg), tensorboard=False)


def bench_runtime(presets: list[str], episodes: int, variant: str = "hammer", central_mode: str = "backprop",
                  out: Path | None = None) -> list[dict]:
    from deploy.settings import RuntimeSettings
    from deploy.up import launch
    from learning.config import merge_config

    rows = []
    with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
        root = Path(out) if out is not None else Path(tmp)
        for preset in presets:
            cfg = merge_config(preset, overrides=[f"episodes={episodes}", f"variant={variant}",
                                                  f"central_mode={central_mode}"])
            load0 = os.getloadavg()[0]
            t0 = time.perf_counter()
            tr = _train(cfg, root / f"{preset}-train")
            t_train = time.perf_counter() - t0
            settings = RuntimeSettings(run_id=f"bench-{preset}-{os.getpid()}")
            res = launch(cfg, settings, root / f"{preset}-up")
            s = res.summary
            rows.append({
                "preset": preset, "variant": variant, "central_mode": central_mode, "episodes": episodes,
                "num_envs": cfg.num_envs, "n_agents": cfg.n_agents,
                "train_env_steps_per_s": tr["env_steps_per_s_this_session"], "train_wall_s": t_train,
                "up_env_steps_per_s": s["env_steps_per_s"], "up_wall_s": res.wall_time,
                "ratio_up_over_train": s["env_steps_per_s"] / tr["env_steps_per_s_this_session"],
                "step_latency_ms_p50": s["step_latency_ms_p50"], "step_latency_ms_p99": s["step_latency_ms_p99"],
                "same_metrics": _same_metrics(root / f"{preset}-train", root / f"{preset}-up"),
                "loadavg_1m_before": load0, "cpu_count": psutil.cpu_count(),
            })
    return rows


def _same_metrics(a: Path, b: Path) -> bool:
    import csv

    def col(p: Path) -> list[str]:
        with open(p / "metrics.csv", newline="") as f:
            return [r["paper_metric"] for r in csv.DictReader(f)]

    return col(a) == col(b)
