"""Seeds as one process against solo processes, measured whole (docs/fast-envs.md, "Seeds at the floor").

    python -m hammer.benchmarks.seeds_whole batch|solo EPISODES OUT [il|hammer-rl] [S]

One process: S seeds of cn3 (default 8) as one seed batch (`batch`) or one solo run of seed 0
(`solo`), `compile=true compile_scope=epoch`, the preset otherwise. Prints one JSON line: the
process's CPU time (user + system, `getrusage`) when the first update is done (imports, the
envs, compiling or loading the graphs, the first update) and at the end, its wall time, and per
update the CPU time of collection and of the update, both timed after the first three updates.
CPU time is what a shared machine measures least badly; the wall is printed beside it with the
1-minute load. Eight solo runs cost eight solo processes: run `solo` beside `batch` in one sitting,
pinned to one core (`taskset -c 1`), alternating.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time

T_WALL0 = time.time()


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv: list[str]) -> dict:
    from pathlib import Path

    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.seed_batch import SeedBatch
    from hammer.learning.trainer import Trainer

    mode, episodes, out = argv[0], int(argv[1]), Path(argv[2])
    variant = argv[3] if len(argv) > 3 else "il"
    n = int(argv[4]) if len(argv) > 4 else 8
    extra = {"il": {"variant": "il"}, "hammer-rl": {"variant": "hammer", "central_mode": "rl"}}[variant]
    seeds = list(range(n)) if mode == "batch" else [0]
    cfgs = [merge_config("cn3", None, ["compile=true", "compile_scope=epoch", f"episodes={episodes}"],
                         {**extra, "seed": s}) for s in seeds]
    dirs = [RunDir.create(out / f"{mode}-s{s}", c) for s, c in zip(seeds, cfgs, strict=True)]
    marks: list[tuple[int, float]] = []
    split = {"collect": 0.0, "update": 0.0}

    def timed(obj: object, name: str, key: str) -> None:
        f = getattr(obj, name)

        def g(*a, **k):
            t = time.process_time()
            r = f(*a, **k)
            if len(marks) >= 3:
                split[key] += time.process_time() - t
            return r
        setattr(obj, name, g)

    def mark(p) -> None:
        marks.append((p.update, _cpu()))

    if mode == "batch":
        runner = SeedBatch(cfgs, dirs, on_progress=mark)
        timed(runner, "_act", "collect")
        timed(runner, "_learn", "update")
        trainers = runner.trainers
    else:
        runner = Trainer(cfgs[0], dirs[0], on_progress=mark)
        timed(runner, "_collect", "collect")
        timed(runner.learner, "learn", "update")
        trainers = [runner]
    try:
        sums = runner.run()
    finally:
        for tr in trainers:
            tr.env.close()
    sums = sums if isinstance(sums, list) else [sums]
    timed_updates = max(marks[-1][0] - 3, 1)
    return {"mode": mode, "variant": variant, "seeds": len(seeds), "episodes": episodes, "updates": marks[-1][0],
            "cpu_first_update_s": round(marks[0][1], 2), "cpu_total_s": round(_cpu(), 2),
            "wall_total_s": round(time.time() - T_WALL0, 2),
            "collect_ms_per_update": round(1000 * split["collect"] / timed_updates, 1),
            "update_ms_per_update": round(1000 * split["update"] / timed_updates, 1),
            "env_steps": sum(s["env_steps"] for s in sums), "load1": round(os.getloadavg()[0], 2),
            "final_paper_metric": [round(s["final_paper_metric_last500"], 4) for s in sums]}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:])), flush=True)
