"""What a warehouse fleet does when its site feed goes silent, docs/fleet.md "The site feed".

A fleet of a team with a site feed (`hammer serve BUNDLE --realtime 20 --external-site`, every robot
its own process) on loopback, and the site an SDK client (`hammer.site.SiteFeed`) publishing at 20 Hz
the warehouse's current columns (`hammer.site.simulated_warehouse`: as the world writes them) from the
world's clock start; it stops for `--cut-s` at `--cut-at` s, then publishes again until the
fleet's end. Printed: the central agent's view of the feed (states taken, ticks on zeros, silences,
longest silence), the verdict, the robots' control rates, the load; the central agent's log lines
about the feed.

    python -m hammer.benchmarks.site_outage BUNDLE [--cut-at 8] [--cut-s 3] [--seconds 22] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path


def measure(bundle: Path, run: Path, cut_at: float, cut_s: float, seconds: float, hz: float = 20.0) -> dict:
    from hammer.deploy.fleet_launch import FleetPlan, run_fleet
    from hammer.serve.site_feed import SiteFeed, simulated_warehouse

    wms_state = simulated_warehouse(run)  # the world's current columns, as its management system knows them
    sent = {"published": 0}

    def publish(s: SiteFeed) -> None:
        state = wms_state()
        if state is not None:
            s.publish(state)

    def site() -> None:
        while not (run / "fleet.json").is_file():
            time.sleep(0.1)
        connect = "tcp/" + json.loads((run / "fleet.json").read_text())["hub"].split("/", 1)[1]
        env_log = run / "logs" / "env.log"
        with SiteFeed(bundle, run_id=run.name, connect=connect, wait=True) as s:
            while not (env_log.is_file() and "world clock starts" in env_log.read_text(errors="replace")):
                publish(s)
                time.sleep(1 / hz)
            t0 = time.monotonic()
            while (t := time.monotonic() - t0) < seconds + 2:  # past the fleet's end: its last silence is the cut's
                if not cut_at <= t < cut_at + cut_s:
                    publish(s)
                time.sleep(1 / hz)
            sent["published"] = s.counts["published"]

    threading.Thread(target=site, daemon=True).start()
    load = os.getloadavg()[0]
    s = run_fleet(FleetPlan(bundle=bundle, hz=hz, seconds=seconds, site_external=True), run)
    log = (run / "logs" / "central.log").read_text(errors="replace").splitlines()
    return {"site": s["site"], "site_published": sent["published"], "degraded_reasons": s["degraded_reasons"], "cut_at_s": cut_at, "cut_s": cut_s,
            "control_hz": {k: r["control_hz"] for k, r in s["robots"].items()}, "load_1min": round(load, 2),
            "central_log": [line for line in log if "site" in line and ("missing" in line or "rejoined" in line
                                                                          or "silent" in line)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--cut-at", type=float, default=8.0, help="seconds after the world's clock starts")
    ap.add_argument("--cut-s", type=float, default=3.0, help="how long the feed is silent")
    ap.add_argument("--seconds", type=float, default=22.0, help="the fleet's run")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        r = measure(a.bundle, Path(d) / "site-outage", a.cut_at, a.cut_s, a.seconds)
    site = r["site"]
    print(f"site feed: {site['states']} states taken, {site['silent_ticks']} ticks on zeros, {site['silences']} "
          f"silence(s), longest {site['longest_silence_s']:.2f} s; control Hz {r['control_hz']}; load {r['load_1min']}")
    print("degraded: " + ("; ".join(r["degraded_reasons"]) or "no"))
    for line in r["central_log"]:
        print("  " + line)
    if a.out is not None:
        a.out.write_text(json.dumps(r, indent=1))


if __name__ == "__main__":
    main()
