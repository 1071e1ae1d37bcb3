"""The lite edge agent's acting in plain Python against numpy's: the stream draw for draw, the
safetensors reader, the forward and softmax, the sampling rule, and whole agents step for step.
(The draw on other CPUs' exps: tests/test_exactness.py.)"""

from __future__ import annotations

import itertools
import struct

import numpy as np
import pytest
from hammer.learning import sampling
from hammer.learning.categorical import categorical_inverse_cdf, draw, softmax
from hammer.learning.lite_policy import (
    LiteLocalPolicy,
    LiteWeightsError,
    lite_supported,
    read_safetensors,
    safetensors_names,
)
from hammer.learning.numpy_policy import NumpyLocalPolicy, float16_blob, params_from_blob
from hammer.learning.pcg64 import LOCAL_STREAM, PCG64, lite_stream, seed_sequence_state
from hammer.local_agent.client import AgentSpec, LocalAgent, MessageFallback
from hammer.local_agent.lite import LiteLocalAgent, LiteMessageFallback
from safetensors.numpy import save


@pytest.mark.parametrize("entropy", [0, 1, 2**32, 2**64 + 3, [0, 1, 0], [7, 1, 2], [2**40 + 5, 1, 3], [2**70, 2, 0],
                                     [1, 2, 3, 4, 5, 6, 7]])
def test_pcg64_and_seed_sequence_are_numpys(entropy):
    assert seed_sequence_state(entropy, 4) == [int(x) for x in np.random.SeedSequence(entropy).generate_state(4, np.uint64)]
    g, p = np.random.default_rng(entropy), PCG64(entropy)
    for k in (1, 3, 1000):
        assert g.random(k).tolist() == p.random(k)


def test_the_lite_stream_is_the_contracts_stream():
    assert LOCAL_STREAM == sampling.LOCAL_STREAM
    assert lite_stream(11, LOCAL_STREAM, 2).random(50) == sampling.stream(11, LOCAL_STREAM, 2).random(50).tolist()


def _mlp(rng, sizes, log_std=False) -> dict[str, np.ndarray]:
    p = {}
    for i, (a, b) in enumerate(itertools.pairwise(sizes)):
        p[f"actor.layers.{i}.weight"] = (rng.standard_normal((b, a)) / np.sqrt(a)).astype(np.float32)
        p[f"actor.layers.{i}.bias"] = (0.1 * rng.standard_normal(b)).astype(np.float32)
        p[f"critic.layers.{i}.weight"] = rng.standard_normal((1 if i == len(sizes) - 2 else b, a)).astype(np.float32)
        p[f"critic.layers.{i}.bias"] = np.zeros(1 if i == len(sizes) - 2 else b, np.float32)
    if log_std:
        p["log_std"] = np.zeros(sizes[-1], np.float32)
    return p


def test_safetensors_are_read_as_safetensors_reads_them(tmp_path):
    rng = np.random.default_rng(0)
    params = {**_mlp(rng, [6, 8, 3]), "f64": rng.standard_normal((2, 2))}
    blob = save(params, metadata={"k": "v"})
    got = read_safetensors(blob)
    assert set(got) == set(params)
    for k, v in params.items():
        assert got[k][0] == v.shape and got[k][1] == v.astype(np.float32).ravel().tolist()
    half = read_safetensors(float16_blob(save(_mlp(rng, [6, 8, 3]))))  # float16 weights: read as float32
    ref = params_from_blob(float16_blob(save(_mlp(np.random.default_rng(0), [6, 8, 3]))))
    assert half.keys() == ref.keys()
    (tmp_path / "w.safetensors").write_bytes(blob)
    assert safetensors_names(tmp_path / "w.safetensors") == set(params)


@pytest.mark.parametrize("bad", [b"", b"\x05\x00\x00\x00\x00\x00\x00\x00{}", struct.pack("<Q", 2) + b"[]",
                                 struct.pack("<Q", 4) + b"\xff\xfe{}",
                                 struct.pack("<Q", 2**62) + b"{}",
                                 struct.pack("<Q", 51) + b'{"w":{"dtype":"F32","shape":[2],"data_offsets":[0,9]}}',
                                 struct.pack("<Q", 51) + b'{"w":{"dtype":"I64","shape":[1],"data_offsets":[0,8]}}'
                                 + bytes(8),
                                 struct.pack("<Q", 14) + b'{"w":{"x":1}}'])
def test_malformed_safetensors_are_refused(bad):
    with pytest.raises(LiteWeightsError):
        read_safetensors(bad)


def test_what_the_lite_policy_runs():
    rng = np.random.default_rng(1)
    assert lite_supported(_mlp(rng, [4, 8, 2])) is None
    assert lite_supported(_mlp(rng, [4, 8, 2], log_std=True)) == "continuous actions"
    assert lite_supported({**_mlp(rng, [4, 8, 2]), "actor_enc.image": 0}) == "a conv encoder"
    with pytest.raises(LiteWeightsError, match="continuous"):
        LiteLocalPolicy(save(_mlp(rng, [4, 8, 2], log_std=True)))


def test_forward_softmax_and_inverse_cdf_agree_with_numpy():
    rng = np.random.default_rng(2)
    params = _mlp(rng, [22, 64, 64, 5])
    lite, ref = LiteLocalPolicy(save(params)), NumpyLocalPolicy(params)
    x = rng.standard_normal((2000, 22)).astype(np.float32)
    want = ref.actor_out(x)
    got = np.array([lite.logits(row) for row in x.tolist()], np.float32)
    assert np.abs(got - want).max() <= 4e-6 * max(1.0, float(np.abs(want).max()))
    u = rng.random(2000)
    exact = [softmax(row) for row in want.tolist()]
    # half the uniforms exactly on a CDF value of the exact softmax: where an exp one ulp off flips the draw
    cdf = np.cumsum(exact, axis=1)
    u[:1000] = cdf[np.arange(1000), rng.integers(0, 4, 1000)]
    ids, probs = sampling.categorical_draw(want, u)
    assert np.abs(probs - np.asarray(exact)).max() <= 1e-15  # numpy's fast softmax: the same to a few ulps
    for j in range(2000):  # same logits in: exactly the numpy agent's draw
        assert draw(want[j].tolist(), float(u[j])) == ids[j]
    assert categorical_inverse_cdf([0.5, 0.5], 0.999999999) == 1 and categorical_inverse_cdf([1.0, 0.0], 0.0) == 0


@pytest.mark.parametrize("mode", ["zeros", "last", "last_k"])
def test_the_fallbacks_agree(mode):
    rng = np.random.default_rng(3)
    ref, lite = MessageFallback(mode, 2, 4, 3), LiteMessageFallback(mode, 2, 4, 3)
    for _ in range(40):
        idx = np.sort(rng.choice(4, rng.integers(1, 5), replace=False)).astype(np.int64)
        if rng.random() < 0.4:
            m = rng.uniform(-1, 1, (len(idx), 3)).astype(np.float32)
            ref.received(idx, m)
            lite.received(idx.tolist(), m.tolist())
        else:
            assert ref.fill(idx).tolist() == lite.fill(idx.tolist())


@pytest.mark.parametrize("onehot", [False, True])
def test_a_lite_agent_acts_as_the_numpy_agent(onehot):
    """Same spec, weights, seed and inputs: the same actions (a float32 rounding apart: none here)."""
    rng = np.random.default_rng(4)
    spec = AgentSpec(agent=1, n_agents=3, obs_dim=10, msg_dim=4, discrete=True, action_dim=5, seed=9, onehot=onehot)
    blob = save(_mlp(rng, [10 + 4 + (3 if onehot else 0), 64, 64, 5]))
    ref, lite = LocalAgent(spec), LiteLocalAgent(spec)
    ref.load_weights(blob, 3)
    lite.load_weights(blob, 3)
    differ = 0
    for _ in range(3000):
        obs = rng.standard_normal((1, 10)).astype(np.float32)
        msg = rng.uniform(-1, 1, (1, 4)).astype(np.float32)
        differ += ref.act(obs, msg).tolist() != lite.act(obs.tolist(), msg.tolist())
    assert differ <= 3, differ  # each a uniform within ~1e-7 of a class boundary
