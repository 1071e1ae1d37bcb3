"""Helpers shared by the tests that start real `hammer` processes."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "HAMMER_TORCH_THREADS": "1"}


def hammer(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run `hammer ARGS` as a fresh interpreter from the repository root (one torch thread)."""
    return subprocess.run([sys.executable, "-m", "hammer.cli", *args], check=False, capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=ENV)


def processes_mentioning(text: str) -> list[psutil.Process]:
    """Live processes whose command line contains `text` (e.g. a run directory): strays."""
    found = []
    for p in psutil.process_iter(["cmdline"]):
        try:
            if any(text in part for part in (p.info["cmdline"] or [])):
                found.append(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return found


def netns_reason(tools: tuple[str, ...] = ("ip",)) -> str | None:
    """Why network namespaces cannot be made here (a test skips with it), or None: root, the
    iproute2 `tools`, and a kernel that lets us add a namespace."""
    import shutil

    if os.geteuid() != 0 or any(shutil.which(t) is None for t in tools):
        return f"needs root and iproute2 ({', '.join(tools)}) to create network namespaces"
    name = f"hmrprobe{os.getpid() % 100000}"
    r = subprocess.run(["ip", "netns", "add", name], check=False, capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], check=False, capture_output=True)
    return None


def trained_bundle(directory: Path, episodes: int) -> Path:
    """A briefly trained cn3 team (8 env copies, seed 4) exported as a bundle under `directory`."""
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train
    from hammer.serve.bundle import export_bundle

    cfg = merge_config("cn3", overrides=["num_envs=8", "rollout_steps=25", "epochs=1", "minibatches=2",
                                         f"episodes={episodes}", "seed=4"])
    train(cfg, RunDir.create(directory / "run", cfg), tensorboard=False)
    return export_bundle(directory / "run", directory / "bundle").path
