"""Contract tests of `PettingZooVecEnv` on real PettingZoo envs (mpe2 simple_spread, SISL multiwalker).

The reference in each test is the raw PettingZoo parallel env stepped by hand with the same seed
(seed + k) and the same actions, so shapes, masks, auto-reset and the paper metric are checked
against what PettingZoo itself reports, not against numbers written into the test.
"""

from __future__ import annotations

import numpy as np
import pytest
from hammer.envs.registry import make_vec_env
from mpe2 import simple_spread_v3
from pettingzoo.sisl import multiwalker_v9

MW_PAPER = {"position_noise": 1e-3, "angle_noise": 1e-3, "forward_reward": 1.0, "terminate_reward": -100.0,
            "fall_reward": -10.0, "terminate_on_fall": True, "remove_on_fall": True, "terrain_length": 200,
            "shared_reward": False, "max_cycles": 500}


def raw_mw(**over):
    return multiwalker_v9.parallel_env(n_walkers=3, **{**MW_PAPER, **over})


def topple_actions(steps: int, k: int, walker: int = 2) -> np.ndarray:
    """Torques that make one walker fall while the others stand still (seen to topple it in ~80 steps)."""
    a = np.zeros((steps, k, 3, 4), dtype=np.float32)
    a[:, :, walker] = [1.0, -1.0, 1.0, -1.0]
    return a


def raw_reference(make_env, seed: int, actions: np.ndarray, names: tuple[str, ...]):
    """Step one raw parallel env with auto-reset by hand; per step return what the VecEnv must report."""
    env = make_env()
    env.reset(seed=seed)
    out = []
    for a in actions:
        present = list(env.agents)
        act = {n: (int(a[i]) if a.ndim == 1 else a[i]) for i, n in enumerate(names) if n in present}
        o, r, te, tr, _ = env.step(act)
        rec = {"present": present, "obs": o, "rew": r, "term": te, "trunc": tr, "left": list(env.agents)}
        if not env.agents:
            rec["reset_obs"], _ = env.reset()
        out.append(rec)
    return out


def test_cn_mpe2_shapes_truncation_autoreset_and_metric():
    K, N, T = 3, 3, 60
    venv = make_vec_env("cn-mpe2", N, K)
    spec = venv.spec
    assert (spec.n_agents, spec.obs_dim, spec.discrete, spec.action_dim, spec.max_steps) == (3, 18, True, 5, 25)
    obs, active = venv.reset(seed=11)
    assert obs.shape == (K, N, 18) and obs.dtype == np.float32 and active.dtype == bool and active.all()
    acts = np.random.default_rng(0).integers(0, 5, size=(T, K, N))
    refs = [raw_reference(lambda: simple_spread_v3.parallel_env(N=3, max_cycles=25, local_ratio=0.5),
                          11 + k, acts[:, k], spec.agent_ids) for k in range(K)]
    paper = np.zeros(K)
    episodes = []
    for t in range(T):
        s = venv.step(acts[t])
        assert s.obs.shape == (K, N, 18) and s.obs.dtype == np.float32
        assert s.reward.shape == (K, N) and s.reward.dtype == np.float32
        for f in ("terminated", "truncated", "active", "next_active"):
            assert getattr(s, f).shape == (K, N) and getattr(s, f).dtype == bool
        assert s.done.shape == (K,) and s.done.dtype == bool
        for k in range(K):
            ref = refs[k][t]
            rew = np.array([ref["rew"][a] for a in spec.agent_ids], dtype=np.float32)
            np.testing.assert_array_equal(s.reward[k], rew)
            paper[k] += rew.mean()
            end = (t + 1) % 25 == 0
            assert s.done[k] == end
            assert not s.terminated[k].any()
            assert s.truncated[k].all() == end and s.truncated[k].any() == end
            last = np.stack([ref["obs"][a] for a in spec.agent_ids])
            np.testing.assert_array_equal(s.final_obs[k], last)
            if end:
                reset = np.stack([ref["reset_obs"][a] for a in spec.agent_ids])
                np.testing.assert_array_equal(s.obs[k], reset)
                assert not np.array_equal(s.obs[k], s.final_obs[k])
            else:
                np.testing.assert_array_equal(s.obs[k], last)
        episodes += s.episodes
        if s.done.any():
            done_eps = {e.env_index: e for e in s.episodes}
            assert set(done_eps) == set(np.flatnonzero(s.done))
            for k, e in done_eps.items():
                assert e.length == 25
                assert e.paper_metric == pytest.approx(paper[k], rel=1e-5)
                assert e.team_return == pytest.approx(paper[k] * N, rel=1e-5)
                paper[k] = 0.0
    assert len(episodes) == 2 * K


def test_mw_paper_settings_fall_terminates_everyone():
    venv = make_vec_env("mw", 3, 2)
    spec = venv.spec
    assert (spec.obs_dim, spec.discrete, spec.action_dim, spec.max_steps) == (31, False, 4, 500)
    assert (spec.action_low, spec.action_high) == (-1.0, 1.0)
    venv.reset(seed=3)
    acts = topple_actions(150, 2)
    for t in range(150):
        s = venv.step(acts[t])
        if s.done.any():
            break
    else:
        pytest.fail("no walker fell within 150 steps")
    k = int(np.flatnonzero(s.done)[0])
    # terminate_on_fall: one fall ends the episode for all walkers; the env reports it as termination.
    assert s.terminated[k].all() and not s.truncated[k].any()
    assert s.reward[k, 2] < -100.0  # fall_reward -10 plus terminate_reward -100 for the fallen walker
    assert s.next_active[k].all()  # auto-reset brought everyone back
    assert s.episodes and s.episodes[0].length == t + 1


def test_mw_removed_walker_is_masked_padded_and_metric_matches_raw_env():
    K, T, seed = 2, 130, 5
    kw = {"terminate_on_fall": False}
    venv = make_vec_env("mw", 3, K, env_kwargs=kw)
    names = venv.spec.agent_ids
    venv.reset(seed=seed)
    acts = topple_actions(T, K)
    # Actions of absent walkers are ignored: give them garbage (NaN) that must not change anything.
    refs = [raw_reference(lambda: raw_mw(**kw), seed + k, acts[:, k], names) for k in range(K)]
    paper, removed_seen, eps = np.zeros(K), 0, []
    prev_active = np.ones((K, 3), dtype=bool)
    for t in range(T):
        a = acts[t].copy()
        a[~prev_active] = np.nan
        s = venv.step(a)
        np.testing.assert_array_equal(s.active, prev_active)
        for k in range(K):
            ref = refs[k][t]
            present = [names.index(n) for n in ref["present"]]
            assert np.flatnonzero(s.active[k]).tolist() == present
            rew = np.zeros(3, dtype=np.float32)
            for n, r in ref["rew"].items():
                rew[names.index(n)] = r
            np.testing.assert_array_equal(s.reward[k], rew)
            paper[k] += rew[present].mean()
            for i, n in enumerate(names):
                assert s.terminated[k, i] == bool(ref["term"].get(n, False))
                assert s.truncated[k, i] == bool(ref["trunc"].get(n, False))
            if not s.done[k]:
                staying = [names.index(n) for n in ref["left"]]
                assert np.flatnonzero(s.next_active[k]).tolist() == staying
                for i in set(present) - set(staying):  # left at this step
                    removed_seen += 1
                    assert s.terminated[k, i]
                    assert not s.obs[k, i].any()  # padded with zeros from now on
                    np.testing.assert_array_equal(s.final_obs[k, i], ref["obs"][names[i]])
                for i in range(3):
                    if not s.next_active[k, i]:
                        assert not s.obs[k, i].any() and (i in present or s.reward[k, i] == 0)
        for e in s.episodes:
            assert e.paper_metric == pytest.approx(paper[e.env_index], rel=1e-5, abs=1e-6)
            paper[e.env_index] = 0.0
        eps += s.episodes
        prev_active = s.next_active
    assert removed_seen >= K, "expected the toppled walker to be removed mid-episode in every copy"
    assert eps, "expected at least one finished episode to check the metric on"


def test_continuous_actions_are_clipped_to_the_box():
    a = make_vec_env("mw", 3, 2)
    b = make_vec_env("mw", 3, 2)
    a.reset(seed=1)
    b.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(20):
        act = rng.uniform(-1, 1, (2, 3, 4)).astype(np.float32)
        big = act * 5.0
        sa, sb = a.step(np.clip(big, -1, 1)), b.step(big)
        np.testing.assert_array_equal(sa.obs, sb.obs)
        np.testing.assert_array_equal(sa.reward, sb.reward)


def test_determinism_by_seed_and_independent_copies():
    K, T = 3, 40
    acts = np.random.default_rng(2).integers(0, 5, size=(T, K, 3))

    def run(seed, actions, k=K):
        v = make_vec_env("cn-mpe2", 3, k)
        out = [v.reset(seed=seed)[0]]
        out += [v.step(a).obs for a in actions]
        return np.stack(out)

    base = run(7, acts)
    np.testing.assert_array_equal(base, run(7, acts))
    assert not np.array_equal(base, run(8, acts))
    # Copy k is seeded with seed + k and is independent of the other copies' actions.
    for k in range(K):
        alone = run(7 + k, acts[:, k:k + 1], k=1)
        np.testing.assert_array_equal(base[:, k], alone[:, 0])
    other = acts.copy()
    other[:, 1] = (other[:, 1] + 1) % 5
    changed = run(7, other)
    np.testing.assert_array_equal(base[:, 0], changed[:, 0])
    np.testing.assert_array_equal(base[:, 2], changed[:, 2])
    assert not np.array_equal(base[:, 1], changed[:, 1])


def test_later_resets_continue_each_copys_stream():
    v = make_vec_env("cn-mpe2", 3, 2)
    first, _ = v.reset(seed=0)
    acts = np.zeros((2, 3), dtype=np.int64)
    for _ in range(24):
        v.step(acts)
    s = v.step(acts)
    assert s.done.all()
    # An unseeded reset continues the stream: not a repeat of the first episode's start.
    assert not np.array_equal(s.obs, first)
    env = simple_spread_v3.parallel_env(N=3, max_cycles=25, local_ratio=0.5)
    env.reset(seed=1)
    for _ in range(25):
        env.step(dict.fromkeys(env.agents, 0))
    o, _ = env.reset()
    np.testing.assert_array_equal(s.obs[1], np.stack([o[a] for a in v.spec.agent_ids]))


def test_step_before_reset_and_wrong_action_shape_are_clear_errors():
    v = make_vec_env("cn-mpe2", 3, 2)
    with pytest.raises(RuntimeError, match="reset"):
        v.step(np.zeros((2, 3), dtype=np.int64))
    v.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(K, N\)"):
        v.step(np.zeros((2, 4), dtype=np.int64))


def test_multiwalker_time_limit_is_a_truncation_not_a_termination():
    """multiwalker marks its max_cycles limit as a termination; the wrapper turns it into a
    truncation so learners bootstrap there (a fall before the limit stays a termination)."""
    from hammer.envs.registry import make_vec_env

    env = make_vec_env("mw", 3, 1, env_kwargs={"max_cycles": 8, "terminate_on_fall": False})
    env.reset(0)
    zero = np.zeros((1, 3, 4), np.float32)
    for t in range(8):
        st = env.step(zero)
    assert st.done[0] and st.truncated[0].all() and not st.terminated[0].any()
    env.close()
