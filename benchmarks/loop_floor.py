"""`hammer bench loop-floor`: the control loop's latency with every role's work taken out.

The runtime's step loop is three hops, env host -> central agent -> local agents -> env host, with
every role its own process. How fast can that loop possibly be on this machine? This benchmark
runs the same topology with the same key expressions, publishers (express) and subscriptions
(SimpleQueue), but with no env, no network forward and no bookkeeping: each role only waits for
its inputs and publishes its outputs. What it measures is the floor the real loop
(`hammer bench runtime`) sits on, so a latency target below the floor is out of reach for the
architecture on this hardware, whatever the roles' code does.

Two payload modes, measured in the same run:
  typed  the real messages of one cn vector step (K copies; `benchmarks.transport.loop_messages`): every
         sender builds and encodes, every receiver decodes and validates, as the roles do.
  raw    bytes of the same sizes, only the step number read: Zenoh plus scheduling alone.

Two topologies: `split` (one process per local agent, as `hammer up` runs them) and `grouped`
(one process serving all N local agents), to show what fewer runnable processes would buy.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import struct
import time
from dataclasses import asdict, dataclass

import numpy as np
from hammer.benchmarks.transport import loop_messages
from hammer.protocol.codec import encode
from hammer.protocol.schemas import Action, CentralMsg, GlobalState, LocalObs
from hammer.protocol.session import HammerSession, TransportConfig, burst_express

_STEP = struct.Struct("<q")


def _role_transport(connect: list[str]) -> TransportConfig:
    """As `hammer up` connects a role: listen on a free port (peers then link directly, found by
    gossip through the hub) and connect to the hub, here the env host."""
    return TransportConfig(listen=["tcp/127.0.0.1:0"], connect=connect)


class _Orphaned:
    """True once the benchmark process is gone (its quit message will never come): roles exit."""

    def __init__(self) -> None:
        self.parent = os.getppid()

    def __bool__(self) -> bool:
        return os.getppid() != self.parent


def _raw(step: int, size: int) -> bytes:
    return _STEP.pack(step) + bytes(max(size - _STEP.size, 0))


def _raw_step(data: bytes) -> int:
    return _STEP.unpack_from(data)[0]


def _sizes(k: int, n: int, d: int, m: int) -> tuple[dict, dict]:
    """(constructor kwargs, encoded size) per message kind of one vector step."""
    kw, size = {}, {}
    stamp = {"sender": "floor"}
    for label, cls, kwargs, _dims in loop_messages(k, n, d, m):
        if label in ("global_state", "local_obs", "central_msg", "action"):
            kw[label] = kwargs
            size[label] = len(encode(cls(**kwargs), stamp=stamp))
    return kw, size


def _dims(k: int, n: int, d: int, m: int):
    return loop_messages(k, n, d, m)[0][3]


def _burst(s, keys: list[str], batched: bool) -> list:
    """Publishers for a burst of puts, as the roles declare them (batched: `protocol.session.burst_express`,
    a long burst goes out as one Zenoh batch) or all express (the runtime before agent pools)."""
    return [s.publisher(key, express=not batched or burst_express(j, len(keys))) for j, key in enumerate(keys)]


def central_main(run_id: str, connect: list[str], k: int, n: int, d: int, m: int, typed: bool,
                 batched: bool = True) -> None:
    """Echo role standing in for the central agent: a state in, N messages out."""
    kw, size = _sizes(k, n, d, m)
    with HammerSession(run_id, _role_transport(connect), sender="central") as s:
        keys = s.keys
        state = s.subscribe(keys.state(), GlobalState, _dims(k, n, d, m)) if typed else s.subscribe_raw(keys.state())
        pubs = _burst(s, [keys.msg(i) for i in range(n)], batched)
        quit_sub = s.subscribe_raw(keys.bench("quit"))
        s.declare_alive("central")
        orphaned = _Orphaned()
        while quit_sub.get(0) is None and not orphaned:
            got = state.get(timeout=0.2)
            if got is None:
                continue
            step = got.step if typed else _raw_step(got)
            for i, p in enumerate(pubs):
                if typed:
                    p.publish(CentralMsg(**{**kw["central_msg"], "step": step, "agent": i}))
                else:
                    p.put_bytes(_raw(step, size["central_msg"]))


def local_main(run_id: str, connect: list[str], agents: list[int], k: int, n: int, d: int, m: int,
               typed: bool, batched: bool = True) -> None:
    """Echo role standing in for one local agent (or, grouped, several): obs and message in, action out."""
    kw, size = _sizes(k, n, d, m)
    dims = _dims(k, n, d, m)
    from hammer.protocol.access import pool_name

    sender = f"local-{agents[0]}" if len(agents) == 1 else pool_name(agents)  # what its action keys say
    with HammerSession(run_id, _role_transport(connect), sender=sender) as s:
        keys = s.keys
        if typed:
            obs = [s.subscribe(keys.obs(i), LocalObs, dims) for i in agents]
            msg = [s.subscribe(keys.msg(i), CentralMsg, dims) for i in agents]
        else:
            obs = [s.subscribe_raw(keys.obs(i)) for i in agents]
            msg = [s.subscribe_raw(keys.msg(i)) for i in agents]
        pubs = _burst(s, [keys.act(i) for i in agents], batched)
        quit_sub = s.subscribe_raw(keys.bench("quit"))
        for i in agents:
            s.declare_alive(f"local-{i}")
        orphaned = _Orphaned()
        while quit_sub.get(0) is None and not orphaned:
            first = obs[0].get(timeout=0.2)
            if first is None:
                continue
            got = [first] + [o.get(timeout=5.0) for o in obs[1:]]  # a grouped client acts on all at once
            for mq in msg:
                mq.get(timeout=5.0)
            for j, (i, p) in enumerate(zip(agents, pubs, strict=True)):
                step = got[j].step if typed else _raw_step(got[j])
                if typed:
                    p.publish(Action(**{**kw["action"], "step": step, "agent": i}))
                else:
                    p.put_bytes(_raw(step, size["action"]))


@dataclass
class FloorRow:
    topology: str
    mode: str
    processes: int  # step-loop processes, the env host included
    p50_us: float
    p99_us: float
    steps: int


def measure(topology: str, typed: bool, k: int = 32, n: int = 3, d: int = 18, m: int = 4, steps: int = 1000,
            warmup: int = 100, timeout: float = 60.0, per_process: int | None = None,
            batched: bool = True) -> FloorRow:
    """One topology and mode: spawn the echo roles, time `steps` loops from the env host's first
    publish to its last action decoded, stop the roles. `per_process`: local agents per process
    (the agent pools of `hammer up`; default: 1 for split, N for grouped). batched=False: every put
    express, as the runtime sent bursts before agent pools."""
    run_id = f"floor{os.getpid()}{topology}{int(typed)}{per_process or 0}"
    transport = TransportConfig.listener()
    ctx = mp.get_context("spawn")  # never fork a process that may hold a Zenoh session
    size = per_process or (1 if topology == "split" else n)
    groups = [list(range(j, min(n, j + size))) for j in range(0, n, size)]
    procs = [ctx.Process(target=central_main, args=(run_id, transport.listen, k, n, d, m, typed, batched),
                         daemon=True)]
    procs += [ctx.Process(target=local_main, args=(run_id, transport.listen, g, k, n, d, m, typed, batched),
                          daemon=True) for g in groups]
    kw, size = _sizes(k, n, d, m)
    dims = _dims(k, n, d, m)
    times = []
    with HammerSession(run_id, transport, sender="env") as s:
        keys = s.keys
        watch = s.watch_alive()
        for p in procs:
            p.start()
        try:
            want = {"central", *(f"local-{i}" for i in range(n))}
            deadline = time.monotonic() + timeout + n  # N=50: 50 interpreters start on a few cores
            while want:
                ev = watch.get(max(0.0, deadline - time.monotonic()))
                if ev is None:
                    raise TimeoutError(f"loop-floor roles did not come up: {sorted(want)}")
                want.discard(ev.role)
            state_pub = s.publisher(keys.state(), express=True)
            obs_pubs = _burst(s, [keys.obs(i) for i in range(n)], batched)
            acts = ([s.subscribe(keys.act(i), Action, dims) for i in range(n)] if typed
                    else [s.subscribe_raw(keys.act(i)) for i in range(n)])
            time.sleep(0.5)  # let every subscription's route settle before the first step
            for step in range(warmup + steps):
                t0 = time.perf_counter_ns()
                if typed:
                    state_pub.publish(GlobalState(**{**kw["global_state"], "step": step}))
                    for i, p in enumerate(obs_pubs):
                        p.publish(LocalObs(**{**kw["local_obs"], "step": step, "agent": i}))
                else:
                    state_pub.put_bytes(_raw(step, size["global_state"]))
                    for p in obs_pubs:
                        p.put_bytes(_raw(step, size["local_obs"]))
                for a in acts:
                    got = a.get(timeout=timeout)
                    if got is None:
                        raise TimeoutError(f"step {step}: an action never came back")
                    if (got.step if typed else _raw_step(got)) != step:
                        raise RuntimeError(f"step {step}: an action for another step came back")
                if step >= warmup:
                    times.append((time.perf_counter_ns() - t0) / 1e3)
        finally:
            s.put_bytes(keys.bench("quit"), b"q")
            for p in procs:
                p.join(10)
                if p.is_alive():
                    p.terminate()
                    p.join(5)
    t = np.array(times)
    return FloorRow(topology, "typed" if typed else "raw", 1 + len(procs), float(np.percentile(t, 50)),
                    float(np.percentile(t, 99)), len(t))


def run_floor(n_values: tuple[int, ...] = (3, 5), k: int = 32, steps: int = 1000) -> list[tuple[int, FloorRow]]:
    """Every (N, topology, mode), with the cn observation sizes for N (D = 6N, M = 4 / 8)."""
    rows = []
    for n in n_values:
        d, m = 6 * n, 4 if n <= 3 else 8
        for topology in ("split", "grouped"):
            for typed in (True, False):
                rows.append((n, measure(topology, typed, k=k, n=n, d=d, m=m, steps=steps)))
    return rows


def rows_as_dicts(rows: list[tuple[int, FloorRow]]) -> list[dict]:
    return [{"n_agents": n, **asdict(r)} for n, r in rows]
