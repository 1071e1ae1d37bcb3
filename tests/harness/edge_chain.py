"""The whole deployment chain, end to end on one machine: a trained cn3 team to torch-free edge agents on real links.

    python -m tests.harness.edge_chain [--team RUN_A --update RUN_B | --train-episodes N] [--rates 1024]
                                    [--episodes 2400] [--work runs/edge-chain] [--edge-venv PY]   (root)
    make edge-chain                                                                  (the same, defaults)

Every step is the real CLI (a fresh process each):
  1. the team: RUN_A (default: the archived cn3-ownobs hammer-rl team of seed 0, 30,000 episodes of
     `hammer train`), or `hammer train --preset cn3` of N episodes (--train-episodes); the update B:
     RUN_B (default: the archived team of seed 1) or a second trained seed
  2. `hammer export` of both teams into bundles
  3. a fresh venv with only the edge install (no torch, PettingZoo, matplotlib), unless --edge-venv
  4. per rate: `hammer serve A` in the hub namespace (router, launcher, env host, policy server),
     `hammer central` in its own namespace, `hammer local --bundle A` from the edge venv in one
     namespace per agent (benchmarks.netns), `hammer push B --to RUN` and `hammer rollback RUN` mid-run
     (benchmarks.push_driver); the env host's trace is replayed with each version's weights: every
     step was acted on with the version it names, and after the rollback exactly as A acts
  5. `hammer play A --out WORK/team.gif`
  6. a warehouse fleet: a trained rware-tiny-2ag team (--warehouse RUN, default the archived hammer rl
     team of seed 0, 5M env steps; or `hammer train` of --warehouse-episodes; --no-warehouse skips it)
     exported and served as a secure fleet (`hammer serve --realtime 20 --secure --external-site`), each
     robot `hammer local --bundle --fleet` from the edge venv in its own namespace and the site feed
     (`hammer.site.SiteFeed`, publishing the warehouse's current columns as the simulated world writes
     them) in its own; robot 0's link and the feed's link cut and restored
     (benchmarks.fleet_bench.run_trials); the site feed's figures and the deliveries in its summary
Writes WORK/chain.json (every figure) and prints it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
ARCHIVE = ROOT / "docs" / "results" / "runs" / "cn3-ownobs"
ARCHIVED_TEAM = "cn3-hammer-rl-env_kwargs_observe_others=false-s{seed}"
ARCHIVED_WAREHOUSE = ROOT / "docs" / "results" / "runs" / "rware5m-2" / "rware-tiny-2ag-hammer-rl-ep10000-s0"


def hammer(*args: str, timeout: float = 900) -> str:
    """`hammer ARGS` as a fresh process; its stdout, or a RuntimeError with its last error line."""
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", *args], check=False, capture_output=True, text=True,
                       timeout=timeout)
    if r.returncode != 0:
        tail = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"hammer {args[0]} exited with {r.returncode}: {tail[0]}")
    return r.stdout.strip()


def train_team(run_dir: Path, seed: int, episodes: int, sets: tuple[str, ...] = ()) -> Path:
    """`hammer train --preset cn3` (HAMMER, RL central mode) into `run_dir`."""
    hammer("train", "--preset", "cn3", "--variant", "hammer", "--central-mode", "rl", "--seed", str(seed),
           "--episodes", str(episodes), "--run-dir", str(run_dir), "--quiet",
           *(x for s in sets for x in ("--set", s)))
    return run_dir


def warehouse_fleet(work: Path, run: Path, edge_python: Path) -> dict:
    """Step 6: the warehouse team `run` exported and run as a secure fleet with its site feed across
    namespaces, robot 0's port cut 2 s and the site feed's 3 s (the trials of `hammer bench fleet`)."""
    from hammer.benchmarks.fleet_bench import run_trials

    bundle = work / "bundle-warehouse"
    export = hammer("export", str(run), "--out", str(bundle), "--force")
    (work / "warehouse-trials.jsonl").unlink(missing_ok=True)
    r = run_trials(bundle, work / "warehouse", [("port", 2.0, 1), ("site", 3.0, 1)], edge_python=edge_python,
                   results=work / "warehouse-trials.jsonl", bytes_s=10.0, progress=lambda _: None)
    return {"run": str(run), "export": export, **r}


def train_warehouse(run_dir: Path, episodes: int) -> Path:
    """`hammer train --preset rware-tiny-2ag` (HAMMER, RL central mode), short episodes, into `run_dir`."""
    hammer("train", "--preset", "rware-tiny-2ag", "--central-mode", "rl", "--episodes", str(episodes),
           "--set", "env_kwargs.max_steps=100", "--set", "num_envs=4", "--set", "rollout_steps=50",
           "--run-dir", str(run_dir), "--quiet")
    return run_dir


def replay_check(trace_file: Path, bundles: dict[int, Path]) -> dict:
    """Replay every local agent on the trace's observations and messages with the weights of the
    version each step names (one random stream per agent, as the edge agents draw): the fraction of
    actions (acted in time) that match, overall and per version."""
    from hammer.local_agent.client import AgentSpec, LocalAgent
    from hammer.serve.bundle import load_bundle

    loaded = {v: load_bundle(p) for v, p in bundles.items()}
    first = loaded[min(loaded)]
    cfg, spec = first.config(), first.env_spec()
    blobs = {v: (b.path / "local.safetensors").read_bytes() for v, b in loaded.items()}
    with np.load(trace_file) as t:
        tr = {k: t[k] for k in ("obs", "msgs", "actions", "defaulted", "versions")}
    agents = [LocalAgent(AgentSpec.from_config(cfg, spec, i)) for i in range(cfg.n_agents)]
    replay = np.zeros(tr["actions"].shape, np.int64)
    for s, v in enumerate(tr["versions"]):
        for i, a in enumerate(agents):
            if a.version != int(v):
                a.load_weights(blobs[int(v)], int(v))
            replay[s, :, i] = a.act(tr["obs"][s, :, i], tr["msgs"][s, :, i])
    ok = ~tr["defaulted"]
    match = replay == tr["actions"]
    per_version = {int(v): float(match[ok & (tr["versions"] == v)[:, None, None]].mean()) for v in np.unique(tr["versions"])}
    return {"match": float(match[ok].mean()), "match_per_version": per_version, "acted_in_time": float(ok.mean())}


def chain(work: Path, team: Path, update: Path, edge_python: Path, rates: tuple[int, ...], episodes: int,
          push_at: int = 150, play_episodes: int = 1, tag: str | None = None, warehouse: Path | None = None) -> dict:
    """Steps 2-6 for two trained run directories (and a warehouse team's, step 6); returns every figure
    (also written to WORK/chain.json)."""
    from hammer.benchmarks.netns import served_run

    work.mkdir(parents=True, exist_ok=True)
    a, b = work / "bundle-a", work / "bundle-b"
    report: dict = {"team": str(team), "update": str(update), "edge_python": str(edge_python),
                    "export": [hammer("export", str(team), "--out", str(a), "--force"),
                               hammer("export", str(update), "--out", str(b), "--force")], "runs": []}
    baseline = None
    for rate in rates:
        r = served_run(a, work / "netns", episodes, rate, tag=tag, edge_python=edge_python, push=b,
                       baseline_steps_per_s=baseline,
                       timeout_s=max(240.0, episodes * 2.0))
        if r.get("updates", {}).get("driver", {}).get("rollback_named_at") is not None:
            r["replay"] = replay_check(Path(r["run_dir"]) / "trace.npz", {0: a, 1: b, 2: a})
        if rate == 0 and r["completed"]:
            baseline = r["env_steps_per_s"]
        report["runs"].append(r)
    gif = work / "team.gif"
    report["play"] = hammer("play", str(a), "--out", str(gif), "--episodes", str(play_episodes), "--max-steps", "25")
    report["gif"] = str(gif)
    if warehouse is not None:
        report["warehouse"] = warehouse_fleet(work, warehouse, edge_python)
    (work / "chain.json").write_text(json.dumps(report, indent=1))
    return report


def summary_lines(report: dict, work: Path) -> list[str]:
    """The chain's result for a person: one line per step, the figures in WORK/chain.json."""
    head = f"edge chain: team {report['team']} (A), update {report['update']} (B); edge agents on {report['edge_python']}"
    lines = [head]
    for r in report["runs"]:
        rate = "no limit" if not r["rate_kbit"] else f"{r['rate_kbit']} kbit/s"
        base = r.get("baseline_env_steps_per_s")
        pace = f" ({r['env_steps_per_s'] / base:.0%} of the unlimited link)" if base else ""
        lines.append(f"served, agent 0's link {rate}: {'completed' if r['completed'] else 'NOT completed'}, "
                     f"{r.get('episodes') or 0} episodes, {r['env_steps_per_s'] or 0:,.0f} env-steps/s{pace}, "
                     f"step p50 {r.get('step_p50_ms') or 0:.1f} ms p99 {r.get('step_p99_ms') or 0:.1f} ms, "
                     f"default actions {r.get('default_actions')}, fallback messages {r.get('msg_fallback_copies')}"
                     f"{'' if r.get('keeps_up') else ' (does not keep up)'}")
        up = r.get("updates")
        if up is not None:
            if "error" in up or "error" in up.get("driver", {}):
                lines.append(f"  push and rollback: {up.get('error') or up['driver'].get('error')}")
            else:
                versions = ", ".join(f"v{v} {n}" for v, n in sorted(up["steps_per_version"].items()))
                lines.append(f"  push and rollback: steps acted per version {versions}; the push took "
                             f"{up.get('push_took_steps', '-')} steps, the rollback {up.get('rollback_took_steps', '-')}; "
                             f"versions only rose: {up['versions_monotone']}, no step missed: {up['no_step_missed']}")
        rp = r.get("replay")
        if rp is not None:
            lines.append(f"  replay with each version's weights: {rp['match']:.1%} of the actions match "
                         f"({rp['acted_in_time']:.1%} acted in time)")
    lines.append(f"play: {report['play']}")
    wh = report.get("warehouse")
    if wh is not None:
        site = (wh["fleets"][0]["summary"].get("site") or {}) if wh["fleets"] else {}
        trials = "; ".join(f"{t['kind']} {t['seconds']:g} s cut: back in {t['back_max_s']} s, healthy "
                           f"{t['healthy_min_fraction']} of rate" for t in wh["trials"])
        link = wh.get("link") or {}
        metric = wh["fleets"][0]["summary"].get("paper_metric_mean") if wh["fleets"] else None
        lines.append(f"warehouse fleet (secure, its site feed from a namespace of its own): {trials}; feed states taken "
                     f"{site.get('states')}, silences {site.get('silences')}; robot 0's link "
                     f"{link.get('bytes_per_step')} B, {link.get('packets_per_step')} packets per step; paper metric "
                     f"{'-' if metric is None else f'{metric:.2f}'} per episode (the whole run, cuts included)")
    lines.append(f"every figure: {work / 'chain.json'}")
    return lines


def main() -> None:
    import argparse

    from hammer.benchmarks.edge_venv import EdgeVenvError, build_edge_venv
    from hammer.benchmarks.netns import NetnsUnavailable

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--team", type=Path, default=ARCHIVE / ARCHIVED_TEAM.format(seed=0))
    ap.add_argument("--update", type=Path, default=ARCHIVE / ARCHIVED_TEAM.format(seed=1))
    ap.add_argument("--train-episodes", type=int, help="train both teams with `hammer train` instead (seeds 0, 1)")
    ap.add_argument("--rates", default="1024", help="kbit/s limits of agent 0's link, e.g. 0,1024,256 (0 = none)")
    ap.add_argument("--episodes", type=int, default=2400,
                    help="per run; the push and the rollback each take a CLI start and a heartbeat (~2 s)")
    ap.add_argument("--work", type=Path, default=Path("runs/edge-chain"))
    ap.add_argument("--edge-venv", type=Path, help="python of a torch-free venv (default: build WORK/edge-venv)")
    ap.add_argument("--warehouse", type=Path, default=ARCHIVED_WAREHOUSE,
                    help="a trained rware team's run directory for step 6 (default: the archived hammer rl s0)")
    ap.add_argument("--warehouse-episodes", type=int, default=0,
                    help="train a warehouse team this long for step 6 instead of --warehouse")
    ap.add_argument("--no-warehouse", action="store_true", help="no warehouse fleet (step 6)")
    a = ap.parse_args()
    import signal

    from hammer.runtime.process import take_signals

    take_signals((signal.SIGTERM,), lambda _: sys.exit(143))  # a stopped chain still deletes its namespaces
    team, update = a.team, a.update
    try:
        if a.train_episodes:
            team = train_team(a.work / "train-a", 0, a.train_episodes)
            update = train_team(a.work / "train-b", 1, a.train_episodes)
        edge = a.edge_venv or build_edge_venv(a.work / "edge-venv")
        warehouse = (None if a.no_warehouse else train_warehouse(a.work / "train-warehouse", a.warehouse_episodes)
                     if a.warehouse_episodes else a.warehouse)
        r = chain(a.work, team, update, edge, tuple(int(x) for x in a.rates.split(",")), a.episodes,
                  warehouse=warehouse)
    except (RuntimeError, EdgeVenvError, NetnsUnavailable) as e:
        sys.exit(f"error: {e}")
    print("\n".join(summary_lines(r, a.work)))


if __name__ == "__main__":
    main()
