"""Experience chunks are typed: checked array by array against the rollout layout, like every other message."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hammer.envs.base import EnvSpec
from hammer.learning.config import RunConfig
from hammer.protocol import codec
from hammer.protocol.dims import Dims
from hammer.protocol.errors import DTypeError, FieldError, NonFiniteError, ShapeError, SizeError
from hammer.protocol.rollout_layout import BUFFER, CHUNK, RECORD, RolloutLayout
from hammer.protocol.schemas import ExperienceChunk
from hammer.protocol.session import HammerSession, TransportConfig

DISCRETE = RolloutLayout(t=4, k=3, n=2, obs_dim=5, action_dim=6, msg_dim=3, discrete=True)
CONTINUOUS = RolloutLayout(t=4, k=3, n=2, obs_dim=5, action_dim=2, msg_dim=0, discrete=False)


def _chunk_arrays(layout: RolloutLayout, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    arrays = layout.allocate(CHUNK)
    for a in arrays.values():
        a[...] = rng.integers(0, 2, a.shape).astype(a.dtype)
    return arrays


def _chunk(layout: RolloutLayout, arrays: dict[str, np.ndarray] | None = None) -> ExperienceChunk:
    return ExperienceChunk(step=9, env_idx=np.arange(layout.k), role="team", policy_version=1,
                           arrays=_chunk_arrays(layout) if arrays is None else arrays)


def _record(layout: RolloutLayout, k: int | None = None) -> ExperienceChunk:
    k = layout.k if k is None else k
    return ExperienceChunk(step=9, env_idx=np.arange(k), role="central", policy_version=1,
                           arrays=RolloutLayout(**{**layout.__dict__, "k": k}).allocate(RECORD))


def _decode(msg: ExperienceChunk, layout: RolloutLayout, **kw) -> ExperienceChunk:
    return codec.decode(codec.encode(msg), ExperienceChunk, Dims.from_layout(layout), **kw)


@pytest.mark.parametrize("layout", [DISCRETE, CONTINUOUS])
def test_good_chunk_and_record_are_accepted(layout):
    got = _decode(_chunk(layout), layout)
    assert set(got.arrays) == {s.name for s in CHUNK}
    assert got.arrays["actions"].dtype == (np.int64 if layout.discrete else np.float32)
    assert _decode(_record(layout), layout).arrays["keep"].dtype == bool
    assert _decode(_record(layout, k=1), layout).k == 1  # a record carries the copies of its state


def _broken(change) -> dict[str, np.ndarray]:
    arrays = _chunk_arrays(DISCRETE)
    change(arrays)
    return arrays


@pytest.mark.parametrize(("error", "change", "names"), [
    (DTypeError, lambda a: a.update(rewards=a["rewards"].astype(np.float64)), "arrays.rewards"),
    (DTypeError, lambda a: a.update(actions=a["actions"].astype(np.float32)), "arrays.actions"),
    (ShapeError, lambda a: a.update(obs=a["obs"][:, :, :, :4].copy()), "arrays.obs"),
    (ShapeError, lambda a: a.update(steps=np.zeros(5, np.int64)), "arrays.steps"),
    (FieldError, lambda a: a.pop("final_prev"), "final_prev"),
    (FieldError, lambda a: a.update(logp=np.zeros((4, 3, 2), np.float32)), "logp"),
])
def test_a_chunk_off_the_layout_is_rejected_naming_the_array(error, change, names):
    bad = _chunk(DISCRETE, _broken(change))  # valid on its own: only the layout knows it is wrong
    with pytest.raises(error, match=names):
        _decode(bad, DISCRETE)
    assert codec.decode(codec.encode(bad), ExperienceChunk).role == "team"  # no dims declared: no layout check


def test_a_record_off_the_layout_is_rejected():
    rec = _record(DISCRETE)
    rec.arrays["msg_raw"] = np.zeros((3, 2, 4), np.float32)
    with pytest.raises(ShapeError, match="arrays.msg_raw"):
        _decode(rec, DISCRETE)
    rec.arrays["msg_raw"] = np.zeros((3, 2, 3), np.float32)
    rec.arrays["keep"] = np.ones((3, 2), np.float32)
    with pytest.raises(DTypeError, match="arrays.keep"):
        _decode(rec, DISCRETE)


def test_nonfinite_and_oversize_chunks_are_rejected():
    arrays = _chunk_arrays(DISCRETE)
    data = codec.encode(_chunk(DISCRETE, arrays))
    nan = data.replace(arrays["rewards"].tobytes(), np.full_like(arrays["rewards"], np.nan).tobytes(), 1)
    assert nan != data
    with pytest.raises(NonFiniteError, match="rewards"):
        codec.decode(nan, ExperienceChunk, Dims.from_layout(DISCRETE))
    with pytest.raises(SizeError):
        codec.encode(_chunk(DISCRETE, arrays), max_bytes=len(data) - 1)
    with pytest.raises(SizeError):
        codec.decode(data, ExperienceChunk, Dims.from_layout(DISCRETE), max_bytes=len(data) - 1)


def test_the_layout_from_a_config_and_from_dims_agree():
    cfg = RunConfig(env="cn", n_agents=3, num_envs=4, rollout_steps=8, variant="hammer", msg_dim=5)
    spec = EnvSpec(name="cn", n_agents=3, obs_dim=18, discrete=True, action_dim=5, max_steps=25,
                   agent_ids=("a0", "a1", "a2"))
    layout = RolloutLayout.from_config(cfg, spec)
    assert layout == RolloutLayout(8, 4, 3, 18, 5, 5, True)
    assert Dims.from_layout(layout).rollout_layout() == layout
    assert Dims(n_agents=3).rollout_layout() is None
    steps = layout.chunk_steps()
    assert steps["obs"].shape == (8, 4, 3, 18) and steps["prev"].shape == (8, 4, 3, 5)
    assert steps["actions"].shape == (8, 4, 3) and steps["steps"].shape == (8,)
    assert "last_obs" not in steps  # sent beside the per-step arrays, from where the next rollout starts
    buffer = RolloutLayout(8, 4, 3, 18, 5, 5, True, state_dim=54 + 15).allocate(BUFFER)
    assert buffer["state"].shape == (8, 4, 69) and buffer["keep"].dtype == np.float32 and buffer["keep"].all()


def test_a_subscriber_with_dims_counts_a_bad_chunk_and_delivers_the_next():
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    with HammerSession("r1", t, sender="env") as a, HammerSession("r1", TransportConfig.connector(port)) as b:
        sub = b.subscribe(b.keys.exp("team"), ExperienceChunk, Dims.from_layout(DISCRETE))
        time.sleep(0.25)  # let the subscriber declaration reach the publisher's side
        bad = _chunk_arrays(DISCRETE)
        bad["defaulted"] = bad["defaulted"].astype(np.uint8)
        a.publish(a.keys.exp("team"), _chunk(DISCRETE, bad))
        a.publish(a.keys.exp("team"), _chunk(DISCRETE))
        got = sub.get(5.0)
        assert got is not None and got.arrays["defaulted"].dtype == bool
        assert sub.stats.rejected["dtype"] == 1 and sub.stats.delivered == 1
