"""How a trained warehouse team plays as a fleet with its site feed, and without it: deliveries per episode.

    python -m hammer.benchmarks.site_play BUNDLE [--rounds 4] [--cut-at 5] [--cut-s 10] [--edge-venv PY]
                                          [--sim-episodes 64] [--sim-only] --out F.json       (root)

docs/fleet.md "The site feed". The fleet is `hammer bench fleet`'s (benchmarks/fleet_bench.Fleet): the
documented secure fleet on a LAN of namespaces at HZ, every robot in a namespace of its own, and the
site (`hammer.site.SiteFeed` publishing the warehouse's current columns, `hammer.site.simulated_warehouse`)
in one more. Trials of one episode each, in rounds of three kinds, one after another in one fleet:
`live` (nothing cut), `site` (the feed's switch port down CUT_S from CUT_AT s into the episode: the
central agent holds the feed `site_hold_s`, then puts zeros in its columns), `port` (a robot's switch
port down as long, robots in turn: the world holds its last action `hold_s`, then applies the default
one; the central agent's state has zeros for it). Per trial: the episode's paper metric (rware:
deliveries per episode; from the world's timeline), the cut's figures (fleet_bench's), the load.

The reference without a fleet: the same team in this process (`serve.play.team`: the numpy forwards
and random streams of the runtime, the central agent's state built by `CentralActing.global_state` with
the fleet's rules) on the same env, SIM_EPISODES episodes per kind, 16 at once: `live`; `site` (over the
same ticks as the fleet's cut: the feed's last columns held `site_hold_s`, then zeros); `port` (a robot's
last action held `hold_s`, then the default one; its row zeros in the central agent's state from
`missing_after_s`; robots in turn over the copies); `zeros` (the site's columns zeros for the whole episode). And how much the
central agent's messages depend on the site's columns at all (`message_dependence`).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

KINDS = ("live", "site", "port")
SIM_KINDS = ("live", "site", "port", "zeros")


def simulate(bundle: Path, kind: str, episodes: int, cut_at: float, cut_s: float, hz: float = 20.0,
             site_hold_s: float = 1.0, hold_s: float = 0.5, missing_after_s: float = 0.5, seed: int = 1000,
             copies: int = 16) -> list[float]:
    """The paper metric of `episodes` episodes of the team in `bundle` under `kind` (SIM_KINDS), in
    this process; a cut covers ticks [CUT_AT*HZ, (CUT_AT+CUT_S)*HZ) of every episode."""
    from hammer.envs.local_view import local_view_from_config
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import zero_prev_actions
    from hammer.learning.rollout import next_prev_actions
    from hammer.serve.bundle import load_bundle
    from hammer.serve.play import team

    b = load_bundle(bundle)
    cfg, spec, agents, messages = team(b, seed, num_envs=copies)
    if spec.local_obs_dim in (None, spec.obs_dim):
        raise ValueError(f"bundle {bundle}: the team has no site feed (no central-only columns)")
    local, n, view = spec.local_obs_dim, spec.n_agents, local_view_from_config(cfg, spec)
    a, x = round(cut_at * hz), round(cut_s * hz)
    held_site, held_robot, missing = round(site_hold_s * hz), round(hold_s * hz), round(missing_after_s * hz)
    env = make_vec_env(cfg.env, n, copies, env_kwargs=cfg.env_kwargs or None)
    rows, gone = np.arange(copies), np.arange(copies) % n  # the robot a port cut takes: in turn, as the fleet's
    out: list[float] = []
    try:
        for batch in range(-(-episodes // copies)):
            obs, _ = env.reset(seed + batch)
            prev = zero_prev_actions(spec, copies)
            last_cols, last_act, t, ended = None, None, 0, []
            while len(ended) < copies:
                seen, present, there = obs, None, None
                cut = a <= t < a + x
                if kind == "zeros" or (kind == "site" and t >= a + held_site and cut):
                    there = np.zeros(copies, bool)
                elif kind == "site" and cut:  # held: the columns of the last state before the silence
                    seen = obs.copy()
                    seen[..., local:] = last_cols[:, None]
                if kind == "port" and t >= a + missing and cut:
                    present = np.ones((copies, n), bool)
                    present[rows, gone] = False
                msgs = messages(seen, prev, present, None if there is None else (local, there))
                local_obs = view(obs)
                actions = np.stack([ag.act(local_obs[:, i], msgs[:, i] if cfg.wiring.msg_dim else None)
                                    for i, ag in enumerate(agents)], axis=1)
                if kind == "port" and cut:  # the cut robot hears nothing: its last action held, then the default
                    actions[rows, gone] = last_act if t < a + held_robot else spec.default_actions(copies)[rows, gone]
                elif kind == "port":
                    last_act = actions[rows, gone].copy()
                if not (kind == "site" and cut):
                    last_cols = obs[:, 0, local:].copy()
                step = env.step(spec.env_action(actions))
                ended += [e.paper_metric for e in step.episodes]
                prev, obs, t = next_prev_actions(spec, actions, step).prev, step.obs, t + 1
            out += ended
    finally:
        env.close()
    return [round(float(v), 3) for v in out[:episodes]]


def message_dependence(bundle: Path, steps: int = 300, seed: int = 1000, copies: int = 16) -> dict:
    """How much the team's central messages depend on the site's columns, on the states of `steps`
    steps of the team playing live: the mean |message with the feed - message with its columns zeros|
    (the messages' means, before rl's draw)
    against the messages' own spread (mean |message - its mean|), and how often that change turns a
    robot's most likely action (its policy's argmax) into another."""
    from hammer.envs.local_view import local_view_from_config
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import zero_prev_actions
    from hammer.learning.rollout import next_prev_actions
    from hammer.serve.bundle import load_bundle
    from hammer.serve.play import team

    cfg, spec, agents, messages = team(load_bundle(bundle), seed, num_envs=copies)
    local, view = spec.local_obs_dim, local_view_from_config(cfg, spec)
    zeros = (local, np.zeros(copies, bool))
    env = make_vec_env(cfg.env, spec.n_agents, copies, env_kwargs=cfg.env_kwargs or None)
    shift, spread, flips = [], [], []
    try:
        obs, _ = env.reset(seed)
        prev = zero_prev_actions(spec, copies)
        for _ in range(steps):
            live, blind = messages(obs, prev, means=True), messages(obs, prev, None, zeros, means=True)
            shift.append(np.abs(live - blind).mean())
            spread.append(np.abs(live - live.mean((0, 1))).mean())
            seen = view(obs)
            for i, ag in enumerate(agents):
                out = [ag.policy.actor_out(ag.policy_input(seen[:, i], m[:, i])) for m in (live, blind)]
                flips.append((out[0].argmax(1) != out[1].argmax(1)).mean())
            sent = messages(obs, prev)  # the team plays as in a fleet: on the messages it sends
            actions = np.stack([ag.act(seen[:, i], sent[:, i]) for i, ag in enumerate(agents)], axis=1)
            step = env.step(spec.env_action(actions))
            prev, obs = next_prev_actions(spec, actions, step).prev, step.obs
    finally:
        env.close()
    return {"steps": steps * copies, "msg_shift": round(float(np.mean(shift)), 4),
            "msg_spread": round(float(np.mean(spread)), 4), "argmax_changed": round(float(np.mean(flips)), 4)}


def _episodes(timeline: list[dict]) -> tuple[dict, dict]:
    """From the world's timeline: {episodes ended: the paper metric's running sum then} and {episodes
    ended: the first line's (wall time, ticks)} (lines written once a second)."""
    metric, first = {}, {}
    for x in timeline:
        if "episodes" in x:
            metric.setdefault(x["episodes"], x["metric"])
            first.setdefault(x["episodes"], (x["t"], x["ticks"]))
    return metric, first


def _health(timeline: list[dict], e: int) -> dict:
    """What the fleet was like over episode `e` (the timeline's lines from its first to the next's):
    the wall seconds it took (its ticks at HZ: 25 s for rware's 500 at 20 Hz, more where the world
    stalled) and each robot's ticks on the default action (a robot the world did not hear: a cut, or
    a stall of the machine)."""
    lines = [x for x in timeline if x.get("episodes") in (e, e + 1)]
    a = next(x for x in lines if x["episodes"] == e)
    b = next(x for x in lines if x["episodes"] == e + 1)
    return {"episode_wall_s": round(b["t"] - a["t"], 1), "ticks": b["ticks"] - a["ticks"],
            "defaults": [y - x for x, y in zip(a["defaults"], b["defaults"], strict=True)]}


def fleet_trials(bundle: Path, work: Path, rounds: int, cut_at: float, cut_s: float, hz: float = 20.0,
                 edge_python: Path | None = None, kinds: tuple[str, ...] = KINDS, progress=print) -> dict:
    """Rounds of one-episode trials of each kind in one secure fleet on a LAN of namespaces (module
    docstring); every trial with its episode's paper metric."""
    from hammer.benchmarks.fleet_bench import Fleet, _short, _timeline
    from hammer.benchmarks.netns import lan
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle)
    n, length = int(b.env_spec_data["n_agents"]), int(b.env_spec().max_steps)
    tag = f"{os.getpid() % 1000}s"
    trials: list[dict] = []
    with lan(n + 1, tag) as net:
        fleet = Fleet(bundle, work / f"fleet-{tag}", net, hz, True, edge_python, site=True)
        shutil.rmtree(fleet.work, ignore_errors=True)
        fleet.work.mkdir(parents=True)
        try:
            fleet.start()
            _, first = _episodes(_timeline(fleet.run))
            e = max(first, default=0) + 1  # an episode that starts after the fleet has settled
            for r in range(rounds):
                for kind in kinds:
                    while e not in (first := _episodes(_timeline(fleet.run))[1]):
                        time.sleep(0.2)
                    t_line, ticks = first[e]
                    t0 = t_line - (ticks - e * length) / hz  # the episode's first tick
                    load = os.getloadavg()[0]
                    trial = {"kind": kind, "round": r, "episode": e, "load1": round(load, 2)}
                    if kind != "live":
                        time.sleep(max(0.0, t0 + cut_at - time.time()))
                        trial["cut"] = fleet.cut("port" if kind == "port" else "site", (r % n), cut_s)
                    while e + 1 not in (metric := _episodes(_timeline(fleet.run))[0]):
                        time.sleep(0.5)
                    trial["paper_metric"] = round(metric[e + 1] - metric[e], 3)
                    trial.update(_health(_timeline(fleet.run), e))
                    trials.append(trial)
                    progress(trial_line(trial))
                    e += 1
        finally:
            summary = fleet.stop()
    return {"trials": trials, "summary": _short(summary), "episode_ticks": length}


def trial_line(t: dict) -> str:
    c = t.get("cut")
    cut = "" if c is None else (f"  cut {','.join(c['cut'])} {c['seconds']:g} s, back {c['back_max_s']} s, healthy "
                                f"{c['healthy_min_fraction']} of rate")
    health = "" if "ticks" not in t else (f"  ({t['ticks']} ticks in {t['episode_wall_s']} s, robot-ticks on the "
                                          f"default action {t['defaults']})")
    return (f"{t['kind']:4}  round {t['round']}  episode {t['episode']:3}: {t['paper_metric']:6.2f}{cut}  "
            f"load {t['load1']}{health}")


def _mean(xs: list[float]) -> float | None:
    return round(float(np.mean(xs)), 3) if xs else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--rounds", type=int, default=4, help="fleet trials of each kind")
    ap.add_argument("--cut-at", type=float, default=5.0, help="seconds into the episode")
    ap.add_argument("--cut-s", type=float, default=10.0, help="how long the link is down")
    ap.add_argument("--hz", type=float, default=20.0)
    ap.add_argument("--sim-episodes", type=int, default=64, help="per kind, in this process (0: none)")
    ap.add_argument("--sim-only", action="store_true", help="only the reference without a fleet (no root)")
    ap.add_argument("--edge-venv", type=Path, help="the robots' interpreter (a torch-free venv)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/hammer-site-play"))
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    r: dict = {"bundle": str(a.bundle), "hz": a.hz, "cut_at_s": a.cut_at, "cut_s": a.cut_s,
               "load1_start": round(os.getloadavg()[0], 2)}
    if a.sim_episodes:
        sim = {}
        for kind in SIM_KINDS:
            t = time.monotonic()
            sim[kind] = simulate(a.bundle, kind, a.sim_episodes, a.cut_at, a.cut_s, a.hz)
            print(f"simulation, {kind:5}: {_mean(sim[kind])} per episode over {len(sim[kind])} episodes "
                  f"({time.monotonic() - t:.0f} s, load {os.getloadavg()[0]:.2f})")
        r["simulation"] = {k: {"mean": _mean(v), "std": round(float(np.std(v)), 3), "episodes": v} for k, v in sim.items()}
        dep = r["message_dependence"] = message_dependence(a.bundle)
        print(f"messages with the site's columns zeros: mean change {dep['msg_shift']} (their spread "
              f"{dep['msg_spread']}); a robot's most likely action changed on {dep['argmax_changed']:.1%} of steps")
    if not a.sim_only:
        if os.geteuid() != 0:
            print("error: network namespaces need root (--sim-only: the reference alone)", file=sys.stderr)
            return 2
        from hammer.benchmarks.netns import NetnsUnavailable

        try:
            f = fleet_trials(a.bundle, a.work, a.rounds, a.cut_at, a.cut_s, a.hz, a.edge_venv)
        except NetnsUnavailable as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        r["fleet"] = f
        r["fleet_mean"] = {k: _mean([t["paper_metric"] for t in f["trials"] if t["kind"] == k]) for k in KINDS}
        print("fleet, every trial:")
        for t in f["trials"]:
            print("  " + trial_line(t))
        print("fleet, mean per kind: " + ", ".join(f"{k} {v}" for k, v in r["fleet_mean"].items()))
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
