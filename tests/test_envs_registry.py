"""`make_vec_env`: every name builds the env it documents, and every mistake gets one clear error."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from hammer.envs.base import VecEnv
from hammer.envs.catalog import _PETTINGZOO, env_descriptions, env_names
from hammer.envs.description import EnvConfigError
from hammer.envs.pettingzoo_vec import EnvSpaceError, PettingZooVecEnv
from hammer.envs.registry import make_vec_env
from pettingzoo.sisl.multiwalker import multiwalker_base


def test_names_and_descriptions():
    assert env_names() == ["cn", "cn-mpe2", "mw", "mw-pettingzoo", "rware"]
    assert set(env_descriptions()) == set(env_names())


def test_mw_defaults_are_real_multiwalker_kwargs_with_the_paper_values():
    params = inspect.signature(multiwalker_base.MultiWalkerEnv.__init__).parameters
    mw = _PETTINGZOO["mw"]
    assert set(mw.defaults) | {mw.n_key} <= set(params)
    v = make_vec_env("mw", 3, 1)
    raw = v.envs[0].unwrapped.env  # the MultiWalkerEnv behind the AEC and parallel wrappers
    assert (raw.n_walkers, raw.max_cycles, raw.terrain_length, raw.local_ratio) == (3, 500, 200, 1)
    assert (raw.forward_reward, raw.fall_reward, raw.terminate_reward) == (1.0, -10.0, -100.0)
    assert raw.terminate_on_fall and raw.remove_on_fall
    assert raw.position_noise == raw.angle_noise == 1e-3


@pytest.mark.parametrize(("name", "n", "obs_dim", "discrete"), [
    ("cn", 3, 18, True), ("cn-mpe2", 3, 18, True), ("cn-mpe2", 5, 30, True), ("mw", 5, 31, False),
])
def test_each_name_builds_a_vec_env(name, n, obs_dim, discrete):
    v = make_vec_env(name, n, 2)
    assert isinstance(v, VecEnv) and v.num_envs == 2
    assert (v.spec.n_agents, v.spec.obs_dim, v.spec.discrete) == (n, obs_dim, discrete)
    obs, active = v.reset(seed=0)
    assert obs.shape == (2, n, obs_dim) and active.all()


def test_kwargs_override_defaults():
    v = make_vec_env("cn-mpe2", 3, 1, env_kwargs={"max_cycles": 10})
    assert v.spec.max_steps == 10
    v.reset(seed=0)
    for _ in range(9):
        assert not v.step(np.zeros((1, 3), dtype=np.int64)).done.any()
    assert v.step(np.zeros((1, 3), dtype=np.int64)).done.all()
    assert make_vec_env("cn", 3, 1, env_kwargs={"max_steps": 10}).spec.max_steps == 10
    assert make_vec_env("cn", 3, 1, env_kwargs={"observe_others": False}).spec.obs_dim == 10


def test_module_factory_any_parallel_env():
    v = make_vec_env("mpe2.simple_spread_v3:parallel_env", 4, 2, env_kwargs={"N": 4})
    assert isinstance(v, PettingZooVecEnv)
    assert (v.spec.n_agents, v.spec.obs_dim, v.spec.max_steps) == (4, 24, 25)


@pytest.mark.parametrize(("call", "exc", "pattern"), [
    (lambda: make_vec_env("nope", 3, 1), EnvConfigError, r"unknown name 'nope'; valid names: cn, cn-mpe2, mw"),
    (lambda: make_vec_env("mw", 3, 1, env_kwargs={"terain_length": 5}), EnvConfigError,
     r"unknown env_kwargs field 'terain_length'; valid fields: .*terrain_length"),
    (lambda: make_vec_env("cn-mpe2", 3, 1, env_kwargs={"bogus": 1}), EnvConfigError,
     r"field 'bogus'; valid fields: .*local_ratio"),
    (lambda: make_vec_env("cn", 3, 1, env_kwargs={"max_cycles": 5}), EnvConfigError,
     r"env 'cn': unknown env_kwargs field 'max_cycles'; valid fields: .*max_steps"),
    (lambda: make_vec_env("cn", 3, 1, env_kwargs={"observe_others": "maybe"}), EnvConfigError,
     r"env 'cn': observe_others must be true or false, got 'maybe'"),
    (lambda: make_vec_env("cn", 3, 1, env_kwargs={"local_ratio": 2}), EnvConfigError,
     r"env 'cn': local_ratio is a proportion in \[0, 1\], got 2"),
    (lambda: make_vec_env("mw", 3, 1, env_kwargs={"n_walkers": 4}), EnvConfigError,
     r"'n_walkers' is set by n_agents"),
    (lambda: make_vec_env("cn-mpe2", 3, 1, env_kwargs={"N": 4}), EnvConfigError, r"'N' is set by n_agents"),
    (lambda: make_vec_env("mw", 0, 1), EnvConfigError, r"n_agents: must be an int >= 1"),
    (lambda: make_vec_env("mw", 3, 0), EnvConfigError, r"num_envs: must be an int >= 1"),
    (lambda: make_vec_env("mw", 3, 2, workers=3), EnvConfigError, r"workers: must be an int in \[0, num_envs=2\]"),
    (lambda: make_vec_env("no_such_mod:parallel_env", 3, 1), EnvConfigError, r"cannot import module 'no_such_mod'"),
    (lambda: make_vec_env("mpe2.simple_spread_v3:nope", 3, 1), EnvConfigError, r"has no attribute 'nope'"),
    (lambda: make_vec_env("mpe2.simple_spread_v3:parallel_env", 5, 1), EnvConfigError,
     r"n_agents=5 but the env has 3 agents"),
    (lambda: make_vec_env("mpe2.simple_spread_v3:parallel_env", 3, 1, env_kwargs={"Nn": 3}), EnvConfigError,
     r"unknown env_kwargs field 'Nn'; valid fields: N, "),
    (lambda: make_vec_env("pettingzoo.sisl.pursuit_v5:parallel_env", 8, 1), EnvSpaceError,
     r"needs a flat Box"),
    (lambda: make_vec_env("mpe2.simple_adversary_v3:parallel_env", 3, 1), EnvSpaceError,
     r"agents must be homogeneous"),
    (lambda: make_vec_env("pettingzoo.sisl.multiwalker_v9:env", 3, 1), EnvSpaceError,
     r"not a PettingZoo parallel env"),
])
def test_errors_name_the_field_and_the_fix(call, exc, pattern):
    with pytest.raises(exc, match=pattern):
        call()


def test_cli_envs_list_shows_dims():
    import typer
    from typer.testing import CliRunner

    from hammer.commands import envs as cli

    app = typer.Typer()
    cli.register(app)
    res = CliRunner().invoke(app, ["envs", "list", "-n", "5"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:6]]
            for line in res.output.splitlines() if line.startswith("│")}
    assert rows["mw"] == ["5", "31", "4 in [-1, 1]", "500"]
    assert rows["cn-mpe2"] == ["5", "30", "5 discrete", "25"]
    assert rows["cn"][:2] == ["5", "30"]


def test_space_errors_are_config_errors_and_max_steps_is_found():
    assert issubclass(EnvSpaceError, EnvConfigError)
    v = make_vec_env("pettingzoo.sisl.multiwalker_v9:parallel_env", 3, 1, env_kwargs={"max_cycles": 77})
    assert v.spec.max_steps == 77
    v = make_vec_env("pettingzoo.sisl.multiwalker_v9:parallel_env", 3, 1)
    assert v.spec.max_steps == 500
