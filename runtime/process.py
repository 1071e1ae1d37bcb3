"""What every role process does first: its log, the launcher watchdog, SIGTERM as a clean exit;
and the one signal policy of every hammer process (`on_signals`, `take_signals`).

One definition for every entry that starts a role (the role commands of `hammer up`, the edge
agent's own entry), so they all log the same way, never outlive the launcher that started them and
close their Zenoh session when told to stop.

A role's log is its stderr, which the launcher points at RUN/logs/<role>.log, so that a crash's
traceback and the C libraries' own lines land there too. A run of days must not fill the disk with
it, so the role rotates that file itself (`RotatingStderr`): past `log_max_mb` of runtime.json the
file becomes <role>.log.1 (.1 becomes .2, the oldest goes) and stderr continues in a fresh file,
one writer throughout (logging.handlers.RotatingFileHandler would leave stderr writing into the
renamed file).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import stat
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

PARENT_ENV = "HAMMER_PARENT_PID"  # set by the launcher (deploy.supervisor) for every role it starts
LOG_MAX_MB, LOG_BACKUPS = 10.0, 2  # RuntimeSettings.log_max_mb's default; <role>.log.1 and .2 are kept

log = logging.getLogger("hammer.deploy")


def setup_process(role: str, run_dir: Path | None = None) -> None:
    """Logging line by line to stderr (the launcher's RUN/logs/<role>.log), so a killed role's log
    ends at its last line; Python warnings too; a first line of what it runs (from `run_dir`); the
    launcher watchdog; SIGTERM and SIGINT turned into a clean exit so the Zenoh session closes."""
    sys.stderr.reconfigure(line_buffering=True)
    handler = RotatingStderr(int(_log_max_mb(run_dir) * 2**20))
    handler.setFormatter(logging.Formatter(f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.INFO, handlers=[handler])
    logging.captureWarnings(True)
    _describe(role, run_dir)
    parent_watchdog()

    def on_term(name: str) -> None:
        log.warning("%s: %s, stopping", role, name)
        raise Stopped(name)

    # every signal, not only the first: a role started by hand stops at a second Ctrl-C even mid-cleanup
    take_signals((signal.SIGTERM, signal.SIGINT), on_term, repeat=True)


class Stopped(KeyboardInterrupt):
    """A stop asked from outside by a signal (SIGTERM: what systemd and `docker stop` send; SIGINT).
    A KeyboardInterrupt, so every path that already cleans up after Ctrl-C does the same for it;
    `signal_name` says which."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def _raise_stopped(name: str) -> None:
    raise Stopped(name)


def take_signals(signals: tuple[int, ...], action: Callable[[str], None] = _raise_stopped, *,
                 repeat: bool = False) -> tuple[dict, Callable[[], None]]:
    """The one signal policy of every hammer process: each of `signals` calls `action(name)`
    (default: raise Stopped(name)); once one came, or once the caller set `state["ending"]`, later
    ones are logged and ignored (unless `repeat`), so a stop broadcast, a summary or a clean-up is
    not cut short by a service manager repeating its signal. Returns (state, restore): state["by"]
    is the first signal's name (None: none yet); restore() puts the previous handlers back. Only the
    main thread can take signals: elsewhere nothing is installed."""
    state: dict = {"by": None, "ending": False}
    if not signals or threading.current_thread() is not threading.main_thread():
        return state, lambda: None

    def on_signal(signum, frame) -> None:
        name = signal.Signals(signum).name
        if not repeat and (state["by"] is not None or state["ending"]):
            log.warning("%s: already stopping", name)
            return
        state["by"] = state["by"] or name
        action(name)

    previous = {s: signal.signal(s, on_signal) for s in signals}

    def restore() -> None:
        for s, h in previous.items():
            signal.signal(s, h)

    return state, restore


@contextmanager
def on_signals(signals: tuple[int, ...], action: Callable[[str], None] = _raise_stopped, *,
               repeat: bool = False) -> Iterator[dict]:
    """`take_signals` while inside the block (the previous handlers come back after); yields the state."""
    state, restore = take_signals(signals, action, repeat=repeat)
    try:
        yield state
    finally:
        restore()


M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter
MMAP_THRESHOLD_BYTES = 128 << 10  # glibc's own starting value


def return_large_blocks() -> bool:
    """Make glibc give every block of 128 KiB or more back to the system when it is freed (False where
    the C library is not glibc: nothing changed). Why: glibc raises its mmap threshold to the size of
    each large block freed, up to 32 MiB, so after a flood of multi-MiB messages (which Zenoh
    reassembles before a subscriber refuses them by size) the next ones are carved from the heap and
    stay there: +1-2 MiB of RSS kept after a 4 MiB flood (docs/fleet.md, "Bounded under attack").
    A fixed threshold turns the adjustment off. For the long-lived processes that face robots (a
    fleet's world and central agent), not for training (torch's tensors would pay a mmap each)."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    except (OSError, AttributeError):
        return False


def _log_max_mb(run_dir: Path | None) -> float:
    try:
        return float(json.loads((Path(run_dir) / "runtime.json").read_text()).get("log_max_mb", LOG_MAX_MB))
    except (OSError, ValueError, TypeError):
        return LOG_MAX_MB


class RotatingStderr(logging.StreamHandler):
    """Log records to stderr; when stderr is a log file (a regular file named *.log) past
    `max_bytes`, rotate it: rename it <name>.1 (older ones shifted, `backups` kept) and point this
    process's stderr (and stdout, where it shares the file) at a fresh file of the old name."""

    def __init__(self, max_bytes: int, backups: int = LOG_BACKUPS) -> None:
        super().__init__(sys.stderr)
        self.max_bytes, self.backups = max(1, max_bytes), max(1, backups)
        self.path = _log_file(2)

    def emit(self, record: logging.LogRecord) -> None:
        super().emit(record)
        if self.path is not None:
            try:
                if os.fstat(2).st_size > self.max_bytes:
                    self.rotate()
            except OSError:  # the file went away under us: go on logging to whatever stderr is
                self.path = None

    def rotate(self) -> None:
        path = self.path
        try:
            same = os.stat(path).st_ino == os.fstat(2).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # renamed or replaced by someone else: leave it to them
            self.path = None
            return
        sys.stderr.flush()
        sys.stdout.flush()
        try:
            stdout_too = os.fstat(1).st_ino == os.fstat(2).st_ino
        except OSError:  # no stdout
            stdout_too = False
        for i in range(self.backups - 1, 0, -1):
            older = path.with_name(f"{path.name}.{i}")
            if older.exists():
                older.replace(path.with_name(f"{path.name}.{i + 1}"))
        path.replace(path.with_name(f"{path.name}.1"))
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.dup2(fd, 2)
            if stdout_too:
                os.dup2(fd, 1)
        finally:
            os.close(fd)


def _log_file(fd: int) -> Path | None:
    """The file behind `fd` when it is a regular *.log file (None otherwise: a terminal, a pipe)."""
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        path = Path(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:
        return None
    return path if path.name.endswith(".log") and path.is_absolute() else None


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
