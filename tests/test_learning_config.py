"""Config: strict fields, one-line errors naming the field, merge order, presets."""

import pytest
from hammer.learning.config import ConfigError, RunConfig, config_changes, merge_config
from hammer.learning.presets import PRESETS


@pytest.mark.parametrize(("overrides", "field"), [
    (["gama=0.9"], "gama"),
    (["gamma=1.5"], "gamma"),
    (["variant=foo"], "variant"),
    (["central_mode=dial"], "central_mode"),
    (["msg_dropout=2"], "msg_dropout"),
    (["num_envs=0"], "num_envs"),
    (["actor_hidden=[]"], "actor_hidden"),
    (["variant=hammer", "msg_dim=0"], "msg_dim"),
    (["lr_local=fast"], "lr_local"),
])
def test_errors_name_the_field_and_a_fix(overrides, field):
    with pytest.raises(ConfigError) as e:
        merge_config("cn3", overrides=overrides)
    msg = str(e.value)
    assert f"'{field}'" in msg and "fix:" in msg and "\n" not in msg


def test_unknown_field_suggests_the_close_one():
    with pytest.raises(ConfigError, match="did you mean 'gamma'"):
        merge_config(overrides=["gama=0.9"])


def test_merge_order_preset_file_flags_overrides(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("gamma: 0.9\nmsg_dim: 6\nseed: 3\nenv_kwargs: {local_ratio: 0.25}\n")
    cfg = merge_config("cn5", f, ["seed=7", "env_kwargs.max_steps=30"], {"msg_dim": 2, "variant": None})
    assert (cfg.gamma, cfg.msg_dim, cfg.seed, cfg.n_agents) == (0.9, 2, 7, 5)
    assert cfg.env_kwargs == {"local_ratio": 0.25, "max_steps": 30}
    assert cfg.variant == "hammer"  # None flags do not override


def test_a_yaml_mapping_merges_into_the_presets_mapping(tmp_path):
    """`env_kwargs: {n_walkers: 3}` in a --config file over mw3 keeps the preset's other env_kwargs,
    exactly as `--set env_kwargs.n_walkers=3` does (it used to replace them all)."""
    f = tmp_path / "c.yaml"
    f.write_text("env_kwargs: {n_walkers: 3}\n")
    preset = merge_config("mw3").env_kwargs
    from_file, from_set = merge_config("mw3", f).env_kwargs, merge_config("mw3", overrides=["env_kwargs.n_walkers=3"]).env_kwargs
    assert len(preset) > 1 and from_file == from_set == {**preset, "n_walkers": 3}


def test_bad_yaml_file_names_the_file(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="c.yaml"):
        merge_config(file=f)
    with pytest.raises(ConfigError, match="preset 'cn7'"):
        merge_config("cn7")


def test_presets_carry_the_paper_settings():
    expected = {"cn3": (3, 4, 30_000), "cn5": (5, 8, 30_000), "mw3": (3, 8, 10_000), "mw5": (5, 10, 10_000)}
    for name, (n, m, budget) in expected.items():
        cfg = merge_config(name)
        assert (cfg.n_agents, cfg.msg_dim, cfg.episodes, cfg.gamma, cfg.clip) == (n, m, budget, 0.95, 0.2)
        assert cfg.lr_central == 3e-4
    rware = {"rware-tiny-2ag": 2, "rware-tiny-4ag": 4}  # docs/results/plan-warehouse.md: B = 5M env steps
    for name, n in rware.items():
        cfg = merge_config(name)
        assert (cfg.env, cfg.env_kwargs, cfg.n_agents, cfg.episodes, cfg.gamma) == ("rware", {"size": "tiny", "impl": "numpy"}, n,
                                                                                  10_000, 0.99)
        assert cfg.rollout_steps * cfg.checkpoint_every % 500 == 0  # env reseeds fall on episode ends
    assert set(PRESETS) == set(expected) | set(rware)
    assert RunConfig().use_prev_actions and RunConfig().msg_dropout == 0.0
    assert merge_config("cn3", overrides=["variant=il"]).effective_msg_dim == 0


def test_config_changes_names_every_differing_field_including_nested_ones():
    ref = merge_config(preset="mw3").model_dump(mode="json")
    ours = merge_config(preset="mw3", overrides=["lr_local=1e-4", "seed=3", "env_kwargs.forward_reward=2.0",
                                                  "env_kwargs.extra_flag=true"]).model_dump(mode="json")
    assert config_changes(ours, ref) == {"env_kwargs.extra_flag": True, "env_kwargs.forward_reward": 2.0,
                                         "lr_local": 1e-4, "seed": 3}
    assert config_changes(ours, ref, ignore={"seed"}) == {"env_kwargs.extra_flag": True,
                                                          "env_kwargs.forward_reward": 2.0, "lr_local": 1e-4}
    # A nested key only the reference has is a change too (ours: None); equal configs have none.
    assert config_changes(ref, ours, ignore={"seed", "lr_local"}) == {"env_kwargs.extra_flag": None,
                                                                       "env_kwargs.forward_reward": ref["env_kwargs"]["forward_reward"]}
    assert config_changes(ref, dict(ref)) == {}
    # A top-level field the reference lacks (renamed since ours was written) is not compared.
    assert config_changes({**ref, "old_field": 1}, ref) == {}


def test_invalid_yaml_is_reported_with_its_line_and_column(tmp_path):
    import subprocess
    import sys

    from tests.runtime_helpers import ENV

    bad = tmp_path / "my.yaml"
    bad.write_text("episodes: 10\nseed: 2\n  variant: il\n")
    for command in (["train", "--config", str(bad)], ["up", "--config", str(bad)], ["up", "--faults", str(bad)]):
        r = subprocess.run([sys.executable, "-m", "hammer", *command, "--run-dir", str(tmp_path / "run")],
                           capture_output=True, text=True, env=ENV, timeout=60, check=False)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, (command, r.stderr)
        assert str(bad) in r.stderr and "line 3, column 10: invalid YAML (mapping values are not allowed here)" \
            in r.stderr, r.stderr
        assert not (tmp_path / "run").exists()


def test_a_warehouse_run_on_either_implementation_is_the_same_run():
    # The numpy warehouse is exact to rware, so a sweep must not restart an archived plain-rware
    # run (written before `impl` existed, or with impl=rware) as "config differs".
    numpy_cfg = merge_config(preset="rware-tiny-2ag").model_dump(mode="json")
    assert numpy_cfg["env_kwargs"]["impl"] == "numpy"
    plain = {**numpy_cfg, "env_kwargs": {**numpy_cfg["env_kwargs"], "impl": "rware"}}
    older = {**numpy_cfg, "env_kwargs": {k: v for k, v in numpy_cfg["env_kwargs"].items() if k != "impl"}}
    assert config_changes(numpy_cfg, plain) == {} and config_changes(older, numpy_cfg) == {}
    # anything else in env_kwargs still counts
    other = {**plain, "env_kwargs": {**plain["env_kwargs"], "max_steps": 1}}
    assert config_changes(numpy_cfg, other) == {"env_kwargs.max_steps": numpy_cfg["env_kwargs"].get("max_steps")}
