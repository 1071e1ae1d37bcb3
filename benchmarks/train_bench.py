"""`hammer bench train`: how fast the in-process trainer runs, PPO updates included.

Every figure is env-copy steps per second of the real training loop (acting, env stepping, GAE and
the PPO epochs), measured in this process, next to the 1-min load average when it was taken: on a
shared machine another busy process takes its share of every figure here.

  cn3     the preset (`hammer train --preset cn3`) on the vectorised `cn` env and on the `cn-mpe2`
          reference backend (PettingZoo, one copy at a time), same config, same run: the ratio is
          what the vectorised env buys for whole training.
  full    wall time of one whole 30,000-episode cn3 `hammer train` process (imports, TensorBoard and
          checkpoints included): measured with --full, otherwise extrapolated from a measured
          2,000-episode process (its startup + 15 x its loop time), and labelled so.
  mw3     a few PPO updates of the mw3 preset with the walkers stepped in-process and in
          `env_workers=2` subprocesses (envs/workers.py): the speed-up of the worker pool.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from hammer.learning.config import RunConfig, merge_config


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _cfg(preset: str, variant: str, central_mode: str, seed: int, **over: Any) -> RunConfig:
    sets = [f"{k}={v}" for k, v in over.items()]
    return merge_config(preset, overrides=sets, extra={"variant": variant, "central_mode": central_mode,
                                                       "seed": seed})


def time_train(cfg: RunConfig) -> dict[str, Any]:
    """One real `train` run to its episode budget in a temporary run directory (no TensorBoard).

    Returns env-steps/s of the training loop (the trainer's own figure), the whole wall time
    including startup (env, networks, optimisers, first checkpoint) and the load average.
    """
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train

    load = _load()
    with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
        t0 = time.perf_counter()
        rd = RunDir.create(Path(tmp) / "run", cfg)
        summary = train(cfg, rd, tensorboard=False)
        wall = time.perf_counter() - t0
    loop_s = summary["env_steps"] / summary["env_steps_per_s_this_session"]
    return {"env": cfg.env, "episodes": summary["episodes"], "env_steps": summary["env_steps"],
            "env_steps_per_s": summary["env_steps_per_s_this_session"], "wall_s": wall,
            "startup_s": max(wall - loop_s, 0.0), "loop_s": loop_s, "load_before": load, "load_after": _load()}


def time_updates(cfg: RunConfig, updates: int, warmup: int = 1) -> dict[str, Any]:
    """env-steps/s over `updates` rollout+PPO updates after `warmup` ones (for long-episode envs,
    where an episode budget would make the run length depend on how soon the walkers fall)."""
    from hammer.learning.run_env import make_env
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import Trainer

    load = _load()
    t0 = time.perf_counter()
    env = make_env(cfg)
    start_s = time.perf_counter() - t0
    try:
        with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
            tr = Trainer(cfg, RunDir.create(Path(tmp) / "run", cfg.model_copy(update={"episodes": 10**9})),
                         env=env, tensorboard=False)
            tr._t0 = time.perf_counter()
            obs, _ = env.reset(cfg.seed)
            prev = tr.team.zero_prev_actions(cfg.num_envs)
            for u in range(warmup):
                obs, prev, _ = tr._collect(obs, prev)
                tr.learner.learn(obs, prev, u)
            steps0, t1 = tr.env_steps, time.perf_counter()
            for u in range(warmup, warmup + updates):
                obs, prev, _ = tr._collect(obs, prev)
                tr.learner.learn(obs, prev, u)
            dt = time.perf_counter() - t1
            tr.rd.close()
    finally:
        env.close()
    return {"env": cfg.env, "env_workers": cfg.env_workers, "updates": updates, "warmup": warmup,
            "steps_per_update": cfg.num_envs * cfg.rollout_steps,
            "env_steps": tr.env_steps - steps0, "env_steps_per_s": (tr.env_steps - steps0) / dt,
            "env_start_s": start_s, "load_before": load, "load_after": _load()}


def time_cli_train(cfg: RunConfig) -> dict[str, Any]:
    """Wall time of a whole `hammer train` process (imports, startup, TensorBoard, checkpoints: what a
    user waits for) with this config's preset fields, and the loop's own env-steps/s from summary.json."""
    import subprocess
    import sys

    import yaml

    load = _load()
    with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
        conf = Path(tmp) / "config.yaml"
        conf.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
        cmd = [sys.executable, "-c", "from hammer.cli import app; app()", "train", "--config", str(conf),
               "--run-dir", str(Path(tmp) / "run"), "--quiet"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, check=False, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"hammer train failed ({proc.returncode}): {proc.stderr[-2000:]}")
        summary = json.loads((Path(tmp) / "run" / "summary.json").read_text())
    loop_s = summary["env_steps"] / summary["env_steps_per_s_this_session"]
    return {"env": cfg.env, "episodes": summary["episodes"], "env_steps": summary["env_steps"],
            "env_steps_per_s": summary["env_steps_per_s_this_session"], "wall_s": wall,
            "startup_s": max(wall - loop_s, 0.0), "loop_s": loop_s, "load_before": load, "load_after": _load()}


def run_bench(variant: str = "hammer", central_mode: str = "rl", cn_episodes: int = 300,
              mw_updates: int = 2, full: bool = False, extrapolate_from: int = 2000, seed: int = 0,
              progress: Any = None, mw_overrides: dict[str, Any] | None = None, mw_warmup: int = 1
              ) -> dict[str, Any]:
    """All figures of `hammer bench train` as one dict (see the module docstring).

    mw_overrides / mw_warmup shrink the multiwalker runs (tests only: the figures are then not the
    preset's)."""
    say = progress or (lambda msg: None)
    out: dict[str, Any] = {"variant": variant, "central_mode": central_mode, "cores": os.cpu_count(),
                           "load_start": _load()}
    say(f"cn3 on cn, {cn_episodes} episodes")
    cn = time_train(_cfg("cn3", variant, central_mode, seed, episodes=cn_episodes))
    say(f"cn3 on cn-mpe2, {cn_episodes} episodes")
    ref = time_train(_cfg("cn3", variant, central_mode, seed, episodes=cn_episodes, env="cn-mpe2"))
    out["cn3"] = {"cn": cn, "cn-mpe2": ref, "ratio": cn["env_steps_per_s"] / ref["env_steps_per_s"]}
    if full:
        say("cn3 full run, 30,000 episodes (a `hammer train` process)")
        run = time_cli_train(_cfg("cn3", variant, central_mode, seed))
        out["full"] = {**run, "extrapolated": False, "full_wall_s": run["wall_s"]}
    else:
        say(f"cn3, {extrapolate_from} episodes (a `hammer train` process, for the full-run extrapolation)")
        run = time_cli_train(_cfg("cn3", variant, central_mode, seed, episodes=extrapolate_from))
        budget = _cfg("cn3", variant, central_mode, seed).episodes
        est = run["startup_s"] + run["loop_s"] * budget / run["episodes"]
        out["full"] = {**run, "extrapolated": True, "full_wall_s": est, "full_episodes": budget}
    mw: dict[str, Any] = {}
    for workers in (0, 2):
        say(f"mw3, {mw_updates} updates, env_workers={workers}")
        cfg = _cfg("mw3", variant, central_mode, seed, env_workers=workers, **(mw_overrides or {}))
        mw[f"workers={workers}"] = time_updates(cfg, mw_updates, mw_warmup)
    mw["speedup"] = mw["workers=2"]["env_steps_per_s"] / mw["workers=0"]["env_steps_per_s"]
    out["mw3"] = mw
    out["load_end"] = _load()
    return out
