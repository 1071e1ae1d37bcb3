"""How a sweep starts one training command and learns that it ended: the one thing its backends differ in.

`experiments.sweep.run_sweep` decides what to run, what to skip, what to resume, what to batch and
what to archive; a `Launcher` only runs the command it is handed (`python -m hammer.cli train ...`
or `python -m hammer.commands.seeds ...`) somewhere and reports its exit status. Keeping that seam
this narrow is what lets a cluster backend (`experiments.ray_backend`) keep every semantic of the
local one: the same points, the same run directories, the same locks, archive and snapshots.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Protocol

# One thread per run: a sweep fills every core with runs, not one run with every core.
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "HAMMER_TORCH_THREADS": "1"}


class Job(Protocol):
    """One launched command."""

    pid: int | None  # its process id on this machine (recorded in the run's lock), None if elsewhere
    reason: str  # why it failed beyond its exit status (e.g. "node X cannot see OUT"), "" if nothing to add

    def poll(self) -> int | None:
        """Its exit status once it has ended, None while it runs. Never blocks."""

    def stop(self) -> None:
        """End it and whatever it started, and wait for that (Ctrl-C, SIGTERM, the sweep's end)."""


class Launcher(Protocol):
    def slots(self) -> int:
        """How many commands run at once by default (`--jobs`)."""

    def launch(self, args: list[str], log: Path, run_dirs: list[Path]) -> Job:
        """Start `python *args` (with THREAD_ENV) appending its output to `log`; `run_dirs` are the
        run directories it writes (already created and locked by the sweep)."""

    def close(self) -> None:
        """Release what the launcher holds (nothing locally; the Ray connection)."""


class _Process:
    """A command running as a child process of the sweep."""

    reason = ""

    def __init__(self, proc: subprocess.Popen, logf) -> None:
        self.proc, self.logf, self.pid = proc, logf, proc.pid

    def poll(self) -> int | None:
        code = self.proc.poll()
        if code is not None and not self.logf.closed:
            self.logf.close()
        return code

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.logf.close()


class LocalLauncher:
    """Each command a child process of the sweep on this machine (the default backend)."""

    def slots(self) -> int:
        return max(1, os.cpu_count() or 1)

    def launch(self, args: list[str], log: Path, run_dirs: list[Path]) -> Job:
        logf = open(log, "ab")  # noqa: SIM115 - closed by the job once the command ends
        proc = subprocess.Popen([sys.executable, *args], stdout=logf, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=dict(os.environ, **THREAD_ENV))
        return _Process(proc, logf)

    def close(self) -> None:
        pass
