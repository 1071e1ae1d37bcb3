"""HammerSession over real Zenoh on 127.0.0.1 (explicit endpoints, multicast scouting off)."""

from __future__ import annotations

import multiprocessing as mp
import pickle
import time

import msgpack
import numpy as np
import pytest
from hammer.benchmarks.transport import echo_main
from hammer.protocol.codec import encode
from hammer.protocol.dims import Dims
from hammer.protocol.fields import DTYPE_CODES
from hammer.protocol.samples import sample_messages
from hammer.protocol.schemas import SCHEMA_VERSION, Control, GlobalState, LocalObs, Message, fields_of
from hammer.protocol.session import HammerSession, TransportConfig

HEADER_STAMPS = {"sender"}


def _same_payload(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    for name in fields_of(type(a)):
        if name in HEADER_STAMPS:
            continue
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y), name
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), name
            for k in x:
                assert np.array_equal(x[k], y[k]) if isinstance(x[k], np.ndarray) else x[k] == y[k], f"{name}.{k}"
        else:
            assert x == y, name


@pytest.fixture
def pair():
    """Two sessions of run 'r1' in this process: `a` listens, `b` connects to it."""
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    with HammerSession("r1", t, sender="env") as a, \
            HammerSession("r1", TransportConfig.connector(port), sender="local-0") as b:
        yield a, b


def _settle() -> None:
    time.sleep(0.25)  # let subscriber declarations reach the publisher's side


def test_every_message_type_through_zenoh(pair):
    a, b = pair
    sub = b.subscribe(b.keys.bench("all"))
    _settle()
    sent = sample_messages()
    seqs = [a.publish(a.keys.bench("all"), m) for m in sent]
    got = [sub.get(5.0) for _ in sent]
    assert seqs == list(range(len(sent)))
    for m, g in zip(sent, got):
        assert g is not None
        _same_payload(m, g)
        assert g.sender == "env"  # a key that implies no sender: the session's name is sent
    assert sub.stats.delivered == len(sent) and sub.stats.rejected_total == 0


def test_bounded_queue_counts_overflow_and_keeps_the_oldest(pair):
    a, b = pair
    typed = b.subscribe(b.keys.bench("bounded"), Control, maxsize=3)
    raw = b.subscribe_raw(b.keys.bench("bounded"), maxsize=5)
    free = b.subscribe_raw(b.keys.bench("bounded"))
    _settle()
    targets = [f"role-{i}" for i in range(10)]
    for t in targets:
        a.publish(a.keys.bench("bounded"), Control(command="stop", target=t))
    deadline = time.monotonic() + 5.0
    while free.pending() < 10 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert free.pending() == 10 and free.stats.overflow == 0
    assert typed.pending() == 3 and typed.stats.overflow == 7
    assert raw.pending() == 5 and raw.stats.overflow == 5
    assert [m.target for m in typed.drain()] == targets[:3] and typed.get(0) is None
    assert len([raw.get(0) for _ in range(5)]) == 5 and raw.get(0) is None and raw.get(0.05) is None
    a.publish(a.keys.bench("bounded"), Control(command="stop"))  # room again once drained
    assert typed.get(5.0) is not None and typed.stats.overflow == 7


def test_malformed_input_is_counted_and_never_stops_delivery(pair):
    a, b = pair
    key = a.keys.state()
    sub = b.subscribe(b.keys.state(), GlobalState, Dims(n_agents=3, obs_dim=18), max_bytes=64 << 10)
    _settle()
    good = sample_messages()[1]
    valid = encode(good)
    names = ("type", *fields_of(GlobalState))
    full = [*msgpack.unpackb(valid), 0, [0, [4, 3], b"\x01" * 12]][:len(names)]  # with policy_version, active
    d = dict(zip(names, full))
    parts = {"dtype": 0, "shape": 1, "data": 2}

    def variant(**kv) -> bytes:
        x = msgpack.unpackb(msgpack.packb(full))
        for k, v in kv.items():
            if "__" in k:
                f, g = k.split("__")
                x[names.index(f)][parts[g]] = v
            else:
                x[names.index(k)] = v
        return msgpack.packb(x)

    bad = {
        "decode": [b"\x93\x01", valid[:-3], bytes(np.random.default_rng(0).integers(0, 256, 200, dtype=np.uint8))],
        "version": [variant(v=SCHEMA_VERSION + 1)],
        "type": [encode(sample_messages()[0])],  # a LocalObs where GlobalState is expected
        "dtype": [variant(obs__dtype=DTYPE_CODES["float64"], obs__data=d["obs"][2] * 2)],
        "shape": [variant(obs__shape=[4, 3, 9, 2]), variant(active__shape=[2, 6])],
        "nonfinite": [variant(obs__data=np.full((4, 3, 18), np.nan, np.float32).tobytes()),
                      variant(obs__data=np.full((4, 3, 18), -np.inf, np.float32).tobytes())],
        "size": [valid + bytes(70 << 10)],
        "field": [variant(step=-3)],
    }
    n_valid = 0
    for payloads in bad.values():
        for p in payloads:
            a.put_bytes(key, p)
            a.publish(key, good)  # the next valid message must still come through
            n_valid += 1
    got = []
    while len(got) < n_valid:
        m = sub.get(5.0)
        assert m is not None, f"only {len(got)} of {n_valid} valid messages delivered"
        got.append(m)
    assert all(isinstance(m, GlobalState) for m in got)
    # Dims mismatch is a rejection too, not a crash.
    other_dims = b.subscribe(b.keys.state(), GlobalState, Dims(obs_dim=30))
    _settle()
    a.publish(key, good)
    assert other_dims.get(0.5) is None and other_dims.stats.rejected["shape"] == 1
    assert sub.get(2.0) is not None
    assert dict(sub.stats.rejected) == {r: len(p) for r, p in bad.items()}
    assert sub.stats.delivered == n_valid + 1


def test_two_runs_on_one_host_do_not_cross_talk():
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    # Both runs are connected to the same listener; only key prefixes separate them.
    with HammerSession("runA", t, sender="env") as hub, \
            HammerSession("runB", TransportConfig.connector(port), sender="env") as other, \
         HammerSession("runA", TransportConfig.connector(port)) as same:
        sub_a = same.subscribe(same.keys.obs("*"), LocalObs)
        sub_b = other.subscribe(other.keys.obs("*"), LocalObs)
        _settle()
        lo = sample_messages()[0]
        for _ in range(5):
            hub.publish(hub.keys.obs(1), lo)
            other.publish(other.keys.obs(1), lo)
        got_a = [sub_a.get(2.0) for _ in range(5)]
        got_b = [sub_b.get(2.0) for _ in range(5)]
        assert all(m is not None and m.sender == hub.sender for m in got_a)
        assert all(m is not None for m in got_b)
        time.sleep(0.2)
        assert sub_a.get(0) is None and sub_b.get(0) is None
        assert sub_a.stats.rejected_total == 0 and sub_b.stats.rejected_total == 0
        with pytest.raises(ValueError, match="not under this run"):
            hub.subscribe("hammer/runB/**")


def test_liveliness_tokens_appear_and_disappear(pair):
    a, b = pair
    watch = b.watch_alive()
    token = a.declare_alive("env")
    ev = watch.get(3.0)
    assert ev is not None and (ev.role, ev.alive) == ("env", True)
    assert b.alive_roles(1.0) == {"env"}
    token.undeclare()
    ev = watch.get(3.0)
    assert ev is not None and (ev.role, ev.alive) == ("env", False)
    assert b.alive_roles(1.0) == set()


def test_sessions_refuse_pickling_and_bad_config():
    s = HammerSession("r1")
    with pytest.raises(TypeError, match="open a session there"):
        pickle.dumps(s)
    with pytest.raises(RuntimeError, match="not open"):
        s.publisher(s.keys.state())
    with pytest.raises(ValueError, match="tcp/127.0.0.1:7447"):
        TransportConfig(listen=["127.0.0.1:7447"])
    with pytest.raises(ValueError, match="connect endpoint"):
        TransportConfig(mode="client")
    with pytest.raises(ValueError, match="run id"):
        HammerSession("bad run")


def test_round_trip_across_two_spawned_processes():
    """Every message type goes to an echo peer in a spawned process and back, decoded both ways."""
    t = TransportConfig.listener()
    ctx = mp.get_context("spawn")
    echo = ctx.Process(target=echo_main, args=("x2proc", t.listen, 60.0), daemon=True)
    with HammerSession("x2proc", t, sender="main") as s:
        pong = s.subscribe(s.keys.bench("pong"))
        watch = s.watch_alive()
        echo.start()
        try:
            ev = watch.get(30.0)
            assert ev is not None and ev.role == "echo" and ev.alive
            for m in sample_messages():
                s.publish(s.keys.bench("ping"), m)
                back = pong.get(10.0)
                assert back is not None, f"no echo of {m.TYPE}"
                _same_payload(m, back)
                assert back.sender == "echo"
            assert pong.stats.rejected_total == 0
            s.put_bytes(s.keys.bench("quit"), b"q")
            echo.join(15)
            assert echo.exitcode == 0
            # The echo's liveliness token went away with its session.
            ev = watch.get(3.0)
            assert ev is not None and ev.role == "echo" and not ev.alive
        finally:
            if echo.is_alive():
                echo.terminate()


def test_a_session_opted_into_float16_halves_observations_and_messages_only(pair):
    """RuntimeSettings.wire_float16 (serving only): the publishers of such a session send float32
    observations and messages as float16, read back as float32; everything else goes as it is."""
    from hammer.runtime.settings import RuntimeSettings

    a, b = pair
    a.wire_float16 = True
    sub = b.subscribe(b.keys.bench("half"))
    pub = a.publisher(a.keys.bench("half"))
    _settle()
    sent = sample_messages()
    for m in sent:
        pub.publish(m)
    for m in sent:
        got = sub.get(5.0)
        assert got is not None and type(got) is type(m)
        for name, spec in type(m).ARRAYS.items():
            x, y = getattr(m, name), getattr(got, name)
            if x is None or x.dtype != np.float32 or ("float16", "float32") not in spec.wire:
                assert x is None or (x.dtype == y.dtype and np.array_equal(x, y)), (m.TYPE, name)
            else:
                assert y.dtype == np.float32 and np.array_equal(y, x.astype(np.float16).astype(np.float32))
        if m.TYPE in ("experience", "weights"):
            _same_payload(m, got)
    with pytest.raises(ValueError, match="wire_float16"):
        RuntimeSettings(run_id="r", wire_float16=True)
    assert RuntimeSettings(run_id="r", mode="eval", policy_dir="p", wire_float16=True).wire_float16


def test_close_returns_only_once_zenoh_has_let_go_of_every_callback(pair):
    """A Zenoh thread calling a Python callback while the interpreter finalizes aborts the process
    ("FATAL: exception not rethrown", a robot's exit code -6): close() waits until Zenoh has released
    every callback the session gave it, a query still waiting for its answer included."""
    a, b = pair
    a.answer(a.keys.bench("quiet"), lambda: None)  # answers nothing: the query stays open until closed
    sub = b.subscribe(b.keys.bench("quiet"))
    b.watch_alive()
    _settle()
    b.fetch(b.keys.bench("quiet"), sub, timeout=30.0)
    held = list(b._released)
    assert len(held) == 3 and not any(e.is_set() for e in held)  # subscriber, watch and the open query
    t0 = time.monotonic()
    b.close()
    assert time.monotonic() - t0 < 2.0 and all(e.is_set() for e in held)
