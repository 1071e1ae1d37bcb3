"""`SubprocVecEnv` against the in-process env, and its process hygiene (real spawn workers)."""

from __future__ import annotations

import gc
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import psutil
import pytest
from hammer.envs.registry import make_vec_env
from hammer.envs.workers import SubprocVecEnv, WorkerError

FIELDS = ("obs", "final_obs", "reward", "terminated", "truncated", "active", "next_active", "done")


def fail_in_worker(**kwargs):
    """A factory that works in the parent but fails inside a worker process (module:factory target)."""
    if mp.parent_process() is not None:
        raise RuntimeError("boom: this factory refuses to build inside a worker")
    from pettingzoo.sisl import multiwalker_v9

    return multiwalker_v9.parallel_env(**kwargs)


def gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def wait_gone(pids: list[int], timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all(gone(p) for p in pids):
            return True
        time.sleep(0.1)
    return False


@pytest.mark.parametrize("parent_slice", [False, True])
@pytest.mark.parametrize(("name", "kwargs"), [("mw", {"terminate_on_fall": False}), ("cn-mpe2", {})])
def test_workers_match_in_process_exactly(name, kwargs, parent_slice):
    K, T = 5, 110
    local = make_vec_env(name, 3, K, env_kwargs=kwargs)
    with make_vec_env(name, 3, K, env_kwargs=kwargs, workers=2, parent_slice=parent_slice) as sub:
        assert isinstance(sub, SubprocVecEnv) and sub.slices == [(0, 3), (3, 2)]
        assert len(sub.pids) == (1 if parent_slice else 2)
        assert sub.spec == local.spec
        for a, b in zip(local.reset(seed=21), sub.reset(seed=21)):
            np.testing.assert_array_equal(a, b)
        rng = np.random.default_rng(4)
        n_eps, n_removed = 0, 0
        for _ in range(T):
            if local.spec.discrete:
                act = rng.integers(0, 5, (K, 3))
            else:  # one walker kicks itself over (removal), the rest gets noise
                act = rng.uniform(-0.3, 0.3, (K, 3, 4)).astype(np.float32)
                act[:, 2] = [1.0, -1.0, 1.0, -1.0]
            sa, sb = local.step(act), sub.step(act)
            for f in FIELDS:
                np.testing.assert_array_equal(getattr(sa, f), getattr(sb, f), err_msg=f)
            assert sa.episodes == sb.episodes
            n_eps += len(sa.episodes)
            n_removed += int((sa.active & ~sa.next_active & ~sa.done[:, None]).sum())
        assert n_eps > 0, "the comparison must cover episode ends in the workers' slices"
        if name == "mw":
            assert n_removed > 0, "the comparison must cover walkers removed mid-episode"
            assert {e.env_index for e in sa.episodes} <= set(range(K))
        pids = sub.pids
    assert wait_gone(pids), "workers still running after close()"


def test_no_stray_processes_after_close_and_gc():
    sub = make_vec_env("cn-mpe2", 3, 2, workers=2)
    pids = sub.pids
    assert all(psutil.pid_exists(p) and not gone(p) for p in pids)
    sub.reset(seed=0)
    sub.step(np.zeros((2, 3), dtype=np.int64))
    sub.close()
    sub.close()  # idempotent
    assert wait_gone(pids)
    with pytest.raises(RuntimeError, match="closed"):
        sub.reset(seed=0)

    sub = make_vec_env("cn-mpe2", 3, 2, workers=1)
    pids = sub.pids
    del sub
    gc.collect()
    assert wait_gone(pids), "workers survived garbage collection of their SubprocVecEnv"


def test_workers_exit_when_the_parent_is_killed():
    code = textwrap.dedent("""
        import sys, time
        from hammer.envs.registry import make_vec_env
        if __name__ == "__main__":
            v = make_vec_env("cn-mpe2", 3, 2, workers=2)
            v.reset(seed=0)
            print(" ".join(map(str, v.pids)), flush=True)
            time.sleep(120)
    """)
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2 and all(not gone(p) for p in pids)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        assert wait_gone(pids, timeout=15), "workers outlived their SIGKILLed parent"
    finally:
        parent.kill()
        parent.wait(10)


def test_factory_failing_in_worker_is_a_clear_error():
    name = f"{__name__}:fail_in_worker"
    kw = {"n_walkers": 3}
    make_vec_env(name, 3, 1, env_kwargs=kw).close()  # builds fine in this process
    before = {c.pid for c in psutil.Process().children(recursive=True)}
    with pytest.raises(WorkerError, match=r"(?s)worker 0.*fail_in_worker.*boom: this factory refuses"):
        make_vec_env(name, 3, 2, env_kwargs=kw, workers=2)
    after = {c.pid for c in psutil.Process().children(recursive=True)} - before
    assert wait_gone(list(after))


def test_dead_worker_is_reported_not_hung():
    with make_vec_env("cn-mpe2", 3, 2, workers=2) as sub:
        sub.reset(seed=0)
        os.kill(sub.pids[1], signal.SIGKILL)
        with pytest.raises(WorkerError, match="worker 1 .* exited unexpectedly"):
            sub.step(np.zeros((2, 3), dtype=np.int64))


def test_dead_worker_is_reported_with_a_parent_slice():
    with make_vec_env("cn-mpe2", 3, 2, workers=2, parent_slice=True) as sub:
        sub.reset(seed=0)
        os.kill(sub.pids[0], signal.SIGKILL)
        with pytest.raises(WorkerError, match="worker 1 .* exited unexpectedly"):
            sub.step(np.zeros((2, 3), dtype=np.int64))
