"""What a flood on a robot's own keys costs a fleet's world and central agent in memory (RSS before,
during and after), docs/fleet.md "Bounded under attack".

A secure fleet (`hammer serve BUNDLE --realtime 20 --secure`, every robot its own process) on
loopback; after `--before-s` a thief holding robot 1's real identity (RUN/identity/local-1.*: a
stolen key) floods robot 1's own keys (`agent/up/1`, `agent/act/1`: the access rules let it) with
`--mib` MiB payloads at `--rate` a second for `--flood-s`, then stops; the fleet runs `--after-s`
more. RSS of the world and the central agent is sampled every 0.5 s from /proc; the figures are the
median of each phase (before: its last half; after: its last half) and the peak during the flood.

    python -m hammer.benchmarks.fleet_flood BUNDLE [--mib 4] [--rate 25] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROLES = {"env": "fleet-world", "central": "fleet-central"}


def _pids(run_id: str) -> dict[str, int]:
    found = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            args = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        for role, cmd in ROLES.items():
            if cmd.encode() in args and run_id.encode() in args:
                found[role] = int(d.name)
    return found


def _rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _flood(run: Path, n: int, mib: float, rate: float, seconds: float, sent: list[int]) -> None:
    from hammer.protocol.identity import identity_dir
    from hammer.protocol.session import HammerSession, TransportConfig
    from hammer.runtime.settings import RuntimeSettings

    hub = json.loads((run / "fleet.json").read_text())["hub"]
    transport = RuntimeSettings(run_id=run.name, secure=True).secured(
        TransportConfig(connect=["tcp/" + hub.split("/", 1)[1]]), "local-1", None, n,
        identity_directory=identity_dir(run))
    big = bytes(int(mib * (1 << 20)))
    with HammerSession(run.name, transport, sender="local-1") as s:
        pubs = [s.publisher(k, reliable=False) for k in (s.keys.up(1), s.keys.act(1))]
        end, period = time.monotonic() + seconds, 1.0 / rate
        while time.monotonic() < end:
            for p in pubs:
                p.put_bytes(big)
                sent[0] += 1
            time.sleep(period)


def measure(bundle: Path, mib: float, rate: float, before_s: float, flood_s: float, after_s: float) -> dict:
    from hammer.serve.bundle import load_bundle

    n = int(load_bundle(bundle).env_spec_data["n_agents"])
    with tempfile.TemporaryDirectory(prefix="fleet-flood-") as tmp:
        run = Path(tmp) / "flood"
        total = before_s + flood_s + after_s + 5
        serve = subprocess.Popen([sys.executable, "-m", "hammer.cli", "serve", str(bundle), "--realtime", "20",
                                  "--seconds", str(total), "--secure", "--run-dir", str(run)],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            pids: dict[str, int] = {}
            deadline = time.monotonic() + 120
            while (len(pids) < 2 or not (run / "world.json").parent.is_dir()) and time.monotonic() < deadline:
                pids = _pids(run.name)
                time.sleep(0.2)
            world_log = run / "logs" / "env.log"
            while "world clock starts" not in (world_log.read_text() if world_log.is_file() else ""):
                if time.monotonic() > deadline or serve.poll() is not None:
                    raise RuntimeError("the fleet did not start")
                time.sleep(0.2)
            samples: list[tuple[float, str, dict[str, float | None]]] = []
            t0 = time.monotonic()
            sent = [0]
            thread = None
            phase = "before"
            while time.monotonic() - t0 < before_s + flood_s + after_s:
                t = time.monotonic() - t0
                if phase == "before" and t >= before_s:
                    phase = "flood"
                    thread = threading.Thread(target=_flood, args=(run, n, mib, rate, flood_s, sent), daemon=True)
                    thread.start()
                elif phase == "flood" and thread is not None and not thread.is_alive():
                    phase = "after"
                samples.append((t, phase, {r: _rss_mib(p) for r, p in pids.items()}))
                time.sleep(0.5)
            serve.wait(60)
            summary = json.loads((run / "summary.json").read_text())
        finally:
            if serve.poll() is None:
                serve.kill()
    out: dict = {"mib": mib, "rate_per_s": rate, "flood_s": flood_s, "payloads_sent": sent[0],
                 "load_1min": round(os.getloadavg()[0], 2), "roles": {},
                 "rejected_on": summary.get("rejected_on", {}), "degraded_reasons": summary.get("degraded_reasons")}
    for role in ROLES:
        def phase_values(name: str, last_half: bool = True, role: str = role) -> list[float]:
            v = [s[2][role] for s in samples if s[1] == name and s[2].get(role) is not None]
            return v[len(v) // 2:] if last_half else v

        before, during, after = phase_values("before"), phase_values("flood", False), phase_values("after")
        b, a = statistics.median(before), statistics.median(after)
        out["roles"][role] = {"before_mib": round(b, 1), "during_peak_mib": round(max(during), 1),
                              "after_mib": round(a, 1), "after_over_before": round(a / b, 3)}
    out["samples"] = [{"t": round(t, 1), "phase": ph, **{k: v and round(v, 1) for k, v in r.items()}}
                      for t, ph, r in samples]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--mib", type=float, default=4.0, help="payload size, MiB (default 4)")
    ap.add_argument("--rate", type=float, default=25.0, help="payloads per second on each of the two keys")
    ap.add_argument("--before-s", type=float, default=10.0)
    ap.add_argument("--flood-s", type=float, default=10.0)
    ap.add_argument("--after-s", type=float, default=15.0)
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    r = measure(a.bundle, a.mib, a.rate, a.before_s, a.flood_s, a.after_s)
    for role, f in r["roles"].items():
        print(f"{role:8s} RSS before {f['before_mib']:.1f} MiB  during (peak) {f['during_peak_mib']:.1f}  after "
              f"{f['after_mib']:.1f}  after/before {f['after_over_before']:.3f}")
    print(f"{r['payloads_sent']} payloads of {a.mib:g} MiB sent; refused on robot 1's keys: {r['rejected_on']}; "
          f"load {r['load_1min']}")
    if a.out is not None:
        a.out.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
