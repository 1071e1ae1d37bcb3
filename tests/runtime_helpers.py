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
