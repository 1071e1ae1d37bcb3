"""What every role process does first: its log, the launcher watchdog, SIGTERM as a clean exit.

One definition for every entry that starts a role (the role commands of `hammer up`, the edge
agent's own entry), so they all log the same way, never outlive the launcher that started them and
close their Zenoh session when told to stop.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path

PARENT_ENV = "HAMMER_PARENT_PID"  # set by the launcher (deploy.supervisor) for every role it starts

log = logging.getLogger("hammer.deploy")


def setup_process(role: str, run_dir: Path | None = None) -> None:
    """Logging line by line to stderr (the launcher's RUN/logs/<role>.log), so a killed role's log
    ends at its last line; Python warnings too; a first line of what it runs (from `run_dir`); the
    launcher watchdog; SIGTERM and SIGINT turned into a clean exit so the Zenoh session closes."""
    sys.stderr.reconfigure(line_buffering=True)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s")
    logging.captureWarnings(True)
    _describe(role, run_dir)
    parent_watchdog()

    def on_term(signum, frame):
        log.warning("%s: %s, stopping", role, signal.Signals(signum).name)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)


def _describe(role: str, run_dir: Path | None) -> None:
    try:
        cfg = json.loads((Path(run_dir) / "config.json").read_text()) if run_dir is not None else None
        rt = json.loads((Path(run_dir) / "runtime.json").read_text()) if run_dir is not None else None
    except (OSError, ValueError):
        cfg = rt = None
    if cfg and rt:
        log.info("%s: run dir %s; %s N=%s %s/%s seed %s, %s episodes; mode %s, msg deadline %s ms, act deadline "
                 "%s ms, max policy lag %s, fallback %s%s", role, run_dir, cfg.get("env"), cfg.get("n_agents"),
                 cfg.get("variant"), cfg.get("central_mode"), cfg.get("seed"), cfg.get("episodes"), rt.get("mode"),
                 rt.get("msg_deadline_ms"), rt.get("act_deadline_ms"), rt.get("max_policy_lag"), rt.get("fallback"),
                 f", resume from update {rt['resume_from']}" if rt.get("resume_from") is not None else "")


def parent_watchdog(interval: float = 0.5) -> None:
    """In a role process: exit when the launcher that started us is gone (no stray processes)."""
    raw = os.environ.get(PARENT_ENV)
    if not raw:
        return
    parent = int(raw)

    def watch() -> None:
        while True:
            time.sleep(interval)
            # Re-parenting (to init or a subreaper) is the reliable sign: a pid can be reused.
            if os.getppid() != parent:
                log.error("launcher (pid %d) is gone; exiting", parent)
                os._exit(3)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
