"""What the web view costs the run it watches (docs/view.md, "Cost"): a fleet's control rate and action
ages, and `hammer up`'s env-steps/s, with `--view` and a page connected (headless Debian chromium on the
run page, on this same machine: the worst case, an operator's browser is usually elsewhere) against
without, the trials interleaved (the machine is shared: load drifts), each with its load average; and
the view process's peak RSS while the page is connected.

    python -m hammer.benchmarks.view_overhead --bundle BUNDLE --trials 3 --out docs/results/view-overhead.json

Without --view the launcher still writes the live files (RUN/live.json, 5 times a second); that
share is in both arms."""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]


def _browser(url: str):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        opts.add_argument(a)
    d = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
    d.get(url)
    return d


def _cpu(p: psutil.Process) -> float:
    t = p.cpu_times()
    return t.user + t.system


def _run(cmd: list[str], view: bool) -> dict:
    """Run a launcher command; with `view`, open its page. Sampled twice a second: the CPU seconds of the
    launcher itself, of the view process and of the browser (every process of each, by pid), and the
    view's peak RSS. CPU seconds hold on a shared machine where rates drift with the load."""
    env = {**os.environ, "HAMMER_TORCH_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "hammer.cli", *cmd, *(["--view", "0"] if view else []),
                             "--no-dashboard"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True).start()
    driver, rss, page = None, 0, False
    cpu: dict[str, dict[int, float]] = {"launcher": {}, "view": {}, "browser": {}}
    launcher = psutil.Process(proc.pid)
    load0, t0 = os.getloadavg()[0], time.monotonic()
    try:
        while proc.poll() is None:
            if view and driver is None:
                m = next((re.search(r"view: (http://\S+)", x) for x in lines if "view: http" in x), None)
                if m:
                    driver = _browser(m.group(1))
                    page = True
            try:
                cpu["launcher"][proc.pid] = _cpu(launcher)
                for p in launcher.children(recursive=True):
                    if "view" in p.cmdline():
                        cpu["view"][p.pid] = _cpu(p)
                        rss = max(rss, p.memory_info().rss)
                if driver is not None:
                    browser = psutil.Process(driver.service.process.pid)
                    for p in [browser, *browser.children(recursive=True)]:
                        cpu["browser"][p.pid] = _cpu(p)
            except psutil.NoSuchProcess:
                pass
            time.sleep(0.5)
    finally:
        if driver is not None:
            driver.quit()
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError("".join(lines[-10:]))
    return {"load_start": round(load0, 2), "load_end": round(os.getloadavg()[0], 2), "wall_s": round(wall, 1),
            "view_rss_mb": round(rss / 2**20, 1) if view else None, "page": page,
            **{f"cpu_pct_{k}": round(100 * sum(v.values()) / wall, 1) for k, v in cpu.items()}}


def fleet_trial(bundle: Path, hz: float, seconds: float, run: Path, view: bool) -> dict:
    r = _run(["serve", str(bundle), "--realtime", str(hz), "--seconds", str(seconds), "--run-dir", str(run)], view)
    s = json.loads((run / "summary.json").read_text())
    robots = list(s["robots"].values())
    return {**r, "control_hz": round(statistics.mean(x["control_hz"] for x in robots), 3),
            "action_age_ms_p50": round(statistics.mean(x["action_age_ms_p50"] for x in robots), 2),
            "action_age_ms_p99": round(statistics.mean(x["action_age_ms_p99"] for x in robots), 2),
            "ticks_skipped": s["world"]["ticks_skipped"], "defaults": sum(x["defaults"] for x in robots)}


def up_trial(episodes: int, run: Path, view: bool) -> dict:
    r = _run(["up", "--episodes", str(episodes), "--set", "num_envs=8", "--run-dir", str(run)], view)
    s = json.loads((run / "summary.json").read_text())
    return {**r, "env_steps_per_s": round(s["env_steps_per_s"], 1)}


def live_cost(robots: int, ticks: int = 200) -> dict:
    """The launcher's share, apart: CPU time of one `LiveStatus` write (live.json of `robots` robots with
    their heartbeats all new, a world report, a series line each second), times 5 writes a second."""
    from types import SimpleNamespace

    from hammer.deploy.live import WRITE_EVERY_S, LiveStatus
    from hammer.protocol.schemas import Heartbeat

    clock = [0.0]
    with tempfile.TemporaryDirectory(prefix="bench-live-") as tmp:
        live = LiveStatus(Path(tmp), "fleet", "bench", robots=robots, roles=("env", "central", "policy"),
                          clock=lambda: clock[0])
        board = SimpleNamespace(heartbeats={}, restarts={}, chaos_log=[])
        spent = 0.0
        for k in range(ticks):
            clock[0] += WRITE_EVERY_S
            board.heartbeats = {f"local-{i}": Heartbeat(role=f"local-{i}", pid=10 + i, status="running",
                                                        counters={"acts": 10 * k, "msg_none": 0, "msg_stale": k},
                                                        gauges={"policy_version": 0, "policy_held": 0,
                                                                "msg_age_p50_ms": 12.0, "msg_age_p99_ms": 30.0})
                                for i in range(robots)}
            board.heartbeats["env"] = Heartbeat(role="env", pid=2, status="running", counters={
                "ticks": 10 * k, **{f"local_{i}.fresh": 10 * k for i in range(min(robots, 20))}})
            t = time.process_time()
            live.tick(board)
            spent += time.process_time() - t
        size = (Path(tmp) / "live.json").stat().st_size
    per = spent / ticks
    return {"robots": robots, "ms_per_write": round(1e3 * per, 3), "cpu_pct_at_5hz": round(100 * per / WRITE_EVERY_S, 2),
            "live_json_bytes": size}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--hz", type=float, default=50.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--episodes", type=int, default=800)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--skip-up", action="store_true", help="the fleet only")
    ap.add_argument("--live-only", action="store_true", help="only the launcher's share (LiveStatus writes)")
    a = ap.parse_args(argv)
    costs = [live_cost(n) for n in (3, 20, 100)]
    for c in costs:
        print(f"live.json with {c['robots']} robots: {c['ms_per_write']} ms CPU a write, {c['cpu_pct_at_5hz']} % of a "
              f"core at 5 writes/s, {c['live_json_bytes']:,} bytes", flush=True)
    if a.live_only:
        return
    out: dict = {"live_cost": costs, "host_cpus": os.cpu_count(), "hz": a.hz, "seconds": a.seconds, "episodes": a.episodes,
                 "fleet": {"off": [], "view": []}, "up": {"off": [], "view": []}}
    with tempfile.TemporaryDirectory(prefix="bench-view-") as tmp:
        for t in range(a.trials):
            order = ("off", "view") if t % 2 == 0 else ("view", "off")  # interleaved, the first arm alternating
            for arm in order:
                r = fleet_trial(a.bundle, a.hz, a.seconds, Path(tmp) / f"fleet-{arm}-{t}", arm == "view")
                out["fleet"][arm].append(r)
                print(f"fleet trial {t} {arm}: {r}", flush=True)
            for arm in order if not a.skip_up else ():
                r = up_trial(a.episodes, Path(tmp) / f"up-{arm}-{t}", arm == "view")
                out["up"][arm].append(r)
                print(f"up trial {t} {arm}: {r}", flush=True)
    for what, key in (("fleet", "control_hz"), ("fleet", "action_age_ms_p99"), ("up", "env_steps_per_s"),
                      ("fleet", "cpu_pct_launcher"), ("up", "cpu_pct_launcher")):
        if not out[what]["off"]:
            continue
        off = statistics.mean(r[key] for r in out[what]["off"])
        on = statistics.mean(r[key] for r in out[what]["view"])
        out[f"{what}_{key}_change_pct"] = round(100 * (on - off) / off, 2)
        print(f"{what} {key}: without {off:.2f}, with the view and a page {on:.2f} ({out[f'{what}_{key}_change_pct']:+.2f} %)")
    for what in ("fleet", "up"):
        runs = out[what]["view"]
        if not runs:
            continue
        print(f"{what}: the view process {statistics.mean(r['cpu_pct_view'] for r in runs):.1f} % of a core, peak RSS "
              f"{max(r['view_rss_mb'] for r in runs):.1f} MB; the browser {statistics.mean(r['cpu_pct_browser'] for r in runs):.1f} %")
    if a.out is not None:
        a.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
