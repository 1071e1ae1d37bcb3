"""`hammer sweep --backend ray`: the sweep's commands as tasks on a Ray cluster.

Only the launching differs from the local backend (`experiments.launch`): the sweep still decides
what to run, skip, resume, batch and archive, and each Ray task runs exactly the command a local
sweep would run, as a subprocess on whichever node Ray picks (`num_cpus` reserved per task). So the
run directories must be on storage every node mounts at the same path: a task first checks that
it sees the lock file the sweep has just written in each of its run directories, and fails with a
one-line reason if not. Tasks are never retried by Ray: a run cut short is resumed by the next
sweep from its checkpoint, as everywhere else.

Without an address Ray starts a private single-node instance bound to 127.0.0.1; with one, the
sweep joins that cluster (`ray start --head` on one machine, `ray start --address` on the others).
Ray's usage statistics are always switched off here (they would report to Ray's servers).
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from hammer.experiments.launch import THREAD_ENV
from hammer.experiments.sweep import LOCK

EXTRA = "cluster"  # pyproject's optional extra that brings Ray
STOP_GRACE_S = 15.0  # how long a cancelled task has to end its command before its worker is killed


class RayUnavailable(RuntimeError):
    """Ray cannot be used (not installed, or the cluster is unreachable): a one-line reason and fix."""


class RunDirNotVisible(RuntimeError):
    """Raised on a Ray worker whose node does not see the sweep's run directories."""


def _is_loopback(address: str | None) -> bool:
    host = (address or "127.0.0.1").rsplit(":", 1)[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def import_ray(loopback: bool):
    """Import Ray with usage statistics off, and on a single machine with every Ray socket on 127.0.0.1.

    Ray turns 127.0.0.1 into the machine's outward address (so that other nodes could reach it)
    unless it believes it runs single-node: with `loopback`, it is told so before any Ray
    process starts, so a local sweep talks to nothing but loopback."""
    os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
    if loopback:
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    try:
        import ray
        from ray._private import ray_constants
    except ImportError:
        raise RayUnavailable(f"--backend ray needs Ray, which is not installed; fix: pip install 'hammer-marl[{EXTRA}]'"
                             ) from None
    if loopback:
        ray_constants.ENABLE_RAY_CLUSTER = False  # read at import: set it too if Ray was imported before
    return ray


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in seconds, not after Ray's minutes of reconnecting, when nothing listens at HOST:PORT."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or "://" in address:
        return  # "auto", ray://... and other forms Ray resolves itself
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as e:
        raise ConnectionError(f"nothing answers at {address}: {e.strerror or e}") from None


def _token_available() -> bool:
    return bool(os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
                or (Path.home() / ".ray" / "auth_token").is_file())


def _forget_cached_token() -> None:
    """Ray keeps the first token a process reads for the rest of its life: a driver that has
    already run another instance (a private one, whose default token is ~/.ray/auth_token, or
    another cluster) would present that token to this cluster and be refused. Reading it again
    at each connect makes RAY_AUTH_TOKEN(_PATH) mean what it says now."""
    try:
        from ray._raylet import AuthenticationTokenLoader
    except ImportError:  # a Ray without token authentication caches nothing
        return
    AuthenticationTokenLoader.instance().reset_cache()


def _auth_failure(e: BaseException, auth_error: type) -> bool:
    """Whether Ray's error, or one it wraps, is a rejected token."""
    seen = e
    while seen is not None:
        if isinstance(seen, auth_error) or "InvalidAuthToken" in str(seen):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


class RayLauncher:
    """Runs each command as a Ray task holding `num_cpus` CPUs; `address` None starts a local instance."""

    def __init__(self, address: str | None = None, num_cpus: float = 1.0) -> None:
        loopback = _is_loopback(address)
        ray = self.ray = import_ray(loopback)
        kw = {"_node_ip_address": "127.0.0.1"} if loopback else {}
        _forget_cached_token()
        try:
            if address is None:
                ray.init(address="local", include_dashboard=False, object_store_memory=100 * 2**20,
                         logging_level="WARNING", **kw)
            else:
                # Ray reads a token only when told to: a cluster started with token authentication
                # (Ray's default for `ray start --head`) needs it from every driver.
                if "RAY_AUTH_MODE" not in os.environ and _token_available():
                    os.environ["RAY_AUTH_MODE"] = "token"
                _check_reachable(address)
                ray.init(address=address, logging_level="WARNING", **kw)
        except (ray.exceptions.AuthenticationError, ConnectionError) as e:
            # Ray wraps a rejected token in its generic connection error when it joins a cluster
            if _auth_failure(e, ray.exceptions.AuthenticationError):
                raise RayUnavailable(f"Ray token authentication: the cluster at {address or 'this machine'} rejected "
                                     "this machine's token; fix: copy the head node's ~/.ray/auth_token here (or set "
                                     "RAY_AUTH_TOKEN_PATH to it)") from None
            raise RayUnavailable(f"cannot connect to the Ray cluster at {address} ({_first_line(e)}); fix: check "
                                 "--ray-address and that the cluster is up (ray status on its head); with token "
                                 "authentication, copy the head's ~/.ray/auth_token here") from None
        self.num_cpus = num_cpus
        self.task = ray.remote(run_command).options(num_cpus=num_cpus, max_retries=0)

    def describe(self) -> str:
        nodes = [n for n in self.ray.nodes() if n.get("Alive")]
        cpus = self.ray.cluster_resources().get("CPU", 0)
        return f"Ray: {len(nodes)} node{'s' * (len(nodes) != 1)}, {cpus:g} CPUs, {self.num_cpus:g} per run"

    def slots(self) -> int:
        return max(1, int(self.ray.cluster_resources().get("CPU", 1) // self.num_cpus))

    def launch(self, args: list[str], log: Path, run_dirs: list[Path]) -> _RayJob:
        marks = [(str(Path(d).absolute()), (Path(d) / LOCK).read_text()) for d in run_dirs]
        ref = self.task.remote(args, str(Path(log).absolute()), marks, os.getcwd(), socket.gethostname())
        return _RayJob(self.ray, ref)

    def close(self) -> None:
        self.ray.shutdown()  # a local instance stops with it; on a cluster, the job's workers end


class _RayJob:
    pid = None  # the command runs on some node: the run's lock records only this sweep

    def __init__(self, ray, ref) -> None:
        self.ray, self.ref, self.reason = ray, ref, ""
        self.code: int | None = None

    def poll(self) -> int | None:
        if self.code is None and self.ray.wait([self.ref], timeout=0)[0]:
            try:
                self.code = int(self.ray.get(self.ref))
            except self.ray.exceptions.RayTaskError as e:  # raised inside the task
                self.code, self.reason = 1, _first_line(e.cause if e.cause is not None else e)
            except self.ray.exceptions.RayError as e:  # the worker or its node died, the task was cancelled
                self.code, self.reason = 1, f"Ray task lost: {type(e).__name__}: {_first_line(e)}"
        return self.code

    def stop(self) -> None:
        """Cancel the task: its command is terminated by the task itself; if the task does not end
        in time its worker is killed, and the command with it (it dies with its parent)."""
        if self.poll() is not None:
            return
        self.ray.cancel(self.ref)
        if not self.ray.wait([self.ref], timeout=STOP_GRACE_S)[0]:
            self.ray.cancel(self.ref, force=True)
            self.ray.wait([self.ref], timeout=STOP_GRACE_S)


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


# ----- on the worker ---------------------------------------------------------------------------
def run_command(args: list[str], log: str, marks: list[tuple[str, str]], cwd: str, driver: str) -> int:
    """The Ray task: check that this node sees the run directories as the sweep wrote them, then run
    `python *args` as the local backend would, and return its exit status. A cancel (KeyboardInterrupt)
    terminates the command before the task ends, so no training process outlives its task."""
    here = socket.gethostname()
    for path, mark in marks:
        try:
            seen = (Path(path) / LOCK).read_text()
        except OSError:
            seen = None
        if seen != mark:
            raise RunDirNotVisible(
                f"node {here} does not see {path} as the sweep on {driver} wrote it: on a Ray cluster the "
                "run directories must be on storage every node mounts at the same path; fix: put --out on "
                "a shared filesystem (NFS or similar) mounted on every node")
    with open(log, "ab") as logf:
        proc = subprocess.Popen([sys.executable, *args], stdout=logf, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=dict(os.environ, **THREAD_ENV),
                                cwd=cwd if os.path.isdir(cwd) else None,
                                preexec_fn=_die_with_parent())  # noqa: PLW1509 - one libc call, see there
        try:
            while proc.poll() is None:  # not proc.wait(): a cancel arrives only between bytecodes
                time.sleep(0.2)
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    return proc.returncode


def _die_with_parent():
    """A preexec_fn for the command (Linux): it receives SIGTERM when the Ray worker that started it
    dies, e.g. killed by a forced cancel or by Ray when the sweep disconnects. libc is loaded here,
    in the worker, so the forked child only makes the one call before exec."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None  # not Linux: the task's own terminate is the only guard
    return lambda: prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
