"""The numpy warehouse (`envs.rware_numpy`, impl=numpy) against rware's own objects (impl=rware), one run.

Two figures, each with the load average and the cores this process may use (the machine is shared;
pin it with `taskset -c 1` to measure one core):
  env    copy-steps per CPU-second of K copies of rware-tiny-<N>ag, the same uniform-random actions
         for both implementations, auto-resets included, and the ratio numpy / rware;
  train  `hammer train --preset rware-tiny-<N>ag` run twice with the same seed, impl=numpy and
         impl=rware, one after the other: wall and CPU seconds of each whole run (start-up
         included), the ratio, and whether the two metrics.csv are identical but for wall_time
         (they must be: the two implementations are the same env, tests/test_rware_exact.py).

    taskset -c 1 .venv/bin/hammer bench rware [--n 2 4] [--k 1 16 64 256] [--episodes 96] [--json out.json]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from hammer.envs.registry import make_vec_env

IMPLS = ("rware", "numpy")


def env_rate(impl: str, n: int, k: int, seconds: float, seed: int = 0) -> dict:
    """Copy-steps per CPU-second (and per wall second) of K copies stepped for about `seconds`."""
    env = make_vec_env(f"rware-tiny-{n}ag", n, k, env_kwargs={"impl": impl})
    env.reset(seed)
    acts = np.random.default_rng(seed).integers(0, 5, (64, k, n))
    env.step(acts[0])  # warm-up (first-touch allocations)
    steps, c0, t0 = 0, time.process_time(), time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 3:
        env.step(acts[steps % 64])
        steps += 1
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    env.close()
    return {"impl": impl, "n": n, "K": k, "copy_steps_per_cpu_s": steps * k / max(cpu, 1e-9),
            "copy_steps_per_s": steps * k / wall, "steps": steps}


def _metrics(run: Path) -> list[list[str]]:
    with open(run / "metrics.csv", newline="") as f:
        return [row[:-1] for row in csv.reader(f)]  # all but wall_time


def train_run(impl: str, n: int, episodes: int, seed: int, out: Path) -> dict:
    """One whole `hammer train` on the preset; wall and CPU seconds of the child process."""
    run = out / f"rware-tiny-{n}ag-{impl}"
    cmd = [sys.executable, "-m", "hammer", "train", "--preset", f"rware-tiny-{n}ag", "--variant", "hammer",
           "--seed", str(seed), "--episodes", str(episodes), "--set", f"env_kwargs.impl={impl}",
           "--run-dir", str(run), "--quiet"]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, check=False, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"bench rware: hammer train ({impl}) failed:\n{res.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"impl": impl, "n": n, "episodes": episodes, "wall_s": wall, "cpu_s": cpu, "run": run}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[2, 4], help="robots (rware-tiny-<N>ag)")
    ap.add_argument("--k", type=int, nargs="+", default=[1, 16, 64, 256], help="copies K for the env figure")
    ap.add_argument("--seconds", type=float, default=4.0, help="timed seconds per env measurement")
    ap.add_argument("--episodes", type=int, default=96, help="episodes of each hammer train run (0: skip)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args(argv)
    load0 = os.getloadavg()
    print(f"bench rware: load {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, cores allowed "
          f"{sorted(os.sched_getaffinity(0))}", flush=True)
    out: dict = {"load_start": load0, "cores": sorted(os.sched_getaffinity(0)), "env": [], "train": []}
    print(f"{'N':>2} {'K':>4} {'rware /cpu-s':>13} {'numpy /cpu-s':>13} {'ratio':>7}", flush=True)
    for n in a.n:
        for k in a.k:
            plain, fast = env_rate("rware", n, k, a.seconds, a.seed), env_rate("numpy", n, k, a.seconds, a.seed)
            ratio = fast["copy_steps_per_cpu_s"] / plain["copy_steps_per_cpu_s"]
            out["env"].append({"n": n, "K": k, "rware": plain, "numpy": fast, "ratio": ratio,
                               "load": os.getloadavg()[0]})
            print(f"{n:>2} {k:>4} {plain['copy_steps_per_cpu_s']:>13,.0f} {fast['copy_steps_per_cpu_s']:>13,.0f} "
                  f"{ratio:>6.1f}x", flush=True)
    if a.episodes > 0:
        print(f"hammer train, {a.episodes} episodes, seed {a.seed}, hammer (rl):", flush=True)
        with tempfile.TemporaryDirectory(prefix="bench-rware-") as tmp:
            for n in a.n:
                fast = train_run("numpy", n, a.episodes, a.seed, Path(tmp))
                plain = train_run("rware", n, a.episodes, a.seed, Path(tmp))
                same = _metrics(fast.pop("run")) == _metrics(plain.pop("run"))
                row = {"n": n, "numpy": fast, "rware": plain, "wall_ratio": plain["wall_s"] / fast["wall_s"],
                       "cpu_ratio": plain["cpu_s"] / fast["cpu_s"], "same_metrics": same,
                       "load": os.getloadavg()[0]}
                out["train"].append(row)
                print(f"  rware-tiny-{n}ag: rware {plain['wall_s']:.1f} s wall / {plain['cpu_s']:.1f} CPU-s, numpy "
                      f"{fast['wall_s']:.1f} s / {fast['cpu_s']:.1f} CPU-s: {row['wall_ratio']:.2f}x wall, "
                      f"{row['cpu_ratio']:.2f}x CPU; metrics.csv identical but wall_time: {same} "
                      f"(load {row['load']:.2f})", flush=True)
    load1 = os.getloadavg()
    out["load_end"] = load1
    print(f"bench rware: load at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}", flush=True)
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=2))
        print(f"wrote {a.json}")
    return out


if __name__ == "__main__":
    main()
