"""Multiwalker env steps per second: in-process `PettingZooVecEnv` vs `SubprocVecEnv`, same run.

Both are driven with the same seeded uniform-random torques (episodes then last ~50-100 steps, so
auto-resets are part of the cost, as early in training). Phases alternate (in-process, workers,
in-process, workers, ...) so that load from other processes hits both alike; the best phase of each
is compared. The machine's load (1-min load average and system-wide CPU busy % during each phase)
is printed alongside, with the cores our own processes actually got (CPU seconds / wall seconds), because
the speed-up depends on how many cores are free: 2 workers on a machine where others keep one core busy
cannot reach 2x.

    .venv/bin/python benchmarks/bench_workers.py [--num-envs 8] [--workers 2] [--steps 300]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time

import numpy as np
import psutil
from hammer.benchmarks.parallel_ceiling import ceiling, slices
from hammer.envs.registry import make_vec_env

CEIL = "ceiling: independent processes, no IPC"
FREE = "the slices alone, no IPC"
LOCK = "the slices in lockstep, no IPC"
NO_CPU = (CEIL, FREE, LOCK)  # phases run in other processes: no CPU accounting of ours


def _own_cpu_seconds() -> float:
    """CPU time used so far by this process and its workers (user + system)."""
    total = 0.0
    for p in [psutil.Process(), *psutil.Process().children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            t = p.cpu_times()
            total += t.user + t.system
    return total


def _phase(venv, steps: int, seed: int) -> tuple[float, float, float]:
    """(env-steps/s, system CPU busy %, cores our processes got) for `steps` batched steps."""
    venv.reset(seed)
    rng = np.random.default_rng(seed)
    shape = (venv.num_envs, venv.spec.n_agents, venv.spec.action_dim)
    acts = [rng.uniform(-1, 1, shape).astype(np.float32) for _ in range(steps)]
    psutil.cpu_percent(None)
    c0, t0 = _own_cpu_seconds(), time.perf_counter()
    for a in acts:
        venv.step(a)
    dt = time.perf_counter() - t0
    return venv.num_envs * steps / dt, psutil.cpu_percent(None), (_own_cpu_seconds() - c0) / dt


def run(num_envs: int = 8, workers: int = 2, n_agents: int = 3, steps: int = 300, repeats: int = 3) -> dict:
    load_before = os.getloadavg()[0]
    local = make_vec_env("mw", n_agents, num_envs)
    t0 = time.perf_counter()
    sub = make_vec_env("mw", n_agents, num_envs, workers=workers)
    start_s = time.perf_counter() - t0
    shared = make_vec_env("mw", n_agents, num_envs, workers=workers, parent_slice=True)
    names = {"in-process": local, f"{workers} workers": sub, f"{workers} slices, parent steps one": shared}
    try:
        for v in names.values():
            _phase(v, 30, 0)  # warm-up (imports, allocator, first terrain)
        res: dict[str, list[tuple[float, float, float]]] = {k: [] for k in names}
        for k in NO_CPU:
            res[k] = []
        nan = float("nan")
        for r in range(repeats):
            for k, v in names.items():
                res[k].append(_phase(v, steps, 100 + r))
            res[CEIL].append((ceiling(n_agents, num_envs, workers, steps, 100 + r), nan, nan))
            free, lock = slices(n_agents, num_envs, workers, steps, 100 + r)
            res[FREE].append((free, nan, nan))
            res[LOCK].append((lock, nan, nan))
    finally:
        for v in names.values():
            v.close()
    best = {k: max(v) for k, v in res.items()}
    speedup = best[f"{workers} workers"][0] / best["in-process"][0]
    speedup_parent = best[f"{workers} slices, parent steps one"][0] / best["in-process"][0]
    speedup_ceiling = best[CEIL][0] / best["in-process"][0]
    # The machine's speed drifts between phases (in-process alone moves by +-25 % within a run), so
    # also pair each repeat's phases with that repeat's in-process phase and take the median ratio.
    paired = {k: float(np.median([p[0] / b[0] for p, b in zip(v, res["in-process"])]))
              for k, v in res.items() if k != "in-process"}
    return {"num_envs": num_envs, "workers": workers, "n_agents": n_agents, "steps": steps,
            "cores": os.cpu_count(), "load_before": load_before, "load_after": os.getloadavg()[0],
            "worker_start_s": start_s, "phases": res, "best": best, "speedup": speedup,
            "speedup_parent_slice": speedup_parent, "speedup_ceiling": speedup_ceiling,
            "median_paired_speedup": paired}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--n-agents", type=int, default=3)
    p.add_argument("--steps", type=int, default=300, help="batched steps per timed phase")
    p.add_argument("--repeats", type=int, default=3)
    a = p.parse_args(argv)
    r = run(a.num_envs, a.workers, a.n_agents, a.steps, a.repeats)
    print(f"multiwalker N={r['n_agents']} K={r['num_envs']}, {r['steps']} batched steps x {a.repeats} phases, "
          f"{r['cores']} cores; 1-min load average {r['load_before']:.2f} before, {r['load_after']:.2f} after; "
          f"workers started in {r['worker_start_s']:.2f} s")
    for name, phases in r["phases"].items():
        runs = ", ".join(f"{sps:,.0f}" + ("" if name in NO_CPU else f" ({cpu:.0f}% busy, {own:.2f} cores ours)")
                         for sps, cpu, own in phases)
        print(f"  {name:>30}: env-steps/s per phase (system cpu busy, cores our processes got): {runs}")
    print(f"speed-up over in-process (best phases): {r['workers']} workers {r['speedup']:.2f}x, "
          f"{r['workers']} slices with the parent stepping one {r['speedup_parent_slice']:.2f}x")
    print(f"ceiling: {r['workers']} independent processes with no IPC {r['speedup_ceiling']:.2f}x in-process "
          "(what this machine's cores give two busy processes at once; no worker design can beat it)")
    print("median over repeats of (phase / the same repeat's in-process phase): "
          + ", ".join(f"{k} {v:.2f}x" for k, v in r["median_paired_speedup"].items()))
    print(f"  ({FREE!r} is each worker's slice stepped alone in its own process; {LOCK!r} charges every "
          "batched step its slower slice, i.e. a lockstep pool with free IPC: from alone to lockstep costs the uneven"
          " slices, from lockstep to the worker phases costs the IPC and hand-off)")
    per_core = {name: max(sps / own for sps, _, own in phases) for name, phases in r["phases"].items()
                if name not in NO_CPU}
    ratio = per_core[f"{r['workers']} workers"] / per_core["in-process"]
    print("env-steps per core-second our processes used: " + ", ".join(f"{k} {v:,.0f}" for k, v in per_core.items())
          + f" (workers/in-process {ratio:.2f}: below 1 is IPC and load-imbalance overhead; the speed-up can"
          f" only approach {ratio:.2f} x the cores the workers get)")


if __name__ == "__main__":
    main()
