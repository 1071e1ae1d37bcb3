"""`hammer bench fleet`: the documented fleet across network namespaces, links cut, every trial reported.

    hammer bench fleet BUNDLE [--trials port:8x10,port:30x10,hub:8x5] [--insecure] --out F.json   (root)
    hammer bench fleet BUNDLE --soak-minutes 60          (a fleet on loopback: RSS and disk over time)
    hammer bench fleet BUNDLE --push B                   (a hot update mid-run: each robot's switch, rates)

A site's LAN (benchmarks/netns.lan): the serving machine and one namespace per robot, each plugged
into a bridge (the switch). On the serving machine the command docs/fleet.md gives, `hammer serve
BUNDLE --realtime HZ --external 0,..,N-1 --listen tcp/<its address>:7447 --secure --run-dir RUN`
(the same launcher as every fleet: deploy/fleet_launch.py); in each robot's namespace, from a folder
holding only the bundle and its copy of its three identity files, the robot command that launcher
printed and wrote to RUN/fleet.json. Secure by default; `--insecure` runs the plain profile.

Trials (`--trials KIND:SECONDS[xN],...`), one after another, GAP_S apart, robots in turn: `port`
takes the cut robot's switch port down (the switch or access point lost it), `nic` the robot's own
interface (it drove out of range), `hub` the serving machine's port (every robot cut); no link
down: `world` stops the world process (SIGSTOP) and `router` the launcher, whose session is the
fleet's router, for SECONDS, then lets it go (SIGCONT): a server starved of CPU. Each trial
is appended to a JSON-lines file as it finishes (`<out>.trials.jsonl`). `site` (a team with a site
feed, docs/fleet.md "The site feed"): the site is a `hammer.site.SiteFeed` in a namespace of its own
(`hammer serve --external-site`), publishing at HZ the warehouse's current columns as the simulated
world writes them for its management system (`hammer.site.simulated_warehouse`), and its switch port goes down;
per trial the robots' rates during the cut and how long after the return the central agent took the
feed again. run the same command again
and it runs only the trials still missing. Per trial: every healthy robot's control rate during the
cut (fresh actions the world applied per second, against the world's rate), and for every cut
robot how long after the link returned the robot acted on a fresh central message again, the
world and the central agent heard it again (None: not within RECOVER_WAIT_S, stranded); the
machine's load. `--bytes-s S`: bytes and packets per control step on robot 0's interface (both
ways, everything on the wire) over S quiet seconds first.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from hammer.benchmarks.netns import PORT, NetnsUnavailable, Procs, _wait_for, lan, link_counts
from hammer.benchmarks.results import write_json

GAP_S = 8.0  # after each cut's return, before the next: the fleet settles (and stranding shows)
SETTLE_S = 5.0  # from the world's clock starting to the first cut
RECOVER_WAIT_S = 30.0  # how long after a return a role may take before it counts as stranded
CONTRACT = {"healthy_fraction": 0.98, "back_s": 1.5}  # docs/fleet.md "Recovery"
LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")
KINDS = ("port", "nic", "hub", "site", "world", "router")
STALLED = {"world": "fleet-world", "router": None}  # a stall trial's process: the world role, or the launcher (the router)
SITE_SCRIPT = """
import sys, time
from hammer.site import SiteFeed, simulated_warehouse
bundle, run_dir, run_id, connect, hz, profile = sys.argv[1:7]
wms_state = simulated_warehouse(run_dir)
with SiteFeed(bundle, run_id=run_id, connect=connect, identity="identity" if profile == "secure" else None,
              insecure=profile != "secure", runtime=tuple(sys.argv[7:])) as site:
    while True:
        state = wms_state()
        if state is not None:
            site.publish(state)
        time.sleep(1 / float(hz))
"""


def parse_trials(text: str) -> list[tuple[str, float, int]]:
    """`port:8x10,hub:8x5` -> [("port", 8.0, 10), ("hub", 8.0, 5)]: the cut, its seconds, how many times."""
    out = []
    for item in filter(None, (x.strip() for x in text.split(","))):
        m = re.fullmatch(r"(\w+):([\d.]+)(?:x(\d+))?", item)
        if m is None or m[1] not in KINDS or float(m[2]) <= 0 or (m[3] is not None and int(m[3]) < 1):
            raise ValueError(f"--trials {item!r}: expected KIND:SECONDS[xN] with KIND one of {', '.join(KINDS)}, "
                             "e.g. port:8x10")
        out.append((m[1], float(m[2]), int(m[3] or 1)))
    return out


def _log_lines(path: Path, pattern: str) -> list[tuple[float, str]]:
    """(wall time in s since the epoch, line) of the log lines of `path` that contain `pattern`."""
    out = []
    if not path.is_file():
        return out
    for line in path.read_text(errors="replace").splitlines():
        m = LOG_TIME.match(line)
        if m and pattern in line:
            out.append((datetime.datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S,%f").timestamp(), line))
    return out


def _log_times(path: Path, pattern: str) -> list[float]:
    """Wall times (s since the epoch) of the log lines of `path` that contain `pattern`."""
    return [t for t, _ in _log_lines(path, pattern)]


def robot_back(log: Path, seconds: float, down: float, up: float) -> float | None:
    """Seconds from `up` until the robot acted on a fresh central message again (None: not yet, or not
    within GAP_S, when the next trial's lines would begin). Its first act after a gap over 1 s is
    logged with the message's freshness; a shorter cut shows only as a stale period beginning by
    1.5 s after the return (else 0.0: the messages never went stale)."""
    acts = [(t, line) for t, line in _log_lines(log, "observations again after") if down <= t <= up + GAP_S]
    if acts:
        t, line = acts[0]
        if "(central message fresh)" in line:
            return round(max(0.0, t - up), 2)
        start = t
    elif seconds >= 1.0:
        return None
    else:
        stale = [t for t in _log_times(log, "central messages stale") if down <= t <= up + 1.5]
        if not stale:
            return 0.0
        start = stale[0]
    fresh = min((t for t in _log_times(log, "fresh central messages again") if t >= start), default=None)
    return None if fresh is None else round(max(0.0, fresh - up), 2)


def _timeline(run: Path) -> list[dict]:
    path = run / "timeline.jsonl"
    if not path.is_file():
        return []
    out = []
    for x in path.read_text().splitlines():
        try:
            out.append(json.loads(x))
        except json.JSONDecodeError:
            pass  # the line being written
    return out


def _rates(timeline: list[dict], t0: float, t1: float) -> list[float] | None:
    """Per robot: fresh actions per second between wall times t0 and t1 (timeline lines inside; the
    window widened to 2.5 s at the least, the timeline having a line a second)."""
    if t1 - t0 < 2.5:
        mid = (t0 + t1) / 2
        t0, t1 = mid - 1.25, mid + 1.25
    inside = [x for x in timeline if t0 <= x["t"] <= t1]
    if len(inside) < 2:
        return None
    a, b = inside[0], inside[-1]
    dt = b["t"] - a["t"]
    return [round((fb - fa) / dt, 2) for fa, fb in zip(a["fresh"], b["fresh"], strict=True)]


def _back_after(path: Path, lost: str | None, back: str, down: float, up: float) -> float | None:
    """Seconds from `up` to the first `back` line after `down`; 0.0 when no `lost` line came after
    `down` (the role never lost it; lost None: it did); None when it lost it and is not back (yet)."""
    if lost is not None and not any(t >= down for t in _log_times(path, lost)):
        return 0.0
    t = min((t for t in _log_times(path, back) if t >= down), default=None)
    return None if t is None else round(max(0.0, t - up), 2)


class Fleet:
    """The documented fleet on a LAN of namespaces: the launcher on the serving machine, each robot in
    its own namespace from its own folder. `cut(kind, robot, seconds)` runs one trial."""

    def __init__(self, bundle: Path, work: Path, net, hz: float, secure: bool, edge_python: Path | None,
                 runtime: tuple[str, ...] = (), seconds: float = 86400, site: bool = False) -> None:
        self.bundle, self.work, self.net, self.hz, self.secure = Path(os.path.abspath(bundle)), work, net, hz, secure
        self.site = site  # the site feed from a namespace of its own: the LAN's last "robot" namespace
        self.n = len(net.robots) - site
        self.run = work / "run"
        self.procs = Procs(work)
        # absolute, not resolved: each robot starts from its own folder, and a venv's python is a link
        self.edge_python = None if edge_python is None else Path(os.path.abspath(edge_python))
        self.runtime, self.seconds = runtime, seconds
        self.serve: subprocess.Popen | None = None

    def start(self) -> None:
        py = [sys.executable, "-P", "-m", "hammer.cli"]
        self.serve = self.procs.start(self.net.server, [
            *py, "serve", str(self.bundle), "--realtime", f"{self.hz:g}", "--seconds", f"{self.seconds:g}",
            "--external", ",".join(map(str, range(self.n))), "--listen", f"tcp/{self.net.address}:{PORT}",
            "--secure" if self.secure else "--insecure", "--run-dir", str(self.run),
            "--timeline", str(self.run / "timeline.jsonl"), *(x for r in self.runtime for x in ("--runtime", r)),
            *(["--external-site"] if self.site else [])],
            "serve.log")
        fleet_json = self.run / "fleet.json"
        _wait_for("the launcher's fleet.json", fleet_json.is_file, 120, [self.serve])
        commands = json.loads(fleet_json.read_text())["robot_commands"]
        edge = [str(self.edge_python) if self.edge_python else sys.executable, "-P", "-m", "hammer"]
        env = None
        if self.edge_python is not None:
            from hammer.benchmarks.edge_venv import clean_env

            env = clean_env()
        if self.site:
            self._start_site(json.loads(fleet_json.read_text())["endpoint"])
        for i, ns in enumerate(self.net.robots[:self.n]):
            home = self.work / f"robot-{i}"
            shutil.rmtree(home, ignore_errors=True)
            home.mkdir(parents=True)
            cmd = commands[f"local-{i}"].split()
            if self.secure:  # the robot's copy of its three files, as docs/fleet.md says
                (home / "identity").mkdir()
                for name in ("ca.pem", f"local-{i}.pem", f"local-{i}.key"):
                    shutil.copy(self.run / "identity" / name, home / "identity" / name)
                cmd[cmd.index("--identity") + 1] = "identity"
            with open(self.work / f"local-{i}.log", "wb") as f:
                self.procs.procs.append(subprocess.Popen(["ip", "netns", "exec", ns, *edge, *cmd[1:]], cwd=home,
                                                         stdout=f, stderr=subprocess.STDOUT, env=env))
        _wait_for("the world's clock", lambda: "world clock starts" in self.log("env").read_text(errors="replace")
                  if self.log("env").is_file() else False, 120, [self.serve])

    def _start_site(self, endpoint: str) -> None:
        """The site feed in its namespace, from a folder holding its copy of its three identity files,
        publishing at HZ what the simulated warehouse's management system knows: the world's current
        columns (RUN/warehouse.npy, read out of band: the port cut silences the feed, not the site)."""
        from hammer.deploy.fleet_launch import LINK_FIELDS

        home = self.work / "site"
        shutil.rmtree(home, ignore_errors=True)
        home.mkdir(parents=True)
        links = [r for r in self.runtime if r.split("=", 1)[0] in LINK_FIELDS]  # the link settings robots get
        args = [str(self.bundle.resolve()), str(self.run.resolve()), self.run.name, endpoint, f"{self.hz:g}",
                "secure" if self.secure else "plain", *links]
        if self.secure:
            (home / "identity").mkdir()
            for name in ("ca.pem", "site.pem", "site.key"):
                shutil.copy(self.run / "identity" / name, home / "identity" / name)
        with open(self.work / "site.log", "wb") as f:
            self.procs.procs.append(subprocess.Popen(
                ["ip", "netns", "exec", self.net.robots[self.n], sys.executable, "-P", "-c", SITE_SCRIPT, *args],
                cwd=home, stdout=f, stderr=subprocess.STDOUT))

    def pid(self, kind: str) -> int:
        """The process a stall trial stops: the launcher (whose session is the fleet's router), or its
        child running the world role (`hammer.cli fleet-world`)."""
        if STALLED[kind] is None:
            return self.serve.pid
        for child in Path(f"/proc/{self.serve.pid}/task/{self.serve.pid}/children").read_text().split():
            try:
                argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            except FileNotFoundError:
                continue
            if STALLED[kind].encode() in argv:
                return int(child)
        raise RuntimeError(f"no {STALLED[kind]} process under the launcher (pid {self.serve.pid})")

    def log(self, role: str) -> Path:
        return self.work / f"{role}.log" if role.startswith("local-") else self.run / "logs" / f"{role}.log"

    def cut(self, kind: str, robot: int, seconds: float) -> dict:
        """One trial: the link down `seconds`, back up; the figures once every cut robot is back (or
        RECOVER_WAIT_S passed), and at least GAP_S after the return."""
        ns, dev = ((None, None) if kind in STALLED else
                   (self.net.switch, self.net.ports["server"]) if kind == "hub" else
                   (self.net.switch, self.net.ports[f"local-{self.n}"]) if kind == "site" else
                   (self.net.switch, self.net.ports[f"local-{robot}"]) if kind == "port" else
                   self.net.nics[f"local-{robot}"])
        cut = list(range(self.n)) if kind in ("hub", *STALLED) else [] if kind == "site" else [robot]
        load = os.getloadavg()[0]
        down = time.time()
        if kind in STALLED:  # no link down: the process starved (SIGSTOP), then running again
            pid = self.pid(kind)
            os.kill(pid, signal.SIGSTOP)
            time.sleep(seconds)
            os.kill(pid, signal.SIGCONT)
        else:
            subprocess.run(["ip", "-n", ns, "link", "set", dev, "down"], check=True, timeout=10)
            time.sleep(seconds)
            subprocess.run(["ip", "-n", ns, "link", "set", dev, "up"], check=True, timeout=10)
        up = time.time()

        def back() -> dict:
            if kind == "site":  # the central agent takes the feed again (it logs the silence and the return)
                return {"site": {"central": _back_after(self.log("central"), "site missing", "site rejoined",
                                                        down, up)}}
            return {f"local-{i}": {
                "robot": robot_back(self.log(f"local-{i}"), seconds, down, up),
                "world": _back_after(self.log("env"), f"local-{i} missing", f"local-{i} rejoined", down, up),
                "central": _back_after(self.log("central"), f"local-{i} missing", f"local-{i} rejoined", down, up)}
                for i in cut}

        while True:
            b = back()
            waited = time.time() - up
            if (all(v is not None for r in b.values() for v in r.values()) and waited >= GAP_S) \
                    or waited >= RECOVER_WAIT_S:
                break
            time.sleep(0.5)
        timeline = _timeline(self.run)
        during = _rates(timeline, down, up)
        before = _rates(timeline, down - GAP_S + 2, down)  # the same robots with no link down: the load's share
        healthy = [i for i in range(self.n) if i not in cut]
        hz_during = None if during is None else {f"local-{i}": during[i] for i in healthy}
        worst = [v for r in b.values() for v in r.values()]
        return {"kind": kind, "seconds": seconds, "cut": ["site"] if kind == "site" else [f"local-{i}" for i in cut], "down": round(down, 3),
                "up": round(up, 3), "load1": round(load, 2), "healthy_hz_during": hz_during,
                "healthy_min_fraction": (None if not healthy or during is None else
                                         round(min(during[i] for i in healthy) / self.hz, 3)),
                "healthy_min_fraction_before": (None if not healthy or before is None else
                                                round(min(before[i] for i in healthy) / self.hz, 3)),
                "back_s": b, "back_max_s": None if None in worst else max(worst), "stranded": None in worst}

    def link_use(self, seconds: float) -> dict:
        """Bytes and packets per control step on robot 0's own interface over `seconds` (both ways)."""
        ns, dev = self.net.nics["local-0"]
        t0 = time.time()
        b0, p0 = link_counts(ns, dev)
        time.sleep(seconds)
        b1, p1 = link_counts(ns, dev)
        t1 = time.time()
        ticks = [x for x in _timeline(self.run) if t0 - 1 <= x["t"] <= t1 + 1]
        steps = max(ticks[-1]["ticks"] - ticks[0]["ticks"], 1) if len(ticks) >= 2 else 1
        steps_in = steps * (t1 - t0) / (ticks[-1]["t"] - ticks[0]["t"]) if len(ticks) >= 2 else 1
        return {"seconds": round(t1 - t0, 1), "tls": self.secure, "bytes_per_step": round((b1 - b0) / steps_in, 1),
                "packets_per_step": round((p1 - p0) / steps_in, 2), "information_bytes": None}

    def stop(self) -> dict:
        """SIGTERM to the launcher (it stops every role, the robots included), its summary."""
        try:
            if self.serve is not None and self.serve.poll() is None:
                self.serve.send_signal(signal.SIGTERM)
                self.serve.wait(60)
        except subprocess.TimeoutExpired:
            pass
        finally:
            self.procs.close()
        path = self.run / "summary.json"
        return json.loads(path.read_text()) if path.is_file() else {}


def soak(bundle: Path, work: Path, minutes: float, hz: float, every_s: float = 30.0) -> dict:
    """A fleet on loopback for `minutes` (`hammer serve --realtime`'s launcher): RSS of every role
    process and the run directory's disk use every `every_s`, and each one's growth from the end of
    the first minute to the end."""
    import threading

    import psutil
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet

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




def information_bytes(bundle: Path) -> int:
    """What one control step must carry on a robot's link at the least: its observation up, the
    central message down (float32 each), its action (one byte for a discrete one, float32 each else).
    A team with a site feed: the robot's own columns only (the rest is the site's, not on its link)."""
    from hammer.serve.bundle import load_bundle
    from hammer.serve.edge_agent import site_columns

    b = load_bundle(bundle)
    env = b.env_spec_data
    msg_dim = int(b.config().msg_dim) if b.wiring().uses_central else 0
    act = 1 if env.get("discrete", True) and env.get("action_low") is None else 4 * int(env["action_dim"])
    cols = site_columns(env)
    return 4 * (int(env["obs_dim"]) if cols is None else cols[0]) + 4 * msg_dim + act


def run_trials(bundle: Path, work: Path, trials: list[tuple[str, float, int]], *, hz: float = 20.0,
               secure: bool = True, edge_python: Path | None = None, results: Path | None = None,
               per_fleet: int = 10, bytes_s: float = 0.0, rate_kbit: int = 0, runtime: tuple[str, ...] = (),
               neigh_retrans_ms: int | None = None, progress=print) -> dict:
    """Every trial of `trials` not yet in `results` (a JSON-lines file, appended as each finishes), in
    fleets of at most `per_fleet` trials each; returns every trial in `results` with the fleets'
    summaries. NetnsUnavailable where namespaces cannot be made."""
    from hammer.serve.bundle import load_bundle

    n = int(load_bundle(bundle).env_spec_data["n_agents"])
    site = any(kind == "site" for kind, _, _ in trials)  # the site feed from a namespace of its own
    results = results or work / "trials.jsonl"
    done = [json.loads(x) for x in results.read_text().splitlines() if x.strip()] if results.is_file() else []
    todo, g = [], 0  # g: the trial's place in the whole plan, which picks the robot cut (robots in turn)
    for kind, secs, count in trials:
        have = sum(1 for d in done if d.get("kind") == kind and d.get("seconds") == secs)
        todo += [(kind, secs, have + j, (g + have + j) % n) for j in range(count - have)]
        g += count
    fleets, link = [], None
    work.mkdir(parents=True, exist_ok=True)
    while todo or (bytes_s and link is None):
        batch, todo = todo[:per_fleet], todo[per_fleet:]
        tag = f"{os.getpid() % 1000}{len(fleets)}"
        with lan(n + site, tag, rate_kbit) as net:
            if neigh_retrans_ms is not None:
                for ns, dev in net.nics.values():
                    subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-qw",
                                    f"net.ipv4.neigh.{dev}.retrans_time_ms={neigh_retrans_ms}"], check=True, timeout=10)
            fleet = Fleet(bundle, work / f"fleet-{tag}", net, hz, secure, edge_python, runtime, site=site)
            shutil.rmtree(fleet.work, ignore_errors=True)
            fleet.work.mkdir(parents=True)
            try:
                fleet.start()
                time.sleep(SETTLE_S)
                if bytes_s and link is None:
                    link = {**fleet.link_use(bytes_s), "information_bytes": information_bytes(bundle),
                            "load1": round(os.getloadavg()[0], 2)}
                    link["times_information"] = round(link["bytes_per_step"] / link["information_bytes"], 2)
                    progress(f"robot 0's link: {link['bytes_per_step']} B and {link['packets_per_step']} packets per "
                             f"control step ({'TLS' if secure else 'plain'}; {link['times_information']}x the "
                             f"{link['information_bytes']} B of information)")
                for kind, secs, k, robot in batch:
                    t = {**fleet.cut(kind, robot, secs), "trial": k, "secure": secure, "fleet": fleet.work.name}
                    with open(results, "a") as f:
                        f.write(json.dumps(t) + "\n")
                    done.append(t)
                    progress(trial_line(t))
            finally:
                fleets.append({"fleet": fleet.work.name, "summary": _short(fleet.stop())})
    return {"bundle": str(bundle), "hz": hz, "secure": secure, "rate_kbit": rate_kbit,
            "neigh_retrans_ms": neigh_retrans_ms, "runtime": list(runtime), "contract": CONTRACT,
            "trials": done, "link": link, "fleets": fleets}


def _short(summary: dict) -> dict:
    """What of a fleet's summary.json a bench result keeps."""
    w = summary.get("world", {})
    return {"completed": summary.get("completed"), "stopped_by": summary.get("stopped_by"),
            "degraded_reasons": summary.get("degraded_reasons"), "ticks": w.get("ticks"),
            "ticks_skipped": w.get("ticks_skipped"), "paper_metric_mean": w.get("paper_metric_mean"),
            "defaults": {k: r.get("defaults") for k, r in summary.get("robots", {}).items()},
            # what the loop costs: a tick's start to the robot's action on it; the message a robot acted on
            "msgs": {k: w.get(k) for k in ("msgs_attached", "msgs_late", "msgs_missed")},
            "latency_ms": {k: {f: r.get(f) for f in ("step_to_action_ms_p50", "step_to_action_ms_p99",
                                                     "msg_age_p50_ms", "msg_age_p99_ms")}
                           for k, r in summary.get("robots", {}).items()},
            # a team with a site feed (docs/fleet.md "The site feed"): what the central agent took of it
            "site": summary.get("site")}


def trial_ok(t: dict) -> bool:
    """Whether a trial kept the contract: healthy robots at >= 0.98 of rate, every cut robot, the
    world and the central agent on fresh traffic <= 1.5 s after the return."""
    healthy = t["healthy_min_fraction"]
    return (not t["stranded"] and t["back_max_s"] <= CONTRACT["back_s"]
            and (healthy is None if not t["healthy_hz_during"] else healthy >= CONTRACT["healthy_fraction"]))


def trial_line(t: dict) -> str:
    backs = "; ".join(", ".join(f"{who} {v}" for who, v in b.items()) if r == "site" else
                      f"{r}: robot {b['robot']}, world {b['world']}, central {b['central']} s"
                      for r, b in t["back_s"].items())
    backs = backs if "site" not in t["back_s"] else f"site feed: {backs} s"
    return (f"{t['kind']:4} {t['seconds']:5g} s  #{t['trial']:<2} cut {','.join(t['cut'])}  healthy "
            f"{t['healthy_min_fraction']} of rate (before the cut {t.get('healthy_min_fraction_before')})  back "
            f"{backs}  load {t['load1']}  "
            f"{'ok' if trial_ok(t) else 'FAILS the contract'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hammer bench fleet", description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--hz", type=float, default=20.0)
    ap.add_argument("--trials", default="port:0.5x2,port:5x2,port:8x2,port:30x2,nic:8x2,nic:30x1,hub:8x2",
                    help="KIND:SECONDS[xN], comma-separated: port (the cut robot's switch port), nic (the robot's "
                         "own interface), hub (the serving machine's port: every robot), site (the site feed's "
                         "port: a team with a site feed; the site then runs in a namespace of its own), world (the world "
                         "process stopped: SIGSTOP, SIGCONT after SECONDS), router (the launcher, whose session is "
                         "the fleet's router, stopped likewise); robots in turn.")
    ap.add_argument("--insecure", action="store_true", help="The plain profile (default: --secure, as documented).")
    ap.add_argument("--per-fleet", type=int, default=10, help="Trials per fleet session (a fresh fleet after).")
    ap.add_argument("--bytes-s", type=float, default=0.0, help="First measure bytes and packets per control step "
                                                                "on robot 0's link over this many quiet seconds.")
    ap.add_argument("--rate-kbit", type=int, default=0, help="A tbf limit (kbit/s, both ways) on robot 0's port.")
    ap.add_argument("--neigh-retrans-ms", type=int, help="The kernel's neighbour (ARP) retransmission timer on "
                                                         "every machine's interface (Linux default 1000 ms).")
    ap.add_argument("--runtime", action="append", default=[], metavar="FIELD=VALUE",
                    help="Passed to `hammer serve --realtime --runtime` (e.g. zenoh_lease_s=3).")
    ap.add_argument("--edge-venv", type=Path, help="The robots' interpreter (a torch-free venv: benchmarks/edge_venv.py).")
    ap.add_argument("--work", type=Path, default=Path("/tmp/hammer-bench-fleet"))
    ap.add_argument("--out", type=Path, help="Write the JSON result here; the trials go to OUT.trials.jsonl as "
                                             "they finish (the same command again runs only the missing ones).")
    ap.add_argument("--push", type=Path, help="Instead of trials: a hot update to this bundle 10 s into a 30 s "
                                              "run (it must declare it works with the served central version: "
                                              "hammer export --works-with).")
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
        trials = parse_trials(a.trials)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if os.geteuid() != 0:
        print("error: network namespaces need root", file=sys.stderr)
        return 2
    results = a.out.with_suffix(".trials.jsonl") if a.out else a.work / "trials.jsonl"
    try:
        if a.push is not None:
            r = push_run(a.bundle, a.work, a.push, a.hz, not a.insecure, a.edge_venv, a.rate_kbit)
            print(f"push: robots switched {r['switch_s_after_push']} s after it; control Hz per robot "
                  f"{r['control_hz_before']} before, {r['control_hz_during_pull']} while they pulled")
            write_json(a.out, r)
            return 0
        r = run_trials(a.bundle, a.work, trials, hz=a.hz, secure=not a.insecure, edge_python=a.edge_venv,
                       results=results, per_fleet=a.per_fleet, bytes_s=a.bytes_s, rate_kbit=a.rate_kbit,
                       runtime=tuple(a.runtime), neigh_retrans_ms=a.neigh_retrans_ms)
    except NetnsUnavailable as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not r["trials"]:
        write_json(a.out, r)
        return 0
    print(f"\nevery trial ({'secure' if r['secure'] else 'plain'}, {a.hz:g} Hz; contract: healthy >= "
          f"{CONTRACT['healthy_fraction']} of rate, back <= {CONTRACT['back_s']} s):")
    for t in r["trials"]:
        print("  " + trial_line(t))
    bad = [t for t in r["trials"] if not trial_ok(t)]
    print(f"{len(r['trials']) - len(bad)} of {len(r['trials'])} trials keep the contract")
    write_json(a.out, r)
    return 0


def push_run(bundle: Path, work: Path, push: Path, hz: float, secure: bool, edge_python: Path | None,
             rate_kbit: int) -> dict:
    """A fleet on the LAN, `hammer push B --to RUN` SETTLE_S + 5 s after its clock starts: each robot's
    switch (its log line) and every robot's control rate while the pulls ran against before."""
    from hammer.serve.bundle import load_bundle

    n = int(load_bundle(bundle).env_spec_data["n_agents"])
    tag = f"{os.getpid() % 1000}p"
    with lan(n, tag, rate_kbit) as net:
        fleet = Fleet(bundle, work / f"fleet-{tag}", net, hz, secure, edge_python)
        shutil.rmtree(fleet.work, ignore_errors=True)
        fleet.work.mkdir(parents=True)
        try:
            fleet.start()
            time.sleep(SETTLE_S + 5)
            t = time.time()
            reply = subprocess.run(["ip", "netns", "exec", net.server, sys.executable, "-P", "-m", "hammer.cli", "push",
                                    str(push), "--to", str(fleet.run)], capture_output=True, text=True, timeout=120,
                                   check=False).stdout.strip()[-300:]
            time.sleep(15)
            switched = [min((x for x in _log_times(fleet.log(f"local-{i}"), "acting with policy version 1") if x >= t),
                            default=None) for i in range(n)]
            last = max((x for x in switched if x is not None), default=None)
            timeline = _timeline(fleet.run)
        finally:
            summary = fleet.stop()
    return {"push": reply, "rate_kbit": rate_kbit, "secure": secure,
            "switch_s_after_push": [None if x is None else round(x - t, 2) for x in switched],
            "control_hz_before": _rates(timeline, t - 5, t),
            "control_hz_during_pull": None if last is None else _rates(timeline, t, last), "summary": _short(summary)}


if __name__ == "__main__":
    sys.exit(main())
