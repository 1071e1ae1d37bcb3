"""The msgpack codec and schemas: round trips, every rejection reason, fuzzing, JSON Schema."""

from __future__ import annotations

import json

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
    RunMismatchError,
    ShapeError,
    SizeError,
    TypeTagError,
    VersionError,
)
from hammer.protocol.keys import Keys, validate_run_id
from hammer.protocol.samples import assert_same, sample_messages
from hammer.protocol.schemas import (
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Action,
    CentralMsg,
    GlobalState,
    LocalObs,
    Weights,
    json_schemas,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

MSGS = sample_messages()
GOOD = codec.encode(MSGS[1])  # a GlobalState K=4 N=3 D=18


def _tamper(data: bytes, **changes) -> bytes:
    d = msgpack.unpackb(data)
    for path, value in changes.items():
        *head, last = path.split("__")
        target = d
        for p in head:
            target = target[p]
        if value is ...:
            del target[last]
        else:
            target[last] = value
    return msgpack.packb(d, use_bin_type=True)


@pytest.mark.parametrize("msg", MSGS, ids=lambda m: m.TYPE)
def test_every_message_round_trips(msg):
    back = codec.decode(codec.encode(msg))
    assert_same(msg, back)
    # And with the exact expected type plus its own dims.
    assert_same(msg, codec.decode(codec.encode(msg), type(msg), Dims(num_envs=4, n_agents=3)))


def test_every_type_has_a_sample_and_a_json_schema():
    assert {m.TYPE for m in MSGS} == set(MESSAGE_TYPES)
    schemas = json_schemas()
    assert schemas["schema_version"] == SCHEMA_VERSION
    assert set(schemas["messages"]) == set(MESSAGE_TYPES)
    obs = schemas["messages"]["local_obs"]["properties"]["obs"]
    assert obs["properties"]["dtype"]["enum"] == ["float32"]
    json.dumps(schemas)  # serialisable


def test_decoded_arrays_are_writable_native_copies():
    back = codec.decode(GOOD, GlobalState)
    back.obs[0, 0, 0] = 5.0
    assert back.obs.flags.writeable and back.obs.dtype == np.float32


def test_stamp_overrides_header():
    data = codec.encode(MSGS[0], stamp={"run": "other", "seq": 99, "ts": 1, "sender": "s"})
    back = codec.decode(data)
    assert (back.run, back.seq, back.ts, back.sender) == ("other", 99, 1, "s")
    with pytest.raises(RunMismatchError):
        codec.decode(data, run="run1")


@pytest.mark.parametrize(
    ("data", "error", "field"),
    [
        (b"\xc1", DecodeError, None),
        (GOOD[:-7], DecodeError, None),
        (GOOD + b"\x00", DecodeError, None),
        (msgpack.packb([1, 2, 3]), DecodeError, None),
        (msgpack.packb({1: 2}), DecodeError, None),
        (msgpack.packb(msgpack.ExtType(5, b"x")), DecodeError, None),
        (_tamper(GOOD, v=SCHEMA_VERSION + 1), VersionError, "v"),
        (_tamper(GOOD, v=...), VersionError, "v"),
        (_tamper(GOOD, type="nope"), TypeTagError, "type"),
        (_tamper(GOOD, step="7"), FieldError, "step"),
        (_tamper(GOOD, step=-1), FieldError, "step"),
        (_tamper(GOOD, obs=...), FieldError, "obs"),
        (_tamper(GOOD, extra=1), FieldError, "extra"),
        (_tamper(GOOD, run="bad/run"), FieldError, "run"),
        (_tamper(GOOD, run=""), FieldError, "run"),
        (_tamper(GOOD, obs=[1, 2]), FieldError, "obs"),
        (_tamper(GOOD, obs__dtype="float16"), DTypeError, "obs"),
        (_tamper(GOOD, obs__dtype="object"), DTypeError, "obs"),
        (_tamper(GOOD, active__dtype="uint8"), DTypeError, "active"),
        (_tamper(GOOD, obs__shape=[4, 3, 17]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[4, -3, 18]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[4, 54]), ShapeError, "obs"),
        (_tamper(GOOD, obs__shape=[2, 6, 18]), ShapeError, "obs"),
        (_tamper(GOOD, active__shape=[3, 4]), ShapeError, "active"),
        (_tamper(GOOD, active__data=b"\x02" * 12), FieldError, "active"),
        (_tamper(GOOD, env_idx__data=np.array([0, 1, 1, 2]).tobytes()), ShapeError, "env_idx"),
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
    big = GlobalState(run="r", env_idx=np.arange(4000), obs=np.zeros((4000, 5, 30), np.float32),
                      prev_actions=np.zeros((4000, 5, 5), np.float32), active=np.ones((4000, 5), bool))
    with pytest.raises(SizeError):  # 2.9 MB > cap 2 MB: refused at the sender
        codec.encode(big, max_bytes=2 << 20)
    data = codec.encode(big)
    with pytest.raises(SizeError):  # and at the receiver before parsing
        codec.decode(data, max_bytes=2 << 20)
    # Weights may be larger than the default cap of small messages.
    w = Weights.from_blob("local", 1, bytes(6 << 20), run="r")
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
        codec.decode(_tamper(GOOD, env_idx__data=np.array([0, 1, 2, 9]).tobytes()), dims=Dims(num_envs=5))
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
        LocalObs(run="r", env_idx=np.arange(2), agent=0, obs=np.zeros((2, 3)), active=np.ones(2, bool))
    with pytest.raises(ValueError, match="NaN"):
        CentralMsg(run="r", env_idx=np.arange(1), agent=0, msg=np.full((1, 2), np.nan, np.float32))
    with pytest.raises(ValueError, match="K=2"):
        Action(run="r", env_idx=np.arange(2), agent=0, action=np.zeros(3, np.int64))
    with pytest.raises(ValueError, match="action"):
        Action(run="r", env_idx=np.arange(2), agent=0, action=np.zeros((2, 2), np.int64))
    a = Action(run="r", env_idx=np.arange(2), agent=0, action=np.zeros(2, np.int64))
    assert a.fallback.tolist() == [False, False] and a.discrete


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
    key = draw.draw(st.sampled_from(sorted(d)))
    d[key] = draw.draw(_values)
    try:
        codec.decode(msgpack.packb(d, use_bin_type=True))
    except ProtocolError:
        pass


def test_hand_built_map_from_the_docs_decodes():
    """A client in another language following docs/wire-format.md produces what we accept."""
    import struct

    wire = {
        "v": 3, "type": "local_obs", "run": "exp1", "step": 12,
        "env_idx": {"dtype": "int64", "shape": [1], "data": struct.pack("<q", 0)},
        "ts": 1732240000000000000, "seq": 12, "sender": "env", "agent": 1,
        "obs": {"dtype": "float32", "shape": [1, 2], "data": struct.pack("<2f", 1.0, -2.0)},
        "active": {"dtype": "bool", "shape": [1], "data": b"\x01"}, "policy_version": 3,
    }
    msg = codec.decode(msgpack.packb(wire, use_bin_type=True), LocalObs)
    assert msg.obs.tolist() == [[1.0, -2.0]] and msg.active.tolist() == [True] and msg.agent == 1
    assert struct.pack("<2f", 1.0, -2.0) == bytes.fromhex("0000803f000000c0")
    assert msgpack.unpackb(codec.encode(msg)) == wire
