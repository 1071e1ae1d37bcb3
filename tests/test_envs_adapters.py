"""Adapters for PettingZoo envs that do not fit as they are (envs/adapters.py, SuperSuit), on real
installed envs: image observations (pistonball), different spaces per agent (simple_speaker_listener),
Discrete observations (rock-paper-scissors); `hammer envs check`; a module in the current folder."""

import sys

import numpy as np
import pytest
from hammer.envs.description import EnvConfigError
from hammer.envs.registry import make_vec_env
from typer.testing import CliRunner

from hammer.cli import app

PISTONBALL = "pettingzoo.butterfly.pistonball_v6:parallel_env"
SPEAKER = "mpe2.simple_speaker_listener_v4:parallel_env"
RPS = "pettingzoo.classic.rps_v2:parallel_env"


def _random_steps(v, n, seed=0):
    s, rng = v.spec, np.random.default_rng(seed)
    out = []
    for _ in range(n):
        a = (rng.integers(0, s.action_dim, (v.num_envs, s.n_agents)) if s.discrete else
             rng.uniform(s.action_low, s.action_high, (v.num_envs, s.n_agents, s.action_dim)).astype(np.float32))
        out.append(v.step(a))
    return out


def test_image_observations_grey_small_flat_in_unit_range():
    kw = {"n_pistons": 3, "max_cycles": 20}
    with pytest.raises(EnvConfigError, match=r"env_adapters=\[gray,resize:32x32,flatten\]"):
        make_vec_env(PISTONBALL, 3, 1, env_kwargs=kw)
    v = make_vec_env(PISTONBALL, 3, 2, env_kwargs=kw, adapters=["flatten", "resize:16x12", "gray"])  # any order
    try:
        assert v.spec.obs_dim == 16 * 12 and not v.spec.discrete
        obs = v.reset(0)[0].copy()  # the env reuses its observation buffer
        steps = _random_steps(v, 10)
        assert obs.dtype == np.float32 and 0.0 <= obs.min() and obs.max() <= 1.0 and obs.std() > 0
        assert not np.array_equal(steps[-1].obs, obs)  # the pistons' views change as they move
    finally:
        v.close()


def test_heterogeneous_spaces_padded_with_an_agent_id():
    with pytest.raises(EnvConfigError, match=r"env_adapters=\[pad,agent_id\]"):
        make_vec_env(SPEAKER, 2, 1)
    v = make_vec_env(SPEAKER, 2, 3, adapters=["pad", "agent_id"])
    try:
        assert (v.spec.obs_dim, v.spec.action_dim, v.spec.discrete) == (11 + 2, 5, True)
        obs, _ = v.reset(0)
        assert np.array_equal(obs[:, :, -2:], np.broadcast_to(np.eye(2), (3, 2, 2)))  # who is who
        assert not obs[:, 0, 3:11].any()  # the speaker's 3 values padded to the listener's 11
        steps = _random_steps(v, 30)  # includes actions 3-4, beyond the speaker's own 3: taken as action 0
        assert sum(len(s.episodes) for s in steps) == 3  # 25-step episodes of 3 copies
    finally:
        v.close()


def test_discrete_observations_one_hot_and_the_same_in_worker_processes():
    with pytest.raises(EnvConfigError, match=r"env_adapters=\[one_hot\]"):
        make_vec_env(RPS, 2, 1)
    local = make_vec_env(RPS, 2, 2, adapters=["one_hot"])
    sub = make_vec_env(RPS, 2, 2, adapters=["one_hot"], workers=2, parent_slice=False)
    try:
        assert local.spec.obs_dim == 4
        a, _ = local.reset(3)
        b, _ = sub.reset(3)
        assert np.array_equal(a, b) and np.all(a.sum(axis=-1) == 1)
        for x, y in zip(_random_steps(local, 6), _random_steps(sub, 6)):
            assert np.array_equal(x.obs, y.obs) and np.array_equal(x.reward, y.reward)
            assert np.all(x.obs.sum(axis=-1) == 1)
    finally:
        local.close()
        sub.close()


def test_adapter_errors_name_the_valid_ones(tmp_path):
    with pytest.raises(EnvConfigError, match="valid: gray, resize:WxH"):
        make_vec_env(SPEAKER, 2, 1, adapters=["pad", "flaten"])
    with pytest.raises(EnvConfigError, match="env 'cn'"):
        make_vec_env("cn", 3, 1, adapters=["flatten"])
    res = CliRunner().invoke(app, ["train", "--set", f"env={SPEAKER}", "--set", "n_agents=2", "--set",
                                   "env_adapters=[pad,agentid]", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "agent_id" in res.output and not any(tmp_path.iterdir())


def test_envs_check_says_what_an_env_needs_or_why_it_cannot_run():
    runner = CliRunner()
    res = runner.invoke(app, ["envs", "check", SPEAKER, "--seconds", "0.2"])
    text = " ".join(res.output.split())
    assert res.exit_code == 0, res.output
    assert "speaker_0" in text and "Discrete(5)" in text and "needs adapters: pad, agent_id" in text
    assert "env_adapters=[pad,agent_id]" in text and "n_agents=2" in text and "obs dim 13" in text
    res = runner.invoke(app, ["envs", "check", PISTONBALL, "--set", "env_kwargs.n_pistons=3", "--seconds", "0.2"])
    assert res.exit_code == 0 and "gray, resize:32x32, flatten" in res.output and "obs dim 1024" in res.output
    res = runner.invoke(app, ["envs", "check", "pettingzoo.classic.rps_v2:env"])  # the AEC factory
    assert res.exit_code == 1 and "cannot run" in res.output and "parallel_env" in res.output
    res = runner.invoke(app, ["envs", "check", "mw", "--seconds", "0.2"])
    assert res.exit_code == 0 and "needs adapters" not in res.output and "obs dim 31" in res.output


def test_a_module_in_the_current_folder_is_found(tmp_path, monkeypatch):
    (tmp_path / "my_team_env.py").write_text(
        "from mpe2 import simple_spread_v3\n\n\ndef parallel_env(**kw):\n"
        "    return simple_spread_v3.parallel_env(N=2, max_cycles=10, **kw)\n")
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.chdir(tmp_path)
    v = make_vec_env("my_team_env:parallel_env", 2, 1)
    try:
        assert v.spec.n_agents == 2 and v.spec.max_steps == 10
    finally:
        v.close()
        sys.modules.pop("my_team_env", None)
