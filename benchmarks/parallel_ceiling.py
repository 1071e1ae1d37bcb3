"""The most any design of env workers could reach on this machine (`benchmarks/bench_workers.py`).

Two busy processes on two cores need not get 2x one: cores share caches and memory bandwidth,
and the host may be busy. So a worker pool's speed-up is measured against this ceiling too:
`workers` independent processes, each stepping the in-process benchmark's exact workload (same
copies, seed and actions) with no pipes, shared memory or waiting on each other, started together.
A module of its own because spawned processes must import their target.

`slices` splits the same gap in two: each process steps only *its* slice of that workload (the
copies a worker would own, with their global seeds), still with no IPC, and times every step. Its
throughput is what the slices cost without pipes or waiting; the sum over steps of the slower
slice's time is what a lockstep batch of those slices would take if IPC were free.
"""

from __future__ import annotations

import multiprocessing as mp
import time

import numpy as np
from hammer.envs.catalog import build_local
from hammer.envs.description import EnvDescription
from hammer.envs.workers import slice_counts


def _one_slice(env: str, n_agents: int, num_envs: int, offset: int, count: int, steps: int, seed: int,
               ready, go, out) -> None:
    """Step copies offset..offset+count of the benchmark's workload in this process; put the step times."""
    v = build_local(EnvDescription(env, n_agents), count, index_offset=offset)
    try:
        shape = (num_envs, n_agents, v.spec.action_dim)
        warm = np.random.default_rng(0)
        v.reset(0)
        for _ in range(30):  # imports, allocator, first terrain: as the benchmark's warm-up
            v.step(warm.uniform(-1, 1, shape).astype(np.float32)[offset:offset + count])
        v.reset(seed)
        rng = np.random.default_rng(seed)  # the whole batch's draws, as the in-process phase makes them
        acts = [rng.uniform(-1, 1, shape).astype(np.float32)[offset:offset + count] for _ in range(steps)]
        times = np.empty(steps)
        ready.wait()
        go.wait()
        for t, a in enumerate(acts):
            t0 = time.perf_counter()
            v.step(a)
            times[t] = time.perf_counter() - t0
        out.put((offset, times.tolist()))
    finally:
        v.close()


def _run_together(env: str, n_agents: int, num_envs: int, parts: list[tuple[int, int]], steps: int,
                  seed: int) -> np.ndarray:
    """Start one process per (offset, count) part, release them together; their step times (P, steps)."""
    ctx = mp.get_context("spawn")
    ready, go, out = ctx.Barrier(len(parts) + 1), ctx.Barrier(len(parts) + 1), ctx.Queue()
    procs = [ctx.Process(target=_one_slice, args=(env, n_agents, num_envs, off, cnt, steps, seed, ready, go, out))
             for off, cnt in parts]
    for pr in procs:
        pr.start()
    try:
        ready.wait(timeout=300)
        go.wait(timeout=60)
        return np.array([t for _, t in sorted(out.get(timeout=600) for _ in procs)])
    finally:
        for pr in procs:
            pr.join(timeout=30)
            if pr.is_alive():
                pr.kill()


def slices(n_agents: int, num_envs: int, workers: int, steps: int, seed: int,
           env: str = "mw") -> tuple[float, float]:
    """(independent, lockstep) env-steps/s of the worker slices stepped in separate processes with
    no IPC: `independent` lets each slice run freely (total steps / slowest slice's wall time),
    `lockstep` charges every batched step the slowest slice's time at that step."""
    times = _run_together(env, n_agents, num_envs, slice_counts(num_envs, workers), steps, seed)  # (W, steps)
    total = num_envs * steps
    return total / times.sum(axis=1).max(), total / times.max(axis=0).sum()


def ceiling(n_agents: int, num_envs: int, workers: int, steps: int, seed: int, env: str = "mw") -> float:
    """env-steps/s of `workers` independent processes stepping num_envs copies each, with the same
    seeded uniform actions as the benchmark's in-process phase of this seed."""
    times = _run_together(env, n_agents, num_envs, [(0, num_envs)] * workers, steps, seed)
    return workers * num_envs * steps / times.sum(axis=1).max()
