"""Per-call wall time of the central agent's acting path: the torch forward + `CentralActing.messages`
(what the in-process trainer runs on a GPU, and ran on the CPU until it took the central server's)
against the numpy path the central server runs (`NumpyCentralAgent` forward + the same sampling),
same weights, same states, same process; and, with --rss,
the peak RSS of every role of a short `hammer up` run.

One call = one vector step of the central server: global state (K, S) in, messages for K x N
agents out (plus the Gaussian sample, log-density and critic values in rl mode). The two paths
alternate in blocks so load from other processes hits both alike; the 1-min load average is
printed with the figures (the machine is shared: compare the ratio, not the absolute times).

    .venv/bin/python benchmarks/bench_central_acting.py [--calls 4000] [--k 32] [--rss]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # as the supervisor runs the roles (before numpy loads BLAS)

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _load() -> str:
    return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def time_acting(preset: str, mode: str, k: int, calls: int, block: int = 200) -> dict:
    import torch
    from hammer.envs.registry import make_vec_env
    from hammer.learner.worker import weights_blob
    from hammer.learning.config import merge_config
    from hammer.learning.numpy_policy import NumpyCentralAgent
    from hammer.learning.sampling import ActingStreams
    from hammer.learning.team import Team
    from safetensors.numpy import load as load_safetensors

    torch.set_num_threads(1)
    cfg = merge_config(preset, overrides=[f"num_envs={k}", f"central_mode={mode}"])
    env = make_vec_env(cfg.env, cfg.n_agents, k)
    team = Team(cfg, env.spec)
    net = NumpyCentralAgent(load_safetensors(weights_blob(team.central.export_numpy())))
    env.reset(0)
    rng = np.random.default_rng(0)
    states = []
    for _ in range(16):
        action = rng.integers(0, env.spec.action_dim, (k, cfg.n_agents))
        st = env.step(action)
        states.append(team.global_state(st.obs, team.encode_actions(action, st.active)))
    values = net.values if team.central_rl else None

    def torch_mean(s: np.ndarray) -> np.ndarray:
        return team.host(team.central.message_mean(team.tensor(s)))

    def torch_values(s: np.ndarray) -> np.ndarray:
        return team.host(team.central.values(team.tensor(s)))

    @torch.inference_mode()
    def run_torch(streams: ActingStreams, n: int) -> float:
        t0 = time.perf_counter()
        for i in range(n):
            team.acting.messages(states[i % 16], streams, cfg.msg_dropout, torch_mean,
                                 torch_values if team.central_rl else None)
        return time.perf_counter() - t0

    def run_numpy(streams: ActingStreams, n: int) -> float:
        t0 = time.perf_counter()
        for i in range(n):
            team.acting.messages(states[i % 16], streams, cfg.msg_dropout, net.message_mean, values)
        return time.perf_counter() - t0

    ts, ns = ActingStreams(0, cfg.n_agents), ActingStreams(0, cfg.n_agents)
    run_torch(ts, 50), run_numpy(ns, 50)  # warm-up
    t_torch, t_numpy = [], []
    load0 = _load()
    for _ in range(max(calls // block, 1)):
        t_torch.append(run_torch(ts, block) / block)
        t_numpy.append(run_numpy(ns, block) / block)
    return {"preset": preset, "mode": mode, "k": k, "n": cfg.n_agents, "calls": len(t_torch) * block,
            "torch_us": statistics.median(t_torch) * 1e6, "numpy_us": statistics.median(t_numpy) * 1e6,
            "load_before": load0, "load_after": _load()}


def central_rss(episodes: int) -> dict:
    """Peak RSS (MiB) per role of a real `hammer up` run of the cn3 preset (RssSampler of benchmarks.runtime),
    with its env-steps/s and control-loop latency (env host publishes -> every action back)."""
    from hammer.benchmarks.runtime import RssSampler
    from hammer.deploy.up import launch
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    cfg = merge_config("cn3", overrides=[f"episodes={episodes}"])
    rss = RssSampler()
    load0 = _load()
    with tempfile.TemporaryDirectory(prefix="hammer-bench-") as tmp:
        res = launch(cfg, RuntimeSettings(run_id=f"bench-rss-{os.getpid()}"), Path(tmp) / "run", chaos=rss)
    s = res.summary
    return {"completed": s["completed"], "rss_mib": {k: round(v) for k, v in sorted(rss.peak.items())},
            "env_steps_per_s": round(s["env_steps_per_s"]), "step_latency_ms_p50": s["step_latency_ms_p50"],
            "step_latency_ms_p99": s["step_latency_ms_p99"], "load_before": load0, "load_after": _load()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=4000, help="calls per path and case")
    ap.add_argument("--k", type=int, default=32, help="env copies K per call")
    ap.add_argument("--rss", action="store_true", help="also run a short `hammer up` and report peak RSS per role")
    ap.add_argument("--episodes", type=int, default=64, help="episodes of the --rss run")
    args = ap.parse_args()
    print(f"central acting path, median over blocks of 200 calls, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}")
    print(f"{'preset':6} {'mode':8} {'K':>3} {'N':>2} {'calls':>6} {'torch us':>9} {'numpy us':>9} "
          f"{'torch/numpy':>11}  load (1/5/15 min) before -> after")
    for preset in ("cn3", "cn5"):
        for mode in ("rl", "backprop"):
            r = time_acting(preset, mode, args.k, args.calls)
            print(f"{r['preset']:6} {r['mode']:8} {r['k']:>3} {r['n']:>2} {r['calls']:>6} {r['torch_us']:>9.1f} "
                  f"{r['numpy_us']:>9.1f} {r['torch_us'] / r['numpy_us']:>11.2f}  "
                  f"{r['load_before']} -> {r['load_after']}")
    if args.rss:
        r = central_rss(args.episodes)
        print(f"hammer up cn3 --episodes {args.episodes}: completed={r['completed']}, peak RSS MiB {r['rss_mib']}, "
              f"{r['env_steps_per_s']} env-steps/s, step latency p50/p99 {r['step_latency_ms_p50']:.2f}/"
              f"{r['step_latency_ms_p99']:.2f} ms, {r['load_before']} -> {r['load_after']}")


if __name__ == "__main__":
    main()
