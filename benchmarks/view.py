"""What the web view costs the run it watches (docs/view.md, "Cost"): a fleet's control rate and action
ages, and `hammer up`'s env-steps/s, with `--view` and a page connected (headless Debian chromium on the
run page, on this same machine: the worst case, an operator's browser is usually elsewhere) against
without, the trials interleaved (the machine is shared: load drifts), each with its load average; and
the view process's peak RSS while the page is connected.

    python -m hammer.benchmarks.view --bundle BUNDLE --trials 3 --out docs/results/view-overhead.json

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


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundle", type=Path, required=True)
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument("--hz", type=float, default=50.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--episodes", type=int, default=800)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--skip-up", action="store_true", help="the fleet only")
    a = ap.parse_args(argv)
    out: dict = {"host_cpus": os.cpu_count(), "hz": a.hz, "seconds": a.seconds, "episodes": a.episodes,
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
