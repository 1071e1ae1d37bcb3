"""`hammer bench peers`: hammer's training speed against JaxMARL's IPPO-FF on the same CPU, in one sitting.

    hammer bench peers --jaxmarl-repo DIR [--jax-venv DIR] [--env-steps 400000] [--out FILE.json]

JaxMARL (its pip package, in a venv of its own: `--jax-venv`, built here with `pip install jaxmarl
distrax pyyaml` when it does not exist) runs its own IPPO-FF baseline on MPE simple spread
(`DIR/baselines/IPPO/ippo_ff_mpe.py` of the public FLAIROx/JaxMARL repository, which the pip
package does not ship) at hammer's cn3 schedule and at its own defaults (benchmarks/jaxmarl_ippo.py);
hammer trains cn3 IL with `compile=true`, the same schedule. Each run is pinned to one core
(`taskset -c 0`), one after the other. An env step is one step of the whole team in one env copy
in both. Rates are steady rates: JaxMARL's compile is timed apart (`jit(...).lower().compile()`);
hammer's rate is taken over its episodes after the first fifth (its compile and warm-up done).
Prints both rates, their ratio, the compile times and the end of both learning curves (each
system's own measure: JaxMARL's mean episode return, hammer's paper metric and team return);
skipped with the reason where JaxMARL cannot be installed or the repository is not given.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

from hammer.benchmarks.results import write_json

HERE = Path(__file__).resolve().parent


def _one_core() -> list[str]:
    return ["taskset", "-c", "0"] if shutil.which("taskset") else []


def jax_python(venv: Path) -> tuple[Path | None, str]:
    """The jax venv's interpreter (built if missing), or None and why."""
    py = venv / "bin" / "python"
    if py.is_file():
        return py, ""
    r = subprocess.run([sys.executable, "-m", "venv", str(venv)], capture_output=True, text=True, check=False)
    if r.returncode == 0:
        r = subprocess.run([str(py), "-m", "pip", "install", "-q", "jaxmarl", "distrax", "pyyaml"],
                           capture_output=True, text=True, timeout=1800, check=False)
    if r.returncode != 0:
        shutil.rmtree(venv, ignore_errors=True)
        return None, f"JaxMARL could not be installed in {venv}: {(r.stderr or r.stdout).strip()[-300:]}"
    return py, ""


def run_jaxmarl(py: Path, repo: Path, schedule: str, env_steps: int) -> dict:
    r = subprocess.run([*_one_core(), str(py), str(HERE / "jaxmarl_ippo.py"), str(repo), schedule, str(env_steps)],
                       capture_output=True, text=True, timeout=3600, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"JaxMARL IPPO-FF ({schedule}) failed: {r.stderr.strip()[-1500:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


# hammer's schedules: its cn3 preset (what JaxMARL's "hammer" schedule copies), JaxMARL's defaults
# exactly, and JaxMARL's PPO settings (2,048 samples an update, 4 epochs x 4 minibatches, gamma 0.99)
# over more env copies and shorter rollouts, which suits hammer's per-vector-step cost.
SCHEDULES = {
    "cn3": [],
    "jaxmarl": ["num_envs=16", "rollout_steps=128", "epochs=4", "minibatches=4", "gamma=0.99"],
    "jaxmarl-ppo-k64": ["num_envs=64", "rollout_steps=32", "epochs=4", "minibatches=4", "gamma=0.99"],
    "jaxmarl-ppo-k128": ["num_envs=128", "rollout_steps=16", "epochs=4", "minibatches=4", "gamma=0.99"],
    "jaxmarl-ppo-k256": ["num_envs=256", "rollout_steps=8", "epochs=4", "minibatches=4", "gamma=0.99"],
}


def run_hammer(work: Path, env_steps: int, sets: list[str] | None = None, schedule: str = "cn3") -> dict:
    sets = [*SCHEDULES[schedule], *(sets or [])]
    run = work / f"hammer-cn3-il-{schedule}"
    shutil.rmtree(run, ignore_errors=True)
    episodes = max(1, env_steps // 25)  # cn3 episodes are 25 steps of each env copy
    cmd = [*_one_core(), sys.executable, "-P", "-m", "hammer.cli", "train", "--preset", "cn3", "--variant", "il",
           "--set", "compile=true", *(x for kv in sets or [] for x in ("--set", kv)),
           "--episodes", str(episodes), "--run-dir", str(run), "--quiet"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"hammer train failed: {r.stderr.strip()[-1500:]}")
    with open(run / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    a, b = rows[len(rows) // 5], rows[-1]
    steps, secs = int(b["env_steps"]) - int(a["env_steps"]), float(b["wall_time"]) - float(a["wall_time"])
    tail = rows[-max(1, len(rows) // 10):]
    return {"system": "hammer", "schedule": schedule, "sets": ["compile=true", *sets],
            "env_steps": int(b["env_steps"]),
            "warmup_s": float(a["wall_time"]), "steady_s": round(secs, 3),
            "env_steps_per_s": round(steps / secs, 1),
            "final_paper_metric_mean": sum(float(x["paper_metric"]) for x in tail) / len(tail),
            "final_team_return_mean": sum(float(x["team_return"]) for x in tail) / len(tail)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hammer bench peers", description=__doc__.split("\n\n")[0])
    ap.add_argument("--jaxmarl-repo", type=Path, help="A checkout of FLAIROx/JaxMARL (its baselines/IPPO).")
    ap.add_argument("--jax-venv", type=Path, default=Path("/tmp/hammer-jaxmarl-venv"))
    ap.add_argument("--env-steps", type=int, default=400_000, help="Env steps of each run (defaults: x2.5).")
    ap.add_argument("--work", type=Path, default=Path("/tmp/hammer-bench-peers"))
    ap.add_argument("--out", type=Path)
    ap.add_argument("--hammer-set", action="append", default=[], metavar="KEY=VALUE",
                    help="More config for hammer's runs (repeatable), e.g. compile_scope=epoch.")
    ap.add_argument("--hammer-schedules", default="cn3",
                    help=f"hammer's runs, comma-separated, from {', '.join(SCHEDULES)} (cn3: the matched "
                         "schedule; jaxmarl: JaxMARL's defaults exactly; jaxmarl-ppo-kK: its PPO settings "
                         "over K env copies, 2,048 samples an update).")
    a = ap.parse_args(argv)
    schedules = [x for x in a.hammer_schedules.split(",") if x]
    if unknown := [x for x in schedules if x not in SCHEDULES]:
        ap.error(f"--hammer-schedules: unknown {', '.join(unknown)}; fix: one or more of {', '.join(SCHEDULES)}")
    if a.jaxmarl_repo is None or not (a.jaxmarl_repo / "baselines/IPPO/ippo_ff_mpe.py").is_file():
        print("skipped: JaxMARL's IPPO baseline is not here; fix: git clone https://github.com/FLAIROx/JaxMARL and "
              "pass --jaxmarl-repo to it (the pip package does not ship baselines/)")
        return 0
    py, why = jax_python(a.jax_venv)
    if py is None:
        print(f"skipped: {why}")
        return 0
    a.work.mkdir(parents=True, exist_ok=True)
    jm = run_jaxmarl(py, a.jaxmarl_repo, "hammer", a.env_steps)
    jd = run_jaxmarl(py, a.jaxmarl_repo, "defaults", int(a.env_steps * 2.5))
    runs = {sch: run_hammer(a.work, a.env_steps, a.hammer_set, sch) for sch in schedules}
    hm = runs[schedules[0]]
    best = max(runs.values(), key=lambda r: r["env_steps_per_s"])
    result = {"jaxmarl_hammer_schedule": jm, "jaxmarl_defaults": jd, "hammer": hm, "hammer_runs": runs,
              "ratio_matched": round(runs["cn3"]["env_steps_per_s"] / jm["env_steps_per_s"], 3) if "cn3" in runs else None,
              "ratio_best_vs_jaxmarl_defaults": round(best["env_steps_per_s"] / jd["env_steps_per_s"], 3),
              "ratio_vs_jaxmarl_defaults": round(hm["env_steps_per_s"] / jd["env_steps_per_s"], 3)}
    print(f"JaxMARL IPPO-FF (jax {jm['jax']}), hammer's schedule: {jm['env_steps_per_s']:,.0f} env-steps/s "
          f"(compile {jm['compile_s']} s, {jm['env_steps']:,} steps); final mean episode return "
          f"{jm['final_return_mean']:.2f}")
    print(f"JaxMARL IPPO-FF, its defaults ({jd['num_envs']} envs x {jd['num_steps']} steps): "
          f"{jd['env_steps_per_s']:,.0f} env-steps/s (compile {jd['compile_s']} s)")
    for hm in runs.values():
        print(f"hammer cn3 IL, schedule {hm['schedule']} ({' '.join(hm['sets'])}): {hm['env_steps_per_s']:,.0f} "
              f"env-steps/s steady (first fifth, with compile: {hm['warmup_s']:.1f} s); final paper metric "
              f"{hm['final_paper_metric_mean']:.2f}, team return {hm['final_team_return_mean']:.2f}")
    if result["ratio_matched"] is not None:
        print(f"hammer / JaxMARL at the same schedule: {result['ratio_matched']}x (one core each)")
    print(f"hammer at its best ({best['schedule']}) / JaxMARL at its defaults: "
          f"{result['ratio_best_vs_jaxmarl_defaults']}x")
    write_json(a.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
