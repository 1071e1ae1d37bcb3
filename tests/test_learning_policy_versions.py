"""Actors load exactly the policy version a step asks for, even when newer weights are already in."""

from hammer.learning.policy_versions import WeightsInbox


def test_inbox_loads_the_newest_version_not_above_the_need():
    loaded = []
    inbox = WeightsInbox(lambda blob, v: loaded.append((blob, v)))
    inbox.offer(0, b"w0")
    inbox.offer(1, b"w1")  # the learner is one version ahead of the rollout
    assert inbox.select(0) and loaded == [(b"w0", 0)] and inbox.version == 0
    assert not inbox.select(0)  # nothing newer allowed yet: version 1 stays held
    assert 1 in inbox.held
    inbox.offer(0, b"again")  # a re-published old version is ignored
    inbox.offer(2, b"w2")
    assert inbox.select(2) and loaded[-1] == (b"w2", 2) and inbox.held == {}
    assert inbox.select(None) is False


def test_inbox_without_a_need_takes_the_newest_and_caps_what_it_holds():
    loaded = []
    inbox = WeightsInbox(lambda blob, v: loaded.append(v), keep=2)
    for v in range(5):
        inbox.offer(v, b"x")
    assert sorted(inbox.held) == [3, 4]
    assert inbox.select(None) and loaded == [4]


def test_learner_evaluates_lagged_experience_with_the_behaviour_version():
    """The learner's correction for a policy lag: inside acting_as(v) the networks are exactly
    version v's (log-probs and values as when it acted); afterwards the current ones are back."""
    import numpy as np
    import pytest
    import torch
    from hammer.envs.registry import make_vec_env
    from hammer.learner.remote_rollout import BehaviourSnapshots
    from hammer.learning.config import merge_config
    from hammer.learning.ppo_update import TeamLearner

    cfg = merge_config("cn3", overrides=["num_envs=4", "variant=hammer"])
    env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs)
    team = TeamLearner(cfg, env.spec).team
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(4, 3, env.spec.obs_dim)).astype(np.float32)
    msg = rng.normal(size=(4, 3, team.msg_dim)).astype(np.float32)
    act = rng.integers(0, env.spec.action_dim, (4, 3))
    snaps = BehaviourSnapshots(team, max_lag=1)
    snaps.keep(0)
    v0 = team.local_evaluate(obs, msg, act)
    state = torch.from_numpy(rng.normal(size=(4, team.state_dim)).astype(np.float32))
    with torch.no_grad():
        c0 = team.central.message_mean(state)
    with torch.no_grad():  # "an update": version 1
        for p in [*team.local.parameters(), *team.central.parameters()]:
            p.add_(0.05)
    snaps.keep(1)
    v1 = team.local_evaluate(obs, msg, act)
    assert not np.allclose(v0[0], v1[0])
    with snaps.acting_as(0, current=1):
        np.testing.assert_array_equal(team.local_evaluate(obs, msg, act)[0], v0[0])
        np.testing.assert_array_equal(team.local_evaluate(obs, msg, act)[1], v0[1])
        with torch.no_grad():
            torch.testing.assert_close(team.central.message_mean(state), c0, rtol=0, atol=0)
    np.testing.assert_array_equal(team.local_evaluate(obs, msg, act)[0], v1[0])
    snaps.keep(2)  # lag 1: version 0 is forgotten
    with pytest.raises(KeyError, match="version 0"), snaps.acting_as(0, current=2):
        pass
    env.close()
