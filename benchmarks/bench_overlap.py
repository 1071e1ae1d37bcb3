"""Would collecting rollout u+1 while updating on u pay on this machine? (cn3, hammer rl, compile).

A probe, not a feature: one real `Trainer`, its collect and its compiled update timed one after the
other and then in two threads at once (the threads race on the rollout buffer and the weights, which
is harmless for timing and is why this is not a training mode). Prints ms per collect+update pair.

    .venv/bin/python benchmarks/bench_overlap.py [--pairs 15] [--repeats 5]
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time

from hammer.learning.config import build_config, preset_dict
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import Trainer


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=15)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args(argv)
    cfg = build_config({**preset_dict("cn3"), "variant": "hammer", "central_mode": "rl", "seed": 0, "compile": True})
    with tempfile.TemporaryDirectory() as tmp:
        tr = Trainer(cfg, RunDir.create(f"{tmp}/run", cfg), tensorboard=False)
        state = {"obs": tr.env.reset(0)[0], "prev": tr.team.zero_prev_actions(cfg.num_envs), "u": 0}

        def collect() -> None:
            for _ in range(a.pairs):
                state["obs"], state["prev"], _ = tr._collect(state["obs"], state["prev"])

        def learn() -> None:
            for _ in range(a.pairs):
                tr.learner.learn(state["obs"], state["prev"], state["u"])
                state["u"] += 1

        for _ in range(3):  # warm-up, including the compile
            state["obs"], state["prev"], _ = tr._collect(state["obs"], state["prev"])
            tr.learner.learn(state["obs"], state["prev"], state["u"])
            state["u"] += 1
        for _ in range(a.repeats):
            t = time.perf_counter(); collect(); tc = time.perf_counter() - t
            t = time.perf_counter(); learn(); tl = time.perf_counter() - t
            th = threading.Thread(target=learn)
            t = time.perf_counter(); th.start(); collect(); th.join(); tb = time.perf_counter() - t
            n = a.pairs
            print(f"collect {tc / n * 1e3:.1f} ms, update {tl / n * 1e3:.1f} ms, one after the other "
                  f"{(tc + tl) / n * 1e3:.1f} ms, in two threads {tb / n * 1e3:.1f} ms per pair "
                  f"({1 - tb / (tc + tl):+.0%} saved)", flush=True)
        tr.env.close()


if __name__ == "__main__":
    main()
