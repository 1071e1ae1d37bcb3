"""`hammer bench runtime`: the distributed runtime against the in-process trainer, same config, same run.

`bench_runtime` trains the same number of episodes twice per preset: in-process
(`learning.trainer`) and as separate processes over Zenoh (`deploy.launcher.launch`), and reports the
env-steps/s of both (PPO updates included in both), their ratio, the control-loop latency of the
distributed step (env host publishes observations -> every action is back) p50/p99, and the peak
resident memory of every role process. `raw_env_steps` measures the environment alone (the
ceiling).
"""

from __future__ import annotations

import csv
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil


def raw_env_steps(env_name: str, n_agents: int, num_envs: int, seconds: float = 2.0) -> float:
    """Env-copy steps per second of the bare VecEnv with uniform random actions."""
    from hammer.envs.registry import make_vec_env

    env = make_vec_env(env_name, n_agents, num_envs)
    spec = env.spec
    rng = np.random.default_rng(0)
    env.reset(0)
    if spec.discrete:
        acts = [rng.integers(0, spec.action_dim, (num_envs, n_agents)) for _ in range(64)]
    else:
        acts = [rng.uniform(-1, 1, (num_envs, n_agents, spec.action_dim)).astype(np.float32) for _ in range(64)]
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        env.step(acts[steps % 64])
        steps += 1
    rate = steps * num_envs / (time.perf_counter() - t0)
    env.close()
    return rate


def _train(cfg, path: Path) -> dict:
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train

    return train(cfg, RunDir.create(path, cfg), tensorboard=False)


def _same_metrics(a: Path, b: Path, tol: float = 1e-5) -> bool:
    """The same episodes with the same paper metric, to float tolerance: the agents' numpy forward
    matches the trainer's torch forward to ~1e-7, not bit for bit (docs/runtime.md)."""
    def col(p: Path) -> list[float]:
        with open(p / "metrics.csv", newline="") as f:
            return [float(r["paper_metric"]) for r in csv.DictReader(f)]

    x, y = col(a), col(b)
    return len(x) == len(y) and all(abs(u - v) <= tol for u, v in zip(x, y, strict=True))


def same_label(row: dict) -> str:
    """up == train for a bench row, and if not, whether deadlines were missed (then up legitimately
    differs: a fallback message or a default action is not what the trainer did)."""
    if row["same_metrics"]:
        return "True"
    return f"False ({row.get('up_msg_fallback_copies')} fallbacks, {row.get('up_default_actions')} defaults)"


class RssSampler:
    """Peak RSS (MiB) of every role process, sampled from the launcher's tick."""

    def __init__(self) -> None:
        self.peak: dict[str, float] = {}

    def __call__(self, sup, board) -> None:
        for name in list(sup.roles):
            pid = sup.pid(name)
            if pid is None:
                continue
            try:
                rss = psutil.Process(pid).memory_info().rss / 2**20
            except psutil.Error:
                continue
            kind = "local" if name.startswith("local") else name  # local-i or a pool locals-a-b
            self.peak[kind] = max(self.peak.get(kind, 0.0), rss)


def bench_runtime(presets: list[str], episodes: int, variant: str = "hammer", central_mode: str = "backprop",
                  out: Path | None = None, raw: bool = True, lagged: bool = True) -> list[dict]:
    """One row per preset. `lagged`: also run `hammer up` with max_policy_lag=1 (the env host
    collects the next rollout while the learner updates), reported as up_lag1_*."""
    from hammer.deploy.launcher import launch
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    rows = []
    with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
        root = Path(out) if out is not None else Path(tmp)
        for preset in presets:
            cfg = merge_config(preset, overrides=[f"episodes={episodes}", f"variant={variant}",
                                                  f"central_mode={central_mode}"])
            load0 = os.getloadavg()[0]
            raw_rate = raw_env_steps(cfg.env, cfg.n_agents, cfg.num_envs) if raw else float("nan")
            t0 = time.perf_counter()
            tr = _train(cfg, root / f"{preset}-train")
            t_train = time.perf_counter() - t0
            settings = RuntimeSettings(run_id=f"bench-{preset}-{os.getpid()}")
            rss = RssSampler()
            res = launch(cfg, settings, root / f"{preset}-up", chaos=rss)
            s = res.summary
            train_rate = tr["env_steps_per_s_this_session"]
            lag = {}
            if lagged:
                settings = RuntimeSettings(run_id=f"bench-{preset}-lag1-{os.getpid()}", max_policy_lag=1)
                res1 = launch(cfg, settings, root / f"{preset}-up-lag1")
                s1 = res1.summary
                lag = {"up_lag1_env_steps_per_s": s1["env_steps_per_s"],
                       "ratio_up_lag1_over_train": s1["env_steps_per_s"] / train_rate,
                       "up_lag1_step_latency_ms_p50": s1["step_latency_ms_p50"],
                       "up_lag1_step_latency_ms_p99": s1["step_latency_ms_p99"],
                       "up_lag1_final_paper_metric": s1.get("final_paper_metric_last500")}
            rows.append({
                "preset": preset, "variant": variant, "central_mode": central_mode, "episodes": episodes,
                "num_envs": cfg.num_envs, "n_agents": cfg.n_agents, "rollout_steps": cfg.rollout_steps,
                "raw_env_steps_per_s": raw_rate,
                "train_env_steps_per_s": train_rate, "train_wall_s": t_train,
                "up_env_steps_per_s": s["env_steps_per_s"], "up_wall_s": res.wall_time,
                "ratio_train_over_raw": train_rate / raw_rate if raw else float("nan"),
                "ratio_up_over_train": s["env_steps_per_s"] / train_rate,
                "step_latency_ms_p50": s["step_latency_ms_p50"], "step_latency_ms_p99": s["step_latency_ms_p99"],
                **lag,
                "rss_mib": {k: round(v, 1) for k, v in sorted(rss.peak.items())},
                "same_metrics": _same_metrics(root / f"{preset}-train", root / f"{preset}-up"),
                # Under load a message or action can miss its deadline; then up legitimately differs.
                "up_msg_fallback_copies": s.get("links", {}).get("msg_fallback_copies"),
                "up_default_actions": s.get("links", {}).get("default_actions"),
                "loadavg_1m_before": load0, "loadavg_1m_after": os.getloadavg()[0], "cpu_count": psutil.cpu_count(),
            })
    return rows
