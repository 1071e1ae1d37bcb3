"""The warehouse's speed in the loop (docs/results/plan-warehouse.md, step 1).

Three figures per team size, each with the machine's load and the cores our processes got, because
this machine is shared and the wall-clock speed moves with what else runs:
  env      raw env-steps/s of K copies through `make_vec_env` (in-process, and 2 slices with the
           parent stepping one), uniform-random actions, auto-resets included;
  train    `hammer train` env-steps/s with its PPO updates (the preset, one process, eager torch);
  budget   the wall time 1M and 5M env steps imply, at the measured speed and per full core.

    PYTHONPATH=. .venv/bin/python -m hammer.benchmarks.bench_rware [--n 2 4] [--seconds 8] [--episodes 48]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
from hammer.envs.registry import make_vec_env


def _own_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and its children so far."""
    total = 0.0
    for p in [psutil.Process(), *psutil.Process().children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            total += t.user + t.system
    return total


def env_phase(n: int, num_envs: int, workers: int, seconds: float, seed: int = 0) -> dict:
    """Step K copies of rware-tiny-<n>ag with random actions for about `seconds`."""
    env = make_vec_env(f"rware-tiny-{n}ag", n, num_envs, workers=workers, parent_slice=workers > 0)
    try:
        env.reset(seed)
        rng = np.random.default_rng(seed)
        steps, load0 = 0, os.getloadavg()[0]
        c0, t0 = _own_cpu_seconds(), time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            env.step(rng.integers(0, 5, (num_envs, n)))
            steps += 1
        dt, cpu = time.perf_counter() - t0, _own_cpu_seconds() - c0
    finally:
        env.close()
    sps = steps * num_envs / dt
    return {"n": n, "K": num_envs, "workers": workers, "env_steps_per_s": sps, "cores": cpu / dt,
            "env_steps_per_cpu_s": steps * num_envs / max(cpu, 1e-9), "load1": load0}


def train_phase(n: int, variant: str, episodes: int, seed: int = 0) -> dict:
    """`hammer train` on the preset for `episodes` episodes (16 copies x 500 steps each)."""
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train

    cfg = merge_config(preset=f"rware-tiny-{n}ag", extra={"variant": variant, "episodes": episodes, "seed": seed})
    with tempfile.TemporaryDirectory() as tmp:
        load0 = os.getloadavg()[0]
        c0, t0 = _own_cpu_seconds(), time.perf_counter()
        summary = train(cfg, RunDir.create(Path(tmp) / "run", cfg), tensorboard=False)
        dt, cpu = time.perf_counter() - t0, _own_cpu_seconds() - c0
    steps = summary["env_steps"]
    return {"n": n, "variant": variant, "env_steps": steps, "env_steps_per_s": steps / dt, "cores": cpu / dt,
            "env_steps_per_cpu_s": steps / max(cpu, 1e-9), "load1": load0}


def budget(sps: float) -> dict:
    """Hours for 1M and 5M env steps at `sps` env-steps/s."""
    return {f"{m}M_h": m * 1e6 / sps / 3600 for m in (1, 5)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--num-envs", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--episodes", type=int, default=48, help="per train phase (16 copies: 3 episodes each)")
    ap.add_argument("--variants", nargs="+", default=["hammer", "il"])
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    out: dict = {"date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "cpus": os.cpu_count(),
                 "env": [], "train": []}
    for n in a.n:
        for workers in (0, 2):
            r = env_phase(n, a.num_envs, workers, a.seconds)
            out["env"].append(r)
            print(f"env   N={n} K={a.num_envs} workers={workers}: {r['env_steps_per_s']:7.0f} env-steps/s, "
                  f"{r['env_steps_per_cpu_s']:7.0f} per CPU-s, cores {r['cores']:.2f}, load {r['load1']:.1f}",
                  flush=True)
        for variant in a.variants:
            r = train_phase(n, variant, a.episodes)
            r.update(budget(r["env_steps_per_s"]), **{f"{k}_per_core": v for k, v in
                                                      budget(r["env_steps_per_cpu_s"]).items()})
            out["train"].append(r)
            print(f"train N={n} {variant:7s}: {r['env_steps_per_s']:7.0f} env-steps/s, "
                  f"{r['env_steps_per_cpu_s']:7.0f} per CPU-s, cores {r['cores']:.2f}, load {r['load1']:.1f}; "
                  f"1M {r['1M_h']:.2f} h, 5M {r['5M_h']:.2f} h (per full core {r['1M_h_per_core']:.2f} / "
                  f"{r['5M_h_per_core']:.2f} h)", flush=True)
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
