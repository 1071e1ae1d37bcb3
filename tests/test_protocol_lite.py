"""The pure-Python array checks (the lite edge agent, no numpy) give the same verdict as numpy's.

protocol/fields.py checks an array field with numpy where the process has loaded it, and without
(`ArraySpec.take_lite`, `WireArray`) where it has not: the edge agent of a discrete K=1 team never
imports numpy (serve/edge_entry.py). One schema, two ways to run its array checks: this runs the corpora
of the codec tests (tests/test_protocol_codec.py: every named rejection, the fuzzed mutations),
of the live fuzz (tests/test_live_fuzz.py: every key's receiver with its declared dims, key binding
included) and of the hostile peer (tests/hostile_peer.py: its forgeries) through both paths and
asserts the same verdict: accepted with the same values and the same re-encoded bytes, or refused
with the same error class, field and text.
"""

from __future__ import annotations

import random

import msgpack
import numpy as np
import pytest
from hammer.protocol import codec
from hammer.protocol.binding import check_key
from hammer.protocol.dims import Dims
from hammer.protocol.errors import ProtocolError
from hammer.protocol.fields import WireArray, lite_arrays
from hammer.protocol.keys import Keys
from hammer.protocol.samples import sample_messages
from hammer.protocol.schemas import Action, CentralMsg, Control, LocalObs, Weights
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests import test_live_fuzz as live
from tests import test_protocol_codec as codec_tests
from tests.hostile_peer import zeroed


def _value(v):
    """A field's value comparable across the two paths: an array as (dtype, shape, bytes)."""
    if isinstance(v, np.ndarray):
        return ("array", str(v.dtype), tuple(v.shape), v.tobytes())
    if isinstance(v, WireArray):
        return ("array", v.dtype, tuple(v.shape), v.tobytes())
    if isinstance(v, dict):
        return {k: _value(x) for k, x in v.items()}
    return v


def verdict(payload: bytes, expected=None, dims: Dims | None = None, key: str | None = None) -> tuple:
    """What a receiver makes of `payload`: the message's values and its bytes re-encoded, or the error."""
    try:
        msg = codec.decode(payload, expected)
        if key is not None:
            check_key(msg, Keys(live.RUN).relative(key))
        if dims is not None:
            msg.check_dims(dims)
    except ProtocolError as e:
        return ("refused", type(e).__name__, e.field, str(e))
    values = {name: _value(getattr(msg, name)) for name in type(msg).__struct_fields__}
    return ("accepted", type(msg).__name__, values, _encoded(msg, False), _encoded(msg, True))


def _encoded(msg, half: bool) -> bytes | tuple:
    """The message re-encoded (float16 where `half`), or the sender's refusal (beyond float16's range)."""
    try:
        return codec.encode(msg, half=half)
    except ProtocolError as e:
        return ("refused", type(e).__name__, e.field, str(e))


def both(payload: bytes, expected=None, dims: Dims | None = None, key: str | None = None) -> tuple:
    """The numpy verdict, asserted equal to the pure-Python one."""
    with_numpy = verdict(payload, expected, dims, key)
    with lite_arrays():
        without = verdict(payload, expected, dims, key)
    assert with_numpy == without, (payload[:80], with_numpy[:4], without[:4])
    return with_numpy


def test_the_lite_path_makes_wire_arrays_and_restores_numpy():
    data = codec.encode(sample_messages()[0])
    with lite_arrays():
        m = codec.decode(data)
        assert type(m.obs) is WireArray and type(m.env_idx) is WireArray and type(m.active) is WireArray
    assert type(codec.decode(data).obs) is np.ndarray


def test_named_rejections_of_the_codec_tests():
    cases = codec_tests.test_malformed_payloads_raise_named_errors.pytestmark[0].args[1]
    assert len(cases) > 30
    for data, error, _field in cases:
        v = both(data)
        assert v[0] == "refused" and v[1] == error.__name__


@pytest.mark.parametrize("half", [False, True])
def test_every_sample_message(half):
    for m in sample_messages():
        assert both(codec.encode(m, half=half))[0] == "accepted"


def test_messages_built_by_code_encode_to_the_same_bytes():
    """What the lite agent builds (an Action from WireArrays) is on the wire what numpy builds."""
    for action, fb, msg in [([3], [False], None), ([0], [True], [[0.25, -1.0, 0.5]]), ([300, 2], [False, False], None)]:
        k = len(action)
        ref = Action(step=5, env_idx=np.arange(k), agent=1, action=np.array(action, np.int64), policy_version=2,
                     fallback=np.array(fb), msg=None if msg is None else np.array(msg, np.float32))
        with lite_arrays():
            lite = Action(step=5, env_idx=k, agent=1, action=WireArray.of("int64", (k,), action), policy_version=2,
                          fallback=WireArray.of("bool", (k,), fb),
                          msg=None if msg is None else WireArray.of("float32", (k, 3), [x for r in msg for x in r]))
            lite_bytes = [codec.encode(lite), codec.encode(lite, half=True)]
        assert lite_bytes == [codec.encode(ref), codec.encode(ref, half=True)]


def test_code_built_values_are_refused_alike():
    with lite_arrays():
        for bad in ({"action": WireArray.of("float64", (1,), [1.0])},
                    {"msg": WireArray.of("float32", (1, 2), [0.0, float("nan")])},
                    {"fallback": WireArray.of("bool", (2,), [False, True])}):
            with pytest.raises(ProtocolError):
                Action(step=1, env_idx=1, agent=0, **{"action": WireArray.of("int64", (1,), [0]), **bad})
        with pytest.raises(ProtocolError, match="must lie in"):
            CentralMsg(step=1, env_idx=1, agent=0, msg=WireArray.of("float32", (1, 2), [0.5, 1.5]))
        with pytest.raises(ProtocolError, match="NaN"):
            Control(command="stop", args={"x": float("inf")})


_FUZZ = settings(max_examples=400, derandomize=True, database=None, deadline=None,
                 suppress_health_check=list(HealthCheck))


def _mutations(data: bytes, rng: random.Random) -> bytes:
    """The codec tests' mutations (flip, truncate, insert) and field replacements, seeded."""
    i = rng.randrange(len(data))
    mode = rng.choice(["flip", "truncate", "insert", "field"])
    if mode == "flip":
        b = bytearray(data)
        b[i] ^= rng.randrange(1, 256)
        return bytes(b)
    if mode == "truncate":
        return data[:i]
    if mode == "insert":
        return data[:i] + rng.randbytes(rng.randrange(1, 9)) + data[i:]
    d = msgpack.unpackb(data)
    d[rng.randrange(len(d))] = rng.choice([None, True, -1, 2**63, 1.5, float("nan"), "x", b"\x00\x01", [5, [1], b""],
                                           [0, [2], b"\x01\x02"], {"a": 1}])
    return msgpack.packb(d, use_bin_type=True)


def test_fuzzed_mutations_of_the_codec_corpus():
    rng = random.Random(0)
    encoded = [codec.encode(m, half=h) for m in sample_messages() for h in (False, True)]
    seen = {"accepted": 0, "refused": 0}
    for _ in range(3000):
        seen[both(_mutations(rng.choice(encoded), rng))[0]] += 1
    assert seen["refused"] > 1000 and seen["accepted"] > 0


@_FUZZ
@given(st.binary(max_size=256))
def test_fuzzed_random_bytes(data):
    both(data)


_TARGETS = live._targets()


@_FUZZ
@given(st.data())
def test_the_live_fuzz_corpus_with_each_keys_dims(data):
    t = data.draw(st.sampled_from(_TARGETS))
    payload = data.draw(live.mutated(t.base))
    both(payload, t.expected, t.dims, t.key)


def test_the_live_fuzz_targets_unmutated_and_at_k1():
    for t in _TARGETS:  # the bases claim sender "fuzz": refused by key binding where the key names the sender
        assert both(t.base, t.expected, t.dims)[0] == "accepted"
        both(t.base, t.expected, t.dims, t.key)
    k1 = Dims(num_envs=1, n_agents=3, obs_dim=18, msg_dim=4, action_dim=5, discrete=True)
    for m in (LocalObs(step=2, env_idx=np.arange(1), agent=0, obs=np.ones((1, 18), np.float32)),
              LocalObs(step=2, env_idx=np.array([3]), agent=0, obs=np.ones((1, 18), np.float32)),
              CentralMsg(step=2, env_idx=np.arange(1), agent=0, msg=np.full((1, 4), 0.5, np.float32)),
              CentralMsg(step=2, env_idx=np.arange(1), agent=0, msg=np.ones((1, 3), np.float32))):
        both(codec.encode(m), type(m), k1, f"hammer/{live.RUN}/agent/obs/0" if m.TYPE == "local_obs"
             else f"hammer/{live.RUN}/agent/msg/0")


def test_the_hostile_peers_forgeries():
    from safetensors.numpy import save

    blob = zeroed(save({"actor.layers.0.weight": np.ones((4, 3), np.float32), "log_std": np.zeros(2, np.float32)}))
    forged = [Action(agent=0, step=s, env_idx=np.arange(k), action=np.zeros(k, np.int64), policy_version=v,
                     msg=None if m == 0 else np.zeros((k, m), np.float32))
              for s, k, m, v in [(0, 1, 0, 0), (7, 4, 2, 9), (2**40, 32, 4, 1)]]
    forged += [Weights.from_blob("local", 5, blob), Weights.from_blob("central", 2**31, blob),
               Control(command="stop"), Control(command="stop", target="local-0", args={"why": "x"})]
    for m in forged:
        for sender in ("launcher", "env", ""):
            v = both(codec.encode(m, stamp={"sender": sender}))
            assert v[0] == "accepted"
