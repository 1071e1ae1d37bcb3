"""What a newcomer's mistakes get back: one `error:` line naming the field and the fix, exit 2, and
nothing touched on disk. All through the real CLI (CliRunner) and real envs; no process is started."""

import re

from typer.testing import CliRunner

from hammer.cli import app

runner = CliRunner()


def _err(res) -> str:
    return " ".join(res.output.split())


def test_train_resume_of_an_up_run_refuses_before_touching_it(tmp_path):
    from hammer.deploy.launcher import prepare_run_dir
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    run = tmp_path / "up-run"
    prepare_run_dir(merge_config("cn3", overrides=["episodes=10"]), RuntimeSettings(run_id="t"), run)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    res = runner.invoke(app, ["train", "--resume", str(run), "--episodes", "20"])
    assert res.exit_code == 2, res.output
    assert "error:" in res.output and f"hammer up --resume {run}" in _err(res) and "Traceback" not in res.output
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    res = runner.invoke(app, ["train", "--branch", str(run), "--run-dir", str(tmp_path / "b")])
    assert res.exit_code == 2 and "hammer up --resume" in _err(res) and not (tmp_path / "b").exists()


def test_up_config_errors_are_one_line_and_exit_2(tmp_path):
    out = ["--out", str(tmp_path), "--no-dashboard"]
    cases = [
        (["--set", "env=nosuchmod:parallel_env", "--episodes", "1"], "cannot import module 'nosuchmod'"),
        (["--set", "env=pettingzoo.butterfly.pistonball_v6:parallel_env", "--episodes", "1"], "flat Box"),
        (["--set", "env=mpe2.simple_speaker_listener_v4:parallel_env", "--set", "n_agents=2", "--episodes", "1"],
         "env_adapters=[pad,agent_id]"),  # heterogeneous spaces: the adapter that fixes it
        (["--set", "env=pettingzoo.sisl.multiwalker_v9:env", "--episodes", "1"], "not a PettingZoo parallel env"),
        (["--runtime", "max_policy_lagg=1"], "did you mean 'max_policy_lag'?"),
        (["--episodes", "0"], "--episodes 2000"),
        (["--config", str(tmp_path / "missing.yaml")], "--config"),
        ([str(tmp_path / "missing.yaml")], "--config"),
    ]
    for args, expected in cases:
        res = runner.invoke(app, ["up", *args, *out])
        text = _err(res)
        assert res.exit_code == 2, (args, res.output)
        assert expected in text and "error:" in text and "Traceback" not in res.output, (args, res.output)
        assert "https://" not in text  # no pydantic URL
    assert not any(tmp_path.glob("up-*")), "a refused config must not leave a run directory"


def test_both_runners_take_the_config_file_with_dash_dash_config(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("gamma: 2\n")
    for cmd in ("train", "up"):
        res = runner.invoke(app, [cmd, "--config", str(cfg), "--out", str(tmp_path)])
        assert res.exit_code == 2 and "'gamma'" in res.output, (cmd, res.output)


def test_a_mistyped_env_kwarg_lists_the_valid_ones(tmp_path):
    res = runner.invoke(app, ["train", "--set", "env=pettingzoo.sisl.multiwalker_v9:parallel_env",
                              "--set", "env_kwargs.n_walkerz=3", "--out", str(tmp_path)])
    assert res.exit_code == 2, res.output
    text = _err(res)
    assert "n_walkerz" in text and re.search(r"valid fields: .*n_walkers", text), text
    res = runner.invoke(app, ["train", "--set", "env_kwargs.local_ratoi=0.5", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "valid fields" in _err(res) and "local_ratio" in _err(res)


def test_train_seeds_with_a_bad_env_is_one_line_and_writes_nothing(tmp_path):
    res = runner.invoke(app, ["train", "--seeds", "0-1", "--set", "env=nosuchmod:parallel_env", "--out", str(tmp_path)])
    assert res.exit_code == 2, res.output
    text = _err(res)
    assert "error:" in text and "cannot import module 'nosuchmod'" in text and "Traceback" not in res.output
    assert not any(tmp_path.iterdir()), "a refused seed batch must not leave run directories"


def test_train_takes_the_sweeps_variant_spellings(tmp_path):
    """`--variant hammer-backprop` (as `hammer sweep --variants` spells it) trains backprop mode; a
    contradicting --central-mode is one error line and no run directory."""
    import json

    res = runner.invoke(app, ["train", "--preset", "cn3", "--variant", "hammer-backprop", "--episodes", "8",
                              "--quiet", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    (cfg,) = tmp_path.glob("*/config.json")
    c = json.loads(cfg.read_text())
    assert (c["variant"], c["central_mode"]) == ("hammer", "backprop")
    res = runner.invoke(app, ["train", "--preset", "cn3", "--variant", "hammer-rl", "--central-mode", "backprop",
                              "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "drop --central-mode" in _err(res) and not (tmp_path / "x").exists()
