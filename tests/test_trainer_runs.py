"""The in-process trainer: determinism, exact resume, run-directory files, CLI."""

import csv
import json

import numpy as np
import pytest
from hammer.learning.config import merge_config
from hammer.learning.numpy_policy import NumpyLocalPolicy
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import train
from safetensors.numpy import load_file
from typer.testing import CliRunner

from hammer.cli import app

SMALL = ["num_envs=8", "rollout_steps=25", "epochs=2", "minibatches=2"]


def _rows(path):
    with open(path / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if k != "wall_time"} for r in rows]


def _run(tmp_path, name, sets, resume=False):
    if resume:  # like `hammer train --resume DIR --episodes N`: the stored config, a new budget
        rd, cfg = RunDir.open(tmp_path / name)
        cfg = cfg.model_copy(update={"episodes": int(dict(s.split("=") for s in sets)["episodes"])})
    else:
        cfg = merge_config("cn3", overrides=SMALL + sets)
        rd = RunDir.create(tmp_path / name, cfg)
    return train(cfg, rd, resume=resume, tensorboard=False)


def test_same_seed_same_metrics_and_seed_matters(tmp_path):
    sets = ["variant=hammer", "central_mode=backprop", "episodes=120", "seed=3"]
    _run(tmp_path, "a", sets)
    _run(tmp_path, "b", sets)
    _run(tmp_path, "c", sets[:-1] + ["seed=4"])
    a, b, c = _rows(tmp_path / "a"), _rows(tmp_path / "b"), _rows(tmp_path / "c")
    assert len(a) == 120 and a == b
    assert [r["paper_metric"] for r in a] != [r["paper_metric"] for r in c]
    assert [int(r["episode"]) for r in a] == list(range(1, 121))
    assert int(a[-1]["env_steps"]) == 120 * 25  # 8 synchronous copies, 25-step episodes


def test_resume_continues_the_same_run_exactly(tmp_path):
    sets = ["variant=hammer", "central_mode=rl", "msg_dropout=0.2", "checkpoint_every=3", "seed=1"]
    _run(tmp_path, "full", sets + ["episodes=200"])
    # An interrupted run: stopped at 100 episodes, and its newest checkpoint lost as in a crash mid-write.
    _run(tmp_path, "cut", sets + ["episodes=100"])
    ckpts = sorted((tmp_path / "cut" / "checkpoints").glob("ckpt_*.json"))
    assert [p.stem for p in ckpts] == ["ckpt_0000006", "ckpt_0000009", "ckpt_0000012"]
    ckpts[-1].unlink()
    summary = _run(tmp_path, "cut", ["episodes=200"], resume=True)
    assert summary["episodes"] == 200
    assert _rows(tmp_path / "cut") == _rows(tmp_path / "full")
    fa = load_file(str(tmp_path / "full" / "final" / "central.safetensors"))
    fb = load_file(str(tmp_path / "cut" / "final" / "central.safetensors"))
    assert all(np.array_equal(fa[k], fb[k]) for k in fa)


def test_run_directory_contents(tmp_path):
    _run(tmp_path, "r", ["variant=il", "episodes=48"])
    d = tmp_path / "r"
    cfg = json.loads((d / "config.json").read_text())
    assert cfg["variant"] == "il" and cfg["episodes"] == 48
    summary = json.loads((d / "summary.json").read_text())
    assert summary["episodes"] == 48 and np.isfinite(summary["final_paper_metric_last500"])
    assert summary["n_agents"] == 3 and summary["episode_length"] == 25
    rows = _rows(d)
    assert np.mean([float(r["paper_metric"]) for r in rows]) == pytest.approx(
        summary["final_paper_metric_last500"])
    # team return = N * paper metric when all agents are present
    r0 = rows[0]
    assert float(r0["team_return"]) == pytest.approx(3 * float(r0["paper_metric"]), rel=1e-9)
    policy = NumpyLocalPolicy(load_file(str(d / "final" / "local.safetensors")))
    assert policy.discrete and policy.in_dim == 18  # il: own observation only
    assert not (d / "final" / "central.safetensors").exists()


def test_cli_train_and_one_line_errors(tmp_path):
    runner = CliRunner()
    res = runner.invoke(app, ["train", "--preset", "cn3", "--variant", "random", "--seed", "2", "--episodes", "40",
                              "--out", str(tmp_path), "--quiet", "--set", "num_envs=8", "--set", "rollout_steps=25"])
    assert res.exit_code == 0, res.output
    d = tmp_path / "cn3-random-s2"
    assert len(_rows(d)) == 40 and json.loads((d / "config.json").read_text())["msg_dim"] == 4
    res = runner.invoke(app, ["train", "--preset", "cn3", "--set", "gamma=2", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "'gamma'" in res.output and "fix:" in res.output
    res = runner.invoke(app, ["train", "--preset", "cn3", "--variant", "random", "--seed", "2", "--out",
                              str(tmp_path), "--quiet"])
    assert res.exit_code == 2 and "--resume" in res.output  # refuses to overwrite a run
    res = runner.invoke(app, ["train", "--resume", str(d), "--episodes", "48", "--quiet"])
    assert res.exit_code == 0, res.output
    assert len(_rows(d)) == 48


def test_a_resumed_learner_trains_with_the_configured_learning_rate():
    """The checkpoint restores Adam's moments, but the learning rate comes from the config: a branch
    resumed with another lr (config.json edited) must not silently keep the old one."""
    import torch
    from hammer.envs.registry import make_vec_env
    from hammer.learning.ppo_update import TeamLearner

    cfg = merge_config("cn3", overrides=SMALL + ["variant=hammer", "central_mode=rl"])
    env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs)
    a = TeamLearner(cfg, env.spec)
    for opt in (a.local_opt, a.central_opt):  # give Adam some state to carry over
        opt.optimizer.zero_grad()
        sum(p.sum() for g in opt.optimizer.param_groups for p in g["params"]).backward()
        opt.optimizer.step()
    tensors, meta = a.state_tensors()
    b = TeamLearner(cfg.model_copy(update={"lr_local": 1e-4, "lr_central": 5e-4}), env.spec)
    b.load_state(tensors, meta)
    assert [g["lr"] for g in b.local_opt.optimizer.param_groups] == [1e-4]
    assert [g["lr"] for g in b.central_opt.optimizer.param_groups] == [5e-4]
    state_a, state_b = a.local_opt.optimizer.state_dict()["state"], b.local_opt.optimizer.state_dict()["state"]
    assert state_a.keys() == state_b.keys() and all(
        torch.equal(state_a[k]["exp_avg"], state_b[k]["exp_avg"]) for k in state_a)


def test_branch_continues_a_copy_with_changed_settings(tmp_path):
    """`hammer train --branch RUN --run-dir NEW --set k=v`: an unchanged branch is the run itself
    resumed; a changed one shares everything up to the checkpoint; the original is untouched."""
    sets = ["variant=hammer", "central_mode=rl", "checkpoint_every=3", "seed=1"]
    _run(tmp_path, "full", sets + ["episodes=160"])
    _run(tmp_path, "cut", sets + ["episodes=100"])  # newest checkpoint at 96 episodes
    before = {p.name: p.read_bytes() for p in (tmp_path / "cut").rglob("*") if p.is_file()}
    runner = CliRunner()
    same = runner.invoke(app, ["train", "--branch", str(tmp_path / "cut"), "--run-dir", str(tmp_path / "same"),
                               "--episodes", "160", "--quiet"])
    assert same.exit_code == 0, same.output
    assert _rows(tmp_path / "same") == _rows(tmp_path / "full")
    lr = runner.invoke(app, ["train", "--branch", str(tmp_path / "cut"), "--run-dir", str(tmp_path / "lr"),
                             "--episodes", "160", "--set", "lr_local=0.003", "--quiet"])
    assert lr.exit_code == 0, lr.output
    assert json.loads((tmp_path / "lr" / "config.json").read_text())["lr_local"] == 0.003
    rows_lr, rows_full = _rows(tmp_path / "lr"), _rows(tmp_path / "full")
    assert rows_lr[:96] == rows_full[:96] and rows_lr[96:] != rows_full[96:] and len(rows_lr) == 160
    assert {p.name: p.read_bytes() for p in (tmp_path / "cut").rglob("*") if p.is_file()} == before
    bad = runner.invoke(app, ["train", "--branch", str(tmp_path / "cut"), "--run-dir", str(tmp_path / "bad"),
                              "--set", "msg_dim=2"])
    assert bad.exit_code == 2 and "'msg_dim' cannot change on a branch" in bad.output
    bad = runner.invoke(app, ["train", "--branch", str(tmp_path / "cut")])
    assert bad.exit_code == 2 and "needs --run-dir" in bad.output
    taken = runner.invoke(app, ["train", "--branch", str(tmp_path / "cut"), "--run-dir", str(tmp_path / "lr")])
    assert taken.exit_code == 2 and "already holds a run" in taken.output


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_an_interrupted_hammer_train_says_so_in_one_line_and_how_to_continue(tmp_path, sig):
    """A real `hammer train` process, stopped by Ctrl-C (SIGINT to its process group, as a terminal sends
    it) or SIGTERM once it has a checkpoint; then `--resume` continues it."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.runtime_helpers import ENV

    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "hammer", "train", "--preset", "cn3", "--variant", "il", "--episodes", "100000",
           "--run-dir", str(run), "--quiet", "--set", "num_envs=8", "--set", "rollout_steps=25",
           "--set", "checkpoint_every=1"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                         start_new_session=True)
    deadline = time.monotonic() + 90
    while RunDir(run).latest_checkpoint() is None if run.is_dir() else True:
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.2)
    os.killpg(p.pid, getattr(signal, sig))
    out, err = p.communicate(timeout=60)
    assert p.returncode == {"SIGINT": 130, "SIGTERM": 143}[sig], err
    last = err.strip().splitlines()[-1]
    by = "Ctrl-C" if sig == "SIGINT" else "SIGTERM"
    assert last.startswith(f"interrupted ({by}) after ") and "of 100,000 episodes" in last, err
    assert f"`hammer train --resume {run}` continues from the last checkpoint (ckpt_" in last
    assert "Traceback" not in err and out == ""
    if sig == "SIGINT":
        # the CLI's own path in this process: the stopped process is the one under test
        r = CliRunner().invoke(app, ["train", "--resume", str(run), "--episodes", "16", "--quiet"])
        assert r.exit_code == 0 and (run / "summary.json").is_file(), r.output
