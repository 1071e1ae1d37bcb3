"""`hammer bench transport` and `hammer bench codec`.

`hammer bench codec`: build / encode / decode+validate time per message of the control loop
(K=32 env copies, cn N=3 and N=5 sizes), and a bare msgpack.unpackb of the same bytes.

`hammer bench transport`: what the typed protocol costs over raw Zenoh bytes of the same size.

The echo peer runs in a separate spawned process (as every hammer role does), connected over
tcp/127.0.0.1. For each typical payload we measure, in the same run:
  - codec: encode and decode+validate time in-process;
  - round trip: publish -> echo (decode, validate, re-encode, publish back) -> receive and decode,
    versus raw bytes of the same size echoed back untouched;
  - throughput: a burst of messages the echo decodes and counts, versus raw bytes it only counts.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import threading
import time
import timeit
from dataclasses import asdict, dataclass

import msgpack
import numpy as np
from hammer.protocol.codec import decode, encode
from hammer.protocol.dims import Dims
from hammer.protocol.schemas import Action, CentralMsg, Control, GlobalState, LocalObs, Message
from hammer.protocol.session import HammerSession, TransportConfig, loopback_endpoint

_STOP = "stop"


def echo_main(run_id: str, connect: list[str], max_seconds: float = 300.0) -> None:
    """The echo peer (runs in a spawned process). Keys under hammer/<run>/bench/:
    ping -> pong (typed, any message type), rawping -> rawpong (bytes as they came),
    flood / rawflood counted until an end marker (Control "stop" / empty bytes), then a msgpack
    {"count", "rejected"} on ack. A message on `quit` (or max_seconds) ends the process."""
    with HammerSession(run_id, TransportConfig(connect=connect), sender="echo") as s:
        k = s.keys
        ping, rawping = s.subscribe(k.bench("ping")), s.subscribe_raw(k.bench("rawping"))
        flood, rawflood = s.subscribe(k.bench("flood")), s.subscribe_raw(k.bench("rawflood"))
        quit_sub = s.subscribe_raw(k.bench("quit"))
        pong, rawpong, ack = (s.publisher(k.bench(n)) for n in ("pong", "rawpong", "ack"))
        done = threading.Event()

        def typed_echo() -> None:
            while not done.is_set():
                msg = ping.get(0.2)
                if msg is not None:
                    pong.publish(msg)

        def raw_echo() -> None:
            while not done.is_set():
                data = rawping.get(0.2)
                if data is not None:
                    rawpong.put_bytes(data)

        def typed_count() -> None:
            n = 0
            while not done.is_set():
                msg = flood.get(0.2)
                if isinstance(msg, Control) and msg.command == _STOP:
                    ack.put_bytes(msgpack.packb({"count": n, "rejected": flood.stats.rejected_total}))
                    n = 0
                elif msg is not None:
                    n += 1

        def raw_count() -> None:
            n = 0
            while not done.is_set():
                data = rawflood.get(0.2)
                if data == b"":
                    ack.put_bytes(msgpack.packb({"count": n, "rejected": 0}))
                    n = 0
                elif data is not None:
                    n += 1

        threads = [threading.Thread(target=f, daemon=True) for f in (typed_echo, raw_echo, typed_count, raw_count)]
        for t in threads:
            t.start()
        s.declare_alive("echo")
        quit_sub.get(max_seconds)
        done.set()
        for t in threads:
            t.join(1.0)


def payloads() -> list[tuple[str, Message]]:
    """Typical messages: one local obs (cn N=3, D=18); global states of cn N=3 (D=18) and N=5
    (D=30, simple_spread obs = 4 + 2N landmarks + 2(N-1) others + 2(N-1) comm); a batch of 64."""
    rng = np.random.default_rng(0)

    def gs(k: int, n: int, d: int) -> GlobalState:
        return GlobalState(step=1, env_idx=np.arange(k), obs=rng.standard_normal((k, n, d)).astype(np.float32),
                           prev_actions=np.zeros((k, n, 5), np.float32), active=np.ones((k, n), bool))

    lo = LocalObs(step=1, env_idx=np.arange(1), agent=0, obs=rng.standard_normal((1, 18)).astype(np.float32),
                  active=np.ones(1, bool))
    return [
        ("local_obs K=1 D=18", lo),
        ("global_state K=1 N=3 D=18", gs(1, 3, 18)),
        ("global_state K=1 N=5 D=30", gs(1, 5, 30)),
        ("global_state K=64 N=3 D=18", gs(64, 3, 18)),
    ]


@dataclass
class BenchRow:
    payload: str
    bytes: int
    encode_us: float
    decode_us: float
    typed_msgs_per_s: float
    raw_msgs_per_s: float
    typed_rtt_p50_us: float
    typed_rtt_p99_us: float
    raw_rtt_p50_us: float
    raw_rtt_p99_us: float

    @property
    def rate_ratio(self) -> float:
        return self.typed_msgs_per_s / self.raw_msgs_per_s

    @property
    def rtt_ratio(self) -> float:
        return self.typed_rtt_p50_us / self.raw_rtt_p50_us


def _codec_us(msg: Message) -> tuple[float, float]:
    stamped = encode(msg, stamp={"sender": "bench"})
    n = 2000
    enc = min(timeit.repeat(lambda: encode(msg, stamp={"sender": "bench"}), number=n, repeat=3)) / n * 1e6
    dec = min(timeit.repeat(lambda: decode(stamped, type(msg)), number=n, repeat=3)) / n * 1e6
    return enc, dec


def run_bench(rounds: int = 1000, flood: int = 5000, timeout: float = 60.0) -> list[BenchRow]:
    """Spawn the echo peer, measure every payload, stop the echo; returns one row per payload."""
    run_id = f"bench{os.getpid()}"
    transport = TransportConfig.listener()
    endpoint = transport.listen[0]
    ctx = mp.get_context("spawn")  # never fork a process that may hold a Zenoh session
    echo = ctx.Process(target=echo_main, args=(run_id, [endpoint], timeout * 10), daemon=True)
    rows = []
    with HammerSession(run_id, transport, sender="bench") as s:
        k = s.keys
        pong, rawpong = s.subscribe(k.bench("pong")), s.subscribe_raw(k.bench("rawpong"))
        ack = s.subscribe_raw(k.bench("ack"))
        watch = s.watch_alive()
        echo.start()
        try:
            deadline = time.monotonic() + timeout
            while (ev := watch.get(max(0.0, deadline - time.monotonic()))) is None or ev.role != "echo":
                if time.monotonic() > deadline:
                    raise TimeoutError("echo process did not come up")
            ping, rawping = s.publisher(k.bench("ping")), s.publisher(k.bench("rawping"))
            flood_pub, rawflood_pub = s.publisher(k.bench("flood")), s.publisher(k.bench("rawflood"))
            for name, msg in payloads():
                size = len(encode(msg, stamp={"sender": "bench"}))
                raw = os.urandom(size)
                enc_us, dec_us = _codec_us(msg)

                def rtt_typed(msg: Message = msg) -> float:
                    t0 = time.perf_counter_ns()
                    ping.publish(msg)
                    if pong.get(timeout) is None:
                        raise TimeoutError("typed echo timed out")
                    return (time.perf_counter_ns() - t0) / 1e3

                def rtt_raw(raw: bytes = raw) -> float:
                    t0 = time.perf_counter_ns()
                    rawping.put_bytes(raw)
                    if rawpong.get(timeout) is None:
                        raise TimeoutError("raw echo timed out")
                    return (time.perf_counter_ns() - t0) / 1e3

                for _ in range(50):  # warm up routes and caches
                    rtt_typed()
                    rtt_raw()
                typed_rtt = np.array([rtt_typed() for _ in range(rounds)])
                raw_rtt = np.array([rtt_raw() for _ in range(rounds)])

                def rate(send, end) -> float:
                    t0 = time.perf_counter()
                    for _ in range(flood):
                        send()
                    end()
                    reply = ack.get(timeout)
                    if reply is None:
                        raise TimeoutError("flood ack timed out")
                    got = msgpack.unpackb(reply)
                    if got["count"] != flood:
                        raise RuntimeError(f"echo counted {got['count']} of {flood} messages")
                    return flood / (time.perf_counter() - t0)

                stop = Control(command=_STOP)
                typed_rate = rate(lambda m=msg: flood_pub.publish(m), lambda s=stop: flood_pub.publish(s))
                raw_rate = rate(lambda r=raw: rawflood_pub.put_bytes(r), lambda: rawflood_pub.put_bytes(b""))
                rows.append(BenchRow(
                    name, size, enc_us, dec_us, typed_rate, raw_rate,
                    float(np.percentile(typed_rtt, 50)), float(np.percentile(typed_rtt, 99)),
                    float(np.percentile(raw_rtt, 50)), float(np.percentile(raw_rtt, 99)),
                ))
        finally:
            s.put_bytes(k.bench("quit"), b"q")
            echo.join(10)
            if echo.is_alive():
                echo.terminate()
                echo.join(5)
    return rows


def bench_meta(rounds: int, flood: int) -> dict:
    from importlib.metadata import version

    return {
        "python": platform.python_version(),
        "zenoh": version("eclipse-zenoh"),
        "cpus": os.cpu_count(),
        "rounds": rounds,
        "flood": flood,
        "transport": f"peer <-> peer over {loopback_endpoint(0).rsplit(':', 1)[0]}, spawned echo process",
    }


def rows_as_dicts(rows: list[BenchRow]) -> list[dict]:
    return [dict(asdict(r), rate_ratio=r.rate_ratio, rtt_ratio=r.rtt_ratio) for r in rows]


# --------------------------------------------------------------------------------------------
# hammer bench codec
# --------------------------------------------------------------------------------------------


@dataclass
class CodecRow:
    """Microseconds per message: build (validate), encode, decode (validate, + declared dims); and
    `unpackb_us`, a bare untyped `msgpack.unpackb` of the same bytes (no checks at all), the floor
    a typed decode is measured against."""

    payload: str
    bytes: int
    build_us: float
    encode_us: float
    decode_us: float
    unpackb_us: float

    @property
    def total_us(self) -> float:
        return self.build_us + self.encode_us + self.decode_us


def loop_messages(k: int = 32, n: int = 3, d: int = 18, m: int = 4, a: int = 5,
                  seed: int = 0) -> list[tuple[str, type[Message], dict, Dims]]:
    """The messages of one vector step of the hammer control loop, as (label, type, constructor
    keyword arguments, receiver Dims): what env host, central agent and local agents build and decode."""
    rng = np.random.default_rng(seed)
    idx = np.arange(k, dtype=np.int64)
    obs = rng.standard_normal((k, n, d)).astype(np.float32)
    active = np.ones((k, n), bool)
    dims = Dims(num_envs=k, n_agents=n, obs_dim=d, msg_dim=m, action_dim=a, discrete=True)
    msg = np.tanh(rng.standard_normal((k, m))).astype(np.float32)
    head = {"step": 7, "env_idx": idx, "policy_version": 3}
    return [
        ("global_state", GlobalState, {**head, "obs": obs, "prev_actions": np.zeros((k, n, a), np.float32),
                                       "active": active}, dims),
        ("local_obs", LocalObs, {**head, "agent": 1, "obs": np.ascontiguousarray(obs[:, 1]),
                                 "active": active[:, 1]}, dims),
        ("central_msg", CentralMsg, {**head, "agent": 1, "msg": msg}, dims),
        ("action", Action, {**head, "agent": 1, "action": rng.integers(0, a, k),
                            "fallback": np.zeros(k, bool), "msg": msg}, dims),
    ]


def _best_us(fns: dict[str, object], number: int, repeat: int) -> dict[str, float]:
    """Min time per call of each function, their repeats interleaved so load drifts hit all alike."""
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeat):
        for name, fn in fns.items():
            best[name] = min(best[name], timeit.timeit(fn, number=number) / number * 1e6)
    return best


def _cold_us(fns: dict[str, object], calls: int) -> dict[str, float]:
    """Median CPU time of single calls made cache-cold, as in a role that just woke up: before each
    call, stream 32 MiB through the caches and sleep 1 ms (other processes get the core)."""
    evict = np.ones(32 << 20, np.uint8)
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(calls):
        for name, fn in fns.items():
            evict.sum()
            time.sleep(0.001)
            t0 = time.thread_time()
            fn()
            times[name].append(time.thread_time() - t0)
    return {name: float(np.median(t)) * 1e6 for name, t in times.items()}


def codec_bench(k: int = 32, sizes: tuple[tuple[int, int, int], ...] = ((3, 18, 4), (5, 30, 8)),
                number: int = 500, repeat: int = 7, cold: bool = False) -> list[CodecRow]:
    """Build, encode and decode of each message of the control loop, for each (N, D, M), and a bare
    msgpack.unpackb of the same bytes. Hot (default): best of `repeat` loops of `number` calls.
    cold: median CPU time of `number` single calls, each after evicting the caches (what a woken-up
    role pays; several times more)."""
    import msgpack

    stamp = {"sender": "bench"}
    rows = []
    for n, d, m in sizes:
        for label, cls, kw, dims in loop_messages(k, n, d, m):
            msg = cls(**kw)
            data = encode(msg, stamp=stamp)
            fns = {
                "build": lambda cls=cls, kw=kw: cls(**kw),
                "encode": lambda msg=msg: encode(msg, stamp=stamp),
                "decode": lambda c=cls, b=data, dm=dims: decode(b, c, dm),
                "unpackb": lambda b=data: msgpack.unpackb(b),
            }
            t = _cold_us(fns, number) if cold else _best_us(fns, number, repeat)
            rows.append(CodecRow(f"{label} K={k} N={n} D={d} M={m}", len(data), t["build"], t["encode"],
                                 t["decode"], t["unpackb"]))
    return rows


def codec_rows_as_dicts(rows: list[CodecRow]) -> list[dict]:
    return [dict(asdict(r), total_us=r.total_us) for r in rows]


def role_costs(rows: list[CodecRow], k: int, n: int) -> dict[str, float]:
    """Codec microseconds per vector step and role from the rows of one N: the env host builds and
    encodes the state and N local obs and decodes N actions; the central agent decodes the state and
    builds and encodes N messages; a local agent decodes its obs and message and builds and encodes
    its action."""
    by = {r.payload.split(f" K={k} ")[0]: r for r in rows if f" K={k} N={n} " in r.payload}

    def send(name: str) -> float:
        return by[name].build_us + by[name].encode_us

    def recv(name: str) -> float:
        return by[name].decode_us

    return {
        "env host": send("global_state") + n * send("local_obs") + n * recv("action"),
        "central agent": recv("global_state") + n * send("central_msg"),
        "local agent": recv("local_obs") + recv("central_msg") + send("action"),
    }
