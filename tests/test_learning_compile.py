"""`compile=true` runs the same PPO update as eager, to float rounding.

The compiled update is one graph per minibatch step (losses, `torch.func.grad`, clip, Adam; or,
with compile_scope=epoch, one per epoch holding all of its minibatch steps), so
the checks are on what an update leaves behind: the logged statistics, the parameters and the
Adam state after several optimiser steps, on the same rollout buffer from the same initial weights.
"""

import numpy as np
import pytest
import torch
from hammer.envs.registry import make_vec_env
from hammer.learning.config import merge_config
from hammer.learning.ppo_update import TeamLearner

from tests.runtime_helpers import COMPILE_NETS


def _fill(learner: TeamLearner, rng: np.random.Generator, spec) -> tuple[np.ndarray, np.ndarray]:
    """A rollout buffer of random but well-formed experience (episodes end at the last step)."""
    buf, team = learner.buf, learner.team
    t, k, n = buf.t, buf.k, buf.n
    buf.obs[:] = rng.normal(size=buf.obs.shape)
    buf.state[:] = rng.normal(size=buf.state.shape)
    buf.msg[:] = rng.uniform(-1, 1, size=buf.msg.shape)
    buf.msg_raw[:] = buf.msg + 0.5 * rng.normal(size=buf.msg.shape)
    buf.actions[:] = rng.integers(0, spec.action_dim, size=buf.actions.shape)
    buf.logp[:] = np.log(rng.uniform(0.1, 0.4, size=(t, k, n)))
    buf.c_logp[:] = rng.normal(-3.0, 0.5, size=(t, k, n))
    buf.values[:] = rng.normal(size=(t, k, n))
    buf.c_values[:] = rng.normal(size=(t, k, n))
    buf.rewards[:] = rng.normal(-1.0, 1.0, size=(t, k, n))
    buf.terminated[:] = False
    buf.truncated[:] = False
    buf.truncated[-1] = True
    buf.reset[:] = False
    buf.reset[-1] = True
    buf.final_values[:] = rng.normal(size=(t, k, n))
    buf.c_final_values[:] = rng.normal(size=(t, k, n))
    buf.active[:] = True
    buf.keep[:] = 1.0
    obs = rng.normal(size=(k, n, spec.obs_dim)).astype(np.float32)
    return obs, team.zero_prev_actions(k)


def _copy_buffer(dst: TeamLearner, src: TeamLearner) -> None:
    for name, value in vars(src.buf).items():
        if isinstance(value, np.ndarray):
            getattr(dst.buf, name)[...] = value


def _tensors(learner: TeamLearner) -> dict[str, torch.Tensor]:
    return learner.state_tensors()[0]


def _assert_same_update(eager: TeamLearner, compiled: TeamLearner, obs, prev, updates: range) -> None:
    for u in updates:
        s_eager, s_comp = eager.learn(obs, prev, u), compiled.learn(obs, prev, u)
        assert list(s_comp) == list(s_eager)
        for key in s_eager:
            assert s_comp[key] == pytest.approx(s_eager[key], rel=1e-4, abs=1e-5), key
    t_eager, t_comp = _tensors(eager), _tensors(compiled)
    assert sorted(t_comp) == sorted(t_eager)  # the same parameters and Adam state entries
    for name, value in t_eager.items():
        torch.testing.assert_close(t_comp[name], value, rtol=1e-4, atol=1e-5, msg=name)


@pytest.mark.parametrize("overrides", [
    ["variant=hammer", "central_mode=rl", "epochs=2"],
    ["variant=hammer", "central_mode=backprop", "epochs=1"],
    ["variant=il", "epochs=1"],
    # compile_scope=epoch: a whole epoch (shuffle + every minibatch step) as one graph. Once: the
    # epoch graph runs the step body of its mode on each slice, and each mode's step body the step
    # cases above check.
    ["variant=hammer", "central_mode=rl", "epochs=2", "compile_scope=epoch"],
])
def test_compiled_update_matches_eager(overrides):
    # 4 copies x 25 steps, 2 minibatches: tests/test_device.py's compiled run has these shapes, so
    # in one session its update graph comes from inductor's cache instead of another C++ build.
    cfg = merge_config("cn3", overrides=["num_envs=4", "rollout_steps=25", "minibatches=2", *COMPILE_NETS, *overrides])
    env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs)
    eager = TeamLearner(cfg, env.spec)
    compiled = TeamLearner(cfg.model_copy(update={"compile": True}), env.spec)  # same seed: same weights
    obs, prev = _fill(eager, np.random.default_rng(0), env.spec)
    _copy_buffer(compiled, eager)
    before = {k: v.clone() for k, v in _tensors(compiled).items()}
    _assert_same_update(eager, compiled, obs, prev, range(3))
    moved = [k for k, v in _tensors(compiled).items() if k in before and not torch.equal(v, before[k])]
    assert any(k.startswith("local/") for k in moved)
    if cfg.variant == "hammer":
        assert any(k.startswith("central/") for k in moved)
    if cfg.central_mode == "rl" and cfg.variant == "hammer" and cfg.compile_scope == "step":
        # Absent agents and dropped messages: the masked losses (another graph) match too. Checked
        # on the step graph only: an epoch graph runs that same step body on each slice, and what
        # the epoch adds (the shuffle, the steps in order) the unmasked epoch case checks.
        rng = np.random.default_rng(1)
        eager.buf.active[:] = rng.random(eager.buf.active.shape) > 0.2
        eager.buf.keep[:] = rng.random(eager.buf.keep.shape) > 0.2
        _copy_buffer(compiled, eager)
        _assert_same_update(eager, compiled, obs, prev, range(3, 5))
    env.close()


def test_compiled_update_resumes_from_a_checkpoint_exactly():
    """A compiled learner restored from another's state continues bit-identically (the compiled
    step reads the Adam state the optimiser holds, also after `load_state` replaced it)."""
    cfg = merge_config("cn3", overrides=["num_envs=4", "rollout_steps=25", "minibatches=2", "epochs=1", *COMPILE_NETS,
                                         "variant=hammer", "central_mode=rl", "compile=true"])
    env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs)
    first = TeamLearner(cfg, env.spec)
    obs, prev = _fill(first, np.random.default_rng(2), env.spec)
    first.learn(obs, prev, 0)
    tensors, meta = first.state_tensors()
    second = TeamLearner(cfg, env.spec)
    second.load_state({k: v.clone() for k, v in tensors.items()}, meta)
    _copy_buffer(second, first)
    assert first.learn(obs, prev, 1) == second.learn(obs, prev, 1)
    t1, t2 = _tensors(first), _tensors(second)
    for name, value in t1.items():
        assert torch.equal(t2[name], value), name
    env.close()
