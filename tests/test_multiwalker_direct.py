"""`mw` (multiwalker stepped without PettingZoo's AEC wrappers) is the same env as `mw-pettingzoo`
(the real PettingZoo parallel env), bit for bit: observations, rewards, flags, episode ends and the
unseeded resets that continue each copy's random stream."""

from __future__ import annotations

import numpy as np
import pytest
from hammer.envs.catalog import parallel_env_factory
from hammer.envs.description import EnvDescription
from hammer.envs.multiwalker_direct import DirectMultiwalker
from hammer.envs.registry import make_vec_env
from pettingzoo.sisl import multiwalker_v9

PAPER = {"position_noise": 1e-3, "angle_noise": 1e-3, "forward_reward": 1.0, "terminate_reward": -100.0,
         "fall_reward": -10.0, "terminate_on_fall": True, "remove_on_fall": True, "terrain_length": 200,
         "shared_reward": False}


def _same(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for k, va in a.items():
        assert np.array_equal(np.asarray(va), np.asarray(b[k])), k
        assert np.asarray(va).dtype == np.asarray(b[k]).dtype, k


@pytest.mark.parametrize(("n", "max_cycles", "scale", "seed"), [
    (3, 500, 1.0, 0),  # random torques: walkers fall and the episode ends for all of them
    (3, 40, 0.3, 1),  # gentle torques and a short limit: episodes end at max_cycles
    (5, 60, 1.0, 2),
    (3, 80, 1.6, 3),  # torques outside the box: both clip them
])
def test_direct_step_equals_the_pettingzoo_parallel_env(n, max_cycles, scale, seed):
    ref = multiwalker_v9.parallel_env(n_walkers=n, max_cycles=max_cycles, **PAPER)
    fast = DirectMultiwalker(multiwalker_v9.parallel_env(n_walkers=n, max_cycles=max_cycles, **PAPER))
    rng = np.random.default_rng(seed)
    o1, i1 = ref.reset(seed=seed)
    o2, i2 = fast.reset(seed=seed)
    _same(o1, o2)
    assert i1 == i2
    episodes, limits, steps = 0, 0, 0
    while episodes < 4:
        acts = {a: (scale * rng.uniform(-1, 1, 4)).astype(np.float32) for a in ref.agents}
        r1, r2 = ref.step(acts), fast.step(acts)
        for d1, d2 in zip(r1, r2, strict=True):
            if d1 is r1[4]:
                assert d1 == d2
            else:
                _same(d1, d2)
        for a in r1[1]:
            assert type(r1[1][a]) is type(r2[1][a]), a  # np.float64 both ways
        assert ref.agents == fast.agents
        steps += 1
        if not ref.agents:
            episodes += 1
            limits += ref.unwrapped.env.frames >= max_cycles
            _same(ref.reset()[0], fast.reset()[0])  # unseeded: each continues its own stream
    assert steps > 4 * 10
    if max_cycles == 40:
        assert limits >= 1  # the time limit was exercised
    else:
        assert limits < episodes  # and falls were


def test_vec_env_mw_equals_mw_pettingzoo_and_uses_the_direct_path():
    k, steps = 3, 250
    fast, ref = make_vec_env("mw", 3, k), make_vec_env("mw-pettingzoo", 3, k)
    try:
        assert isinstance(fast.envs[0], DirectMultiwalker) and not isinstance(ref.envs[0], DirectMultiwalker)
        for a, b in zip(fast.reset(5), ref.reset(5), strict=True):
            assert np.array_equal(a, b)
        rng = np.random.default_rng(0)
        done = 0
        for _ in range(steps):
            acts = rng.uniform(-1.5, 1.5, (k, 3, 4)).astype(np.float32)  # out of the box: clipped the same
            s1, s2 = fast.step(acts), ref.step(acts)
            for f in ("obs", "reward", "terminated", "truncated", "active", "next_active", "final_obs", "done"):
                assert np.array_equal(getattr(s1, f), getattr(s2, f)), f
            assert s1.episodes == s2.episodes
            done += int(s1.done.sum())
        assert done >= 3
    finally:
        fast.close()
        ref.close()


def test_direct_path_only_where_exact_and_refuses_what_pettingzoo_refuses():
    factory, _, _ = parallel_env_factory(EnvDescription("mw", 3, {"terminate_on_fall": False}))
    assert not isinstance(factory(), DirectMultiwalker)  # walkers leave one by one: the wrapper's job
    with pytest.raises(ValueError, match="terminate_on_fall"):
        DirectMultiwalker(multiwalker_v9.parallel_env(n_walkers=3, **{**PAPER, "terminate_on_fall": False}))
    with pytest.raises(TypeError, match="multiwalker_v9"):
        from mpe2 import simple_spread_v3

        DirectMultiwalker(simple_spread_v3.parallel_env())
    env = DirectMultiwalker(multiwalker_v9.parallel_env(n_walkers=3, **PAPER))
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    env.reset(seed=0)
    nan = {a: np.full(4, np.nan, np.float32) for a in env.agents}
    with pytest.raises(ValueError, match="nan"):
        env.step(nan)
