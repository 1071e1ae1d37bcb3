"""Starting, watching, restarting and stopping role processes.

Every role runs as a fresh interpreter (`python -m hammer.cli <role> ...`), never a fork of the
launcher: a forked child inherits a Zenoh session that delivers nothing (see docs/architecture.md).
Children learn the launcher's pid from HAMMER_PARENT_PID and exit by themselves if it disappears
(`parent_watchdog`), so even a SIGKILLed launcher leaves no stray process behind.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from hammer.runtime.process import PARENT_ENV

log = logging.getLogger("hammer.deploy")



def role_args(command: str, **options) -> list[str]:
    """A role command's line after `hammer`, the one way a launcher writes one: `command`, then each
    keyword as its option in the order given (`run_dir` -> `--run-dir VALUE`; a list or tuple repeats
    it; True is a bare flag; None and False leave it out). The role commands are hammer/commands/
    roles.py, fleet.py and edge.py (`local --bundle`), which this floor may not import:
    tests/test_role_args.py parses every line the launchers make with those commands' own parsers."""
    out = [command]
    for key, value in options.items():
        opt = "--" + key.replace("_", "-")
        if value is None or value is False:
            continue
        if value is True:
            out.append(opt)
        elif isinstance(value, list | tuple):
            for v in value:
                out += [opt, str(v)]
        else:
            out += [opt, str(value)]
    return out


@dataclass
class RoleSpec:
    """One role process: its name (used for logs and liveliness) and CLI arguments after `hammer`."""

    name: str
    args: list[str]
    restart: bool = False  # restart when it dies before the run is over
    max_restarts: int = 3
    essential: bool = True  # past max_restarts the run ends (False: it goes on without it: a fleet's robot)
    members: tuple[str, ...] = ()  # an agent pool: the liveliness names of its agents (else the role's own name)


@dataclass
class RoleProcess:
    spec: RoleSpec
    log_path: Path
    proc: subprocess.Popen | None = None
    restarts: int = 0
    started_at: float = 0.0
    exit_codes: list[int] = field(default_factory=list)
    pids: list[int] = field(default_factory=list)  # every process started for this role, restarts included


class Supervisor:
    """Owns the role processes of one run."""

    def __init__(self, log_dir: Path, env: dict[str, str] | None = None) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.roles: dict[str, RoleProcess] = {}
        self._env = dict(os.environ if env is None else env)
        self._env[PARENT_ENV] = str(os.getpid())
        # One torch/BLAS thread a role: a run's roles already outnumber the cores.
        self._env.setdefault("OMP_NUM_THREADS", "1")
        self._env.setdefault("MKL_NUM_THREADS", "1")

    def set_env(self, key: str, value: str | None) -> None:
        """An environment variable of every role started from now on (None: not set)."""
        if value is None:
            self._env.pop(key, None)
        else:
            self._env[key] = value

    def start(self, spec: RoleSpec) -> RoleProcess:
        rp = self.roles.get(spec.name) or RoleProcess(spec, self.log_dir / f"{spec.name}.log")
        self.roles[spec.name] = rp
        logf = open(rp.log_path, "ab")  # noqa: SIM115 - owned by the child for its lifetime
        # -P: the current folder is not put first on sys.path, so no folder of the user's project (an
        # `experiments/` of their own) can shadow a part of hammer in a role process.
        # hammer.entry, as the console script: `local --bundle` (an edge robot) loads no CLI framework
        cmd = [sys.executable, "-P", "-m", "hammer.entry", *spec.args]
        log.info("starting %s: %s", spec.name, " ".join(cmd))
        rp.proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   env=self._env, close_fds=True)
        logf.close()
        rp.pids.append(rp.proc.pid)
        rp.started_at = time.monotonic()
        return rp

    def poll(self) -> list[RoleProcess]:
        """Roles that exited since the last poll (their exit code is recorded)."""
        dead = []
        for rp in self.roles.values():
            if rp.proc is not None and rp.proc.poll() is not None:
                rp.exit_codes.append(rp.proc.returncode)
                rp.proc = None
                dead.append(rp)
        return dead

    def alive(self, name: str) -> bool:
        rp = self.roles.get(name)
        return rp is not None and rp.proc is not None and rp.proc.poll() is None

    def started_pids(self, member: str) -> set[int] | None:
        """The pids of every process started for `member` (a role, or an agent of a pool); None if
        no process of it was started here (a hand-started or external role)."""
        for rp in self.roles.values():
            if rp.spec.name == member or member in rp.spec.members:
                return set(rp.pids)
        return None

    def pid(self, name: str) -> int | None:
        rp = self.roles.get(name)
        return rp.proc.pid if rp and rp.proc else None

    def signal(self, name: str, sig: int) -> None:
        rp = self.roles.get(name)
        if rp and rp.proc and rp.proc.poll() is None:
            rp.proc.send_signal(sig)

    def stop_all(self, timeout: float = 5.0) -> None:
        """SIGTERM every role, then SIGKILL whatever is still there after `timeout`."""
        procs = [rp.proc for rp in self.roles.values() if rp.proc is not None and rp.proc.poll() is None]
        for p in procs:
            try:
                p.send_signal(signal.SIGCONT)  # a paused (SIGSTOPped) role cannot handle SIGTERM
                p.terminate()
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + timeout
        for p in procs:
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("role pid %d ignored SIGTERM; killing", p.pid)
                p.kill()
                p.wait(2.0)
        for rp in self.roles.values():
            if rp.proc is not None:
                rp.exit_codes.append(rp.proc.returncode)
                rp.proc = None
