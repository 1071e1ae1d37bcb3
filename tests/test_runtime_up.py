"""`hammer up` end to end: real processes, real Zenoh on 127.0.0.1, real env and torch."""

from __future__ import annotations

import csv
import json
import os
import signal
from pathlib import Path

import psutil
import pytest
import torch
from hammer.deploy.launcher import launch
from hammer.experiments.train_stats import load_train_stats
from hammer.learning.config import merge_config
from hammer.runtime.settings import RuntimeSettings

from tests.runtime_helpers import (
    CN3_RL,
    CN3_RL_100,
    CN3_SET_VIEW,
    UP_CN3_BACKPROP,
    UP_CN3_SET_VIEW,
    hammer,
    pipelined_run,
    processes_mentioning,
    trained_run,
    up_cn3,
    up_run,
)


def _metric_column(run_dir: Path) -> list[float]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [float(r["paper_metric"]) for r in csv.DictReader(f)]






def test_short_up_run_completes_writes_metrics_and_leaves_no_process(tmp_path):
    """The session's one `hammer up` CLI run of cn3 (up_run, the reference of the trainer comparison
    below and of test_local_pool; up_run checks that no process of it outlives the CLI)."""
    run = up_run(tmp_path / "up", UP_CN3_BACKPROP)
    assert "done: 100 episodes" in (run / "up.out").read_text()  # the verdict is on stdout
    assert len(_metric_column(run)) == 100
    summary = json.loads((run / "summary.json").read_text())
    assert summary["episodes"] == 100 and summary["completed"]
    for role in ("env", "central", "learner", "local-0", "local-1", "local-2"):
        assert (run / "logs" / f"{role}.log").is_file()
    # Nothing lost or counted twice: the learner trained on every agent-step of every full rollout.
    learner = json.loads((run / "learner_summary.json").read_text())
    cfg = json.loads((run / "config.json").read_text())
    per_update = cfg["rollout_steps"] * cfg["num_envs"] * cfg["n_agents"]
    assert learner["updates"] == summary["updates"] >= 2
    assert learner["samples"] == learner["updates"] * per_update
    assert learner["stale_chunks"] == learner["bad_chunks"] == 0
    links = summary["links"]
    assert links["default_actions"] == 0 and links["off_policy_actions"] == 0
    assert (run / "final" / "local.safetensors").is_file()
    # its learner logs per update, not per env step: `hammer diagnose` says so instead of a wrong axis
    with pytest.raises(ValueError, match="hammer up"):
        load_train_stats(run)


@pytest.mark.parametrize("mode", ["backprop", "rl"])
def test_up_reproduces_the_in_process_trainer(tmp_path, mode):
    """Same config and seed, no faults: the distributed run's episode returns equal hammer train's
    over the first updates (100 episodes = 3 PPO updates of 32 episodes + the start of a 4th). The
    reference is the trainer run in process, as the CLI runs it (the session's cached team: the rl
    one is the reference of other tests too)."""
    # Generous deadlines: this test is about equality without faults, so a loaded CI machine must
    # not turn a slow message into a fallback (that case is tested in test_faults_runtime.py). The
    # backprop run is also test_local_pool's reference: the session runs it once.
    up = up_run(tmp_path / "up", up_cn3(mode))
    tr = trained_run(tmp_path / "train", tuple(o.replace("=rl", f"={mode}") for o in CN3_RL_100), tensorboard=True)
    summary = json.loads((up / "summary.json").read_text())
    links = summary["links"]
    assert links["msg_fallback_copies"] == 0 and links["default_actions"] == 0
    # an undisturbed run says so: nothing rejected, not degraded (test_runtime_stall's attacked runs are)
    assert summary["completed"] and summary["degraded"] is False and summary["rejected"] == {}
    a, b = _metric_column(up), _metric_column(tr)
    assert len(a) == len(b) == 100
    assert a == pytest.approx(b, abs=1e-5)
    assert len(set(a)) > 50  # real, varied episodes, not a constant
    # TensorBoard: the same tags on the same env-step axis, the same reward curve
    tb_up, tb_tr = _tensorboard(up), _tensorboard(tr)
    assert set(tb_up) == set(tb_tr), set(tb_up) ^ set(tb_tr)
    assert "episode/paper_metric_100" in tb_up and "perf/env_steps_per_s" in tb_up
    assert [s for s, _ in tb_up["episode/paper_metric_100"]] == [s for s, _ in tb_tr["episode/paper_metric_100"]]
    assert [s for s, _ in tb_up["train/local/policy_loss"]] == [800, 1600, 2400]  # K=32 x T=25 env steps per update
    assert [v for _, v in tb_up["episode/paper_metric_100"]] == pytest.approx(
        [v for _, v in tb_tr["episode/paper_metric_100"]], abs=1e-4)
    # every role's log says how it started and why it stopped
    for log in sorted((up / "logs").glob("*.log")):
        text = log.read_text()
        assert " started: " in text and " stopped: " in text, (log.name, text[-500:])


def test_up_reproduces_the_in_process_trainer_with_the_set_central_net(tmp_path):
    """central_net=set through every role: the central server runs the numpy twin of the set net on
    the weights the learner publishes (two updates), and the episodes equal hammer train's. The run
    is the session's UP_CN3_SET_VIEW (also test_local_view's: its local view touches only the local
    agents' inputs)."""
    up = up_run(tmp_path / "up", UP_CN3_SET_VIEW)
    tr = trained_run(tmp_path / "train", (*CN3_SET_VIEW, "episodes=70"))
    assert json.loads((up / "config.json").read_text())["central_net"] == "set"
    links = json.loads((up / "summary.json").read_text())["links"]
    assert links["msg_fallback_copies"] == 0 and links["default_actions"] == 0
    a, b = _metric_column(up), _metric_column(tr)
    assert len(a) == len(b) == 70 and len(set(a)) > 40
    assert a == pytest.approx(b, abs=1e-5)
    assert json.loads((up / "learner_summary.json").read_text())["updates"] >= 2


def test_up_reproduces_the_in_process_trainer_in_bf16(tmp_path, monkeypatch):
    """precision=bf16: the learner's update runs under bfloat16 autocast as the trainer's does (one
    `TeamLearner.losses`), acting stays float32 in both, so the episodes are equal; over 100
    episodes they are not the float32 run's (bf16's first update changes an action by episode ~80;
    the float32 run is the rl reference of test_up_reproduces_the_in_process_trainer)."""
    from hammer.learning.precision import EMULATED_ENV, bf16_unsupported

    env = {EMULATED_ENV: "1"} if bf16_unsupported(torch.device("cpu")) else {}
    for k, v in env.items():
        monkeypatch.setenv(k, v)  # the in-process trainer reads it as the CLI would
    up = tmp_path / "up"
    r1 = hammer("up", "--episodes", "100", "--central-mode", "rl", "--set", "precision=bf16", "--run-dir", str(up),
                "--no-dashboard", "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000", env=env)
    assert r1.returncode == 0, r1.stderr[-2000:]
    tr = trained_run(tmp_path / "train", (*CN3_RL, "precision=bf16", "episodes=100"))
    fp32 = trained_run(tmp_path / "fp32", CN3_RL_100, tensorboard=True)
    assert json.loads((up / "config.json").read_text())["precision"] == "bf16"
    a, b, c = _metric_column(up), _metric_column(tr), _metric_column(fp32)
    assert len(a) == len(b) == len(c) == 100 and len(set(a)) > 80
    assert a == pytest.approx(b, abs=1e-5)
    assert a != pytest.approx(c, abs=1e-5)


def test_up_reproduces_the_trainer_with_simulated_absences(tmp_path):
    """missing_prob: in training the central agent sees robots go missing (a fleet's missing rule:
    zeros) for windows of steps. `hammer up`'s central server and learner derive who is missing
    from the step number as the trainer does, so the episodes are equal; they differ from a run
    without absences (the central agent's inputs did change)."""
    up = tmp_path / "up"
    absences = ["--set", "missing_prob=0.3", "--set", "missing_window=5"]
    r1 = hammer("up", "--episodes", "70", "--central-mode", "rl", *absences, "--run-dir", str(up), "--no-dashboard",
                "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000")
    assert r1.returncode == 0, r1.stderr[-2000:]
    tr = trained_run(tmp_path / "train", (*CN3_RL, *absences[1::2], "episodes=70"))
    plain = trained_run(tmp_path / "plain", CN3_RL_100, tensorboard=True)  # its first 70 episodes
    links = json.loads((up / "summary.json").read_text())["links"]
    assert links["msg_fallback_copies"] == 0 and links["default_actions"] == 0
    a, b, c = _metric_column(up), _metric_column(tr), _metric_column(plain)[:70]
    assert len(a) == len(b) == len(c) == 70 and len(set(a)) > 40
    assert a == pytest.approx(b, abs=1e-5)
    assert a != pytest.approx(c, abs=1e-5)


def _tensorboard(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_multiwalker_runs_distributed_like_the_trainer(tmp_path):
    """mw3 (continuous torques, walkers removed when they fall, episodes of varying length) through
    every role: the episodes of the first rollout equal hammer train's. Box2D is chaotic, so the
    ~1e-7 difference between the agents' numpy forward and the trainer's torch forward grows to
    ~1e-4 within an episode and the runs part ways some updates later; hence only the first
    rollout, to 1e-2 with equal lengths (a wrong action, agent or step would be off by far more)."""
    up, tr = tmp_path / "up", tmp_path / "train"
    r1 = hammer("up", "--preset", "mw3", "--episodes", "12", "--run-dir", str(up), "--no-dashboard",
                "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000")
    assert r1.returncode == 0, r1.stderr[-2000:]
    trained_run(tr, ("episodes=12", "torch_threads=1"), preset="mw3")
    summary = json.loads((up / "summary.json").read_text())
    assert summary["links"]["default_actions"] == 0 and summary["links"]["msg_fallback_copies"] == 0
    cfg = json.loads((up / "config.json").read_text())
    first_rollout = cfg["rollout_steps"] * cfg["num_envs"]
    a = [r for r in _rows(up) if int(r["env_steps"]) <= first_rollout]
    b = [r for r in _rows(tr) if int(r["env_steps"]) <= first_rollout]
    assert len(a) == len(b) >= 8
    assert [r["length"] for r in a] == [r["length"] for r in b]
    assert [float(r["paper_metric"]) for r in a] == pytest.approx([float(r["paper_metric"]) for r in b], abs=1e-2)
    assert processes_mentioning(str(up)) == []


def test_policy_lag_pipelines_rollouts_with_one_version_each(tmp_path):
    """max_policy_lag=1: the env host steps on while the learner updates. Every rollout is still
    acted by one version (no off-policy action), the learner evaluates lagged chunks with that
    version, and nothing is lost or counted twice. The run is the session's pipelined one
    (runtime_helpers.pipelined_run, which also checks that none of its processes outlives it)."""
    run = pipelined_run(tmp_path / "lag")
    summary = json.loads((run / "summary.json").read_text())
    learner = json.loads((run / "learner_summary.json").read_text())
    cfg = json.loads((run / "config.json").read_text())
    per_update = cfg["rollout_steps"] * cfg["num_envs"] * cfg["n_agents"]
    assert learner["max_policy_lag"] == 1 and learner["lagged_updates"] >= 1 and learner["policy_lag_max"] == 1
    assert learner["samples"] == learner["updates"] * per_update and learner["updates"] >= 3
    assert learner["stale_chunks"] == learner["bad_chunks"] == learner["central_steps_missing"] == 0
    links = summary["links"]
    assert links["off_policy_actions"] == 0 and links["default_actions"] == 0 and links["msg_fallback_copies"] == 0
    assert summary["completed"] and len(_metric_column(run)) == summary["episodes"] == 320


def test_sigkilled_local_agent_is_restarted_and_the_run_completes(tmp_path):
    # Long enough that the kill lands mid-run on an idle machine too: the env host reports its
    # episodes twice a second and 160 episodes (5 rollouts) can be over within one report.
    cfg = merge_config("cn3", overrides=["episodes=960", "variant=il"])
    settings = RuntimeSettings(run_id="killtest", act_deadline_ms=100)
    killed: list[int] = []

    def chaos(sup, board) -> None:
        env = board.heartbeats.get("env")
        if not killed and env is not None and env.counters.get("episodes", 0) >= 20:
            pid = sup.pid("local-1")
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    res = launch(cfg, settings, tmp_path / "run", chaos=chaos)
    assert killed, "the run ended before the chaos hook fired"
    assert res.restarts["local-1"] == 1
    assert res.summary["completed"] and res.summary["episodes"] == 960
    # While local-1 was down the env host kept stepping on its declared default action.
    assert res.summary["links"]["default_actions"] > 0
    assert not psutil.pid_exists(killed[0]) or psutil.Process(killed[0]).status() == psutil.STATUS_ZOMBIE
    assert processes_mentioning(str(tmp_path / "run")) == []
