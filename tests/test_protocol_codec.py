"""The msgpack codec and schemas: round trips, every rejection reason, the compact wire, fuzzing,
JSON Schema."""

from __future__ import annotations

import json
import re
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hammer.protocol import codec
from hammer.protocol.dims import Dims
from hammer.protocol.errors import (
    ChecksumError,
    DecodeError,
    DTypeError,
    FieldError,
    NonFiniteError,
    ProtocolError,
    RangeError,
    ShapeError,
    SizeError,
    TypeTagError,
    VersionError,
)
from hammer.protocol.fields import DTYPE_CODES
from hammer.protocol.keys import Keys, validate_run_id
from hammer.protocol.samples import assert_same, sample_messages
from hammer.protocol.schemas import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Action,
    CentralMsg,
    Control,
    GlobalState,
    LocalObs,
    Weights,
    fields_of,
    json_schemas,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from msgspec.structs import replace

MSGS = sample_messages()
GOOD = codec.encode(MSGS[1])  # a GlobalState K=4 N=3 D=18
NAMES = ("type", *fields_of(GlobalState))
PARTS = {"dtype": 0, "shape": 1, "data": 2}
F32 = DTYPE_CODES["float32"]


def _tamper(data: bytes, **changes) -> bytes:
    """`data` with fields changed by name (`obs__shape`: a part of an array), dropped (`...`) or
    added (`extra`); a GlobalState gets its trailing policy_version and active filled in first."""
    x = msgpack.unpackb(data)
    names = ("type", *fields_of(MESSAGE_TYPES_BY_TAG[x[0]]))
    if names == NAMES:
        x += [0, [DTYPE_CODES["bool"], [4, 3], b"\x01" * 12]][len(x) - len(NAMES):]
    for path, value in changes.items():
        name, _, part = path.partition("__")
        if name == "extra":
            x.append(value)
        elif value is ...:
            del x[names.index(name)]
        elif part:
            x[names.index(name)][PARTS[part]] = value
        else:
            x[names.index(name)] = value
    return msgpack.packb(x, use_bin_type=True)


MESSAGE_TYPES_BY_TAG = {cls.TAG: cls for cls in MESSAGE_TYPES.values()}


@pytest.mark.parametrize("msg", MSGS, ids=lambda m: m.TYPE)
def test_every_message_round_trips(msg):
    back = codec.decode(codec.encode(msg))
    assert_same(msg, back)
    # And with the exact expected type plus its own dims.
    assert_same(msg, codec.decode(codec.encode(msg), type(msg), Dims(num_envs=8, n_agents=3)))


def test_every_type_has_a_sample_and_a_json_schema():
    assert {m.TYPE for m in MSGS} == set(MESSAGE_TYPES)
    schemas = json_schemas()
    assert schemas["schema_version"] == SCHEMA_VERSION
    assert set(schemas["messages"]) == set(MESSAGE_TYPES)
    local = schemas["messages"]["local_obs"]
    assert local["fields"][:5] == ["type tag", "v", "step", "env_idx", "sender"]
    assert local["prefixItems"][0] == {"enum": [LocalObs.TAG]}
    obs = local["prefixItems"][local["fields"].index("obs")]
    assert obs["prefixItems"][0]["enum"] == sorted([F32, DTYPE_CODES["float16"]])
    json.dumps(schemas)  # serialisable


def test_decoded_arrays_are_writable_native_copies():
    back = codec.decode(GOOD, GlobalState)
    back.obs[0, 0, 0] = 5.0
    assert back.obs.flags.writeable and back.obs.dtype == np.float32


def test_stamp_sets_the_sender_and_nothing_else():
    back = codec.decode(codec.encode(MSGS[0], stamp={"sender": "s"}))
    assert back.sender == "s" and MSGS[0].sender == "tester"
    with pytest.raises(TypeError, match="stamp"):
        codec.encode(MSGS[0], stamp={"run": "other"})


def test_big_endian_and_strided_arrays_encode_as_native_ones():
    m = MSGS[0]
    for obs in (m.obs.astype(">f4"), np.asfortranarray(m.obs)):
        assert codec.encode(replace(m, obs=obs)) == codec.encode(m)


def test_encode_is_thread_safe():
    msgs = [m for m in MSGS if m.TYPE != "weights"]
    want = [codec.encode(m) for m in msgs]
    with ThreadPoolExecutor(4) as pool:
        for got in pool.map(lambda _: [codec.encode(m) for m in msgs], range(64)):
            assert got == want


@pytest.mark.parametrize(
    ("data", "error", "field"),
    [
        (b"\xc1", DecodeError, None),
        (GOOD[:-7], DecodeError, None),
        (GOOD + b"\x00", DecodeError, None),
        (msgpack.packb({"v": 4, "type": "global_state"}), DecodeError, None),
        (msgpack.packb([1]), VersionError, "v"),
        (msgpack.packb(msgpack.ExtType(5, b"x")), DecodeError, None),
        (_tamper(GOOD, v=SCHEMA_VERSION + 1), VersionError, "v"),
        (_tamper(GOOD, v="4"), VersionError, "v"),
        (_tamper(GOOD, type=99), TypeTagError, "type"),
        (_tamper(GOOD, type="global_state"), TypeTagError, "type"),
        (_tamper(GOOD, step="7"), FieldError, "step"),
        (_tamper(GOOD, step=-1), FieldError, "step"),
        (_tamper(GOOD, step=True), FieldError, "step"),
        (_tamper(GOOD, step=msgpack.ExtType(1, b"")), FieldError, "step"),
        (_tamper(GOOD, sender="x" * 129), FieldError, "sender"),
        (_tamper(GOOD, active=..., policy_version=..., prev_actions=...), FieldError, "prev_actions"),
        (_tamper(GOOD, extra=1), FieldError, None),
        (_tamper(GOOD, obs=[1, 2]), FieldError, "obs"),
        (_tamper(GOOD, obs={"dtype": "float32", "shape": [4, 3, 18], "data": b""}), FieldError, "obs"),
        (_tamper(GOOD, obs__dtype=DTYPE_CODES["int64"]), DTypeError, "obs"),
        (_tamper(GOOD, obs__dtype=17), DTypeError, "obs"),
        (_tamper(GOOD, active__dtype=DTYPE_CODES["uint8"]), DTypeError, "active"),
        (_tamper(GOOD, obs__shape=[4, 3, 17]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[4, -3, 18]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[4, 54]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[2, 6, 18]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[1] * 9), ShapeError, "obs"),
        (_tamper(GOOD, active__shape=[3, 4]), ShapeError, "active"),
        (_tamper(GOOD, active__data=b"\x02" * 12), FieldError, "active"),
        (_tamper(GOOD, env_idx=[0, 1, 1, 2]), ShapeError, "env_idx"),
        (_tamper(GOOD, env_idx=[0, 1, -1, 2]), FieldError, "env_idx"),
        (_tamper(GOOD, env_idx=3), ShapeError, "obs"),
        (_tamper(GOOD, env_idx=1 << 40), FieldError, "env_idx"),
        (_tamper(GOOD, obs__data=np.full((4, 3, 18), np.nan, np.float32).tobytes()), NonFiniteError, "obs"),
        (_tamper(GOOD, prev_actions__data=np.full((4, 3, 5), np.inf, np.float32).tobytes()), NonFiniteError,
         "prev_actions"),
    ],
)
def test_malformed_payloads_raise_named_errors(data, error, field):
    with pytest.raises(error) as ei:
        codec.decode(data)
    assert isinstance(ei.value, ProtocolError)
    if field is not None:
        assert ei.value.field == field and str(ei.value).startswith(field)


def test_expected_type_and_size_caps():
    with pytest.raises(TypeTagError, match="expected local_obs"):
        codec.decode(GOOD, LocalObs)
    assert isinstance(codec.decode(GOOD, (LocalObs, GlobalState)), GlobalState)
    with pytest.raises(SizeError):
        codec.decode(GOOD, max_bytes=len(GOOD) - 1)
    big = GlobalState(env_idx=np.arange(4000), obs=np.zeros((4000, 5, 30), np.float32),
                      prev_actions=np.zeros((4000, 5, 5), np.float32), active=np.ones((4000, 5), bool))
    with pytest.raises(SizeError):  # 2.9 MB > cap 2 MB: refused at the sender
        codec.encode(big, max_bytes=2 << 20)
    data = codec.encode(big)
    with pytest.raises(SizeError):  # and at the receiver before parsing
        codec.decode(data, max_bytes=2 << 20)
    # Weights may be larger than the default cap of small messages.
    w = Weights.from_blob("local", 1, bytes(6 << 20))
    assert codec.decode(codec.encode(w), Weights).version == 1
    with pytest.raises(SizeError):
        codec.decode(codec.encode(w), LocalObs)


def test_weights_checksum_and_message_range():
    w = codec.encode(next(m for m in sample_messages() if isinstance(m, Weights)))
    with pytest.raises(ChecksumError):
        codec.decode(_tamper(w, blob=b"tampered"))
    m = codec.encode(sample_messages()[2])
    with pytest.raises(RangeError, match="msg"):
        codec.decode(_tamper(m, msg__data=np.full((4, 4), 1.01, np.float32).tobytes()))


def test_declared_dims_are_checked():
    with pytest.raises(ShapeError, match="obs_dim is 18, expected 30"):
        codec.decode(GOOD, dims=Dims(obs_dim=30))
    with pytest.raises(ShapeError, match="n_agents"):
        codec.decode(GOOD, dims=Dims(n_agents=5))
    with pytest.raises(ShapeError, match="num_envs"):
        codec.decode(GOOD, dims=Dims(num_envs=3))
    with pytest.raises(RangeError, match="num_envs"):
        codec.decode(_tamper(GOOD, env_idx=[0, 1, 2, 9]), dims=Dims(num_envs=5))
    codec.decode(GOOD, dims=Dims(num_envs=4, n_agents=3, obs_dim=18, action_dim=5, discrete=True))
    act = codec.encode(MSGS[3])
    with pytest.raises(RangeError, match="action ids"):
        codec.decode(act, dims=Dims(action_dim=2, discrete=True))
    with pytest.raises(ShapeError, match="action"):
        codec.decode(act, dims=Dims(action_dim=5, discrete=False))
    with pytest.raises(RangeError, match="agent"):
        codec.decode(act, dims=Dims(n_agents=0))
    with pytest.raises(ShapeError, match="msg_dim"):
        codec.decode(codec.encode(MSGS[2]), dims=Dims(msg_dim=8))


def test_building_invalid_messages_fails_at_the_sender():
    with pytest.raises(ValueError, match="astype"):
        LocalObs(env_idx=np.arange(2), agent=0, obs=np.zeros((2, 3)), active=np.ones(2, bool))
    with pytest.raises(ValueError, match="NaN"):
        CentralMsg(env_idx=np.arange(1), agent=0, msg=np.full((1, 2), np.nan, np.float32))
    with pytest.raises(ValueError, match="K=2"):
        Action(env_idx=np.arange(2), agent=0, action=np.zeros(3, np.int64))
    with pytest.raises(ValueError, match="action"):
        Action(env_idx=np.arange(2), agent=0, action=np.zeros((2, 2), np.int64))
    with pytest.raises(ValueError, match="unique"):
        LocalObs(env_idx=np.array([1, 1]), agent=0, obs=np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match="int64"):
        LocalObs(env_idx=np.arange(2, dtype=np.int32), agent=0, obs=np.zeros((2, 3), np.float32))
    for bad in (None, [[0.0] * 3] * 2, np.ma.masked_array(np.zeros((2, 3), np.float32)),
                np.zeros((2, 3, 1), np.float32), np.zeros((3, 3), np.float32)):
        with pytest.raises(ProtocolError):
            LocalObs(env_idx=np.arange(2), agent=0, obs=bad)
    a = Action(env_idx=np.arange(2), agent=0, action=np.zeros(2, np.int64))
    assert a.fallback.tolist() == [False, False] and a.discrete
    o = LocalObs(env_idx=np.arange(2), agent=0, obs=np.zeros((2, 3), np.float32))
    assert o.active.tolist() == [True, True]


# --- the compact wire ------------------------------------------------------------------------------


def _wire(msg) -> list:
    return msgpack.unpackb(codec.encode(msg))


def test_the_usual_values_are_the_narrowest_on_the_wire():
    """env_idx 0..K-1 as K, every agent active and no fallback as nil, ids that fit as uint8, the
    optional fields at their default left off the end; anything else in full, and all of it decodes
    to the same message."""
    k, idx = 3, np.arange(3)
    obs = LocalObs(env_idx=idx, agent=1, obs=np.ones((k, 2), np.float32), policy_version=2)
    assert _wire(obs) == [LocalObs.TAG, SCHEMA_VERSION, 0, k, "", 1, [F32, [k, 2], np.ones((k, 2), "<f4").tobytes()], 2]
    some = replace(obs, env_idx=np.array([4, 0, 2]), active=np.array([True, False, True]))
    assert _wire(some)[3] == [4, 0, 2] and _wire(some)[-1] == [DTYPE_CODES["bool"], [k], b"\x01\x00\x01"]
    act = Action(env_idx=idx, agent=1, action=np.array([0, 4, 255]))
    assert _wire(act)[6:] == [[DTYPE_CODES["uint8"], [k], bytes([0, 4, 255])]]  # no policy_version, fallback, msg
    wide = replace(act, action=np.array([0, 256, 1]))
    assert _wire(wide)[6][0] == DTYPE_CODES["int64"]
    for m in (obs, some, act, wide):
        back = codec.decode(codec.encode(m))
        assert_same(m, back)
    assert codec.decode(codec.encode(act)).action.dtype == np.int64
    stop = Control(command="stop", sender="launcher")
    assert _wire(stop) == [Control.TAG, SCHEMA_VERSION, 0, 0, "launcher", "stop"]


def test_float16_is_opt_in_and_read_as_float32():
    msg = MSGS[2]  # a CentralMsg
    half = codec.encode(msg, half=True)
    assert len(half) < len(codec.encode(msg)) - msg.msg.size
    back = codec.decode(half, CentralMsg)
    assert back.msg.dtype == np.float32 and np.array_equal(back.msg, msg.msg.astype(np.float16).astype(np.float32))
    assert codec.decode(codec.encode(msg)).msg.tobytes() == msg.msg.tobytes()  # float32 by default, exactly
    far = LocalObs(env_idx=np.arange(1), agent=0, obs=np.array([[1e5]], np.float32))
    with pytest.raises(NonFiniteError, match="obs"):
        codec.encode(far, half=True)
    ids = codec.encode(MSGS[3], half=True)  # actions are never halved; ids stay ids
    assert codec.decode(ids).action.dtype == np.int64
    with pytest.raises(DTypeError):  # nor are the arrays of an experience chunk
        codec.decode(_tamper(codec.encode(MSGS[5]), arrays={"x": [DTYPE_CODES["float16"], [1], b"\x00\x3c"]}))


def test_the_echoed_message_is_required_only_where_declared():
    """An action in training carries the message it acted on (the rollout records it); serving
    leaves it out. A receiver that declares echo=True refuses an action without it."""
    train = Dims(num_envs=4, msg_dim=4, echo=True)
    with_msg, without = MSGS[-3], MSGS[3]
    assert with_msg.TYPE == without.TYPE == "action" and with_msg.msg is not None and without.msg is None
    codec.decode(codec.encode(replace(with_msg, action=np.array([0, 3, 2, 1]))), Action, train)
    with pytest.raises(FieldError, match="msg"):
        codec.decode(codec.encode(without), Action, train)
    codec.decode(codec.encode(without), Action, Dims(num_envs=4, msg_dim=4))
    codec.decode(codec.encode(without), Action, Dims(num_envs=4, msg_dim=0, echo=True))  # no messages at all


def test_an_observation_carries_its_central_message_checked_as_a_central_message_is():
    """A fleet's world puts the central message into each robot's observation (one message down per
    tick): range and width are checked as a central_msg's are; without one the field is left off."""
    one = np.arange(1)
    obs = LocalObs(step=3, env_idx=one, agent=0, obs=np.zeros((1, 2), np.float32), msg=np.full((1, 4), 0.5, np.float32))
    got = codec.decode(codec.encode(obs), LocalObs, Dims(num_envs=1, obs_dim=2, msg_dim=4))
    assert got.msg.tolist() == [[0.5] * 4] and got.active.tolist() == [True]
    with pytest.raises(ShapeError, match="msg_dim is 4, expected 3"):
        codec.decode(codec.encode(obs), LocalObs, Dims(num_envs=1, obs_dim=2, msg_dim=3))
    with pytest.raises(RangeError, match=r"\[-1, 1\]"):
        LocalObs(step=3, env_idx=one, agent=0, obs=np.zeros((1, 2), np.float32), msg=np.full((1, 4), 1.5, np.float32))
    with pytest.raises(ShapeError, match="msg"):
        LocalObs(step=3, env_idx=np.arange(2), agent=0, obs=np.zeros((2, 2), np.float32),
                 msg=np.zeros((1, 4), np.float32))
    bare = replace(obs, msg=None)
    assert codec.decode(codec.encode(bare), LocalObs).msg is None
    # the floats, their array header, and the three defaults before them that `bare` leaves off
    assert len(codec.encode(obs)) - len(codec.encode(bare)) == 16 + 7 + 3
    # the cap a receiver's dims give an observation leaves room for the message it may carry
    assert LocalObs.cap_for_dims(Dims(num_envs=1, obs_dim=2, msg_dim=4)) >= len(codec.encode(obs))


@pytest.mark.parametrize("extra", [1, 2])
def test_extra_elements_are_counted_without_the_type_tag(extra):
    """A message with `extra` elements more than its type has is refused naming that count (the type
    tag is not one of the fields)."""
    for msg in (MSGS[-3], MSGS[0]):
        wire = msgpack.unpackb(codec.encode(msg))
        wire += [None] * (1 + len(fields_of(type(msg))) - len(wire))  # every field, the optional ones as nil
        with pytest.raises(FieldError, match=rf"unknown: {extra} more element\(s\) than {msg.TYPE} has"):
            codec.decode(msgpack.packb([*wire, *([None] * extra)]), type(msg))


def test_keys_and_run_ids():
    k = Keys("exp-1.a_b")
    assert k.obs(2) == "hammer/exp-1.a_b/env/obs/2"
    assert k.msg("*") == "hammer/exp-1.a_b/central/msg/*"
    assert k.act(0) == "hammer/exp-1.a_b/agent/act/0"
    assert k.state() == "hammer/exp-1.a_b/env/state"
    assert k.exp("local") == "hammer/exp-1.a_b/learn/local/exp"
    assert k.weights("central") == "hammer/exp-1.a_b/learn/central/weights"
    assert k.alive("env") == "hammer/exp-1.a_b/alive/env" and k.ctl() == "hammer/exp-1.a_b/ctl/all"
    assert k.relative(k.act(3)) == "agent/act/3"
    for bad in ["", "a/b", "a*", "run id", "-x", "ä", "x" * 65, "$x"]:
        with pytest.raises(ValueError, match="run id"):
            validate_run_id(bad)
    with pytest.raises(ValueError):
        k.obs(-1)
    with pytest.raises(ValueError):
        k.relative("hammer/other/env/state")


# --- fuzzing: the decoder only ever raises ProtocolError ----------------------------------------

_FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
_ENCODED = [codec.encode(m) for m in MSGS]


@_FUZZ
@given(st.binary(max_size=512))
def test_fuzz_random_bytes(data):
    try:
        codec.decode(data)
    except ProtocolError:
        pass


@_FUZZ
@given(st.sampled_from(_ENCODED), st.data())
def test_fuzz_mutated_valid_messages(data, draw):
    i = draw.draw(st.integers(0, len(data) - 1))
    mode = draw.draw(st.sampled_from(["flip", "truncate", "insert"]))
    if mode == "flip":
        b = bytearray(data)
        b[i] ^= draw.draw(st.integers(1, 255))
        data = bytes(b)
    elif mode == "truncate":
        data = data[:i]
    else:
        data = data[:i] + draw.draw(st.binary(min_size=1, max_size=8)) + data[i:]
    try:
        msg = codec.decode(data)
    except ProtocolError:
        return
    assert msg.TYPE in MESSAGE_TYPES  # a surviving mutation must still be a valid message


_scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**63), 2**63 - 1), st.floats(),
                     st.text(max_size=8), st.binary(max_size=16))
_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c,
                                                                                         max_size=4), max_leaves=12)


@_FUZZ
@given(st.sampled_from(_ENCODED), st.data())
def test_fuzz_structured_field_replacement(data, draw):
    d = msgpack.unpackb(data)
    i = draw.draw(st.integers(0, len(d) - 1))
    d[i] = draw.draw(_values)
    try:
        codec.decode(msgpack.packb(d, use_bin_type=True))
    except ProtocolError:
        pass


def test_hand_built_array_from_the_docs_decodes():
    """A client in another language following docs/wire-format.md produces what we accept, and the
    bytes of the page's example are what hammer sends for it."""
    wire = [1, SCHEMA_VERSION, 12, 1, "", 1, [5, [1, 2], struct.pack("<2f", 1.0, -2.0)], 3]
    msg = codec.decode(msgpack.packb(wire, use_bin_type=True), LocalObs)
    assert msg.obs.tolist() == [[1.0, -2.0]] and msg.active.tolist() == [True] and msg.agent == 1
    assert not msg.echo  # left off: the env host records no message (serving)
    text = (Path(__file__).resolve().parents[1] / "docs" / "wire-format.md").read_text()
    example = re.search(r"\n((?:[0-9a-f]{2} )+[0-9a-f]{2}) +\((\d+) bytes\)", text)
    data = bytes.fromhex(example[1])
    assert len(data) == int(example[2]) and data == msgpack.packb(wire, use_bin_type=True)
    assert codec.encode(msg, stamp={"sender": ""}) == data
    assert msg.env_idx.tolist() == [0] and msg.policy_version == 3 and msg.step == 12
    assert struct.pack("<2f", 1.0, -2.0) == bytes.fromhex("0000803f000000c0")
    assert msgpack.unpackb(codec.encode(msg)) == wire
    assert codec.encode(msg).hex() == "980107 0c 01 a0 01 93 05 920102 c408 0000803f000000c0 03".replace(" ", "")


def test_the_wire_path_imports_no_pydantic():
    """The codec, the messages and their field types load without pydantic (the edge agent's memory): a typed msgspec Struct per message instead of a pydantic model."""
    import subprocess
    import sys

    code = ("import sys, hammer.protocol.codec, hammer.protocol.binding, hammer.protocol.samples; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pydantic', 'pydantic_core')))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    assert out.strip() == "[]", out


def test_numpy_scalars_in_maps_go_as_python_ones():
    """A heartbeat's counters, a chunk's meta or a control's args may be summed with numpy: they
    travel as msgpack ints and floats; what is no scalar at all is refused at the sender."""
    from hammer.protocol.schemas import Heartbeat

    hb = Heartbeat(role="env", pid=1, status="running", counters={"steps": np.int64(3), "busy_s": np.float64(0.5)},
                   gauges={"policy_version": np.int32(-1), "ok": np.float32(2.5)})
    back = codec.decode(codec.encode(hb), Heartbeat)
    assert back.counters == {"steps": 3, "busy_s": 0.5} and back.gauges == {"policy_version": -1, "ok": 2.5}
    assert type(back.counters["steps"]) is int and type(back.gauges["ok"]) is float
    with pytest.raises(FieldError, match="counters.x"):
        Heartbeat(role="env", pid=1, status="running", counters={"x": np.zeros(2)})
    with pytest.raises(NonFiniteError, match="gauges.x"):
        Heartbeat(role="env", pid=1, status="running", gauges={"x": np.float64("nan")})
