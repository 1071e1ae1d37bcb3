"""`hammer bench soak`: does a served team stay flat for hours? Memory of every process and disk over time.

A served team (`hammer serve`, frozen weights, no learner) runs far longer than any training run
and nobody watches it, so a few bytes kept per step or per episode become the outage of the night.
This starts a real `hammer serve` of a cn3 team (an untrained HAMMER team exported as a bundle, as
`hammer bench edge` makes one, unless `--bundle` names one) with an episode budget it never reaches,
samples the resident memory of the launcher and of every role process and the run directory's disk
use every `every_s` seconds, stops it with Ctrl-C (SIGINT) after `minutes`, and reports the growth
of each from the end of the first minute (start-up, imports and first allocations are done by then)
to the end. The figures go to the terminal and to a JSON file (docs/results/soak-<time>.json).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

WARM_S = 60.0  # growth is measured from the first sample at or after this many seconds


def role_of(cmdline: list[str]) -> str | None:
    """The role a process of the run serves, from its command line (`python -P -m hammer.entry local
    --agent 1` -> local-1); None for a process that is no role (a vector env's worker, a shell)."""
    i = next((j for j, a in enumerate(cmdline) if a in ("hammer.cli", "hammer.entry", "hammer")
              or (j == 1 and a.endswith("/hammer"))), None)  # python -m MODULE ..., or the console script
    if i is None:
        return None
    args = cmdline[i + 1:]
    if not args:
        return None
    cmd = args[0]
    if cmd == "local":
        for flag in ("--agent", "--agents"):
            if flag in args:
                v = args[args.index(flag) + 1]
                return f"local-{v}" if flag == "--agent" else f"locals-{v.replace(',', '-')}"
        return "local"
    return {"env-host": "env", "learner": "policy-server", "serve": "launcher", "up": "launcher"}.get(cmd, cmd)


def disk_use(path: Path) -> dict[str, int]:
    """Bytes under `path` per top-level entry (logs, linksteps, metrics.csv, ...) and in all."""
    out: dict[str, int] = {}
    for entry in sorted(Path(path).iterdir()) if Path(path).is_dir() else []:
        size = 0
        if entry.is_file():
            size = entry.stat().st_size
        else:
            for root, _, files in os.walk(entry):
                for f in files:
                    try:
                        size += os.stat(os.path.join(root, f)).st_size
                    except FileNotFoundError:  # rotated away between the listing and the stat
                        pass
        out[entry.name] = size
    out["total"] = sum(out.values())
    return out


def _episodes(run: Path) -> int | None:
    """The env host's episode count from the last progress line of its log (written every 30 s)."""
    try:
        with open(run / "logs" / "env.log", "rb") as f:
            f.seek(0, 2)
            f.seek(max(0, f.tell() - 20_000))
            tail = f.read().decode(errors="replace")
    except OSError:
        return None
    found = re.findall(r"\bepisodes (\d+)", tail)
    return int(found[-1]) if found else None


def _sample(launcher, t: float, run: Path) -> dict:
    import psutil

    rss: dict[str, float] = {}
    pids: dict[str, int] = {}
    procs = [launcher]
    try:
        procs += launcher.children(recursive=True)
    except psutil.NoSuchProcess:
        pass
    for p in procs:
        try:
            name = role_of(p.cmdline())
            if name is None:
                continue
            rss[name] = round(rss.get(name, 0.0) + p.memory_info().rss / 2**20, 1)
            pids[name] = p.pid
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    disk = disk_use(run)
    return {"t_s": round(t, 1), "rss_mib": rss, "pids": pids, "disk_mib": round(disk["total"] / 2**20, 2),
            "disk_by_entry_kib": {k: round(v / 1024, 1) for k, v in disk.items() if k != "total"},
            "episodes": _episodes(run), "load_1m": round(os.getloadavg()[0], 2)}


def growth(samples: list[dict], warm_s: float = WARM_S) -> dict:
    """Per process: RSS at the first sample at or after `warm_s` and at the end, and the growth in %;
    the same for the run directory's disk use (MiB, and MiB per hour at that pace)."""
    warm = next((s for s in samples if s["t_s"] >= warm_s), samples[0])
    end = samples[-1]
    procs = {}
    for name, end_mib in end["rss_mib"].items():
        first = warm["rss_mib"].get(name)
        if first is None:
            continue
        restarted = warm["pids"].get(name) != end["pids"].get(name)
        procs[name] = {"first_mib": first, "end_mib": end_mib, "growth_pct": round(100 * (end_mib - first) / first, 1),
                       "restarted": restarted}
    span_h = max(end["t_s"] - warm["t_s"], 1e-9) / 3600
    disk = {"first_mib": warm["disk_mib"], "end_mib": end["disk_mib"],
            "growth_mib_per_h": round((end["disk_mib"] - warm["disk_mib"]) / span_h, 1)}
    if warm.get("episodes") is not None and end.get("episodes") is not None and end["episodes"] > warm["episodes"]:
        disk["bytes_per_episode"] = round((end["disk_mib"] - warm["disk_mib"]) * 2**20 / (end["episodes"] - warm["episodes"]), 1)
    return {"from_s": warm["t_s"], "to_s": end["t_s"], "processes": procs, "disk": disk}


def run_soak(minutes: float, every_s: float = 30.0, work: Path | None = None, bundle: Path | None = None,
             runtime: tuple[str, ...] = (), progress=print) -> dict:
    """Serve a team for `minutes` and sample it every `every_s` seconds; returns the figures."""
    import psutil

    work = Path(work or Path("runs") / f"soak-{time.strftime('%Y%m%d-%H%M%S')}")
    work.mkdir(parents=True, exist_ok=True)
    if bundle is None:
        from hammer.benchmarks.edge_bench import make_team

        bundle = make_team(work / "team")[0].path
    run = work / "run"
    cmd = [sys.executable, "-P", "-m", "hammer.cli", "serve", str(bundle), "--episodes", str(10**9),
           "--run-dir", str(run), "--no-dashboard", *(x for r in runtime for x in ("--runtime", r))]
    log_path = work / "serve.log"
    progress(f"soak: {' '.join(cmd[3:])} for {minutes:g} min, a sample every {every_s:g} s (output: {log_path})")
    with open(log_path, "ab") as out:
        # its own process group: what is left after the stop can be ended without touching anything else
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
    launcher = psutil.Process(proc.pid)
    samples: list[dict] = []
    try:
        deadline = time.monotonic() + 180
        while not _started(run):
            if proc.poll() is not None:
                raise RuntimeError(f"hammer serve exited with code {proc.returncode} before serving; see {log_path}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"hammer serve did not start stepping within 180 s; see {log_path}")
            time.sleep(0.5)
        t0 = time.monotonic()
        end = t0 + minutes * 60
        next_t = t0
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"hammer serve exited with code {proc.returncode} during the soak; see {log_path}")
            now = time.monotonic()
            if now >= next_t:
                s = _sample(launcher, now - t0, run)
                samples.append(s)
                progress(f"t={s['t_s']:6.0f}s  " + "  ".join(f"{k} {v:.1f}" for k, v in sorted(s["rss_mib"].items()))
                         + f"  MiB RSS | disk {s['disk_mib']:.2f} MiB | episodes {s['episodes']} | load {s['load_1m']}")
                next_t += every_s
            if now >= end and samples and samples[-1]["t_s"] >= minutes * 60 - 0.5:
                break
            time.sleep(min(0.5, max(0.0, min(next_t, end) - now)))
    finally:
        _stop(proc)
    result = {"minutes": minutes, "every_s": every_s, "bundle": str(bundle), "runtime": list(runtime),
              "run_dir": str(run), "cpus": os.cpu_count(), "python": sys.version.split()[0],
              "started_at": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(time.time() - samples[-1]["t_s"])),
              "samples": samples, "growth": growth(samples, min(WARM_S, minutes * 60 / 3))}
    return result


def _started(run: Path) -> bool:
    """The env host has begun stepping (its loop logs `policy version`/progress only later, so the
    first episode rows are the sign)."""
    m = run / "metrics.csv"
    try:
        return m.is_file() and m.stat().st_size > 80
    except OSError:
        return False


def _stop(proc: subprocess.Popen) -> None:
    """Ctrl-C as a user would; the whole group only if it outlives that by a minute."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)


def print_soak(r: dict, console) -> None:
    from rich.table import Table

    g = r["growth"]
    t = Table(title=f"hammer bench soak: {r['minutes']:g} min served"
                    f"{' (' + ', '.join(r['runtime']) + ')' if r['runtime'] else ''}")
    for col in ("process", "RSS first (MiB)", "RSS end (MiB)", "growth"):
        t.add_column(col, justify="left" if col == "process" else "right")
    for name, p in sorted(g["processes"].items()):
        t.add_row(name + (" (restarted)" if p["restarted"] else ""), f"{p['first_mib']:.1f}", f"{p['end_mib']:.1f}",
                  f"{p['growth_pct']:+.1f} %")
    d = g["disk"]
    t.caption = (f"RSS from t={g['from_s']:.0f} s to t={g['to_s']:.0f} s; run directory {d['first_mib']:.2f} -> "
                 f"{d['end_mib']:.2f} MiB ({d['growth_mib_per_h']:.1f} MiB/h"
                 + (f", {d['bytes_per_episode']:.0f} B per episode" if "bytes_per_episode" in d else "") + ")")
    console.print(t)


def write_result(r: dict, json_dir: Path) -> Path:
    json_dir.mkdir(parents=True, exist_ok=True)
    path = json_dir / f"soak-{time.strftime('%Y%m%d-%H%M')}.json"
    path.write_text(json.dumps(r, indent=1) + "\n")
    return path
