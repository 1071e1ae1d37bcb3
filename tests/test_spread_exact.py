"""VecSimpleSpread is the same environment as mpe2.simple_spread_v3 (discrete actions).

The reference is the real mpe2 parallel env. Equality is checked three ways:
  1. same seeds -> identical initial states and identical auto-reset states (our copy k is seeded
     like `mpe2.reset(seed=seed + k)` and continues the stream like mpe2's unseeded reset()),
  2. mpe2's world state copied into ours mid-episode (and ours into mpe2's) -> same continuation,
  3. step by step over whole episodes: observations, rewards, terminated/truncated flags,
with random actions and with "everyone drives to the same point" actions that force collisions;
the tests assert collisions really happened so they cannot pass vacuously.
"""

from __future__ import annotations

import numpy as np
import pytest
from hammer.envs.spread import VecSimpleSpread, spread_obs_dim
from mpe2 import simple_spread_v3
from scipy import stats

TOL = 1e-5
MAX_CYCLES = 25


def make_mpe(n: int):
    return simple_spread_v3.parallel_env(
        N=n, max_cycles=MAX_CYCLES, local_ratio=0.5, continuous_actions=False
    )


def mpe_state(env) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    world = env.unwrapped.world
    pos = np.array([a.state.p_pos for a in world.agents])
    vel = np.array([a.state.p_vel for a in world.agents])
    lm = np.array([lm.state.p_pos for lm in world.landmarks])
    return pos, vel, lm


def set_mpe_state(env, pos: np.ndarray, vel: np.ndarray, lm: np.ndarray) -> None:
    world = env.unwrapped.world
    for i, a in enumerate(world.agents):
        a.state.p_pos = pos[i].astype(np.float64).copy()
        a.state.p_vel = vel[i].astype(np.float64).copy()
    for i, landmark in enumerate(world.landmarks):
        landmark.state.p_pos = lm[i].astype(np.float64).copy()


def stack(d: dict, n: int) -> np.ndarray:
    return np.stack([np.asarray(d[f"agent_{i}"]) for i in range(n)])


def converge_actions(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Each agent pushes along its larger offset axis towards `target` (causes pile-ups)."""
    off = target[None, :] - pos
    horiz = np.abs(off[:, 0]) >= np.abs(off[:, 1])
    a = np.where(horiz, np.where(off[:, 0] < 0, 1, 2), np.where(off[:, 1] < 0, 3, 4))
    return a.astype(np.int64)


def n_colliding_pairs(pos: np.ndarray) -> int:
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    iu = np.triu_indices(len(pos), 1)
    return int((d[iu] < 0.3).sum())


def run_lockstep(n: int, k_copies: int, seed: int, policy: str, episodes: int = 2) -> dict[str, float]:
    """Step our K copies and K mpe2 envs (seeds seed+k) with the same actions; compare everything."""
    rng = np.random.default_rng(1234 + n)
    ours = VecSimpleSpread(k_copies, n_agents=n)
    obs, active = ours.reset(seed)
    refs = [make_mpe(n) for _ in range(k_copies)]
    ref_obs = [stack(r.reset(seed=seed + k)[0], n) for k, r in enumerate(refs)]
    assert active.all()
    np.testing.assert_array_equal(obs, np.stack(ref_obs))  # same seeds -> bit-identical start
    targets = rng.uniform(-0.5, 0.5, (k_copies, 2))
    worst = {"obs": 0.0, "reward": 0.0, "collisions": 0}
    for ep in range(episodes):
        for t in range(1, MAX_CYCLES + 1):
            if policy == "random":
                actions = rng.integers(0, 5, (k_copies, n))
            else:
                actions = np.stack(
                    [converge_actions(mpe_state(r)[0], targets[k]) for k, r in enumerate(refs)]
                )
            out = ours.step(actions)
            for k, r in enumerate(refs):
                o, rew, term, trunc, _ = r.step({f"agent_{i}": int(actions[k, i]) for i in range(n)})
                o, rew = stack(o, n), stack(rew, n)
                worst["obs"] = max(worst["obs"], float(np.abs(out.final_obs[k] - o).max()))
                worst["reward"] = max(worst["reward"], float(np.abs(out.reward[k] - rew).max()))
                worst["collisions"] += n_colliding_pairs(mpe_state(r)[0])
                np.testing.assert_allclose(out.final_obs[k], o, atol=TOL, rtol=0)
                np.testing.assert_allclose(out.reward[k], rew, atol=TOL, rtol=0)
                np.testing.assert_array_equal(out.terminated[k], stack(term, n))
                np.testing.assert_array_equal(out.truncated[k], stack(trunc, n))
                assert out.done[k] == (t == MAX_CYCLES)
                if t < MAX_CYCLES:
                    np.testing.assert_array_equal(out.obs[k], out.final_obs[k])
                else:
                    assert r.agents == []  # mpe2 removed every agent: the episode is over
                    # our auto-reset continues copy k's stream exactly like mpe2's unseeded reset
                    new = stack(r.reset()[0], n)
                    np.testing.assert_array_equal(out.obs[k], new)
    return worst


@pytest.mark.parametrize("n", [3, 5])
def test_random_actions_match_mpe2(n: int) -> None:
    worst = run_lockstep(n, k_copies=3, seed=10 * n, policy="random")
    assert worst["obs"] <= TOL and worst["reward"] <= TOL


@pytest.mark.parametrize("n", [3, 5])
def test_collisions_match_mpe2(n: int) -> None:
    worst = run_lockstep(n, k_copies=3, seed=100 + n, policy="converge")
    # agents piled up on a common point: many agent-step pairs were in contact
    assert worst["collisions"] >= 20 * n, worst


def test_state_copy_both_directions() -> None:
    """Crowded states with velocities, copied mpe2 -> ours and ours -> mpe2, continue identically."""
    n = 5
    rng = np.random.default_rng(7)
    ours = VecSimpleSpread(2, n_agents=n)
    ours.reset(0)
    ref = make_mpe(n)
    ref.reset(seed=3)
    collisions = 0
    for direction in ("mpe_to_ours", "ours_to_mpe"):
        pos = rng.uniform(-0.2, 0.2, (n, 2))  # everyone overlapping: strong contact forces
        vel = rng.normal(0, 0.5, (n, 2))
        lm = rng.uniform(-1, 1, (n, 2))
        if direction == "mpe_to_ours":
            set_mpe_state(ref, pos, vel, lm)
            got = ours.set_state(1, *mpe_state(ref), t=3)
        else:
            ours.set_state(1, pos, vel, lm, t=3)
            st = ours.get_state(1)
            set_mpe_state(ref, st["agent_pos"], st["agent_vel"], st["landmark_pos"])
            got = ours.get_state(1)
            got = ours.set_state(1, got["agent_pos"], got["agent_vel"], got["landmark_pos"])
        np.testing.assert_array_equal(got, np.stack([ref.unwrapped.observe(f"agent_{i}") for i in range(n)]))
        for _ in range(10):
            actions = rng.integers(0, 5, (2, n))
            out = ours.step(actions)
            o, rew, *_ = ref.step({f"agent_{i}": int(actions[1, i]) for i in range(n)})
            collisions += n_colliding_pairs(mpe_state(ref)[0])
            np.testing.assert_allclose(out.obs[1], stack(o, n), atol=TOL, rtol=0)
            np.testing.assert_allclose(out.reward[1], stack(rew, n), atol=TOL, rtol=0)
            st = ours.get_state(1)
            p, v, _ = mpe_state(ref)
            np.testing.assert_allclose(st["agent_pos"], p, atol=1e-12, rtol=0)
            np.testing.assert_allclose(st["agent_vel"], v, atol=1e-12, rtol=0)
        ref.reset(seed=3)
    assert collisions > 10


def test_initial_state_distribution() -> None:
    """Positions of agents and landmarks ~ U(-1,1)^2 independently, velocities 0 (as mpe2)."""
    k, n = 2000, 3
    env = VecSimpleSpread(k, n_agents=n)
    obs, _ = env.reset(5)
    assert obs.shape == (k, n, spread_obs_dim(n)) and obs.dtype == np.float32
    assert spread_obs_dim(3) == 18 and env.spec.obs_dim == 18
    np.testing.assert_array_equal(env.vel, 0.0)
    for arr in (env.pos, env.landmarks):
        assert arr.min() >= -1.0 and arr.max() < 1.0
        for x in arr.reshape(-1, 2).T:
            assert stats.kstest(x, stats.uniform(loc=-1, scale=2).cdf).pvalue > 1e-3
    # and the same draws as mpe2 for the same seeds (a few copies)
    for c in (0, 1, 999):
        ref = make_mpe(n)
        ref.reset(seed=5 + c)
        pos, _vel, lm = mpe_state(ref)
        np.testing.assert_array_equal(env.pos[c], pos)
        np.testing.assert_array_equal(env.landmarks[c], lm)


def test_auto_reset_final_obs_and_episode_stats() -> None:
    k, n = 4, 3
    env = VecSimpleSpread(k, n_agents=n)
    env.reset(11)
    rng = np.random.default_rng(0)
    paper = np.zeros(k)
    team = np.zeros(k)
    for t in range(1, MAX_CYCLES + 1):
        before = env.get_state(0)
        out = env.step(rng.integers(0, 5, (k, n)))
        paper += out.reward.mean(axis=1)
        team += out.reward.sum(axis=1)
        assert out.active.all() and out.next_active.all()
        assert not out.terminated.any()
        assert before["t"] == t - 1
        if t < MAX_CYCLES:
            assert not out.done.any() and not out.truncated.any() and out.episodes == []
            np.testing.assert_array_equal(out.obs, out.final_obs)
    assert out.done.all() and out.truncated.all()
    # obs is the first observation of the new episode: zero velocity, fresh positions
    np.testing.assert_array_equal(out.obs[:, :, 0:2], 0.0)
    assert np.abs(out.final_obs[:, :, 0:2]).max() > 0  # final obs still has the old velocities
    assert not np.allclose(out.obs, out.final_obs)
    np.testing.assert_array_equal(out.obs, env._refresh(np.arange(k)))
    assert (env.t == 0).all()
    assert sorted(e.env_index for e in out.episodes) == list(range(k))
    for e in out.episodes:
        assert e.length == MAX_CYCLES
        assert e.paper_metric == pytest.approx(paper[e.env_index], rel=1e-6)
        assert e.team_return == pytest.approx(team[e.env_index], rel=1e-6)
    out2 = env.step(np.zeros((k, n), dtype=np.int64))
    assert not out2.done.any()


def test_determinism_and_independent_copies() -> None:
    n, k = 3, 4
    rng = np.random.default_rng(3)
    acts = rng.integers(0, 5, (60, k, n))

    def rollout(seed: int, actions: np.ndarray, num: int) -> np.ndarray:
        env = VecSimpleSpread(num, n_agents=n)
        first, _ = env.reset(seed)
        frames = [first]
        for a in actions:
            out = env.step(a)
            frames += [out.final_obs, out.obs, out.reward[..., None].repeat(2, -1)]
        return np.concatenate([f.reshape(num, -1) for f in frames], axis=1)

    a = rollout(42, acts, k)
    np.testing.assert_array_equal(a, rollout(42, acts, k))  # same seed -> same run
    assert not np.allclose(a, rollout(43, acts, k))  # different seed -> different run
    # copy c of a K-copy env is the same as a single env seeded seed + c (seeding is per copy) ...
    for c in range(k):
        np.testing.assert_array_equal(a[c], rollout(42 + c, acts[:, c : c + 1], 1)[0])
    # ... and other copies' actions have no influence on it
    changed = acts.copy()
    changed[:, 0] = (changed[:, 0] + 1) % 5
    b = rollout(42, changed, k)
    np.testing.assert_array_equal(a[1:], b[1:])
    assert not np.array_equal(a[0], b[0])


def test_spec_and_errors() -> None:
    env = VecSimpleSpread(2, n_agents=5)
    assert env.spec.name == "cn" and env.spec.discrete and env.spec.action_dim == 5
    assert env.spec.agent_ids == tuple(f"agent_{i}" for i in range(5))
    assert env.spec.obs_dim == make_mpe(5).observation_space("agent_0").shape[0] == 30
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 5), dtype=np.int64))
    env.reset(0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((2, 3), dtype=np.int64))
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        env.step(np.full((2, 5), 5))
    with pytest.raises(ValueError, match="agent_pos"):
        env.set_state(0, np.zeros((3, 2)), np.zeros((5, 2)), np.zeros((5, 2)))


def test_observe_others_false_keeps_only_own_state_and_landmarks() -> None:
    """observe_others=False is the same world with a shorter observation: the first 4 + 2N values of
    the full one ([v_i, p_i, landmarks - p_i]); rewards, episode ends and resets are unchanged."""
    k, n = 8, 3
    full, own = VecSimpleSpread(k, n_agents=n), VecSimpleSpread(k, n_agents=n, observe_others=False)
    assert own.spec.obs_dim == spread_obs_dim(n, observe_others=False) == 4 + 2 * n
    obs_full, _ = full.reset(21)
    obs_own, _ = own.reset(21)
    np.testing.assert_array_equal(obs_own, obs_full[..., : 4 + 2 * n])
    rng = np.random.default_rng(1)
    for _ in range(3 * MAX_CYCLES):  # crosses two auto-resets
        actions = rng.integers(0, 5, (k, n))
        a, b = full.step(actions), own.step(actions)
        np.testing.assert_array_equal(b.obs, a.obs[..., : 4 + 2 * n])
        np.testing.assert_array_equal(b.final_obs, a.final_obs[..., : 4 + 2 * n])
        np.testing.assert_array_equal(b.reward, a.reward)
        np.testing.assert_array_equal(b.done, a.done)
    with pytest.raises(TypeError, match="observe_others"):
        VecSimpleSpread(k, n_agents=n, observe_others="no")
