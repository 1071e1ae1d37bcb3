"""`hammer up --resume`: a distributed run whose whole process group was SIGKILLed continues from
its latest checkpoint to the budget. Real processes, real Zenoh on 127.0.0.1, real env and torch."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from hammer.deploy.launcher import prepare_run_dir
from hammer.learning.config import merge_config
from hammer.runtime.settings import RuntimeSettings

from tests.runtime_helpers import ENV, ROOT, hammer, processes_mentioning

BUDGET = 256  # 8 updates of 32 cn3 episodes: the kill lands after update 2, well before the end






def _updates(d: Path) -> set[int]:
    return {int(p.name[5:12]) for p in d.glob("ckpt_*.json")} if d.is_dir() else set()


def _common_checkpoints(run: Path) -> set[int]:
    return _updates(run / "checkpoints") & _updates(run / "host_state")


def _max_logged_step(run: Path) -> int:
    """The highest step any role's step log mentions (complete lines only)."""
    top = -1
    for path in (run / "linksteps").glob("*.csv"):
        for line in path.read_text().split("\n")[1:-1]:
            top = max(top, int(line.split(",")[0]))
    return top


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _kill_group_when_checkpointed(run: Path, log: Path) -> None:
    """Start `hammer up`, wait for a complete checkpoint (learner + env host, update >= 2) and for
    the env host to step beyond it, then SIGKILL the launcher's whole process group."""
    with open(log, "w") as logf:
        proc = subprocess.Popen([sys.executable, "-m", "hammer.cli", "up", "--episodes", str(BUDGET), "--set",
                                 "checkpoint_every=2", "--run-dir", str(run), "--no-dashboard"],
                                stdout=logf, stderr=subprocess.STDOUT, cwd=ROOT, env=ENV, start_new_session=True)
    try:
        deadline = time.monotonic() + 150
        while time.monotonic() < deadline:
            assert proc.poll() is None, f"the run ended before the kill: {log.read_text()[-1500:]}"
            common = [u for u in _common_checkpoints(run) if u >= 2]
            if common:
                saved = json.loads((run / "host_state" / f"ckpt_{max(common):07d}.json").read_text())
                if _max_logged_step(run) > saved["step"]:
                    break
            time.sleep(0.1)
        else:
            raise AssertionError(f"no checkpoint within 150 s: {log.read_text()[-1500:]}")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        # The roles share the launcher's process group; anything that escaped it is killed here.
        deadline = time.monotonic() + 10
        while (left := processes_mentioning(str(run))) and time.monotonic() < deadline:
            for p in left:
                p.kill()
            time.sleep(0.2)
    assert processes_mentioning(str(run)) == []


def test_sigkilled_up_run_resumes_to_its_budget(tmp_path):
    run = tmp_path / "run"
    _kill_group_when_checkpointed(run, tmp_path / "first.log")
    assert not (run / "summary.json").exists()
    u = max(_common_checkpoints(run))
    saved = json.loads((run / "host_state" / f"ckpt_{u:07d}.json").read_text())
    kept = _rows(run / "metrics.csv")[: saved["episodes"]]
    old_step_top = _max_logged_step(run)
    old_run_id = json.loads((run / "runtime.json").read_text())["run_id"]
    assert 0 < saved["episodes"] < BUDGET and old_step_top > saved["step"]

    # Starting it afresh is refused (it holds a run); only --episodes may change on resume.
    fresh = hammer("up", "--run-dir", str(run), "--no-dashboard")
    assert fresh.returncode == 1 and "--resume" in fresh.stderr, fresh.stderr[-1500:]
    other = hammer("up", "--resume", str(run), "--set", "checkpoint_every=3")
    assert other.returncode == 2 and "only --episodes may be changed" in other.stderr and "--set" in other.stderr

    res = hammer("up", "--resume", str(run), "--no-dashboard")
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"resumed at update {u}" in res.stderr

    rows = _rows(run / "metrics.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, BUDGET + 1))
    assert rows[: saved["episodes"]] == kept  # the part before the checkpoint is untouched
    assert float(rows[saved["episodes"]]["wall_time"]) >= float(kept[-1]["wall_time"])  # the clock continues
    assert int(rows[saved["episodes"]]["env_steps"]) > saved["env_steps"]

    summary = json.loads((run / "summary.json").read_text())
    learner = json.loads((run / "learner_summary.json").read_text())
    cfg = json.loads((run / "config.json").read_text())
    per_update = cfg["rollout_steps"] * cfg["num_envs"] * cfg["n_agents"]
    assert summary["completed"] and summary["episodes"] == BUDGET and summary["resumed_from"] == u
    assert learner["resumed_from"] == u
    assert learner["policy_version"] == learner["updates"] == summary["updates"] > u
    assert learner["samples"] == (learner["updates"] - u) * per_update  # this session's updates only
    assert learner["stale_chunks"] == learner["bad_chunks"] == 0

    # A fresh run id, and no step number of the killed session reused by the new episodes.
    rt = json.loads((run / "runtime.json").read_text())
    assert rt["resume_from"] == u and rt["run_id"] != old_run_id
    links = _rows(run / "episode_links.csv")
    assert [int(r["episode"]) for r in links] == list(range(1, BUDGET + 1))
    new = links[saved["episodes"]:]
    assert min(int(r["start_step"]) for r in new) > old_step_top
    assert all(int(r["end_step"]) <= saved["step"] for r in links[: saved["episodes"]])
    # The per-link columns count each resumed episode's own steps only: one state message per step.
    assert all(int(r["env_central_sent"]) == int(r["length"]) for r in new)

    again = hammer("up", "--resume", str(run), "--no-dashboard")
    assert again.returncode == 1 and "already complete" in again.stderr
    assert processes_mentioning(str(run)) == []


def test_resume_without_checkpoint_or_with_other_options_is_refused(tmp_path):
    run = tmp_path / "young"
    cfg = merge_config("cn3", overrides=["episodes=64", "variant=hammer"])
    prepare_run_dir(cfg, RuntimeSettings(run_id="young"), run)  # what `hammer up` writes before any role starts
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}

    res = hammer("up", "--resume", str(run), "--no-dashboard")
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert lines[-1] == f"error: {run} has no checkpoint yet; start it again (hammer up --run-dir {run})"
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before  # nothing touched

    for extra in (["--seed", "3"], ["--runtime", "fallback=last"], ["--preset", "cn5"], ["--chaos", "kill:central@t=1s"]):
        res = hammer("up", "--resume", str(run), *extra)
        assert res.returncode == 2 and "only --episodes may be changed" in res.stderr and extra[0] in res.stderr

    train_run = tmp_path / "train"
    train_run.mkdir()
    (train_run / "config.json").write_text((run / "config.json").read_text())
    res = hammer("up", "--resume", str(train_run))
    assert res.returncode == 2 and "hammer train --resume" in res.stderr
