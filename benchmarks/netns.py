"""A served team across Linux network namespaces: real links instead of loopback.

    python -m benchmarks.netns BUNDLE [--rates 0,1024,256] [--episodes 16]     (root; see docs/deploy.md)

The hub namespace holds the Zenoh router (`hammer hub`), the launcher, env host, central agent and
policy server (`hammer serve --external ...`, every role a Zenoh client of the router); each local
agent runs from the bundle (`hammer local --bundle`) in its own namespace, joined to the hub
namespace by a veth pair with addresses private to the two namespaces (10.213.<i>.1/.2 /30, no
route anywhere else). A rate limits agent 0's link both ways with `tc tbf` (a constrained radio
link); delay and drop stay in hammer's own fault layer. Reported per run: bytes per vector step on
each agent link (veth counters, both directions), env-steps/s, step latency, actions that missed
their deadline. Everything created is deleted at the end (namespaces take their veths with them).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

PORT = 7447


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be created here (not root, no `ip`, or a kernel without veth)."""


def _ip(*args: str, ns: str | None = None) -> str:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise NetnsUnavailable(f"{' '.join(cmd)}: {r.stderr.strip()}")
    return r.stdout


@contextmanager
def topology(n_agents: int, tag: str, rate_kbit: int = 0):
    """Namespaces hub + one per agent, veth pairs hub<->agent i, optional tbf on agent 0's link.
    Yields (hub ns, [agent ns], [hub-side veth]); deletes everything on the way out."""
    hub = f"hmr{tag}h"
    agents = [f"hmr{tag}a{i}" for i in range(n_agents)]
    made: list[str] = []
    try:
        for ns in [hub, *agents]:
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("link", "set", "lo", "up", ns=ns)
        veths = []
        for i, ns in enumerate(agents):
            h, a = f"h{tag}{i}"[:15], f"a{tag}{i}"[:15]
            _ip("link", "add", h, "netns", hub, "type", "veth", "peer", "name", a, "netns", ns)
            _ip("addr", "add", f"10.213.{i}.1/30", "dev", h, ns=hub)
            _ip("addr", "add", f"10.213.{i}.2/30", "dev", a, ns=ns)
            _ip("link", "set", h, "up", ns=hub)
            _ip("link", "set", a, "up", ns=ns)
            veths.append(h)
            if i == 0 and rate_kbit:
                for dev, n in ((h, hub), (a, ns)):
                    r = subprocess.run(["ip", "netns", "exec", n, "tc", "qdisc", "add", "dev", dev, "root", "tbf",
                                        "rate", f"{rate_kbit}kbit", "burst", "16kb", "latency", "400ms"], check=False, capture_output=True, text=True, timeout=10)
                    if r.returncode != 0:
                        raise NetnsUnavailable(f"tc tbf on {dev}: {r.stderr.strip()}")
        yield hub, agents, veths
    finally:
        for ns in reversed(made):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True, timeout=10)


def link_bytes(ns: str, dev: str) -> int:
    """Bytes both ways through `dev` so far (its stats64 counters)."""
    st = json.loads(_ip("-j", "-s", "link", "show", "dev", dev, ns=ns))[0]["stats64"]
    return int(st["rx"]["bytes"]) + int(st["tx"]["bytes"])


def _client_config(path: Path, endpoint: str) -> Path:
    path.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [endpoint]},
                                "scouting": {"multicast": {"enabled": False}}}))
    return path


def served_run(bundle: Path, work: Path, episodes: int = 16, rate_kbit: int = 0, tag: str | None = None,
               timeout_s: float = 240) -> dict:
    """One served run across namespaces; returns its figures (raises NetnsUnavailable where it cannot)."""
    from serve.bundle import load_bundle

    b = load_bundle(bundle)
    n = b.config().n_agents
    tag = tag or str(os.getpid() % 100000)
    work.mkdir(parents=True, exist_ok=True)
    run = work / f"served-{rate_kbit}"
    py = [sys.executable, "-m", "hammer.cli"]
    procs: list[subprocess.Popen] = []

    def start(ns: str, args: list[str], log: str) -> subprocess.Popen:
        with open(work / log, "wb") as f:
            p = subprocess.Popen(["ip", "netns", "exec", ns, *py, *args], stdout=f, stderr=subprocess.STDOUT)
        procs.append(p)
        return p

    with topology(n, tag, rate_kbit) as (hub, agents, veths):
        try:
            start(hub, ["hub", "--listen", f"tcp/0.0.0.0:{PORT}"], f"hub-{rate_kbit}.log")
            time.sleep(1.0)
            inside = _client_config(work / "hub-client.json5", f"tcp/127.0.0.1:{PORT}")
            before = [link_bytes(hub, v) for v in veths]
            serve = start(hub, ["serve", str(bundle), "--episodes", str(episodes), "--external",
                                ",".join(map(str, range(n))), "--runtime", f"zenoh_config_file={inside}",
                                "--run-dir", str(run), "--no-dashboard"], f"serve-{rate_kbit}.log")
            edges = [start(ns, ["local", "--bundle", str(bundle), "--agent", str(i), "--run-id", run.name,
                                "--zenoh-config", str(_client_config(work / f"edge{i}.json5",
                                                                     f"tcp/10.213.{i}.1:{PORT}"))],
                           f"local-{i}-{rate_kbit}.log") for i, ns in enumerate(agents)]
            code = serve.wait(timeout=timeout_s)
            after = [link_bytes(hub, v) for v in veths]
            for e in edges:
                e.wait(timeout=30)
        finally:
            for p in procs:
                if p.poll() is None:
                    p.terminate()
                    try:
                        p.wait(timeout=10)
                    except subprocess.TimeoutExpired:
                        p.kill()
    summary = json.loads((run / "env_summary.json").read_text()) if (run / "env_summary.json").is_file() else {}
    steps = max(int(summary.get("step", 0)), 1)
    return {"rate_kbit": rate_kbit, "completed": code == 0 and bool(summary.get("completed")),
            "edge_exit_codes": [e.returncode for e in edges], "steps": summary.get("step", 0),
            "bytes_per_step": [(a - b_) / steps for a, b_ in zip(after, before)],
            "env_steps_per_s": summary.get("env_steps_per_s"), "step_p50_ms": summary.get("step_latency_ms_p50"),
            "step_p99_ms": summary.get("step_latency_ms_p99"),
            "default_actions": summary.get("links", {}).get("default_actions"),
            "msg_fallback_copies": summary.get("links", {}).get("msg_fallback_copies"), "run_dir": str(run)}


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--rates", default="0,1024,256", help="kbit/s limits of agent 0's link (0 = none)")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--work", type=Path, default=Path("runs/netns"))
    a = ap.parse_args()
    for rate in [int(x) for x in a.rates.split(",")]:
        try:
            r = served_run(a.bundle, a.work, a.episodes, rate)
        except NetnsUnavailable as e:
            sys.exit(f"error: network namespaces unavailable here: {e}")
        print(json.dumps(r))


if __name__ == "__main__":
    main()
