"""The hand-written fast path of the hot message types agrees with the pydantic reference.

Agreement means: on every input, the fast path accepts exactly when pydantic accepts, and then
builds an equal object (same field values, dtypes, shapes, fields set). Errors need no test of
their own: the fast path never raises, a declined input goes to pydantic, which names the error.
Inputs: a corpus of valid and deliberately broken wire maps and constructor arguments derived from
real control-loop messages, plus hypothesis-generated field replacements.
"""

from __future__ import annotations

import copy
import threading

import msgpack
import numpy as np
import pytest
from hammer.benchmarks.transport import loop_messages
from hammer.protocol import codec
from hammer.protocol.errors import ProtocolError
from hammer.protocol.fast_path import fast_from_wire, fast_state, fast_types
from hammer.protocol.fields import WIRE_DTYPES
from hammer.protocol.samples import sample_messages
from hammer.protocol.schemas import SCHEMA_VERSION, Action, Control, GlobalState, Message
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

STAMP = {"run": "run1", "ts": 5, "seq": 3, "sender": "env"}


def _hot_messages() -> list[Message]:
    """Hot-type messages of several shapes: the K=4 samples and real control-loop sizes."""
    msgs = [m for m in sample_messages() if type(m) in fast_types()]
    for k, n, d, m in ((1, 3, 18, 4), (32, 3, 18, 4), (32, 5, 30, 8)):
        msgs += [cls(**kw) for _, cls, kw, _ in loop_messages(k, n, d, m)]
    rng = np.random.default_rng(1)
    msgs.append(Action(env_idx=np.array([5, 2, 9]), agent=1, action=rng.standard_normal((3, 2)).astype(np.float32)))
    msgs.append(GlobalState(obs=np.zeros((0, 2, 5), np.float32), prev_actions=np.zeros((0, 2, 3), np.float32),
                            active=np.zeros((0, 2), bool)))  # K=0, env_idx defaulted
    return msgs


HOT = _hot_messages()
HOT_WIRE = [msgpack.unpackb(codec.encode(m, stamp=STAMP)) for m in HOT]


def _reference(cls: type[Message], data: dict) -> Message | None:
    try:
        return cls.model_validate(data)
    except ValidationError:
        return None


def assert_equal_models(fast: Message, ref: Message, given: dict | None = None) -> None:
    """Equal as objects: field order and values, array dtype/shape/values/flags, fields set."""
    assert type(fast) is type(ref)
    assert list(fast.__dict__) == list(ref.__dict__)
    for name, x in fast.__dict__.items():
        y = ref.__dict__[name]
        assert type(x) is type(y), name
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
            assert x.flags.writeable == y.flags.writeable and x.flags.c_contiguous == y.flags.c_contiguous, name
            if given is not None and given.get(name) is y:  # pydantic keeps the caller's arrays
                assert x is y, name
        elif isinstance(x, list):
            assert x == y and all(type(a) is type(b) for a, b in zip(x, y)), name
            for a, b in zip(x, y):
                assert a.model_fields_set == b.model_fields_set, name
        else:
            assert x == y, name
    assert fast.model_fields_set == ref.model_fields_set
    assert fast.__pydantic_extra__ == ref.__pydantic_extra__
    assert fast.__pydantic_private__ == ref.__pydantic_private__


def check_wire_agreement(cls: type[Message], data: dict) -> bool:
    """Fast path and pydantic agree on wire map `data`; returns whether it was accepted."""
    ref = _reference(cls, data)
    fast = fast_from_wire(cls, data)
    assert (fast is None) == (ref is None), f"fast {'accepted' if fast else 'declined'} what pydantic " \
                                            f"{'rejected' if ref is None else 'accepted'}"
    if fast is not None:
        assert_equal_models(fast, ref)
    return fast is not None


def check_build_agreement(cls: type[Message], kw: dict) -> bool:
    """Building from constructor arguments: `cls(**kw)` (fast path first) equals pydantic's result,
    or both raise the same errors."""
    try:
        ref = cls.model_validate(kw)
    except ValidationError as e:
        with pytest.raises(ValidationError) as ei:
            cls(**kw)
        assert ei.value.errors(include_url=False) == e.errors(include_url=False)
        assert fast_state(cls, kw) is None
        return False
    assert_equal_models(cls(**kw), ref, given=kw)
    return True


# --- the fast path is really used, and pydantic stays the reference ---------------------------


def test_model_validate_is_pure_pydantic():
    for cls in fast_types():
        assert cls.__pydantic_custom_init__ is False  # model_validate never routes through __init__


@pytest.mark.parametrize("i", range(len(HOT)), ids=lambda i: f"{HOT[i].TYPE}-{i}")
def test_hot_messages_take_the_fast_path_and_equal_pydantic(i):
    msg, wire = HOT[i], HOT_WIRE[i]
    assert fast_from_wire(type(msg), wire) is not None
    assert check_wire_agreement(type(msg), wire)
    data = codec.encode(msg, stamp=STAMP)
    assert_equal_models(codec.decode(data), codec.decode(data, fast=False))
    kw = {name: getattr(msg, name) for name in msg.model_fields_set}
    assert fast_state(type(msg), kw) is not None
    assert check_build_agreement(type(msg), kw)


def test_encode_fast_equals_reference_bytes():
    msgs = HOT + sample_messages()
    # Arrays pydantic accepts but the fast encoder does not inline: big-endian and non-contiguous.
    be = HOT[0].model_copy(update={"obs": HOT[0].obs.astype(">f4")})
    view = HOT[0].model_copy(update={"obs": np.asfortranarray(HOT[0].obs)})
    for m in [*msgs, be, view]:
        assert codec.encode(m, stamp=STAMP) == codec.encode(m, stamp=STAMP, fast=False), m.TYPE
        assert codec.to_wire_dict(m) == codec.to_wire_dict_reference(m)


def test_encode_recovers_after_a_packing_error_and_is_thread_safe():
    bad = Control(command="stop", args={"x": 1})
    bad.args["x"] = object()  # no validate_assignment: only packing can catch it
    with pytest.raises(TypeError):
        codec.encode(bad)
    good = HOT[3]
    assert codec.encode(good, stamp=STAMP) == codec.encode(good, stamp=STAMP, fast=False)
    expected = {i: codec.encode(m, stamp=STAMP, fast=False) for i, m in enumerate(HOT)}
    errors: list[str] = []

    def worker(offset: int) -> None:
        for r in range(200):
            i = (r + offset) % len(HOT)
            if codec.encode(HOT[i], stamp=STAMP) != expected[i]:
                errors.append(f"message {i}")

    threads = [threading.Thread(target=worker, args=(o,)) for o in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


# --- corpus of broken wire maps ------------------------------------------------------------------

_BAD_SCALARS = [None, True, False, -1, 0, 1, 7, 2**64 - 1, 1.5, float("nan"), float("inf"), "", "x", b"x",
                [], [1], {}, {"a": 1}]
_RUNS = ["", "a", "run-1.x_y", "a\n", "\na", "a" * 64, "a" * 65, "-a", ".a", "ä", "a/b", "a b", "a*"]


def _array_variants(arr: dict, k: int) -> list:
    """Broken (and a few valid) versions of one wire array map."""
    name, shape, data = arr["dtype"], arr["shape"], arr["data"]
    dt = WIRE_DTYPES[name]
    out: list = [{**arr, "extra": 1}, {"dtype": name, "shape": shape}, {**arr, "dtype": "float16"},
                 {**arr, "dtype": 3}, {**arr, "dtype": None}, {**arr, "shape": [*shape, 1]},
                 {**arr, "shape": shape[:-1]}, {**arr, "shape": [-1, *shape[1:]]}, {**arr, "shape": tuple(shape)},
                 {**arr, "shape": [float(s) for s in shape]}, {**arr, "shape": [True] * len(shape)},
                 {**arr, "shape": [1] * 9}, {**arr, "shape": "x"}, {**arr, "data": data[:-1]},
                 {**arr, "data": data + b"\x00"}, {**arr, "data": data.decode("latin-1")},
                 {**arr, "data": bytearray(data)}, {**arr, "data": None}]
    for other in WIRE_DTYPES:
        if other != name:
            n = len(data) // dt.itemsize
            out.append({"dtype": other, "shape": shape, "data": np.zeros(n, WIRE_DTYPES[other]).tobytes()})
            out.append({**arr, "dtype": other})
    if shape and shape[0] == k and k > 0:  # wrong K with a consistent byte count
        row = len(data) // k
        out.append({**arr, "shape": [k + 1, *shape[1:]], "data": data + data[:row]})
        out.append({**arr, "shape": [k - 1, *shape[1:]], "data": data[row:]})
    for axis in range(1, len(shape)):  # one inner dim grown, byte count consistent
        grown = [*shape[:axis], shape[axis] + 1, *shape[axis + 1:]]
        out.append({"dtype": name, "shape": grown, "data": np.zeros(grown, dt).tobytes()})
    if len(shape) >= 2:  # same bytes, dims swapped / merged
        out.append({**arr, "shape": [shape[1], shape[0], *shape[2:]]})
        prod = 1
        for s in shape:
            prod *= s
        out.append({**arr, "shape": [prod]})
    n = len(data) // dt.itemsize
    if name in ("float32", "float64") and n:
        a = np.frombuffer(data, dt).copy()
        for v in (np.nan, np.inf, -np.inf, 1.0000001, -1.0000001, 1.0, -1.0, -0.0, 3.0e38):
            b = a.copy()
            b[n // 2] = v
            out.append({**arr, "data": b.tobytes()})
        out.append({**arr, "data": np.clip(a, -1, 1).tobytes()})
    if name == "bool" and n:
        for byte in (b"\x02", b"\xff", b"\x01"):
            out.append({**arr, "data": data[:-1] + byte})
    if name == "int64" and n:
        a = np.frombuffer(data, dt).copy()
        for v in (-1, 10**6, 2**63 - 1):
            b = a.copy()
            b[-1] = v
            out.append({**arr, "data": b.tobytes()})
        if n > 1:
            b = a.copy()
            b[0] = b[1]  # duplicate
            out.append({**arr, "data": b.tobytes()})
            out.append({**arr, "data": a[::-1].copy().tobytes()})  # valid, not 0..K-1
    return out


def _wire_corpus(wire: dict) -> list[dict]:
    k = wire["env_idx"]["shape"][0]
    out = [{**wire, "extra": 1}, {**wire, b"step": 1}]
    for key, value in wire.items():
        out.append({n: v for n, v in wire.items() if n != key})  # missing field (or defaulted)
        out += [{**wire, key: bad} for bad in _BAD_SCALARS]
        if isinstance(value, dict):
            out += [{**wire, key: variant} for variant in _array_variants(value, k)]
    out += [{**wire, "run": r} for r in _RUNS]
    out += [{**wire, "sender": s} for s in ("x" * 128, "x" * 129, "é" * 128, "é" * 129)]
    out += [{**wire, "type": t} for t in ("local_obs", "global_state", "central_msg", "action", "step_result")]  # step_result: a retired tag
    out += [{**wire, "v": v} for v in (0, SCHEMA_VERSION - 1, SCHEMA_VERSION + 1, float(SCHEMA_VERSION))]
    return out


CORPUS = [(type(m), d) for m, w in zip(HOT, HOT_WIRE) for d in _wire_corpus(w)]


def test_wire_corpus_agrees():
    accepted = sum(check_wire_agreement(cls, d) for cls, d in CORPUS)
    # The corpus must exercise both sides.
    assert 0.02 * len(CORPUS) < accepted < 0.5 * len(CORPUS), (accepted, len(CORPUS))


def test_decode_agrees_on_broken_payloads():
    """At the codec level: same message, or the same error class, field and text."""
    for cls, d in CORPUS[::7]:
        try:
            data = msgpack.packb(d, use_bin_type=True)
        except (TypeError, ValueError):
            continue  # not representable in msgpack (e.g. a tuple key): cannot come off the wire
        outcomes = []
        for fast in (True, False):
            try:
                outcomes.append(codec.decode(data, cls, run="run1", fast=fast))
            except ProtocolError as e:
                outcomes.append(e)
        a, b = outcomes
        if isinstance(b, ProtocolError):
            assert type(a) is type(b) and a.field == b.field and str(a) == str(b)
        else:
            assert_equal_models(a, b)


# --- constructor arguments (the sender side) -----------------------------------------------------


def _kw_corpus(msg: Message) -> list[dict]:
    kw = {name: getattr(msg, name) for name in msg.model_fields_set}
    out = [kw, {**kw, "extra": 1}]
    for key, value in kw.items():
        out.append({n: v for n, v in kw.items() if n != key})
        out += [{**kw, key: bad} for bad in (None, True, -1, 1.5, "x", np.int64(1), [1])]
        if isinstance(value, np.ndarray):
            out += [{**kw, key: v} for v in (
                value.astype(value.dtype.newbyteorder(">")), value.astype(np.float64), value.astype(np.int32),
                value.astype(np.uint8), np.asfortranarray(value), value.tolist(), value[..., None],
                value.reshape(-1), np.ma.masked_array(value), codec.to_wire_dict(msg)[key])]
            if value.size and value.dtype.kind == "f":
                for v in (np.nan, np.inf, 1.5):
                    b = value.copy()
                    b.flat[0] = v
                    out.append({**kw, key: b})
            if value.ndim and value.shape[0] > 1:
                out.append({**kw, key: value[::2]})  # K disagrees
            for axis in range(1, value.ndim):  # an inner dim disagrees
                pad = [(0, 1 if a == axis else 0) for a in range(value.ndim)]
                out.append({**kw, key: np.pad(value, pad)})
    return out


KW_CORPUS = [(type(m), kw) for m in HOT for kw in _kw_corpus(m)]


def test_constructor_corpus_agrees():
    accepted = sum(check_build_agreement(cls, kw) for cls, kw in KW_CORPUS)
    assert 0.05 * len(KW_CORPUS) < accepted < 0.6 * len(KW_CORPUS), (accepted, len(KW_CORPUS))


# --- fuzzing -------------------------------------------------------------------------------------

_FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**64 - 1), st.floats(),
                     st.text(max_size=8), st.binary(max_size=16))
_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                                         max_size=4), max_leaves=12)


@st.composite
def _arrays(draw) -> dict:
    """Wire array maps: any whitelisted dtype, small shapes, data mostly of the right length."""
    name = draw(st.sampled_from([*WIRE_DTYPES, "float16"]))
    shape = draw(st.lists(st.integers(0, 5), max_size=4))
    itemsize = WIRE_DTYPES[name].itemsize if name in WIRE_DTYPES else 2
    n = int(np.prod(shape)) if shape else 1
    size = draw(st.sampled_from([n * itemsize, max(0, n * itemsize - 1), n * itemsize + 1]))
    data = draw(st.binary(min_size=size, max_size=size))
    if name == "bool" and draw(st.booleans()):
        data = bytes(b & 1 for b in data)
    if name == "float32" and draw(st.booleans()):
        floats = draw(st.lists(st.floats(-1.5, 1.5, width=32), min_size=n, max_size=n))
        data = np.array(floats, np.float32).tobytes()
    return {"dtype": name, "shape": shape, "data": data}


@_FUZZ
@given(st.sampled_from(range(len(HOT))), st.data())
def test_fuzz_field_replacement_agrees(i, draw):
    wire = copy.copy(HOT_WIRE[i])
    for key in draw.draw(st.lists(st.sampled_from(sorted(wire)), min_size=1, max_size=3)):
        wire[key] = draw.draw(st.one_of(_values, _arrays()))
    check_wire_agreement(type(HOT[i]), wire)


@_FUZZ
@given(st.sampled_from(range(len(HOT))), st.data())
def test_fuzz_array_data_agrees(i, draw):
    """Keep dtypes and shapes, randomise the bytes of one array (NaN, inf, out of range, bad bools)."""
    wire = copy.copy(HOT_WIRE[i])
    arrays = sorted(k for k, v in wire.items() if isinstance(v, dict))
    key = draw.draw(st.sampled_from(arrays))
    arr = wire[key]
    wire[key] = {**arr, "data": draw.draw(st.binary(min_size=len(arr["data"]), max_size=len(arr["data"])))}
    check_wire_agreement(type(HOT[i]), wire)
