"""`hammer bench edge`: what an edge agent costs: resident memory while acting, and cold start.

Each measured process is a real `hammer local` (a fresh interpreter) joined to a harness that plays
the rest of the run on 127.0.0.1: a hub session that publishes the frozen policy (as the policy
server does), one observation and one central message per step, and waits for the agent's action
before the next step (as the env host does). Cold start = process start to the first action
received; RSS = the largest resident set sampled while it acts. Measured in the same run for the
edge entry (`--bundle`, no run directory) and today's entry (`--run-dir` of a `hammer up` run), on
one env copy by default (K=1, a robot: the edge entry then runs the lite agent, which never imports
numpy, local_agent/lite.py), and the edge entry again with HAMMER_EDGE_NUMPY=1 (the numpy agent),
so the table says what the lite agent saves.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

RSS_TARGET_MB, COLD_TARGET_S = 40.0, 0.5  # an edge agent's budget (docs/deploy.md "Footprint")


@dataclass
class EdgeFigures:
    entry: str
    cold_start_s: float  # process start -> first action received by the harness
    rss_mb: float  # largest RSS while acting
    steps: int  # steps acted during the RSS window
    step_ms_p50: float  # harness: obs published -> action received


def make_team(work: Path, preset: str = "cn3", overrides: tuple[str, ...] = ()):
    """An untrained HAMMER team (cn3 unless told) as a bundle and as a `hammer up` run directory (same weights)."""
    from hammer.deploy.launcher import prepare_run_dir
    from hammer.envs.registry import make_vec_env
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.team import Team
    from hammer.runtime.settings import RuntimeSettings
    from hammer.serve.bundle import export_bundle

    cfg = merge_config(preset, overrides=["variant=hammer", "central_mode=rl", "seed=0", *overrides])
    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
    spec = env.spec
    env.close()
    team = Team(cfg, spec)
    run = work / "run"
    settings = RuntimeSettings(run_id="bench-edge")
    prepare_run_dir(cfg, settings, run)
    RunDir(run).export_policy(team.local.export_numpy(), team.central.export_numpy(), {"variant": cfg.variant})
    return export_bundle(run, work / "bundle", force=True), run, cfg, spec


def measure(cmd: list[str], run_id: str, port: int, cfg, spec, blob: bytes, act_s: float,
            env: dict | None = None) -> EdgeFigures:
    """Start `cmd` (a `hammer local` joining run `run_id` at the hub on `port`) and play the run to it."""
    import psutil
    from hammer.protocol.dims import Dims
    from hammer.protocol.schemas import Action, CentralMsg, LocalObs, Weights
    from hammer.protocol.session import HammerSession, TransportConfig, loopback_endpoint

    k, agent = cfg.num_envs, 0
    dims = Dims(num_envs=k, n_agents=cfg.n_agents, obs_dim=spec.obs_dim, msg_dim=cfg.msg_dim,
                action_dim=spec.action_dim, discrete=spec.discrete)
    rng = np.random.default_rng(0)
    env_idx = np.arange(k, dtype=np.int64)
    with HammerSession(run_id, TransportConfig(listen=[loopback_endpoint(port)]), sender="bench") as hub:
        hub.declare_alive("policy")  # the harness is the rest of the (served) run: an edge agent joins once it sees a role
        w_pub = hub.publisher(hub.keys.weights("local"))
        obs_pub, msg_pub = hub.publisher(hub.keys.obs(agent)), hub.publisher(hub.keys.msg(agent))
        actions = hub.subscribe(hub.keys.act(agent), Action, dims)
        weights = Weights.from_blob("local", 0, blob)

        def step(s: int) -> None:
            obs_pub.publish(LocalObs(step=s, env_idx=env_idx, agent=agent, active=np.ones(k, bool),
                                     obs=rng.standard_normal((k, spec.obs_dim)).astype(np.float32)))
            msg_pub.publish(CentralMsg(step=s, env_idx=env_idx, agent=agent,
                                       msg=rng.uniform(-1, 1, (k, cfg.msg_dim)).astype(np.float32)))

        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        try:
            s, cold = 0, None
            while cold is None:  # until the first action: offer the policy and a fresh step every 5 ms
                if proc.poll() is not None:
                    raise RuntimeError(f"{' '.join(cmd[:6])}... exited with code {proc.returncode} before acting")
                if time.perf_counter() - t0 > 30:
                    raise RuntimeError("no action within 30 s")
                w_pub.publish(weights)
                s += 1
                step(s)
                if actions.get(timeout=0.005) is not None:
                    cold = time.perf_counter() - t0
            ps, rss, lat = psutil.Process(proc.pid), 0, []
            end = time.perf_counter() + act_s
            while time.perf_counter() < end:  # lock-step, as the env host drives it
                s += 1
                t = time.perf_counter()
                step(s)
                while (a := actions.get(timeout=1.0)) is not None and a.step < s:
                    pass
                lat.append(time.perf_counter() - t)
                if len(lat) % 20 == 0:
                    rss = max(rss, ps.memory_info().rss)
            rss = max(rss, ps.memory_info().rss)
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
    return EdgeFigures(entry="", cold_start_s=cold, rss_mb=rss / 2**20, steps=len(lat),
                       step_ms_p50=float(np.median(lat) * 1e3))


EDGE, EDGE_NUMPY = "edge (hammer local --bundle)", "edge, numpy agent (HAMMER_EDGE_NUMPY=1)"


def bench_edge(work: Path, act_s: float = 3.0, repeats: int = 2, python: Path | None = None,
               num_envs: int = 1) -> dict:
    """The entries, alternated `repeats` times; the median of each figure per entry. python: the agents'
    interpreter (e.g. a torch-free edge venv: its own install, so PYTHONPATH is dropped). num_envs:
    the team's env copies K (1: a robot; the edge entry then runs the lite agent)."""
    from hammer.benchmarks.edge_venv import clean_env
    from hammer.protocol.session import free_loopback_port
    from hammer.runtime.settings import RuntimeSettings

    bundle, run, cfg, spec = make_team(work, overrides=(f"num_envs={num_envs}",))
    blob = (bundle.path / "local.safetensors").read_bytes()
    hammer = [str(python or sys.executable), "-P", "-m", "hammer", "local", "--agent", "0"]  # the edge entry with --bundle
    runs: dict[str, list[EdgeFigures]] = {"run dir (hammer local --run-dir)": [], EDGE: [], EDGE_NUMPY: []}
    base = clean_env() if python is not None else dict(os.environ)
    base.pop("HAMMER_EDGE_NUMPY", None)
    for r in range(repeats):
        for i, (entry, done) in enumerate(runs.items()):
            port = free_loopback_port()
            run_id = f"bench-edge-{r}-{i}"
            env = {**base, "HAMMER_EDGE_NUMPY": "1"} if entry == EDGE_NUMPY else base
            if entry in (EDGE, EDGE_NUMPY):
                cmd = [*hammer, "--bundle", str(bundle.path), "--run-id", run_id,
                       "--connect", f"tcp/127.0.0.1:{port}"]
            else:  # today's entry reads runtime.json: point it at this harness
                RuntimeSettings(run_id=run_id, hub_port=port).save(run)
                cmd = [*hammer, "--run-dir", str(run)]
            f = measure(cmd, run_id, port, cfg, spec, blob, act_s, env=env)
            f.entry = entry
            done.append(f)
    med = {e: {k: float(np.median([getattr(f, k) for f in fs])) for k in ("cold_start_s", "rss_mb", "step_ms_p50")}
           for e, fs in runs.items()}
    return {"median": med, "runs": [asdict(f) for fs in runs.values() for f in fs], "repeats": repeats,
            "act_s": act_s, "num_envs": num_envs, "load": os.getloadavg(), "targets": {"rss_mb": RSS_TARGET_MB, "cold_start_s": COLD_TARGET_S}}
