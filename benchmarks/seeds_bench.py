"""`hammer bench seeds`: what training many seeds as one batched computation buys.

For cn3 and cn5 (hammer-rl, the presets) and S = 1, 2, 4, 8, 16 seeds, the aggregate env-copy
steps per second of the training loop (acting, env stepping, GAE, PPO epochs) of one
`learning.seed_batch.SeedBatch` process over a few updates, next to a solo `Trainer` run of the
same config measured in the same run (the baseline every ratio is against). The clock starts
when the first update is done: construction, imports, first calls and compiling are left out. From those figures: the wall time of the paper's cn3 grid
(5 variants x 5 seeds x 30,000 episodes) run one solo process after another, and as five
seed-batched processes (S=5, throughput interpolated between S=4 and S=8). The estimate uses
hammer-rl's throughput for every variant (the slowest of them), so it is an upper bound.
The machine is shared: the 1-min load average is printed with every row.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

from hammer.learning.config import merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.seed_batch import SeedBatch
from hammer.learning.trainer import Trainer

GRID_RUNS, GRID_SEEDS, GRID_EPISODES = 25, 5, 30_000


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _cfgs(preset: str, seeds: list[int], updates: int, compile_: bool) -> list:
    per_update = merge_config(preset).num_envs  # whole episodes per update (25-step episodes)
    return [merge_config(preset, overrides=[f"episodes={per_update * updates}", "checkpoint_every=1000",
                                            f"compile={str(compile_).lower()}"],
                         extra={"variant": "hammer", "central_mode": "rl", "seed": s}) for s in seeds]


def measure(preset: str, s: int, updates: int, compile_: bool = False) -> dict[str, Any]:
    """One timed run of `updates` + 1 updates: S seeds batched (s > 0) or one solo Trainer (s == 0)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfgs = _cfgs(preset, list(range(max(s, 1))), updates + 1, compile_)
        dirs = [RunDir.create(Path(tmp) / f"s{c.seed}", c) for c in cfgs]
        first: list[float] = []  # (time, lead seed's env steps) when the first update is done

        def mark(p: Any) -> None:
            if not first:
                first.extend((time.perf_counter(), p.env_steps))

        if s == 0:
            runner: Any = Trainer(cfgs[0], dirs[0], tensorboard=False, on_progress=mark)
            closers = [runner.env]
        else:
            runner = SeedBatch(cfgs, dirs, tensorboard=False, on_progress=mark)
            closers = [tr.env for tr in runner.trainers]
        out = runner.run()
        t_end = time.perf_counter()
        for env in closers:
            env.close()
    summaries = out if isinstance(out, list) else [out]
    # timed from the end of the first update: compiling (compile=true) and first calls are left out
    dt = t_end - first[0]
    steps = sum(sm["env_steps"] - first[1] for sm in summaries)
    return {"preset": preset, "seeds": max(s, 1), "mode": "solo" if s == 0 else "batched", "seconds": round(dt, 2),
            "env_steps_per_s": round(steps / dt), "load": _load()}


def run_bench(presets: tuple[str, ...] = ("cn3", "cn5"), sizes: tuple[int, ...] = (1, 2, 4, 8, 16),
              updates: int = 3, compile_: bool = False) -> list[dict[str, Any]]:
    rows = []
    for preset in presets:
        measure(preset, 1, 1, compile_)  # warm-up: imports, the inductor cache (compile=true)
        solo = measure(preset, 0, updates, compile_)  # the baseline runs with the same compile setting
        rows.append({**solo, "ratio": 1.0})
        for s in sizes:
            r = measure(preset, s, updates, compile_)
            rows.append({**r, "ratio": round(r["env_steps_per_s"] / solo["env_steps_per_s"], 2)})
    return rows


def grid_estimate(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Wall time (s) of the cn3 grid solo vs seed-batched (S=5), from the cn3 rows."""
    cn3 = {(r["mode"], r["seeds"]): r["env_steps_per_s"] for r in rows if r["preset"] == "cn3"}
    steps_per_run = GRID_EPISODES * 25
    solo = GRID_RUNS * steps_per_run / cn3[("solo", 1)]
    s4, s8 = cn3.get(("batched", 4)), cn3.get(("batched", 8))
    agg5 = s4 + (s8 - s4) / 4 if s4 and s8 else (s4 or s8 or cn3[("solo", 1)])
    batched = GRID_RUNS * steps_per_run / agg5
    return {"solo_s": round(solo), "batched_s": round(batched), "speedup": round(solo / batched, 2)}
