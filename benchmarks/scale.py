"""`hammer bench scale`: cn with N = 3 ... 50 agents, in-process and distributed, with and without pools.

Per N (cn, K=32 env copies, the cn5 settings beyond N=5) this measures, in one sitting:

  train      `hammer train` (one process, a subprocess here so its CPU and RSS are its own), run
             before and after the two `hammer up` runs: the mean of the two is the baseline
  up         `hammer up`, one process per local agent (agents_per_process=1)
  up-pools   `hammer up` with agent pools (the machine's default, `auto_agents_per_process`,
             or one pool of all N where the default is one agent per process)
  floor      `hammer bench loop-floor` at the same N and payload sizes, typed messages, with one
             process per local agent and with the same pools: the loop with no work in any role

and reports env-steps/s (PPO updates included), the env host's step latency p50/p99, messages and
bytes per vector step (every role's publishes, from its final counters), CPU seconds per vector
step and peak RSS per role. The step's time is split three ways from the same figures: the raw
floor (Zenoh and scheduling), typed floor minus raw (serialisation and validation) and the real
loop minus the typed floor (the roles' own work: env step, forwards, bookkeeping).

Each point is short (a fixed number of episodes), so figures on a shared machine vary between
sittings; the JSON keeps the load average before and after every point.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import psutil

ROLE_KINDS = ("env", "central", "learner", "local")


def scale_config(n: int, episodes: int):
    """cn with N agents: the cn3 preset at N=3, the cn5 settings (message length 8) beyond."""
    from hammer.learning.config import merge_config

    return merge_config("cn3" if n <= 3 else "cn5", overrides=[f"n_agents={n}", f"episodes={episodes}"])


def pooled_size(n: int) -> int:
    """Agents per process of the `up-pools` runner: the machine's default, or all N in one pool
    where the default is one agent per process (so every N has a pooled figure)."""
    from hammer.runtime.settings import auto_agents_per_process

    k = auto_agents_per_process(n)
    return k if k > 1 else n


def run_train(n: int, episodes: int, path: Path) -> dict:
    """`hammer train` as a subprocess: its env-steps/s, CPU seconds and peak RSS."""
    cmd = [sys.executable, "-P", "-m", "hammer.cli", "train", "--preset", "cn3" if n <= 3 else "cn5", "--set",
           f"n_agents={n}", "--episodes", str(episodes), "--run-dir", str(path), "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)
    ps, rss, cpu, cpu0 = psutil.Process(proc.pid), 0.0, 0.0, None
    while proc.poll() is None:
        try:
            rss = max(rss, ps.memory_info().rss / 2**20)
            t = ps.cpu_times()
            cpu = t.user + t.system
        except psutil.Error:
            pass
        if cpu0 is None and (path / "metrics.csv").is_file():  # set-up done (imports, run dir): as the roles count
            cpu0 = cpu
        time.sleep(0.1)
    cpu -= cpu0 or 0.0
    if proc.returncode != 0:
        raise RuntimeError(f"hammer train N={n} failed: {proc.stderr.read()[-1000:]}")
    s = json.loads((path / "summary.json").read_text())
    steps = s["env_steps"] / scale_config(n, 1).num_envs
    return {"env_steps_per_s": s.get("env_steps_per_s_this_session") or s["env_steps_per_s"],
            "cpu_ms_per_step": {"train": 1e3 * cpu / steps}, "rss_mib": {"train": round(rss, 1)}}


def run_up(n: int, episodes: int, path: Path, per_process: int) -> dict:
    """`hammer up` (launch in this process): its summary figures plus traffic, CPU and RSS per role
    from the roles' final counters (links.json `roles`)."""
    from hammer.deploy.launcher import launch
    from hammer.runtime.settings import RuntimeSettings

    settings = RuntimeSettings(run_id=f"scale{n}-{per_process}-{os.getpid()}", agents_per_process=per_process,
                               startup_timeout_s=60.0 + 3.0 * n)
    t0 = time.monotonic()
    res = launch(scale_config(n, episodes), settings, path)
    s = res.summary
    roles = json.loads((path / "links.json").read_text())["roles"]
    steps = max(int(s["step"]), 1)
    per_role = {k: {"cpu": 0.0, "encode": 0.0, "put": 0.0, "decode": 0.0, "rss": 0.0} for k in ROLE_KINDS}
    msgs = nbytes = 0
    for name, c in roles.items():
        kind = "local" if name.startswith("local") else name
        if kind not in per_role:
            continue
        r = per_role[kind]
        r["cpu"] += float(c.get("cpu_run_s", c.get("cpu_s", 0.0)))  # a pool's agents carry none: the pool has it
        r["rss"] = max(r["rss"], float(c.get("rss_peak_mib", 0.0)))
        if not name.startswith("locals-"):  # a pool's agents report its traffic and codec time
            msgs += int(c.get("tx_msgs", 0))
            nbytes += int(c.get("tx_bytes", 0))
            for f in ("encode", "put", "decode"):
                r[f] += float(c.get(f"{f}_s", 0.0))
    cpu = {k: round(1e3 * v["cpu"] / steps, 3) for k, v in per_role.items()}
    io = {k: {f: round(1e3 * v[f] / steps, 3) for f in ("encode", "put", "decode")} for k, v in per_role.items()}
    rss = {k: round(v["rss"], 1) for k, v in per_role.items()}
    return {"env_steps_per_s": s["env_steps_per_s_after_start"], "env_steps_per_s_with_start": s["env_steps_per_s"],
            "time_s": s["time_s"], "p50_ms": s["step_latency_ms_p50"],
            "p99_ms": s["step_latency_ms_p99"], "wall_s": round(time.monotonic() - t0, 1),
            "processes": sum(1 for c in roles.values() if "cpu_s" in c),  # a pool's agents carry none
            "msgs_per_step": msgs / steps, "bytes_per_step": nbytes / steps,
            "cpu_ms_per_step": cpu, "io_ms_per_step": io, "rss_mib": rss,
            "fallbacks": s["links"].get("msg_fallback_copies", 0), "defaults": s["links"].get("default_actions", 0),
            "degraded": s.get("degraded")}


def run_floor(n: int, per_process: int, steps: int) -> dict:
    """The loop floor at N with the run's payload sizes: typed and raw, split and pooled."""
    from hammer.benchmarks.loop_floor import measure

    cfg = scale_config(n, 1)
    from hammer.envs.registry import make_vec_env

    env = make_vec_env(cfg.env, n, 1)
    d = env.spec.obs_dim
    env.close()
    out = {}
    for label, k in (("split", 1), ("pooled", per_process)):
        for typed in (True, False):
            r = measure("split", typed, k=cfg.num_envs, n=n, d=d, m=cfg.msg_dim, steps=steps, warmup=30,
                        per_process=k)
            out[f"{label}_{'typed' if typed else 'raw'}_p50_ms"] = r.p50_us / 1e3
            out[f"{label}_{'typed' if typed else 'raw'}_p99_ms"] = r.p99_us / 1e3
    return out


def shares(up: dict, floor: dict, label: str) -> dict:
    """The step's p50 in three parts: Zenoh + scheduling (raw floor), serialisation + validation
    (typed floor - raw), the roles' work (real loop - typed floor)."""
    raw, typed = floor[f"{label}_raw_p50_ms"], floor[f"{label}_typed_p50_ms"]
    return {"zenoh_sched_ms": round(raw, 3), "codec_validation_ms": round(typed - raw, 3),
            "work_ms": round(up["p50_ms"] - typed, 3)}


def bench_scale(ns: tuple[int, ...] = (3, 5, 10, 20, 50), episodes: int = 160, floor_steps: int = 300,
                out_dir: Path | None = None, progress=print) -> dict:
    """Every N: train, up, up with pools, the floor; returns {"meta", "rows"}."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="hammer-scale-") as tmp:
        root = Path(tmp)
        for n in ns:
            k = pooled_size(n)
            load0 = os.getloadavg()[0]
            row: dict = {"n_agents": n, "episodes": episodes, "pool_size": k, "load_1m_before": round(load0, 2)}
            first = run_train(n, episodes, root / f"train{n}a")
            progress(f"N={n} train {first['env_steps_per_s']:.0f} env-steps/s")
            row["up"] = run_up(n, episodes, root / f"up{n}", 1)
            progress(f"N={n} up {row['up']['env_steps_per_s']:.0f} env-steps/s, p50 {row['up']['p50_ms']:.2f} ms")
            row["up_pools"] = run_up(n, episodes, root / f"pools{n}", k)
            progress(f"N={n} up pools of {k}: {row['up_pools']['env_steps_per_s']:.0f} env-steps/s, "
                     f"p50 {row['up_pools']['p50_ms']:.2f} ms")
            # train again after the up runs: the load of a shared machine drifts; the mean of the
            # two brackets the up runs (both figures are kept)
            second = run_train(n, episodes, root / f"train{n}b")
            progress(f"N={n} train again {second['env_steps_per_s']:.0f} env-steps/s")
            row["train"] = {**first, "env_steps_per_s": (first["env_steps_per_s"] + second["env_steps_per_s"]) / 2,
                            "env_steps_per_s_runs": [first["env_steps_per_s"], second["env_steps_per_s"]]}
            row["floor"] = run_floor(n, k, floor_steps)
            progress(f"N={n} floor typed p50 {row['floor']['split_typed_p50_ms']:.2f} ms (split), "
                     f"{row['floor']['pooled_typed_p50_ms']:.2f} ms (pools)")
            row["shares_up"] = shares(row["up"], row["floor"], "split")
            row["shares_pools"] = shares(row["up_pools"], row["floor"], "pooled")
            row["load_1m_after"] = round(os.getloadavg()[0], 2)
            rows.append(row)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "cpu_count": psutil.cpu_count(),
            "ns": list(ns), "episodes": episodes, "floor_steps": floor_steps}
    result = {"meta": meta, "rows": rows}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        stem = out_dir / f"scale-{time.strftime('%Y%m%d-%H%M%S')}"
        stem.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
        stem.with_suffix(".md").write_text(markdown(result) + "\n")
        plot(result, stem.with_suffix(".png"))
        result["files"] = [str(stem.with_suffix(x)) for x in (".json", ".md", ".png")]
    return result


def markdown(result: dict) -> str:
    """The scaling table (and the time shares) as markdown."""
    head = ("| N | train env-steps/s | up env-steps/s (×train) | up pools env-steps/s (×train) | pool size | "
            "up p50 / p99 ms | pools p50 / p99 ms | floor typed p50 split / pools ms | p50 / floor (up, pools) | "
            "msgs/step | bytes/step |\n|" + "---:|" * 11)
    lines = [head]
    for r in result["rows"]:
        t, u, p, f = r["train"]["env_steps_per_s"], r["up"], r["up_pools"], r["floor"]
        lines.append(
            f"| {r['n_agents']} | {t:,.0f} | {u['env_steps_per_s']:,.0f} ({u['env_steps_per_s'] / t:.2f}) | "
            f"{p['env_steps_per_s']:,.0f} ({p['env_steps_per_s'] / t:.2f}) | {r['pool_size']} | "
            f"{u['p50_ms']:.2f} / {u['p99_ms']:.1f} | {p['p50_ms']:.2f} / {p['p99_ms']:.1f} | "
            f"{f['split_typed_p50_ms']:.2f} / {f['pooled_typed_p50_ms']:.2f} | "
            f"{u['p50_ms'] / f['split_typed_p50_ms']:.2f} / {p['p50_ms'] / f['pooled_typed_p50_ms']:.2f} | "
            f"{p['msgs_per_step']:.1f} | {p['bytes_per_step']:,.0f} |")
    lines += ["", ("Per role, per vector step (ms): CPU of the role's processes since they started work (all "
                   "threads; local = every local-agent process together), and the wall time inside encode "
                   "(build + stamp + msgpack), the Zenoh put (fault layer + Zenoh) and decode + validation; "
                   "peak RSS of one process (MiB):"), "",
              "| N | runner | role | CPU | encode | put | decode + validate | RSS |", "|---:|---|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        for label, key in (("up", "up"), ("pools", "up_pools")):
            u = r[key]
            for role in ROLE_KINDS:
                io = u.get("io_ms_per_step", {}).get(role, {})
                lines.append(f"| {r['n_agents']} | {label} | {role} | {u['cpu_ms_per_step'][role]:.2f} | "
                             f"{io.get('encode', 0):.2f} | {io.get('put', 0):.2f} | {io.get('decode', 0):.2f} | "
                             f"{u['rss_mib'][role]:.0f} |")
        lines.append(f"| {r['n_agents']} | train | (one process, set-up included) | {r['train']['cpu_ms_per_step']['train']:.2f} | | | | "
                     f"{r['train']['rss_mib']['train']:.0f} |")
    lines += ["", ("Where the p50 step goes (ms): Zenoh + scheduling = raw floor; serialisation + validation = "
              "typed floor − raw floor; work = real p50 − typed floor:"), "",
              "| N | runner | Zenoh + scheduling | serialisation + validation | roles' work |", "|---:|---|---:|---:|---:|"]
    for r in result["rows"]:
        for label, key in (("up", "shares_up"), ("pools", "shares_pools")):
            s = r[key]
            lines.append(f"| {r['n_agents']} | {label} | {s['zenoh_sched_ms']:.2f} | {s['codec_validation_ms']:.2f} | "
                         f"{s['work_ms']:.2f} |")
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Env-steps/s and step latency p50 against N (log scales), the floors beside the latency."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    ns = [r["n_agents"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    a.plot(ns, [r["train"]["env_steps_per_s"] for r in rows], "o-", color="C0", label="hammer train (in-process)")
    a.plot(ns, [r["up"]["env_steps_per_s"] for r in rows], "s-", color="C1", label="hammer up, 1 agent/process")
    a.plot(ns, [r["up_pools"]["env_steps_per_s"] for r in rows], "^-", color="C2", label="hammer up, agent pools")
    a.set(xscale="log", yscale="log", xlabel="N agents (cn)", ylabel="env-steps/s (PPO included)",
          title="throughput")
    b.plot(ns, [r["up"]["p50_ms"] for r in rows], "s-", color="C1", label="up p50, 1 agent/process")
    b.plot(ns, [r["up_pools"]["p50_ms"] for r in rows], "^-", color="C2", label="up p50, pools")
    b.plot(ns, [r["floor"]["split_typed_p50_ms"] for r in rows], "s--", color="C1", alpha=0.5,
           label="loop floor (typed), 1 agent/process")
    b.plot(ns, [r["floor"]["pooled_typed_p50_ms"] for r in rows], "^--", color="C2", alpha=0.5,
           label="loop floor (typed), pools")
    b.set(xscale="log", yscale="log", xlabel="N agents (cn)", ylabel="ms per vector step", title="step latency p50")
    from matplotlib.ticker import NullFormatter

    for ax in (a, b):
        ax.set_xticks(ns, [str(n) for n in ns])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle(f"hammer bench scale, {result['meta']['date']}, {result['meta']['cpu_count']} cores")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
