"""Fixtures shared by test files."""

from __future__ import annotations

import multiprocessing.process
import os
import shutil
import signal
import subprocess
import tempfile

import pytest

# One BLAS thread for numpy in each test process and every process it starts: make test runs three
# workers beside the serial tests on two cores, and OpenBLAS's idle threads spin on CPU the other tests
# need. Read when numpy loads, so set before any test module imports it; a value given is kept. (Torch
# keeps its own: the trainer and the roles set theirs.)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from tests import tiers
from tests.runtime_helpers import TEAMS_ENV

# Tests stop real processes with SIGINT (Ctrl-C, as a person would). A shell that starts a job in
# the background (`make test &`, nohup) leaves SIGINT ignored, children inherit an ignored signal
# across exec, and Python then never turns it into KeyboardInterrupt: those stops would silently not
# happen. A handled signal is reset to the default at exec, so handling it here gives every child
# the terminal's Ctrl-C again, whatever launched the suite.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def edge_venv(tmp_path_factory):
    """The python of a fresh venv with only the edge install of this checkout (benchmarks.edge_venv),
    built once per session from the session's wheel (tests/runtime_helpers.hammer_wheel), by this
    interpreter's pip (the venv needs none of its own); skipped only when the package index is unreachable."""
    from hammer.benchmarks.edge_venv import EdgeVenvError, build_edge_venv

    from tests.runtime_helpers import hammer_wheel

    edge = tmp_path_factory.mktemp("edge")
    try:
        return build_edge_venv(edge / "venv", compile_pyc=False, wheel=hammer_wheel(edge),  # quicker to build
                               own_pip=False)
    except EdgeVenvError as e:
        if e.offline:
            pytest.skip(f"the package index is unreachable, so no edge venv can be built: {e}")
        raise


def pytest_configure(config):
    """The session's cache of trained teams and `hammer up` runs (tests/runtime_helpers.trained_run,
    up_run), made by the main process before any xdist worker starts, so that every worker inherits
    it; in the fast tier, the watch on started processes (in each xdist worker, not in the main
    process that starts them)."""
    if config.getoption("--fast") and (hasattr(config, "workerinput") or not config.getoption("numprocesses", None)):
        _watch_processes()
    if not hasattr(config, "workerinput") and TEAMS_ENV not in os.environ:
        os.environ[TEAMS_ENV] = config._hammer_teams = tempfile.mkdtemp(prefix="hammer-test-teams-")


def pytest_unconfigure(config):
    teams = getattr(config, "_hammer_teams", None)
    if teams:
        shutil.rmtree(teams, ignore_errors=True)
        os.environ.pop(TEAMS_ENV, None)


def pytest_addoption(parser):
    parser.addoption("--fast", action="store_true",
                     help="the fast tier only (`make check`): no test marked " + ", ".join(tiers.FULL_ONLY)
                          + " (tests/tiers.py), and a test that starts a process there fails")


def pytest_ignore_collect(collection_path, config):
    """`-m serial` alone (make test's run of the serial tests) imports only the files that hold a serial test:
    importing the others (torch, the envs, every module's helpers) would only end in deselecting
    them, seconds spent before the stage's first test."""
    if (config.getoption("markexpr", "") == "serial" and collection_path.suffix == ".py"
            and collection_path.name.startswith("test_") and not tiers.may_hold_serial(collection_path.stem)):
        return True
    return None


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(config, items):
    """Applies tests/tiers.py's marks; groups each module's tests on one xdist worker (a module's
    fixtures, trained teams and served runs, are then built once), and every test that needs the
    session's edge venv on one worker (it is built once per worker); puts the longest groups first
    (`make test` keeps that order: --no-loadscope-reorder); with --fast, keeps the fast tier."""
    group = {}
    for item in items:
        module = item.path.stem
        for mark in tiers.marks_for(module, getattr(item, "originalname", item.name)):
            item.add_marker(mark)
        group[item] = "edge-venv" if "edge_venv" in getattr(item, "fixturenames", ()) else module
        item.add_marker(pytest.mark.xdist_group(group[item]))
    first = {g: i for i, g in enumerate(tiers.LONGEST_FIRST)}
    items.sort(key=lambda i: first.get(group[i], len(first)))  # stable: file order otherwise
    if config.getoption("--fast"):
        keep = [i for i in items if not any(i.get_closest_marker(m) for m in tiers.FULL_ONLY)]
        config.hook.pytest_deselected(items=[i for i in items if i not in keep])
        items[:] = keep


# What tests started in the fast tier, in order (see `_watch_processes`).
_started: list[str] = []
# Programs the standard library runs for itself: platform.platform() asks `uname -p` once a process.
_LIBRARY_PROGRAMS = {"uname"}


def _watch_processes() -> None:
    """In the fast tier, notes every process a test starts, for the whole session (module fixtures
    included); the test then fails naming tests/tiers.py. The process still starts, so the test
    behaves as in `make test` and the failure is only that it is in the wrong tier."""
    execute_child = subprocess.Popen._execute_child

    def watched_child(self, args, *rest, **kwargs):
        argv = [args] if isinstance(args, (str, bytes, os.PathLike)) else list(args)
        if os.path.basename(str(argv[0]).split()[0]) not in _LIBRARY_PROGRAMS:
            _started.append(f"subprocess {os.path.basename(str(argv[0]))}")
        return execute_child(self, args, *rest, **kwargs)

    start = multiprocessing.process.BaseProcess.start

    def watched_start(self, *args, **kwargs):
        _started.append("multiprocessing")
        return start(self, *args, **kwargs)

    subprocess.Popen._execute_child = watched_child
    multiprocessing.process.BaseProcess.start = watched_start
    for name in ("fork", "forkpty", "system"):  # subprocess may posix_spawn itself: watched above
        if hasattr(os, name):
            setattr(os, name, _noted(getattr(os, name), f"os.{name}"))


def _noted(fn, what):
    def noted(*args, **kwargs):
        _started.append(what)
        return fn(*args, **kwargs)
    return noted


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    item.started_before = len(_started)  # its module's fixtures are set up after this


@pytest.fixture(autouse=True)
def _fast_tier_starts_no_process(request):
    yield
    start = getattr(request.node, "started_before", len(_started))
    if len(_started) > start:
        pytest.fail(f"{request.node.nodeid} starts a process ({', '.join(sorted(set(_started[start:])))}) "
                    "in the fast tier: mark it in tests/tiers.py", pytrace=False)


# HAMMER_TEST_CPU=FILE (off by default): each test's CPU seconds, appended to FILE as CSV rows
# (nodeid, cpu_s, wall_s, worker, start as Unix time). The suite is CPU-bound on a small machine, so
# this, not wall time, says which tests to make cheaper; the worker and start show the schedule. Counted: this process (all its threads), the children it reaped, and
# every live descendant with the children each of those reaped (a compile worker pool, a role and
# its own workers), as deltas over the test's setup, call and teardown; a module's fixtures count
# in its first test.
_CPU_FILE = os.environ.get("HAMMER_TEST_CPU")


def _cpu_now() -> float:
    import resource

    import psutil

    total = sum(getattr(resource.getrusage(w), f) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
                for f in ("ru_utime", "ru_stime"))
    for p in psutil.Process().children(recursive=True):
        try:
            t = p.cpu_times()
            total += t.user + t.system + t.children_user + t.children_system
        except psutil.Error:  # gone in between: its parent has it, or it is lost (an orphan)
            pass
    return total


if _CPU_FILE:
    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import time

        cpu, wall = _cpu_now(), time.monotonic()
        yield
        with open(_CPU_FILE, "a") as f:
            f.write(f"{item.nodeid},{_cpu_now() - cpu:.2f},{time.monotonic() - wall:.2f},"
                    f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')},{time.time() - (time.monotonic() - wall):.1f}\n")
