"""Drive a hot update and a rollback of a live served run through the real CLI, at chosen steps.

    python -m hammer.benchmarks.push_driver RUN_DIR BUNDLE_B (--connect tcp/HUB:PORT | --zenoh-config FILE)
                                     [--push-at 150] [--rollback-after 150]

Why a separate process: the env host's step counter is only visible on the wire (its heartbeats),
and a push must land on a run that is stepping, not on one starting up. This joins the run as one
more Zenoh client, follows the env host's heartbeats (step, policy_version), runs
`hammer push BUNDLE_B --to RUN_DIR` once the env host passes --push-at, and `hammer rollback RUN_DIR`
once it has stepped --rollback-after steps with the pushed version; then it waits for the rollback's
version to be named. Prints one JSON line: the steps of each event and the CLI's replies.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path


def _cli(*args: str) -> str:
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", *args], check=False, capture_output=True, text=True,
                       timeout=60)
    if r.returncode != 0:
        raise RuntimeError(f"hammer {' '.join(args[:1])} failed: {(r.stderr or r.stdout).strip()}")
    return r.stdout.strip()


def drive(run_dir: Path, bundle: Path, transport, push_at: int, rollback_after: int, timeout_s: float = 300) -> dict:
    """Push, then roll back, at the env host's steps; returns what happened when."""
    from hammer.protocol.schemas import Heartbeat
    from hammer.protocol.session import HammerSession
    from hammer.runtime.settings import RuntimeSettings

    deadline = time.monotonic() + timeout_s
    while not (run_dir / "runtime.json").is_file():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{run_dir}/runtime.json never appeared")
        time.sleep(0.1)
    report: dict = {}
    with HammerSession(RuntimeSettings.load(run_dir).run_id, transport, sender="push-driver") as s:
        beats = s.subscribe(s.keys.heartbeat("env"), Heartbeat)
        while time.monotonic() < deadline and "rollback_named_at" not in report:
            hb = beats.get(timeout=10)
            if hb is None:  # the run ended (or never stepped) before both updates were named
                raise RuntimeError(f"no heartbeat of the env host for 10 s (so far: {report})")
            # named_version: the version the steps name (a push is named once the agents hold it)
            step, version = int(hb.counters.get("step", 0)), int(hb.gauges.get("named_version",
                                                                               hb.gauges.get("policy_version", 0)))
            if "push_at" not in report and step >= push_at:
                report.update(push_at=step, push=_cli("push", str(bundle), "--to", str(run_dir)))
            elif "push_at" in report and "push_named_at" not in report and version >= 1:
                report["push_named_at"] = step
            elif ("push_named_at" in report and "rollback_at" not in report
                  and step >= report["push_named_at"] + rollback_after):
                report.update(rollback_at=step, rollback=_cli("rollback", str(run_dir)))
            elif "rollback_at" in report and version >= 2:
                report["rollback_named_at"] = step
    return report


def main() -> None:
    import argparse

    from hammer.protocol.session import TransportConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("bundle", type=Path)
    ap.add_argument("--connect", help="Zenoh endpoint of the run's hub")
    ap.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (e.g. a client of the router)")
    ap.add_argument("--push-at", type=int, default=150)
    ap.add_argument("--rollback-after", type=int, default=150)
    a = ap.parse_args()
    if (a.connect is None) == (a.zenoh_config is None):
        sys.exit("error: pass one of --connect and --zenoh-config")
    transport = (TransportConfig(zenoh_config_file=a.zenoh_config) if a.zenoh_config
                 else TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[a.connect]))
    try:
        print(json.dumps(drive(a.run_dir, a.bundle, transport, a.push_at, a.rollback_after)), flush=True)
    except RuntimeError as e:
        print(json.dumps({"error": str(e)}), flush=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
