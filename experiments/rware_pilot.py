"""The warehouse pilot's numbers, by the rule of docs/results/plan-warehouse.md (step 2).

Why its own module: the plan's decision is not a comparison between variants (what `hammer report`
does) but each variant against a floor, the uniform-random policy, so the floor and the rule live
here. Deliveries per episode = the team return (rware's individual reward: +1 per delivery).

  floor     a uniform-random policy, 200 episodes per seed, no training;
  final     a run's mean deliveries per episode over its last 10 % of episodes; AUC over all;
  learning  for a variant and N: all 3 seeds' final > floor mean + 3 standard errors. Judged only
            for runs that finished their budget; unfinished runs are listed with how far they got.

    .venv/bin/python -m hammer.experiments.rware_pilot docs/results/runs/rware-pilot \
        --floor-json docs/results/warehouse-random-floor.json --out docs/results/warehouse-pilot-table.md
(`make paper-report` runs this; the floor is computed once, the first time, and kept in the JSON.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from hammer.envs.registry import make_vec_env
from hammer.experiments.runs import find_runs, load_run


def random_floor(n_agents: int, seed: int, episodes: int = 200, num_envs: int = 16) -> np.ndarray:
    """Deliveries per episode of uniform-random robots in rware-tiny-<N>ag (the first `episodes`)."""
    env = make_vec_env(f"rware-tiny-{n_agents}ag", n_agents, num_envs)
    env.reset(seed)
    rng = np.random.default_rng(seed)
    out: list[float] = []
    while len(out) < episodes:
        out += [e.team_return for e in env.step(rng.integers(0, 5, (num_envs, n_agents))).episodes]
    env.close()
    return np.asarray(out[:episodes])


def floors(ns: list[int], seeds: list[int], episodes: int = 200) -> dict[int, dict]:
    """Per N: the random policy's mean, standard error (pooled over seeds) and threshold."""
    res = {}
    for n in ns:
        x = np.concatenate([random_floor(n, s, episodes) for s in seeds])
        se = float(x.std(ddof=1) / np.sqrt(len(x)))
        res[n] = {"mean": float(x.mean()), "se": se, "threshold": float(x.mean()) + 3 * se, "episodes": len(x)}
    return res


def run_rows(paths: list[Path]) -> list[dict]:
    """One row per run name: variant label, N, seed, episodes done of the budget, final and AUC.
    A run both archived and still in a sweep directory (or given twice) counts once, the copy
    that got furthest."""
    rows: dict[str, dict] = {}
    for row in map(_row, find_runs(paths)):
        old = rows.get(row["run"])
        if old is None or (row["finished"], row["done"]) > (old["finished"], old["done"]):
            rows[row["run"]] = row
    return list(rows.values())


def _row(p: Path) -> dict:
    """The row of one run directory or archived run."""
    r = load_run(p)
    c = r.config
    ret = np.asarray(r.team_return)
    tail = ret[-max(1, len(ret) // 10):] if len(ret) else ret
    label = c["variant"] + (f"-{c['central_mode']}" if c["variant"] == "hammer" else "")
    return {"run": p.name, "variant": label, "n": c["n_agents"], "seed": c["seed"], "done": len(ret),
            "budget": c["episodes"], "finished": bool(r.finished and len(ret) >= c["episodes"]),
            "final": float(tail.mean()) if len(ret) else float("nan"),
            "auc": float(ret.mean()) if len(ret) else float("nan")}


def verdicts(rows: list[dict], floor: dict[int, dict], seeds: int = 3) -> dict[tuple[str, int], str]:
    """The plan's rule per (variant, N): 'learns', 'does not learn', or why it cannot be judged."""
    out = {}
    for key in sorted({(r["variant"], r["n"]) for r in rows}):
        done = [r for r in rows if (r["variant"], r["n"]) == key and r["finished"]]
        if len(done) < seeds or key[1] not in floor:
            out[key] = f"not judged ({len(done)} of {seeds} seeds finished)"
        else:
            out[key] = "learns" if all(r["final"] > floor[key[1]]["threshold"] for r in done) else "does not learn"
    return out


def table(rows: list[dict], floor: dict[int, dict]) -> str:
    lines = ["| run | N | seed | episodes | final (last 10 %) | AUC | finished |", "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for r in sorted(rows, key=lambda r: (r["n"], r["variant"], r["seed"])):
        lines.append(f"| {r['run']} | {r['n']} | {r['seed']} | {r['done']} / {r['budget']} | {r['final']:.3f} | "
                     f"{r['auc']:.3f} | {'yes' if r['finished'] else 'no'} |")
    lines += ["", "| N | random floor: mean deliveries/episode | s.e. | mean + 3 s.e. | episodes |",
              "| ---: | ---: | ---: | ---: | ---: |"]
    for n, f in sorted(floor.items()):
        lines.append(f"| {n} | {f['mean']:.4f} | {f['se']:.4f} | {f['threshold']:.4f} | {f['episodes']} |")
    lines += ["", "| variant | N | learning happens? |", "| --- | ---: | --- |"]
    lines += [f"| {v} | {n} | {verdict} |" for (v, n), verdict in verdicts(rows, floor).items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--n", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--floor-json", type=Path, default=None, help="reuse (or write) the floor figures here")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    if a.floor_json and a.floor_json.is_file():
        floor = {int(k): v for k, v in json.loads(a.floor_json.read_text()).items()}
    else:
        floor = floors(a.n, a.seeds)
        if a.floor_json:
            a.floor_json.write_text(json.dumps(floor, indent=1))
    text = table(run_rows(a.runs), floor)
    if a.out:
        a.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
