"""`hammer bench fleet`: a trained team as a realtime fleet across network namespaces, links cut.

    hammer bench fleet BUNDLE [--hz 20] [--outages local-0:5,local-0:30,central:5,central:30] (root)
    hammer bench fleet BUNDLE --soak-minutes 60          (a fleet on loopback: RSS and disk over time)
    hammer bench fleet BUNDLE --push B                   (a hot update mid-run: each robot's switch, rates)

The hub namespace holds the Zenoh router (`hammer hub`) and the realtime world; the central agent
and every robot (`hammer local --bundle ... --fleet`, the torch-free SDK path) run in namespaces of
their own, joined to the hub by veth pairs (benchmarks/netns.py topology). First a run with no
outage (the baseline), then one run in which each outage takes a link down with `ip link set
... down` for its seconds and brings it back, 10 s apart.

Reported per outage: the healthy robots' control rate during it (actions that reached the world
per second, against the world's rate) and after it; the time from the link coming back to the cut
robot (or, for the central agent's link, every robot) acting on fresh central messages again, and
to the world hearing the cut robot again; defaults and fallbacks; and the team's paper metric
against the baseline. A JSON result goes to docs/results/ with --out.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from hammer.benchmarks.netns import PORT, NetnsUnavailable, Procs, _wait_for, client_config, topology
from hammer.benchmarks.results import write_json

GAP_S = 10.0  # between outages, and before the first: the fleet settles
LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def parse_outages(text: str) -> list[tuple[str, float, str]]:
    """`local-0:5,central:30@robot` -> [("local-0", 5.0, "hub"), ("central", 30.0, "robot")]: the link,
    how long it is down, and which end is taken down: `hub` (default), a cut beyond the robot (its own
    interface stays up, as when a switch or access point fails), or `robot`, its own interface (as
    when it drives out of range). `none`: no outage run (the baseline only)."""
    if text.strip() == "none":
        return []
    out = []
    for item in filter(None, (x.strip() for x in text.split(","))):
        spec, _, side = item.partition("@")
        link, _, secs = spec.partition(":")
        if not re.fullmatch(r"local-\d+|central", link) or not secs or side not in ("", "hub", "robot"):
            raise ValueError(f"--outages {item!r}: expected LINK:SECONDS[@hub|@robot] with LINK local-<i> or central")
        out.append((link, float(secs), side or "hub"))
    return out


def _log_times(path: Path, pattern: str) -> list[float]:
    """Wall times (s since the epoch) of the log lines of `path` that contain `pattern`."""
    times = []
    for line in path.read_text(errors="replace").splitlines():
        m = LOG_TIME.match(line)
        if m and pattern in line:
            times.append(datetime.datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp())
    return times


def _rates(timeline: list[dict], t0: float, t1: float) -> list[float] | None:
    """Per robot: fresh actions per second between wall times t0 and t1 (timeline lines inside)."""
    inside = [x for x in timeline if t0 <= x["t"] <= t1]
    if len(inside) < 2:
        return None
    a, b = inside[0], inside[-1]
    dt = b["t"] - a["t"]
    return [round((fb - fa) / dt, 2) for fa, fb in zip(a["fresh"], b["fresh"], strict=True)]


def fleet_run(bundle: Path, work: Path, outages: list[tuple[str, float, str]], hz: float, tag: str,
              edge_python: Path | None = None, seconds: float | None = None,
              neigh_retrans_ms: int | None = None, rate_kbit: int = 0, push: Path | None = None) -> dict:
    """One fleet across namespaces with `outages` one after another; returns its figures. `push`: no
    outages but a hot update to this bundle GAP_S into the run (the fleet's policy server runs in the
    hub namespace; `hammer push` writes the history it follows), timed to each robot's switch.
    `neigh_retrans_ms`: the kernel's neighbour (ARP) retransmission timer on the robots' and the
    central agent's interfaces, 1000 ms unless set (see main's --neigh-retrans-ms). `rate_kbit`: a tbf
    on robot 0's link, both ways (0 = none; see main's --rate-kbit)."""
    from hammer.serve.bundle import load_bundle

    b = load_bundle(bundle)
    n = int(b.env_spec_data["n_agents"])
    total = seconds or (3 * GAP_S if push else GAP_S + sum(s + GAP_S for _, s, _ in outages))
    run = work / f"fleet-{tag}"
    run.mkdir(parents=True, exist_ok=True)
    py = [sys.executable, "-P", "-m", "hammer.cli"]
    edge_py = [str(edge_python) if edge_python else sys.executable, "-P", "-m", "hammer"]
    common = ["--bundle", str(bundle), "--run-id", run.name, "--insecure"]
    procs = Procs(run)
    events: list[dict] = []
    with topology(n, tag, rate_kbit, central=True) as top:
        if neigh_retrans_ms is not None:
            for ns, dev in top.far.values():
                subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-qw",
                                f"net.ipv4.neigh.{dev}.retrans_time_ms={neigh_retrans_ms}"], check=True, timeout=10)
        try:
            hub = procs.start(top.hub, [*py, "hub", "--listen", f"tcp/0.0.0.0:{PORT}", "--insecure"], "hub.log")
            _wait_for("the hub listening", lambda: b"listening" in (run / "hub.log").read_bytes(), 30, [hub])
            # every role a client of the router, as in benchmarks/netns.py: peers would try to mesh
            # directly, and the namespaces have no route to each other
            def cfg(name: str, addr: str) -> str:
                return str(client_config(run / f"{name}.json5", f"tcp/{addr}:{PORT}"))

            world = procs.start(top.hub, [*py, "fleet-world", *common, "--zenoh-config", cfg("world", "127.0.0.1"),
                                          "--hz", str(hz), "--seconds", str(total), "--run-dir", str(run),
                                          "--timeline", str(run / "timeline.jsonl")], "env.log")
            procs.start(top.central, [*py, "fleet-central", *common, "--hz", str(hz), "--zenoh-config",
                                      cfg("central", top.links["central"][1])], "central.log")
            if push is not None:
                from hammer.deploy.fleet import FleetPlan, write_served_files

                write_served_files(b, FleetPlan(bundle=bundle, hz=hz), run, run.name)
                procs.start(top.hub, [*py, "fleet-policy", *common, "--zenoh-config", cfg("policy", "127.0.0.1"),
                                      "--run-dir", str(run)], "learner.log")
            for i, ns in enumerate(top.agents):
                procs.start(ns, [*edge_py, "local", *common, "--agent", str(i), "--fleet", "--zenoh-config",
                                 cfg(f"local-{i}", top.links[f"local-{i}"][1])], f"local-{i}.log")
            _wait_for("the world's clock", lambda: b"world clock starts" in (run / "env.log").read_bytes(), 90,
                      [world])
            start = time.time()
            if push is not None:
                time.sleep(GAP_S)
                events.append({"push": time.time(), "reply": subprocess.run(
                    [*py, "push", str(push), "--to", str(run)], capture_output=True, text=True, timeout=120,
                    check=False).stdout.strip()[-300:]})
            for link, secs, side in outages:
                time.sleep(max(0.0, start + GAP_S - time.time()))
                ns, dev = (top.hub, top.links[link][0]) if side == "hub" else top.far[link]
                down = time.time()
                subprocess.run(["ip", "-n", ns, "link", "set", dev, "down"], check=True, timeout=10)
                time.sleep(secs)
                subprocess.run(["ip", "-n", ns, "link", "set", dev, "up"], check=True, timeout=10)
                events.append({"link": link, "side": side, "seconds": secs, "down": down, "up": time.time()})
                start = time.time()
            world.wait(timeout=total + 60)
        finally:
            procs.close()
    return _figures(run, n, hz, events)


def _figures(run: Path, n: int, hz: float, events: list[dict]) -> dict:
    world = json.loads((run / "world.json").read_text())
    timeline = [json.loads(x) for x in (run / "timeline.jsonl").read_text().splitlines() if x.strip()]
    out = []
    for e in events:
        if "push" in e:
            out.append(_push_figures(run, n, hz, e, timeline))
            continue
        cut = [int(e["link"].split("-")[1])] if e["link"] != "central" else []
        healthy = [i for i in range(n) if i not in cut]
        during, after = _rates(timeline, e["down"], e["up"]), _rates(timeline, e["up"] + 2, e["up"] + GAP_S - 1)
        robots = [f"local-{i}" for i in (cut or range(n))]
        fresh_again = [min((t for pat in ("fresh central messages again", "(central message fresh)")
                            for t in _log_times(run / f"{r}.log", pat) if t >= e["up"]), default=None) for r in robots]
        heard = [min((t for t in _log_times(run / "env.log", f"{r} rejoined") if t >= e["up"]), default=None)
                 for r in robots] if cut else []
        out.append({
            "link": e["link"], "side": e["side"], "seconds": e["seconds"],
            "healthy_control_hz_during": None if during is None else [during[i] for i in healthy],
            "healthy_control_fraction_during": None if during is None else round(min(during[i] for i in healthy) / hz, 3),
            "control_hz_after": after,
            "fresh_messages_s_after_return": [None if t is None else round(t - e["up"], 2) for t in fresh_again],
            "world_hears_robot_s_after_return": [None if t is None else round(t - e["up"], 2) for t in heard]})
    return {"hz": hz, "world": world, "outages": out}


def _push_figures(run: Path, n: int, hz: float, e: dict, timeline: list[dict]) -> dict:
    """A push: when each robot began acting with the new version (its log line), and every robot's
    control rate while the pulls ran (push to the last switch) against the seconds before the push."""
    switched = [min((t for t in _log_times(run / f"local-{i}.log", "acting with policy version 1") if t >= e["push"]),
                    default=None) for i in range(n)]
    last = max((t for t in switched if t is not None), default=None)
    during = None if last is None else _rates(timeline, e["push"], last)
    before = _rates(timeline, e["push"] - GAP_S + 2, e["push"])
    return {"push": e["reply"], "switch_s_after_push": [None if t is None else round(t - e["push"], 2) for t in switched],
            "control_hz_before": before, "control_hz_during_pull": during,
            "min_control_fraction_during_pull": None if during is None else round(min(during) / hz, 3)}


def soak(bundle: Path, work: Path, minutes: float, hz: float, every_s: float = 30.0) -> dict:
    """A fleet on loopback for `minutes` (`hammer serve --realtime`'s launcher): RSS of every role
    process and the run directory's disk use every `every_s`, and each one's growth from the end of
    the first minute to the end."""
    import threading

    import psutil
    from hammer.deploy.fleet import FleetPlan, run_fleet

    run = work / f"fleet-soak-{os.getpid()}"
    every_s = min(every_s, max(1.0, minutes * 60 / 6))  # a short soak still gets a few samples
    samples: list[dict] = []
    done = threading.Event()

    def sample() -> None:
        me, t0 = psutil.Process(), time.monotonic()
        while not done.wait(0 if not samples else every_s):
            rss = {}
            for c in me.children(recursive=True):
                try:
                    cmd = c.cmdline()
                    agent = next((cmd[i + 1] for i, a in enumerate(cmd) if a == "--agent"), None)
                    role = (f"local-{agent}" if agent else "world" if "fleet-world" in cmd
                            else "central" if "fleet-central" in cmd else None)
                    if role is not None:  # not a child still starting (its command line is ours until exec)
                        rss[role] = round(c.memory_info().rss / 2**20, 1)
                except psutil.Error:
                    pass
            disk = sum(p.stat().st_size for p in run.rglob("*") if p.is_file()) if run.exists() else 0
            samples.append({"t": round(time.monotonic() - t0), "rss_mb": rss, "disk_kb": disk // 1024})

    threading.Thread(target=sample, daemon=True).start()
    try:
        summary = run_fleet(FleetPlan(bundle=bundle, hz=hz, seconds=minutes * 60), run)
    finally:
        done.set()
    settled = [s for s in samples if s["t"] >= 60 and s["rss_mb"]] or [s for s in samples if s["rss_mb"]]
    if not settled:
        raise RuntimeError(f"no process sampled in {minutes:g} min (logs: {run / 'logs'})")
    # the samples with every role up (not one starting, nor the end, when the world has exited first)
    full = max(len(s["rss_mb"]) for s in settled)
    whole = [s for s in settled if len(s["rss_mb"]) == full]
    first, last = whole[0], whole[-1]
    growth = {k: round((last["rss_mb"].get(k, v) - v) / v * 100, 2) for k, v in first["rss_mb"].items()}
    return {"minutes": minutes, "hz": hz, "world": summary["world"], "samples": samples,
            "growth_pct_from": first["t"], "growth_pct": growth, "disk_kb": [first["disk_kb"], last["disk_kb"]]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hammer bench fleet", description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--hz", type=float, default=20.0)
    ap.add_argument("--outages", default="local-0:5,local-0:30,local-0:30@robot,central:5,central:30",
                    help="LINK:SECONDS[@hub|@robot], comma-separated: the link's hub end (a cut beyond the "
                         "robot) or the robot's own interface is taken down.")
    ap.add_argument("--neigh-retrans-ms", type=int, help="The kernel's neighbour (ARP) retransmission timer "
                    "on the robots' and the central agent's interfaces (Linux default 1000 ms).")
    ap.add_argument("--baseline-s", type=float, default=30.0, help="Length of the run without outages.")
    ap.add_argument("--rate-kbit", type=int, default=0, help="A tbf limit (kbit/s, both ways) on robot 0's link in "
                    "both runs: does the loop keep its rate on a thin radio link (0 = none)?")
    ap.add_argument("--push", type=Path, help="Instead of outages: a hot update to this bundle 10 s into a 30 s "
                    "run (it must declare it works with the served central version: hammer export --works-with).")
    ap.add_argument("--edge-venv", type=Path, help="The robots' interpreter (a torch-free venv: benchmarks/edge_venv.py).")
    ap.add_argument("--work", type=Path, default=Path("/tmp/hammer-bench-fleet"))
    ap.add_argument("--out", type=Path, help="Write the JSON result here.")
    ap.add_argument("--soak-minutes", type=float, help="Instead: a fleet on loopback for this long, RSS per "
                                                       "process and disk every 30 s (no root needed).")
    a = ap.parse_args(argv)
    if a.soak_minutes:
        a.work.mkdir(parents=True, exist_ok=True)
        r = soak(a.bundle, a.work, a.soak_minutes, a.hz)
        print(f"fleet soak, {a.soak_minutes:g} min at {a.hz:g} Hz: {r['world']['ticks']} ticks "
              f"({r['world']['ticks_skipped']} skipped), {r['world']['episodes']} episodes; RSS growth from "
              f"t={r['growth_pct_from']} s to the end: " + ", ".join(f"{k} {v:+.1f} %" for k, v in r["growth_pct"].items())
              + f"; run directory {r['disk_kb'][0]} -> {r['disk_kb'][1]} kB")
        write_json(a.out, r)
        return 0
    try:
        outages = parse_outages(a.outages)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if os.geteuid() != 0:
        print("error: network namespaces need root", file=sys.stderr)
        return 2
    a.work.mkdir(parents=True, exist_ok=True)
    tag = str(os.getpid() % 10000)
    try:
        base = fleet_run(a.bundle, a.work, [], a.hz, f"{tag}b", a.edge_venv, seconds=a.baseline_s,
                         rate_kbit=a.rate_kbit)
        if a.push is not None:
            outages = []
        cut = fleet_run(a.bundle, a.work, outages, a.hz, f"{tag}o", a.edge_venv, neigh_retrans_ms=a.neigh_retrans_ms,
                        rate_kbit=a.rate_kbit, push=a.push) if outages or a.push else None
    except NetnsUnavailable as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    result = {"bundle": str(a.bundle), "hz": a.hz, "neigh_retrans_ms": a.neigh_retrans_ms, "rate_kbit": a.rate_kbit,
              "baseline": base["world"], "with_outages": cut}
    b_metric = base["world"].get("paper_metric_mean")
    print(f"fleet at {a.hz:g} Hz{f', robot 0 at {a.rate_kbit} kbit/s' if a.rate_kbit else ''}, "
          f"{base['world']['seconds']:.0f} s without outages: paper metric "
          f"{b_metric if b_metric is None else round(b_metric, 2)}, control Hz per robot "
          f"{[r['control_hz'] for r in base['world']['robots'].values()]}, defaults per robot "
          f"{[r['defaults'] for r in base['world']['robots'].values()]}")
    if cut is None:
        write_json(a.out, result)
        return 0
    c_metric = cut["world"].get("paper_metric_mean")
    for o in cut["outages"]:
        if "push" in o:
            print(f"  push: robots switched {o['switch_s_after_push']} s after it; control Hz per robot "
                  f"{o['control_hz_before']} before, {o['control_hz_during_pull']} while they pulled "
                  f"({o['min_control_fraction_during_pull']} of nominal at the least)")
            continue
        print(f"  {o['link']} down {o['seconds']:g} s ({o['side']} end): healthy robots {o['healthy_control_hz_during']} Hz during "
              f"({o['healthy_control_fraction_during']} of nominal), fresh messages "
              f"{o['fresh_messages_s_after_return']} s after the link returned, world hears the robot "
              f"{o['world_hears_robot_s_after_return']} s after")
    w = cut["world"]
    print(f"  with {'the push' if a.push else 'outages'}: paper metric {w.get('paper_metric_mean') if c_metric is None else round(c_metric, 2)}, "
          f"defaults per robot {[r['defaults'] for r in w['robots'].values()]}, ticks skipped {w['ticks_skipped']}")
    write_json(a.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
