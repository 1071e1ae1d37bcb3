"""The learner role of an evaluation run: serves a frozen, exported policy; never learns.

Evaluation must run the real runtime (every hop, every fault) but not change the policy, so the
learner is replaced by this server: it publishes the exported `local.safetensors` (and
`central.safetensors` for HAMMER) as policy version 0, and republishes them every second so a
restarted agent gets them too. The files are sent as they are (safetensors, never pickle); numpy
and zenoh only, so an evaluation does not pay for a torch import in this process.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from protocol.schemas import Control, Heartbeat, Weights
from protocol.session import HammerSession

log = logging.getLogger("hammer.policy_server")


class PolicyDirError(FileNotFoundError):
    """The policy directory lacks a file the run needs."""


def policy_blobs(policy_dir: Path, needs_central: bool) -> dict[str, bytes]:
    """role -> safetensors bytes from an exported policy directory (RUN/final)."""
    policy_dir = Path(policy_dir)
    files = {"local": policy_dir / "local.safetensors"}
    if needs_central:
        files["central"] = policy_dir / "central.safetensors"
    for role, f in files.items():
        if not f.is_file():
            raise PolicyDirError(f"{f} is missing: policy_dir must hold the {role} policy a run exports "
                                 "(RUN/final/ after `hammer train` or `hammer up`)")
    return {role: f.read_bytes() for role, f in files.items()}


def serve_frozen_policy(session: HammerSession, policy_dir: Path, needs_central: bool,
                        republish_s: float = 1.0) -> int:
    """Publish the frozen weights as version 0 until a stop command; returns publishes done."""
    blobs = policy_blobs(policy_dir, needs_central)
    keys = session.keys
    pubs = {role: session.publisher(keys.weights(role)) for role in blobs}
    ctl_sub = session.subscribe(keys.ctl("all"), Control)
    hb = session.publisher(keys.heartbeat("learner"), reliable=False)
    session.declare_alive("learner")
    published = 0
    while True:
        for role, blob in blobs.items():
            pubs[role].publish(Weights.from_blob(role, 0, blob))
        published += 1
        hb.publish(Heartbeat(role="learner", pid=os.getpid(), status="running",
                             counters={"policy_version": 0, "frozen_publishes": published}))
        deadline = time.monotonic() + republish_s
        while time.monotonic() < deadline:
            cmd = ctl_sub.get(timeout=max(0.0, deadline - time.monotonic()))
            if cmd is not None and cmd.command in ("stop", "shutdown") and cmd.target in ("*", "learner"):
                log.info("stopped after %d publishes", published)
                return published
