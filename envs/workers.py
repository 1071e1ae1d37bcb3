"""`SubprocVecEnv`: the K copies of a PettingZoo env split over W worker processes.

Physics envs such as multiwalker (Box2D) spend almost all their time in the simulator, one copy after
the other, so on a multi-core machine the copies are stepped in parallel worker processes instead.

Design, and why:
  * Workers are started with the `spawn` context (never fork: the parent may hold torch threads, Zenoh
    sessions or locks that a forked child would inherit in a broken state).
  * A worker rebuilds its envs from an `EnvDescription` (registry name + kwargs, plain data), runs a
    `PettingZooVecEnv` over its contiguous slice [offset, offset + count) with `index_offset=offset`,
    so seeds (seed + global k) and `EpisodeStats.env_index` match the in-process env exactly.
  * Bulk data (actions in; obs, rewards, flags, masks out) lives in shared memory (`RawArray`s
    created before the workers start and viewed as numpy arrays on both sides): no copying through
    pipes. The pipe carries only tiny msgpack commands and replies (and finished episodes), never
    pickles.
  * Shutdown: `close()`, garbage collection and interpreter exit all run the same finalizer (ask,
    wait, terminate, kill). A worker whose parent dies sees EOF on its pipe or a changed parent pid
    and exits by itself.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import traceback
import weakref
from typing import Any

import msgpack
import numpy as np
from hammer.envs.base import EnvSpec, EpisodeStats, VecEnv, VecStep
from hammer.envs.catalog import build_local
from hammer.envs.description import EnvDescription

_POLL_S = 0.5  # how often an idle worker checks that its parent is still alive


def _pack(*msg: Any) -> bytes:
    return msgpack.packb(list(msg), use_bin_type=True)


def _array_fields(spec: EnvSpec, num_envs: int) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shapes and dtypes of every shared array, for the whole batch of K copies."""
    K, N, D = num_envs, spec.n_agents, spec.obs_dim
    act_dtype = np.dtype(np.int64 if spec.discrete else np.float32)
    return {
        "actions": ((K, N, *spec.action_shape), act_dtype),
        "obs": ((K, N, D), np.dtype(np.float32)),
        "final_obs": ((K, N, D), np.dtype(np.float32)),
        "reward": ((K, N), np.dtype(np.float32)),
        "terminated": ((K, N), np.dtype(bool)),
        "truncated": ((K, N), np.dtype(bool)),
        "active": ((K, N), np.dtype(bool)),
        "next_active": ((K, N), np.dtype(bool)),
        "done": ((K,), np.dtype(bool)),
    }


def _views(raw: dict[str, Any], fields: dict[str, tuple[tuple[int, ...], np.dtype]]) -> dict[str, np.ndarray]:
    return {name: np.frombuffer(raw[name], dtype=dtype, count=int(np.prod(shape))).reshape(shape)
            for name, (shape, dtype) in fields.items()}


def _worker_main(conn: Any, desc: EnvDescription, offset: int, count: int, spec: EnvSpec, num_envs: int,
                 raw: dict[str, Any], parent_pid: int) -> None:
    """Entry point of one worker process: build the slice, then serve commands until told to stop."""
    # Ctrl-C reaches the whole process group; the parent decides when workers stop (via close()).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        venv = build_local(desc, count, index_offset=offset)
    except BaseException:  # noqa: BLE001 - report any build failure to the parent, then exit
        with contextlib.suppress(OSError):
            conn.send_bytes(_pack("error", traceback.format_exc()))
        return
    full = _views(raw, _array_fields(spec, num_envs))
    v = {name: arr[offset:offset + count] for name, arr in full.items()}
    try:
        conn.send_bytes(_pack("ready", os.getpid()))
        while True:
            if not conn.poll(_POLL_S):
                if os.getppid() != parent_pid:
                    break  # parent died without closing us: nobody will ever send a command
                continue
            cmd, arg = msgpack.unpackb(conn.recv_bytes(), raw=False)
            try:
                if cmd == "step":
                    s = venv.step(v["actions"])
                    for name in ("obs", "final_obs", "reward", "terminated", "truncated", "active",
                                 "next_active", "done"):
                        v[name][...] = getattr(s, name)
                    eps = [[e.env_index, e.paper_metric, e.team_return, e.length] for e in s.episodes]
                    conn.send_bytes(_pack("ok", eps))
                elif cmd == "reset":
                    obs, active = venv.reset(arg)
                    v["obs"][...] = obs
                    v["next_active"][...] = active
                    conn.send_bytes(_pack("ok", None))
                elif cmd == "close":
                    break
                else:
                    conn.send_bytes(_pack("error", f"unknown command {cmd!r}"))
            except Exception:  # noqa: BLE001 - env errors go back to the parent, which raises them
                conn.send_bytes(_pack("error", traceback.format_exc()))
    except (EOFError, OSError):
        pass  # the parent closed its end or died
    finally:
        venv.close()
        conn.close()


def _shutdown(procs: list[Any], conns: list[Any], timeout: float = 3.0) -> None:
    """Stop every worker: ask politely, then terminate, then kill. Safe to call more than once."""
    for c in conns:
        with contextlib.suppress(OSError, ValueError):
            c.send_bytes(_pack("close", None))
    for p in procs:
        p.join(timeout)
    for p in procs:
        if p.is_alive():
            p.terminate()
            p.join(1.0)
        if p.is_alive():
            p.kill()
            p.join(1.0)
    for c in conns:
        with contextlib.suppress(OSError):
            c.close()


def slice_counts(num_envs: int, workers: int) -> list[tuple[int, int]]:
    """(offset, count) of each worker's contiguous slice of the K copies; the first K mod W get one more."""
    base, extra = divmod(num_envs, workers)
    counts = [base + (1 if w < extra else 0) for w in range(workers)]
    return [(sum(counts[:w]), c) for w, c in enumerate(counts)]


class WorkerError(RuntimeError):
    """A worker failed to build its envs, crashed, or raised while stepping; carries its traceback."""


class SubprocVecEnv(VecEnv):
    """`VecEnv` over W contiguous slices of the K copies, each stepped by a spawn-context worker.

    parent_slice=True: the calling process steps slice 0 itself while the W-1 workers step theirs.
    Stepping is synchronous, so the caller would otherwise sit idle until the slowest worker
    replies; doing a share of the work instead saves one process's IPC and lets W slices use W
    cores with only W-1 extra processes (W=2: the trainer and one worker)."""

    def __init__(self, desc: EnvDescription, num_envs: int, workers: int, *, start_timeout: float = 120.0,
                 parent_slice: bool = False) -> None:
        if not 1 <= workers <= num_envs:
            raise ValueError(f"workers must be in [1, num_envs={num_envs}], got {workers}")
        # The spec sizes the shared arrays: take it from one copy built here (also validates early).
        probe = build_local(desc, 1)
        self.spec = probe.spec
        probe.close()
        self.num_envs = num_envs
        self.desc = desc
        ctx = mp.get_context("spawn")
        fields = _array_fields(self.spec, num_envs)
        raw = {name: ctx.RawArray("b", max(1, int(np.prod(shape)) * dtype.itemsize))
               for name, (shape, dtype) in fields.items()}
        self._buf = _views(raw, fields)
        self.slices = slice_counts(num_envs, workers)
        self._procs: list[Any] = []
        self._conns: list[Any] = []
        self._parent: VecEnv | None = None  # slice 0 when parent_slice
        self._w0 = 1 if parent_slice else 0  # slice index of the first subprocess worker
        # Registered before the first start so that a failure half-way still stops what was started.
        self._finalizer = weakref.finalize(self, _shutdown, self._procs, self._conns)
        if parent_slice:
            off, cnt = self.slices[0]
            self._parent = build_local(desc, cnt, index_offset=off)
        for w, (off, cnt) in enumerate(self.slices):
            if w < self._w0:
                continue
            parent_end, child_end = ctx.Pipe(duplex=True)
            p = ctx.Process(target=_worker_main, name=f"hammer-env-worker-{w}", daemon=True,
                            args=(child_end, desc, off, cnt, self.spec, num_envs, raw, os.getpid()))
            p.start()
            child_end.close()  # only the worker holds it now, so its death shows up as EOF here
            self._procs.append(p)
            self._conns.append(parent_end)
        try:
            for i, c in enumerate(self._conns):
                if not c.poll(start_timeout):
                    raise WorkerError(f"env worker {i + self._w0} did not start within {start_timeout:.0f} s")
                self._reply(i, expect="ready")
        except BaseException:
            self.close()
            raise
        self._seeded = False

    @property
    def pids(self) -> list[int]:
        """Process ids of the workers (for tests and monitoring)."""
        return [p.pid for p in self._procs]

    def _reply(self, i: int, expect: str = "ok") -> Any:
        """Reply of the i-th subprocess (slice i + self._w0)."""
        w = i + self._w0
        try:
            kind, payload = msgpack.unpackb(self._conns[i].recv_bytes(), raw=False)
        except (EOFError, OSError) as e:
            raise self._died(i) from e
        if kind == "error":
            raise WorkerError(f"env worker {w} (envs {self.slices[w]}) of {self.desc.name!r} failed:\n{payload}")
        if kind != expect:
            raise WorkerError(f"env worker {w}: expected {expect!r}, got {kind!r}")
        return payload

    def _died(self, i: int) -> WorkerError:
        """The error for a subprocess whose pipe broke (it was killed or crashed)."""
        p = self._procs[i]
        p.join(1.0)
        return WorkerError(f"env worker {i + self._w0} (pid {p.pid}, envs {self.slices[i + self._w0]}) exited "
                           f"unexpectedly with exit code {p.exitcode}")

    def _broadcast(self, cmd: str, arg: Any, parent_work=None) -> list[Any]:
        """Send `cmd` to every worker, run `parent_work()` (the parent's slice) meanwhile, gather."""
        if not self._finalizer.alive:
            raise RuntimeError("SubprocVecEnv is closed")
        msg = _pack(cmd, arg)
        for i, c in enumerate(self._conns):
            try:
                c.send_bytes(msg)
            except OSError as e:  # a worker killed before this send: its end of the pipe is closed
                raise self._died(i) from e
        try:
            mine = [parent_work()] if parent_work is not None else []
        finally:  # even if the parent's slice failed: read every reply, so the pipes stay in step
            theirs = [self._reply(i) for i in range(len(self._conns))]
        return mine + theirs

    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        def parent_reset() -> None:
            off, cnt = self.slices[0]
            obs, active = self._parent.reset(int(seed))
            self._buf["obs"][off:off + cnt] = obs
            self._buf["next_active"][off:off + cnt] = active

        self._broadcast("reset", int(seed), parent_reset if self._parent is not None else None)
        self._seeded = True
        return self._buf["obs"].copy(), self._buf["next_active"].copy()

    def _parent_step(self) -> list[list]:
        off, cnt = self.slices[0]
        s = self._parent.step(self._buf["actions"][off:off + cnt])
        for name in ("obs", "final_obs", "reward", "terminated", "truncated", "active", "next_active", "done"):
            self._buf[name][off:off + cnt] = getattr(s, name)
        return [[e.env_index, e.paper_metric, e.team_return, e.length] for e in s.episodes]

    def step(self, actions: np.ndarray) -> VecStep:
        if not self._seeded:
            raise RuntimeError("call reset(seed) before step(): the copies have not been seeded yet")
        buf = self._buf
        actions = np.asarray(actions)
        if actions.shape != buf["actions"].shape:
            raise ValueError(f"actions must have shape {buf['actions'].shape}, got {actions.shape}")
        np.copyto(buf["actions"], actions, casting="unsafe")
        replies = self._broadcast("step", None, self._parent_step if self._parent is not None else None)
        episodes = [EpisodeStats(int(i), float(p), float(t), int(n)) for eps in replies for i, p, t, n in eps]
        return VecStep(obs=buf["obs"].copy(), reward=buf["reward"].copy(), terminated=buf["terminated"].copy(),
                       truncated=buf["truncated"].copy(), active=buf["active"].copy(),
                       next_active=buf["next_active"].copy(), final_obs=buf["final_obs"].copy(),
                       done=buf["done"].copy(), episodes=episodes)

    def close(self) -> None:
        self._finalizer()
        if self._parent is not None:
            self._parent.close()
            self._parent = None
