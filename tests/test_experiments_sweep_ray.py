"""`hammer sweep --backend ray` against a real Ray head on 127.0.0.1 (`ray start --head`, dashboard
and usage statistics off): the same run directories and metrics as the local backend, finished
points skipped, an interrupted sweep's runs stopped with it and resumed from their checkpoints, and
a node that cannot see OUT failing the run with a message that says so."""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from hammer.experiments.ray_backend import RayLauncher
from hammer.experiments.sweep import expand, run_sweep, state_of

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="ray is not installed (pip install 'hammer-marl[cluster]'; make test installs it)")

GRID = [("num_envs", ["4"]), ("rollout_steps", ["25"]), ("checkpoint_every", ["2"])]
GRID_ARGS = ["--grid", "num_envs=4", "--grid", "rollout_steps=25", "--grid", "checkpoint_every=2"]
EPISODES = 200  # 50 updates of 4 episodes, a checkpoint every 2: the trainers are frozen within one poll
# of their first checkpoint (below), and the 48 updates after it outlast that poll (~30 times over in CPU)


def _metrics(run_dir: Path) -> list[dict[str, str]]:
    """Every column but wall_time (the only one that may differ between two runs of one point)."""
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader(f)]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _can_unshare() -> bool:
    """Whether a private mount namespace can be made here (root, util-linux)."""
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "--mount", "true"], check=False, capture_output=True).returncode == 0


@dataclass
class Head:
    address: str
    pid: int  # `ray start --block`; every process of the node descends from it
    hidden: Path | None  # a directory the Ray node does not see (an empty tmpfs in its namespace)


@pytest.fixture(scope="module")
def ray_head():
    """A one-node Ray cluster on 127.0.0.1 for this module, stopped by its process group at the end.
    Where possible the node runs in its own mount namespace with an empty tmpfs over `hidden`, so
    that it is a node whose storage lacks what the sweep writes there."""
    root = Path(tempfile.mkdtemp(prefix="hray-", dir="/tmp"))  # short: Ray's socket paths live under it
    token = root / "token"
    token.write_text(secrets.token_hex(32))
    port = _free_port()
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0", RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0",
               RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0", RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token))
    cmd = [str(Path(sys.executable).with_name("ray")), "start", "--head", "--block", "--node-ip-address=127.0.0.1",
           f"--port={port}", f"--ray-client-server-port={_free_port()}", f"--dashboard-port={_free_port()}",
           f"--dashboard-agent-listen-port={_free_port()}", "--include-dashboard=false", "--disable-usage-stats",
           "--num-cpus=2", "--object-store-memory=100000000", f"--temp-dir={root / 'ray'}"]
    hidden = None
    if _can_unshare():
        hidden = root / "hidden"
        hidden.mkdir()
        cmd = ["unshare", "--mount", "--propagation", "private", "sh", "-c",
               'mount -t tmpfs -o size=1m hammer-hidden "$0" && exec "$@"', str(hidden), *cmd]
    log = open(root / "head.log", "w")  # noqa: SIM115
    head = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            start_new_session=True)
    saved = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN_PATH")}
    os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token))
    try:
        deadline = time.monotonic() + 90
        while "Ray runtime started" not in (root / "head.log").read_text():
            assert head.poll() is None and time.monotonic() < deadline, (root / "head.log").read_text()[-2000:]
            time.sleep(0.2)
        yield Head(f"127.0.0.1:{port}", head.pid, hidden)
    finally:
        for k, v in saved.items():
            os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
        _stop_group(head)
        log.close()
        shutil.rmtree(root, ignore_errors=True)


def _stop_group(proc: subprocess.Popen) -> None:
    """`ray start --block` stops its node on SIGTERM; whatever is left of its group is killed."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(30)
    except subprocess.TimeoutExpired:
        pass
    except ProcessLookupError:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def _off_loopback(pids: list[int]) -> list[str]:
    """Every TCP/UDP socket of these processes with an address (local or remote) off loopback."""
    import ipaddress

    import psutil

    bad = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        for c in conns:
            for a in (c.laddr, c.raddr):
                ip = ipaddress.ip_address(a.ip) if a else None
                ip = getattr(ip, "ipv4_mapped", None) or ip  # ::ffff:127.0.0.1 is loopback too
                if ip is not None and not ip.is_loopback:
                    bad.append(f"pid {pid} {_name(pid)} {a.ip}:{a.port} {c.status}")
    return bad


def _name(pid: int) -> str:
    import psutil

    try:
        return psutil.Process(pid).name()
    except psutil.NoSuchProcess:
        return "?"


def _family(pid: int) -> list[int]:
    import psutil

    return [pid, *(p.pid for p in psutil.Process(pid).children(recursive=True))]


def _trainers(out: Path) -> list:
    """The training processes of a sweep into `out`, wherever Ray started them on this machine."""
    import psutil

    found = []
    for p in psutil.process_iter(["cmdline"]):
        cmd = p.info["cmdline"] or []
        if any(a.startswith(str(out)) for a in cmd) and ("hammer.cli" in cmd or "hammer.commands.seeds" in cmd):
            found.append(p)
    return found


def _interrupt_cli_sweep(address: str, out: Path) -> list[str]:
    """Start `hammer sweep --backend ray`, SIGTERM it once a run has a checkpoint, check that its
    training processes end with it; returns the points it left to resume."""
    import psutil

    log = out.with_name(out.name + "-cli.log")
    with open(log, "wb") as f:
        sweep = subprocess.Popen([sys.executable, "-m", "hammer.cli", "sweep", "--out", str(out), "--backend", "ray",
                                  "--ray-address", address, "--presets", "cn3", "--variants", "il",
                                  "--seeds", "0-1", *GRID_ARGS, "--episodes", str(EPISODES), "--jobs", "2",
                                  "--seed-batch", "1"],
                                 stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    trainers: list = []
    try:
        deadline = time.monotonic() + 120
        while not any(state_of(d) == "resume" for d in out.glob("cn3-*")):
            assert sweep.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.1)
        trainers = [p for p in _trainers(out) if p.pid != sweep.pid]
        assert trainers, "no training process of the Ray sweep found on this machine"
        # Frozen, the runs cannot finish while the sweep shuts down (Ray's cancel can take longer than
        # a run's remaining updates on a loaded machine): the signals the sweep sends them wait, and
        # act the moment they are thawed, or a SIGKILL ends them frozen.
        for p in trainers:
            p.suspend()
        at_term = {d.name: state_of(d) for d in out.glob("cn3-*")}
        sweep.send_signal(signal.SIGTERM)
        assert sweep.wait(90) != 0
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.wait()
        for p in trainers:
            with contextlib.suppress(psutil.NoSuchProcess):
                p.resume()
    _gone, alive = psutil.wait_procs(trainers, timeout=20)
    for p in alive:  # never leave them running if the test fails
        p.kill()
    assert not alive, f"training processes left behind by the interrupted Ray sweep: {[p.pid for p in alive]}"
    left = sorted(d.name for d in out.glob("cn3-*") if state_of(d) == "resume")
    assert left, (f"the interrupted sweep left no run to resume: states at the SIGTERM {at_term}, after "
                  f"{ {d.name: state_of(d) for d in out.glob('cn3-*')} }, sweep log:\n{log.read_text()[-3000:]}")
    return left


@needs_ray
def test_ray_sweep_matches_local_skips_finished_and_resumes_interrupted(ray_head, tmp_path):

    # Every point alone (--seed-batch 1): a seed batch is not bit-identical to solo runs over 100 updates,
    # and an interrupted batch resumes as solo runs.
    pts = expand(["cn3"], ["il"], [0, 1], GRID, episodes=EPISODES)
    local = run_sweep(pts, tmp_path / "local", jobs=2, seed_batch=1)
    assert sorted(local.done) == sorted(p.name for p in pts) and not local.failed

    interrupted = _interrupt_cli_sweep(ray_head.address, tmp_path / "ray")
    events: list[tuple[str, str]] = []
    launcher = RayLauncher(ray_head.address)
    try:
        res = run_sweep(pts, tmp_path / "ray", jobs=2, launcher=launcher, seed_batch=1,
                        on_event=lambda k, n: events.append((k, n)))
        again = run_sweep(pts, tmp_path / "ray", jobs=2, launcher=launcher, seed_batch=1)
        sockets = _family(ray_head.pid) + [os.getpid()]
        assert len(sockets) > 5, "the Ray node's processes were not found"
        assert _off_loopback(sockets) == []  # the node and this driver: loopback only
    finally:
        launcher.close()
    assert not res.failed, res.failed
    assert sorted(n for k, n in events if k == "resume") == interrupted  # from their checkpoints, not afresh
    assert sorted(res.done + res.skipped) == sorted(p.name for p in pts)
    for p in pts:
        assert _metrics(tmp_path / "ray" / p.name) == _metrics(tmp_path / "local" / p.name), p.name
        assert len(_metrics(tmp_path / "ray" / p.name)) == EPISODES
    assert sorted(again.skipped) == sorted(p.name for p in pts) and not again.done and not again.failed


@needs_ray
def test_a_node_that_cannot_see_out_fails_the_run_saying_so(ray_head, tmp_path):
    """OUT where the sweep can write but the Ray node cannot see it (its own empty disk there): the
    run fails, and both the sweep's report and the run's train.log say why and what to do."""
    if ray_head.hidden is None:
        pytest.skip("needs `unshare --mount` (root) to give the Ray node a view of the disk without OUT")

    pts = expand(["cn3"], ["il"], [0], GRID, episodes=8)
    out = ray_head.hidden / "out"
    events: list[tuple[str, str]] = []
    launcher = RayLauncher(ray_head.address)
    try:
        res = run_sweep(pts, out, jobs=1, launcher=launcher, on_event=lambda k, n: events.append((k, n)))
    finally:
        launcher.close()
    assert res.failed == [(pts[0].name, 1)] and not res.done
    (fail,) = [n for k, n in events if k == "fail"]
    assert "does not see" in fail and "shared filesystem" in fail and "\n" not in fail
    log = (out / pts[0].name / "train.log").read_text()
    assert "does not see" in log and not (out / pts[0].name / "metrics.csv").exists()
    assert state_of(out / pts[0].name) == "new"  # nothing ran: the next sweep (on shared storage) starts it


def test_backend_flags_fail_in_one_line_naming_the_fix(tmp_path, monkeypatch):
    """Without Ray, `--backend ray` names the extra to install; Ray flags need `--backend ray`."""
    from typer.testing import CliRunner

    from hammer.cli import app

    args = ["sweep", "--out", str(tmp_path / "o"), "--presets", "cn3", "--variants", "il", "--seeds", "0"]
    res = CliRunner().invoke(app, [*args, "--ray-address", "127.0.0.1:6379"])
    assert res.exit_code == 2 and "fix: add --backend ray" in res.output
    res = CliRunner().invoke(app, [*args, "--backend", "slurm"])
    assert res.exit_code == 2 and "expected local or ray" in res.output
    monkeypatch.setitem(sys.modules, "ray", None)  # what an install without the extra looks like to Python
    res = CliRunner().invoke(app, [*args, "--backend", "ray"])
    assert res.exit_code == 2, res.output
    assert res.output.strip().count("\n") == 0 and "pip install 'hammer-marl[cluster]'" in res.output
    assert not (tmp_path / "o").exists()  # nothing started


@needs_ray
def test_default_ray_is_a_private_instance_on_loopback(ray_head, tmp_path, monkeypatch):
    """No --ray-address: Ray starts on this machine for the sweep alone, every socket on 127.0.0.1,
    and stops with it; the same driver then joins a cluster that has its own token (Ray keeps the
    first token a process reads: here the private instance's default one)."""
    import psutil

    pts = expand(["cn3"], ["il"], [0], GRID, episodes=8)
    before = {p.pid for p in psutil.Process().children(recursive=True)}  # e.g. this module's Ray head
    with monkeypatch.context() as private:  # a driver with no cluster token: Ray's default, in a home of its own
        private.delenv("RAY_AUTH_TOKEN_PATH")
        private.delenv("RAY_AUTH_MODE")
        private.setenv("HOME", str(tmp_path / "home"))
        launcher = RayLauncher()
        try:
            assert "1 node" in launcher.describe()
            res = run_sweep(pts, tmp_path, jobs=1, launcher=launcher)
            ray_procs = [p for p in psutil.Process().children(recursive=True) if p.pid not in before]
            assert len(ray_procs) > 3, "the local Ray instance's processes were not found"
            assert _off_loopback([os.getpid(), *(p.pid for p in ray_procs)]) == []
        finally:
            launcher.close()
    assert res.done == [pts[0].name] and len(_metrics(tmp_path / pts[0].name)) == 8
    _gone, alive = psutil.wait_procs(ray_procs, timeout=20)
    for p in alive:
        p.kill()
    assert not alive, f"Ray processes left after the sweep: {[p.pid for p in alive]}"
    cluster = RayLauncher(ray_head.address)
    try:
        assert "1 node" in cluster.describe()
    finally:
        cluster.close()


@needs_ray
def test_stopping_a_ray_job_ends_its_command_while_connected(ray_head, tmp_path):
    """`Job.stop()` (what Ctrl-C / SIGTERM to a sweep calls) ends the task's command itself, not
    only Ray's clean-up when the sweep disconnects: the command is gone while the sweep is still
    connected, and the job reports that it ended."""
    import psutil
    from hammer.experiments.sweep import LOCK

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / LOCK).write_text(str(os.getpid()))  # as the sweep's lock would be
    marker = f"hammer-stop-test-{secrets.token_hex(4)}"
    launcher = RayLauncher(ray_head.address)
    try:
        job = launcher.launch(["-c", f"import time; time.sleep(600)  # {marker}"], run_dir / "train.log", [run_dir])
        deadline = time.monotonic() + 60
        while not (found := [p for p in psutil.process_iter(["cmdline"]) if marker in " ".join(p.info["cmdline"] or [])]):
            assert job.poll() is None and time.monotonic() < deadline, f"the command never started: {job.reason}"
            time.sleep(0.1)
        job.stop()
        _gone, alive = psutil.wait_procs(found, timeout=5)
        for p in alive:  # never leave it running if the test fails
            p.kill()
        assert not alive, "the command outlived its stopped task"
        assert job.poll() is not None
        assert launcher.ray.is_initialized()  # still connected: the job's own stop did it
    finally:
        launcher.close()


@needs_ray
def test_an_unreachable_cluster_fails_in_seconds_naming_the_fix(tmp_path):
    from typer.testing import CliRunner

    from hammer.cli import app

    t0 = time.monotonic()
    res = CliRunner().invoke(app, ["sweep", "--out", str(tmp_path / "o"), "--seeds", "0", "--backend", "ray",
                                   "--ray-address", f"127.0.0.1:{_free_port()}"])
    assert res.exit_code == 2 and "cannot connect to the Ray cluster" in res.output and "fix:" in res.output
    assert time.monotonic() - t0 < 20 and not (tmp_path / "o").exists()
