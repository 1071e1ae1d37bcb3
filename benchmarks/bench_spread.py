"""Copy-steps per second of VecSimpleSpread against mpe2's simple_spread_v3 parallel env.

One "copy-step" is one step of one copy of the N-agent environment (all N agents act once). The
mpe2 side steps K independent parallel envs in a Python loop with the same kind of random actions
and resets each after its 25-step episode, which is how a loop-based trainer would drive it.
Both are timed in the same process, back to back, for the same wall-clock budget per cell.

    .venv/bin/python benchmarks/bench_spread.py [--seconds 1.0] [--n 3 5] [--k 1 64 256]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def bench_ours(k: int, n: int, seconds: float) -> float:
    from hammer.envs.spread import VecSimpleSpread

    env = VecSimpleSpread(k, n_agents=n)
    env.reset(0)
    actions = np.random.default_rng(0).integers(0, 5, (64, k, n))
    for i in range(5):  # warm-up
        env.step(actions[i])
    steps, start = 0, time.perf_counter()
    while True:
        for _ in range(25):
            env.step(actions[steps % 64])
            steps += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps * k / elapsed


def bench_mpe2(k: int, n: int, seconds: float) -> float:
    from mpe2 import simple_spread_v3

    envs = [
        simple_spread_v3.parallel_env(N=n, max_cycles=25, local_ratio=0.5, continuous_actions=False)
        for _ in range(k)
    ]
    for c, e in enumerate(envs):
        e.reset(seed=c)
    names = [f"agent_{i}" for i in range(n)]
    actions = np.random.default_rng(0).integers(0, 5, (64, k, n)).tolist()
    steps, start = 0, time.perf_counter()
    while True:
        row = actions[steps % 64]
        for c, e in enumerate(envs):
            e.step(dict(zip(names, row[c], strict=True)))
            if not e.agents:
                e.reset()
        steps += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps * k / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=1.0, help="wall-clock budget per cell")
    ap.add_argument("--n", type=int, nargs="+", default=[3, 5], help="numbers of agents")
    ap.add_argument("--k", type=int, nargs="+", default=[1, 64, 256], help="numbers of copies")
    args = ap.parse_args()
    print(f"{'N':>3} {'K':>5} {'VecSimpleSpread':>18} {'mpe2 loop':>12} {'speed-up':>9}   (copy-steps/s)")
    for n in args.n:
        for k in args.k:
            ours = bench_ours(k, n, args.seconds)
            ref = bench_mpe2(k, n, args.seconds)
            print(f"{n:>3} {k:>5} {ours:>18,.0f} {ref:>12,.0f} {ours / ref:>8.1f}x")
    print(
        "750k env steps (training budget) at K=64, N=3 would take the env alone "
        f"{750_000 / bench_ours(64, 3, args.seconds):.1f} s"
    )


if __name__ == "__main__":
    main()
