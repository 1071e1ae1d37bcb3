"""`hammer faults sweep` as a user runs it: a real process, real signals, real evaluation runs.

Ctrl-C (SIGINT to the whole process group, as a terminal sends it: the role processes get it too) or
SIGTERM stops the sweep at once, writes what finished, says in one line how to continue and exits
128 + the signal; the same command then continues, taking the finished points and evaluating the rest.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def team(tmp_path_factory) -> Path:
    """A run directory as `hammer train` leaves it (config.json, final/ weights), untrained: the sweep
    evaluates whatever it is given."""
    from hammer.envs.registry import make_vec_env
    from hammer.learning.config import merge_config
    from hammer.learning.team import Team
    from safetensors.numpy import save_file

    d = tmp_path_factory.mktemp("team")
    (d / "final").mkdir()
    cfg = merge_config("cn3", overrides=["variant=hammer", "central_mode=rl", "num_envs=2"])
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    spec = env.spec
    env.close()
    t = Team(cfg, spec)
    save_file(t.local.export_numpy(), str(d / "final" / "local.safetensors"))
    save_file(t.central.export_numpy(), str(d / "final" / "central.safetensors"))
    (d / "config.json").write_text(json.dumps(cfg.model_dump(mode="json")))
    return d


def _cmd(team: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "hammer", "faults", "sweep", f"team={team}", "--drops", "0,0.5,1.0", "--delays-ms", "0",
            "--seeds", "1", "--episodes", "2", "--parallel", "1", "--out", str(out)]


def _rows(out: Path) -> list[dict]:
    with open(out / "sweep.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_ctrl_c_stops_the_sweep_at_once_and_the_same_command_continues_it(team, tmp_path):
    out = tmp_path / "sweep"
    p = subprocess.Popen(_cmd(team, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    stdout = []
    for line in p.stdout:  # the first point's progress line: then Ctrl-C, while the second one runs
        stdout.append(line)
        if line.startswith("[1/3]"):
            time.sleep(1.0)
            os.killpg(p.pid, signal.SIGINT)
            t_sig = time.monotonic()
            break
    else:
        pytest.fail(f"no progress line: {''.join(stdout)} {p.stderr.read()}")
    rest, err = p.communicate(timeout=60)
    stopped_in = time.monotonic() - t_sig
    assert p.returncode == 130, (rest, err)
    assert "Traceback" not in err + rest
    said = [ln for ln in err.splitlines() if not ln.startswith("WARNING")]
    assert len(said) == 1 and said[0].startswith("stopped by SIGINT: 1 of 3 evaluation runs finished"), err
    assert "continue with the same command: hammer faults sweep" in said[0]
    assert stopped_in < 20, stopped_in  # the running point is stopped (its roles get 10 s), not run out
    # nothing after the signal: the third point never started; what finished is written
    assert sorted(d.name for d in (out / "points").iterdir()) == ["team-drop0-delay0-seed0", "team-drop0.5-delay0-seed0"]
    assert [(r["drop"], r["episodes"]) for r in _rows(out)] == [("0.0", "2")]
    assert (out / "sweep.md").is_file() and (out / "sweep.png").is_file()
    assert not _left_running(out)
    first = out / "points" / "team-drop0-delay0-seed0" / "point.json"
    kept = first.read_text(), first.stat().st_mtime_ns

    r = subprocess.run(_cmd(team, out), check=False, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    assert "1 of 3 evaluation runs already finished" in r.stdout and "evaluating the other 2" in r.stdout
    assert [ln[:5] for ln in r.stdout.splitlines() if ln.startswith("[")] == ["[2/3]", "[3/3]"]
    assert (first.read_text(), first.stat().st_mtime_ns) == kept  # taken, not evaluated again
    assert sorted(float(r["drop"]) for r in _rows(out)) == [0.0, 0.5, 1.0]

    # the finished points are never mixed with points evaluated otherwise
    r = subprocess.run([*_cmd(team, out)[:-2], "--episodes", "3", "--out", str(out)], check=False, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "episodes=2 (now 3)" in r.stderr, r.stderr


def test_sigterm_during_the_first_evaluation_stops_it_and_writes_nothing(team, tmp_path):
    out = tmp_path / "sweep"
    p = subprocess.Popen(_cmd(team, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (out / "points" / "team-drop0-delay0-seed0" / "logs").is_dir():
        assert p.poll() is None and time.monotonic() < deadline, p.communicate()
        time.sleep(0.1)
    p.send_signal(signal.SIGTERM)  # the sweep alone, as `kill` sends it: it stops its runs itself
    rest, err = p.communicate(timeout=60)
    assert p.returncode == 143, (rest, err)
    said = [ln for ln in err.splitlines() if not ln.startswith("WARNING")]
    assert len(said) == 1 and "stopped by SIGTERM: 0 of 3 evaluation runs finished, nothing written" in said[0], err
    assert not (out / "sweep.csv").exists() and "Traceback" not in err
    assert [d.name for d in (out / "points").iterdir()] == ["team-drop0-delay0-seed0"]
    assert not _left_running(out)


def _left_running(out: Path) -> list[str]:
    import psutil

    left = []
    for proc in psutil.process_iter(["cmdline"]):
        cmd = " ".join(proc.info["cmdline"] or [])
        if str(out) in cmd:
            left.append(cmd)
    return left
