"""A served team across Linux network namespaces: real links instead of loopback.

    python -m hammer.benchmarks.netns BUNDLE [--rates 0,1024,256] [--episodes 16] [--edge-venv PY] [--push BUNDLE_B]
                                                                                (root; see docs/deploy.md)

The hub namespace holds the Zenoh router (`hammer hub`), the launcher, env host and policy server
(`hammer serve --external ...`, every role a Zenoh client of the router); the central agent
(`hammer central`) and each local agent (`hammer local --bundle`, from a torch-free venv with
--edge-venv) run in namespaces of their own, each joined to the hub namespace by a veth pair with
addresses private to the two namespaces (10.213.<i>.1/.2 /30 for agent i, 10.213.200.x for the
central agent; no route anywhere else). A rate limits agent 0's link both ways with `tc tbf` (a
constrained radio link); delay and drop stay in hammer's own fault layer (this kernel has no
netem). --push BUNDLE_B sends a hot update and then a rollback through the real CLI mid-run
(benchmarks.push_driver) and checks in the env host's trace that every step was acted on with one
version. Reported per run: bytes per vector step on every link (veth counters, both directions,
start-up and weights included), env-steps/s, step latency, default actions, message fallbacks,
and `keeps_up`. Everything created is deleted at the end (namespaces take their veths with them).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

PORT = 7447
CENTRAL_NET = 200  # the central agent's link is 10.213.200.0/30
KEEPS_UP_FRACTION = 0.5  # a limited link keeps up at >= half the unlimited env-steps/s with no fallbacks


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be created here (not root, no `ip`, or a kernel without veth)."""


def _ip(*args: str, ns: str | None = None) -> str:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise NetnsUnavailable(f"{' '.join(cmd)}: {r.stderr.strip()}")
    return r.stdout


@dataclass
class Topology:
    """The namespaces of one run and its links: link name (local-<i>, central) -> (hub-side veth, hub
    address); `far`: link name -> (namespace, veth) of its other end, the robot's own interface."""

    hub: str
    agents: list[str]
    central: str | None
    links: dict[str, tuple[str, str]] = field(default_factory=dict)
    far: dict[str, tuple[str, str]] = field(default_factory=dict)


def _veth_names(tag: str, net: int) -> tuple[str, str]:
    """The hub-side and far-side names of the veth pair of subnet `net` (15 characters at most)."""
    return f"h{tag}{net}"[:15], f"a{tag}{net}"[:15]


def _veth(tag: str, net: int, hub: str, ns: str, rate_kbit: int) -> tuple[str, str]:
    """A veth pair hub <-> ns with 10.213.<net>.1 (hub side) / .2 and an optional tbf both ways."""
    h, a = _veth_names(tag, net)
    _ip("link", "add", h, "netns", hub, "type", "veth", "peer", "name", a, "netns", ns)
    _ip("addr", "add", f"10.213.{net}.1/30", "dev", h, ns=hub)
    _ip("addr", "add", f"10.213.{net}.2/30", "dev", a, ns=ns)
    _ip("link", "set", h, "up", ns=hub)
    _ip("link", "set", a, "up", ns=ns)
    for dev, n in ((h, hub), (a, ns)) if rate_kbit else ():
        r = subprocess.run(["ip", "netns", "exec", n, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate",
                            f"{rate_kbit}kbit", "burst", "16kb", "latency", "400ms"],
                           check=False, capture_output=True, text=True, timeout=10)
        if r.returncode != 0:
            raise NetnsUnavailable(f"tc tbf on {dev}: {r.stderr.strip()}")
    return h, f"10.213.{net}.1"


@contextmanager
def topology(n_agents: int, tag: str, rate_kbit: int = 0, central: bool = False):
    """Namespaces hub, one per agent (and one for the central agent), a veth pair from the hub to
    each, tbf on agent 0's link. Yields a Topology; deletes every namespace it made on the way out."""
    top = Topology(f"hmr{tag}h", [f"hmr{tag}a{i}" for i in range(n_agents)], f"hmr{tag}c" if central else None)
    made: list[str] = []
    try:
        for ns in [top.hub, *top.agents, *([top.central] if central else [])]:
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("link", "set", "lo", "up", ns=ns)
        for i, ns in enumerate(top.agents):
            top.links[f"local-{i}"] = _veth(tag, i, top.hub, ns, rate_kbit if i == 0 else 0)
            top.far[f"local-{i}"] = (ns, _veth_names(tag, i)[1])
        if central:
            top.links["central"] = _veth(tag, CENTRAL_NET, top.hub, top.central, 0)
            top.far["central"] = (top.central, _veth_names(tag, CENTRAL_NET)[1])
        yield top
    finally:
        for ns in reversed(made):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True, timeout=10)


@dataclass
class Lan:
    """A site's LAN: the serving machine and one namespace per robot, each with one interface into a
    bridge (the switch) in a namespace of its own. `address`: the serving machine's; `ports`: who
    (`server`, `local-<i>`) -> its port on the switch (a veth in `switch`); `nics`: who -> (namespace,
    its own interface)."""

    server: str
    robots: list[str]
    switch: str
    address: str
    ports: dict[str, str] = field(default_factory=dict)
    nics: dict[str, tuple[str, str]] = field(default_factory=dict)


LAN_NET = "10.214.0"  # the serving machine is .1, robot i is .(10 + i), /24


@contextmanager
def lan(n_robots: int, tag: str, rate_kbit: int = 0):
    """Namespaces server, switch (a bridge) and one per robot, each machine's interface into a switch
    port; tbf both ways on robot 0's port with `rate_kbit` (a thin radio link). Yields a Lan; deletes
    every namespace it made on the way out (their veths go with them)."""
    net = Lan(f"hmr{tag}s", [f"hmr{tag}r{i}" for i in range(n_robots)], f"hmr{tag}w", f"{LAN_NET}.1")
    made: list[str] = []
    try:
        for ns in [net.switch, net.server, *net.robots]:
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("link", "set", "lo", "up", ns=ns)
        _ip("link", "add", "br0", "type", "bridge", ns=net.switch)
        _ip("link", "set", "br0", "up", ns=net.switch)
        for j, (who, ns, addr) in enumerate([("server", net.server, net.address),
                                            *((f"local-{i}", r, f"{LAN_NET}.{10 + i}") for i, r in enumerate(net.robots))]):
            port, nic = f"p{tag}{j}"[:15], f"e{tag}{j}"[:15]
            _ip("link", "add", port, "netns", net.switch, "type", "veth", "peer", "name", nic, "netns", ns)
            _ip("link", "set", port, "master", "br0", ns=net.switch)
            _ip("addr", "add", f"{addr}/24", "dev", nic, ns=ns)
            _ip("link", "set", port, "up", ns=net.switch)
            _ip("link", "set", nic, "up", ns=ns)
            net.ports[who], net.nics[who] = port, (ns, nic)
            if rate_kbit and who == "local-0":
                for dev, n in ((port, net.switch), (nic, ns)):
                    r = subprocess.run(["ip", "netns", "exec", n, "tc", "qdisc", "add", "dev", dev, "root", "tbf",
                                        "rate", f"{rate_kbit}kbit", "burst", "16kb", "latency", "400ms"],
                                       check=False, capture_output=True, text=True, timeout=10)
                    if r.returncode != 0:
                        raise NetnsUnavailable(f"tc tbf on {dev}: {r.stderr.strip()}")
        yield net
    finally:
        for ns in reversed(made):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True, timeout=10)


def link_counts(ns: str, dev: str) -> tuple[int, int]:
    """(bytes, packets) both ways through `dev` so far (its stats64 counters)."""
    st = json.loads(_ip("-j", "-s", "link", "show", "dev", dev, ns=ns))[0]["stats64"]
    return (int(st["rx"]["bytes"]) + int(st["tx"]["bytes"]), int(st["rx"]["packets"]) + int(st["tx"]["packets"]))


def link_bytes(ns: str, dev: str) -> int:
    """Bytes both ways through `dev` so far (its stats64 counters)."""
    return link_counts(ns, dev)[0]


def client_config(path: Path, endpoint: str) -> Path:
    """A Zenoh client config connecting to the router at `endpoint` only (no scouting), without shared
    memory: namespaces share /dev/shm, and Zenoh would pass every message over 3 kB (global states,
    weights) through it instead of the link, which no two machines can do."""
    from hammer.protocol.session import RECONNECT

    path.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [endpoint], "retry": RECONNECT},
                                "scouting": {"multicast": {"enabled": False}},
                                "transport": {"shared_memory": {"enabled": False}}}))
    return path


class Procs:
    """The processes of one run, each in a namespace with its log in `work`; all ended on close."""

    def __init__(self, work: Path) -> None:
        self.work, self.procs = work, []

    def start(self, ns: str, cmd: list[str], log: str, env: dict | None = None) -> subprocess.Popen:
        with open(self.work / log, "wb") as f:
            p = subprocess.Popen(["ip", "netns", "exec", ns, *cmd], stdout=f, stderr=subprocess.STDOUT, env=env)
        self.procs.append(p)
        return p

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()


def _wait_for(what: str, ok, timeout_s: float, procs: list[subprocess.Popen]) -> None:
    deadline = time.monotonic() + timeout_s
    while not ok():
        if time.monotonic() > deadline or any(p.poll() not in (None, 0) for p in procs):
            raise RuntimeError(f"{what} did not happen within {timeout_s:.0f} s (or a process exited early)")
        time.sleep(0.1)


def served_run(bundle: Path, work: Path, episodes: int = 16, rate_kbit: int = 0, tag: str | None = None,
               timeout_s: float = 240, *, edge_python: Path | None = None, push: Path | None = None,
               central_ns: bool = True, baseline_steps_per_s: float | None = None,
               runtime: tuple[str, ...] = (), num_envs: int | None = None) -> dict:
    """One served run across namespaces; returns its figures (raises NetnsUnavailable where it cannot).
    edge_python: the local agents' interpreter (a torch-free venv); push: a bundle to push mid-run and
    roll back; baseline_steps_per_s: the unlimited run's rate, for `keeps_up`; num_envs: serve K env
    copies instead of the bundle's."""
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle)
    cfg, ep_len = b.config(), int(b.env_spec_data.get("max_steps") or 25)
    n, central = cfg.n_agents, central_ns and cfg.wiring.uses_central
    k = num_envs or cfg.num_envs
    k_args = [] if num_envs is None else ["--num-envs", str(num_envs)]
    tag = tag or str(os.getpid() % 100000)
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    run = work / f"served-{rate_kbit}"
    shutil.rmtree(run, ignore_errors=True)  # a stale runtime.json would start the central agent too early
    py = [sys.executable, "-P", "-m", "hammer.cli"]
    edge_py = [str(edge_python) if edge_python else sys.executable, "-P", "-m", "hammer"]  # the edge entry (hammer/entry.py)
    procs = Procs(work)
    with topology(n, tag, rate_kbit, central) as top:
        try:
            hub = procs.start(top.hub, [*py, "hub", "--listen", f"tcp/0.0.0.0:{PORT}", "--insecure"], f"hub-{rate_kbit}.log")
            _wait_for("the hub listening", lambda: b"listening" in (work / f"hub-{rate_kbit}.log").read_bytes(),
                      30, [hub])
            inside = client_config(work / "hub-client.json5", f"tcp/127.0.0.1:{PORT}")
            before = {k: link_bytes(top.hub, dev) for k, (dev, _) in top.links.items()}
            external = ",".join([*map(str, range(n)), *(["central"] if central else [])])
            # Plain across namespaces on purpose (the bench measures the plain wire); --insecure says so.
            rt = [f"zenoh_config_file={inside}", "insecure=true", *(["trace=true"] if push else []), *runtime]
            serve = procs.start(top.hub, [*py, "serve", str(bundle), *k_args, "--episodes", str(episodes), "--external",
                                          external, *(x for r in rt for x in ("--runtime", r)), "--run-dir", str(run),
                                          "--no-dashboard"], f"serve-{rate_kbit}.log")
            edges = [procs.start(ns, [*edge_py, "local", "--bundle", str(bundle), *k_args, "--agent", str(i), "--run-id",
                                      run.name, "--insecure", "--zenoh-config",
                                      str(client_config(work / f"edge{i}.json5", f"tcp/{top.links[f'local-{i}'][1]}:{PORT}"))],
                                 f"local-{i}-{rate_kbit}.log", env=_edge_env(edge_python))
                     for i, ns in enumerate(top.agents)]
            quarter = str(max(-(-episodes // k) * ep_len // 4, 1))
            others = _start_central_and_driver(procs, top, run, py, push and [str(push), "--push-at", quarter,
                                                                             "--rollback-after", quarter],
                                               rate_kbit, inside, serve)
            code = serve.wait(timeout=timeout_s)
            after = {k: link_bytes(top.hub, dev) for k, (dev, _) in top.links.items()}
            for p in [*edges, *others]:
                p.wait(timeout=30)
        finally:
            procs.close()
    return _figures(run, work, rate_kbit, code, edges, before, after, baseline_steps_per_s, push is not None)


def _edge_env(edge_python: Path | None) -> dict | None:
    if edge_python is None:
        return None
    from hammer.benchmarks.edge_venv import clean_env

    return clean_env()


def _start_central_and_driver(procs: Procs, top: Topology, run: Path, py: list[str], push: list[str] | None,
                              rate_kbit: int, inside: Path, serve: subprocess.Popen) -> list[subprocess.Popen]:
    """The central agent in its namespace once the run directory is written (it reads config.json,
    runtime.json, env_spec.json from it, as from a copy on its own machine), and the update driver
    (`push`: its bundle and step arguments: push after a quarter of the run, roll back a quarter later)."""
    out = []
    if top.central is not None:
        _wait_for("the served run directory", lambda: (run / "env_spec.json").is_file(), 60, [serve])
        _, addr = top.links["central"]
        cfg = client_config(procs.work / "central.json5", f"tcp/{addr}:{PORT}")
        out.append(procs.start(top.central, [*py, "central", "--run-dir", str(run), "--zenoh-config", str(cfg)],
                               f"central-{rate_kbit}.log"))
    if push is not None:
        out.append(procs.start(top.hub, [sys.executable, "-P", "-m", "hammer.benchmarks.push_driver", str(run), *push,
                                         "--zenoh-config", str(inside)], f"push-{rate_kbit}.log"))
    return out


def _figures(run: Path, work: Path, rate_kbit: int, code: int, edges, before: dict, after: dict,
             baseline: float | None, pushed: bool) -> dict:
    """What one run measured, and whether the loop kept up on this link."""
    summary = json.loads((run / "env_summary.json").read_text()) if (run / "env_summary.json").is_file() else {}
    steps = max(int(summary.get("step", 0)), 1)
    links = summary.get("links", {})
    rate = summary.get("env_steps_per_s") or 0.0
    completed = code == 0 and bool(summary.get("completed"))
    fallbacks, defaults = links.get("msg_fallback_copies"), links.get("default_actions")
    keeps_up = (completed and fallbacks == 0 and defaults == 0
                and (baseline is None or rate >= KEEPS_UP_FRACTION * baseline))
    out = {"rate_kbit": rate_kbit, "completed": completed, "edge_exit_codes": [e.returncode for e in edges],
           "steps": summary.get("step", 0), "episodes": summary.get("episodes"),
           "bytes_per_step": {k: round((after[k] - before[k]) / steps, 1) for k in after},
           "env_steps_per_s": rate, "step_p50_ms": summary.get("step_latency_ms_p50"),
           "step_p99_ms": summary.get("step_latency_ms_p99"), "default_actions": defaults,
           "msg_fallback_copies": fallbacks, "off_policy_actions": links.get("off_policy_actions"),
           "baseline_env_steps_per_s": baseline, "keeps_up": keeps_up, "run_dir": str(run),
           "pushes": summary.get("pushes")}
    if pushed:
        out["updates"] = update_check(run, work / f"push-{rate_kbit}.log")
    return out


def update_check(run: Path, driver_log: Path) -> dict:
    """What the hot update and the rollback did, from the driver's report and the env host's trace:
    steps acted per version, whether versions only rose and no step was missed."""
    import numpy as np

    lines = driver_log.read_text().strip().splitlines() if driver_log.is_file() else []
    try:
        driver = json.loads(lines[-1])
    except (IndexError, json.JSONDecodeError):
        driver = {"error": f"no report in {driver_log}: {' | '.join(lines[-2:])}"}
    trace_file = run / "trace.npz"
    if not trace_file.is_file():
        return {"driver": driver, "error": "no trace.npz"}
    with np.load(trace_file) as t:
        steps, versions = t["steps"], t["versions"]
    # From the driver's command to the first step acted with its version.
    took = {f"{what}_took_steps": int(steps[np.argmax(versions >= v)]) - driver[f"{what}_at"]
            for what, v in (("push", 1), ("rollback", 2)) if f"{what}_at" in driver and (versions >= v).any()}
    return {"driver": driver, **took, "steps_per_version": {int(v): int((versions == v).sum()) for v in np.unique(versions)},
            "versions_monotone": bool(np.all(np.diff(versions) >= 0)),
            "no_step_missed": bool(np.array_equal(steps, np.arange(steps[0], steps[0] + len(steps))))}


def main() -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--rates", default="0,1024,256", help="kbit/s limits of agent 0's link (0 = none; first = baseline)")
    ap.add_argument("--episodes", type=int, default=16)
    ap.add_argument("--work", type=Path, default=Path("runs/netns"))
    ap.add_argument("--edge-venv", type=Path, help="python of a torch-free venv for the local agents "
                                                   "(python -m hammer.benchmarks.edge_venv PATH builds one)")
    ap.add_argument("--push", type=Path, help="a bundle to push mid-run, then roll back (through the CLI)")
    ap.add_argument("--runtime", action="append", default=[], help="RuntimeSettings FIELD=VALUE for the served run")
    ap.add_argument("--timeout", type=float, default=600)
    ap.add_argument("--num-envs", type=int, help="serve K env copies (default: the bundle's)")
    a = ap.parse_args()
    import signal

    from hammer.runtime.process import take_signals

    take_signals((signal.SIGTERM,), lambda _: sys.exit(143))  # a stopped bench still deletes its namespaces
    baseline = None
    for rate in [int(x) for x in a.rates.split(",")]:
        try:
            r = served_run(a.bundle, a.work, a.episodes, rate, edge_python=a.edge_venv, push=a.push,
                           baseline_steps_per_s=baseline, runtime=tuple(a.runtime), timeout_s=a.timeout,
                           num_envs=a.num_envs)
        except NetnsUnavailable as e:
            sys.exit(f"error: network namespaces unavailable here: {e}")
        if rate == 0 and r["completed"]:
            baseline = r["env_steps_per_s"]
        print(json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
