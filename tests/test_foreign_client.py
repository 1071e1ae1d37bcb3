"""A local agent written from docs/wire-format.md alone (tests/foreign_local_agent.py: zenoh,
msgpack, numpy, no project import) takes agent 1's place in a `hammer up --external local-1` run.

The client follows the documented randomness contract, so beyond completing the run it must act
exactly as `hammer local` would: the run's episodes equal `hammer train`'s.
"""

from __future__ import annotations

import ast
import csv
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from hammer.learning.rundir import CSV_HEADER

from tests.runtime_helpers import CN3_RL_100, ENV, ROOT, hammer, processes_mentioning, trained_run

AGENT_FILE = Path(__file__).with_name("foreign_local_agent.py")
ALLOWED = {"zenoh", "msgpack", "numpy"}


def _metric_column(run_dir: Path) -> list[float]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [float(r["paper_metric"]) for r in csv.DictReader(f)]


def test_foreign_client_imports_only_zenoh_msgpack_numpy_and_the_stdlib():
    tree = ast.parse(AGENT_FILE.read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, "no relative imports"
            imported.add(node.module.split(".")[0])
    foreign = imported - set(sys.stdlib_module_names) - {"__future__"}
    assert foreign == ALLOWED, f"the foreign client may import only {ALLOWED} and the stdlib, got {foreign}"


def test_runtime_json_names_external_roles_only_when_there_are_some(tmp_path):
    from hammer.runtime.settings import RuntimeSettings

    RuntimeSettings(run_id="a").save(tmp_path)
    assert "external" not in json.loads((tmp_path / "runtime.json").read_text())  # a plain run's file is unchanged
    RuntimeSettings(run_id="a", external=["local-2"]).save(tmp_path)
    assert RuntimeSettings.load(tmp_path).external == ["local-2"]


def test_external_role_must_be_a_role_of_the_run(tmp_path):
    res = hammer("up", "--episodes", "1", "--variant", "il", "--run-dir", str(tmp_path / "r"), "--no-dashboard",
                 "--external", "central")
    assert res.returncode != 0
    assert "error: --external central: not a role of this run; fix: use one of learner, local-0" in res.stderr
    assert not (tmp_path / "r" / "config.json").exists()  # refused before anything was written


def test_foreign_local_agent_completes_a_hammer_run_exactly_like_hammer_local(tmp_path):
    run = tmp_path / "up"
    # Generous deadlines: equality is the point here, not behaviour under a loaded machine's delays.
    up = subprocess.Popen(
        [sys.executable, "-m", "hammer.cli", "up", "--episodes", "40", "--central-mode", "rl", "--run-dir", str(run),
         "--no-dashboard", "--external", "local-1", "--runtime", "msg_deadline_ms=5000",
         "--runtime", "act_deadline_ms=10000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
    lines: list[str] = []
    announced = threading.Event()
    command = f"hammer local --run-dir {run} --agent 1 2>> {run / 'logs' / 'local-1.log'}"

    def read() -> None:
        for line in up.stderr:
            lines.append(line)
            if command in line:
                announced.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert announced.wait(120), "".join(lines)[-2000:]
        # A clean environment: no PYTHONPATH, started outside the repository.
        clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        with open(run / "logs" / "local-1.log", "ab") as log:
            agent = subprocess.run([sys.executable, str(AGENT_FILE), str(run), "1"], cwd=tmp_path, env=clean,
                                   stdout=subprocess.DEVNULL, stderr=log, timeout=300, check=False)
        up.wait(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    reader.join(5)
    out = "".join(lines)
    assert agent.returncode == 0, (run / "logs" / "local-1.log").read_text()[-2000:]
    assert up.returncode == 0, out[-2000:]
    assert "done: 40 episodes" in up.stdout.read()  # the verdict is on stdout

    summary = json.loads((run / "summary.json").read_text())
    links = summary["links"]
    # every action of the foreign agent was accepted, on time, with the version the step named
    assert links["default_actions"] == 0 and links["off_policy_actions"] == 0 and links["actions_late"] == 0
    assert links["msg_fallback_copies"] == 0
    (counters_file,) = (run / "counters").glob("local-1-*.json")
    mine = json.loads(counters_file.read_text())["counters"]
    assert mine["steps"] == summary["step"] == mine["msgs_on_time"] and mine["rejected"] == 0
    table = json.loads((run / "links.json").read_text())["links"]
    assert table["local->env"]["delivered"] == table["local->env"]["sent"] == summary["step"] * 3

    # the same run directory as a plain `hammer up`
    assert sorted(p.name for p in (run / "logs").iterdir()) == [f"{r}.log" for r in
                                                                 ("central", "env", "launcher", "learner", "local-0",
                                                                  "local-1", "local-2")]
    with open(run / "metrics.csv", newline="") as f:
        assert next(csv.reader(f)) == CSV_HEADER
    assert processes_mentioning(str(run)) == []

    # the documented randomness contract, followed from the docs: the episodes of hammer train, run
    # in process as the CLI runs it (the session's cached rl team, whose first 40 episodes are a
    # 40-episode run's: no schedule depends on the episode budget)
    tr = trained_run(tmp_path / "train", CN3_RL_100, tensorboard=True)
    a, b = _metric_column(run), _metric_column(tr)[:40]
    assert len(a) == len(b) == 40 and len(set(a)) > 20
    assert a == pytest.approx(b, abs=1e-5)


@pytest.fixture(scope="module")
def teams(tmp_path_factory):
    """A briefly trained cn3 team, and the same team with other local weights that declares the first
    one's central network (a push to a fleet running the first, pulled in chunks)."""
    from tests.runtime_helpers import trained_pair

    return trained_pair(tmp_path_factory.mktemp("teams"))


def test_a_foreign_robot_plays_robot_0_of_a_fleet_and_pulls_a_push_in_chunks(teams, tmp_path):
    """The same client as robot 0 of `hammer serve --realtime 20 --external 0`, from the bundle and the
    hub's endpoint alone: it acts on fresh central messages, and a `hammer push` reaches it in chunks it
    asks for one per act; it switches, says it holds the version, and the central agent, which waits
    for every robot present to hold a push, switches after it."""
    bundle, pushed = teams
    run = tmp_path / "fleet"
    serve = subprocess.Popen([sys.executable, "-m", "hammer.cli", "serve", str(bundle), "--realtime", "20",
                              "--seconds", "14", "--external", "0", "--run-dir", str(run)],
                             cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    robot = None
    try:
        deadline = time.monotonic() + 120
        while not (run / "fleet.json").is_file():
            assert serve.poll() is None and time.monotonic() < deadline, "no fleet.json"
            time.sleep(0.2)
        time.sleep(0.2)
        fleet = json.loads((run / "fleet.json").read_text())
        clean = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        with open(tmp_path / "robot.log", "wb") as log:
            robot = subprocess.Popen([sys.executable, str(AGENT_FILE), "--fleet", str(bundle), fleet["run_id"], "0",
                                      fleet["hub"]], cwd=tmp_path, env=clean, stdout=subprocess.DEVNULL, stderr=log)
        env_log = run / "logs" / "env.log"
        while "world clock starts" not in (env_log.read_text() if env_log.is_file() else ""):
            assert serve.poll() is None and robot.poll() is None and time.monotonic() < deadline, "no world clock"
            time.sleep(0.2)
        time.sleep(2.0)
        r = hammer("push", str(pushed), "--to", str(run))
        assert r.returncode == 0, r.stderr[-2000:]
        out = serve.communicate(timeout=120)[0]
        assert robot.wait(30) == 0, (tmp_path / "robot.log").read_text()[-2000:]
    finally:
        for p in (serve, robot):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(10)
    assert serve.returncode == 0, out[-2000:]
    s = json.loads((run / "summary.json").read_text())
    mine, others = s["robots"]["local-0"], [s["robots"][f"local-{i}"] for i in (1, 2)]
    assert s["completed"] and "local-0" not in s["absences"], (s["absences"], mine)
    # it acted at the world's rate on fresh messages, and said so in its own heartbeats
    assert mine["fresh"] > 0.8 * min(o["fresh"] for o in others), (mine, others)
    assert mine["acts"] > 0 and mine["msg_fresh"] > 0.8 * mine["acts"], mine
    assert mine["msg_age_p50_ms"] is not None and mine["msg_age_p50_ms"] < 500, mine
    # the push: pulled in 512 B chunks, one query at a time, switched to, held; the central agent after it
    n_chunks = -(-(pushed / "local.safetensors").stat().st_size // 512)
    assert mine["versions_pulled"] == 1 and mine["chunks_refused"] == 0 and mine["chunk_queries"] >= n_chunks, mine
    assert mine["policy_version"] == mine["policy_held"] == 1, mine
    assert [(x["from"], x["to"]) for x in mine["version_switches"]] == [(0, 1)], mine
    c = s["central"]
    assert [(x["from"], x["to"]) for x in c["version_switches"]] == [(0, 1)] and c["policy_switched_unheld"] == 0, c
    assert c["version_switches"][0]["t_s"] >= mine["version_switches"][0]["t_s"], (c, mine)


def test_roles_started_by_hand_without_the_launcher_write_metrics_with_their_header(tmp_path):
    """Only config.json, env_spec.json and runtime.json, a `hammer hub` and each role by hand (the
    docs' two-machine recipe on one host): metrics.csv starts with its header like hammer up's."""
    from hammer.envs.registry import make_vec_env
    from hammer.learning.config import merge_config
    from hammer.protocol.session import free_loopback_port
    from hammer.runtime.settings import RuntimeSettings, write_env_spec

    run, port = tmp_path / "hand", free_loopback_port()
    run.mkdir()
    cfg = merge_config("cn3", overrides=["variant=il", "episodes=1"])
    (run / "config.json").write_text(json.dumps(cfg.model_dump(mode="json")))
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    write_env_spec(run, env.spec)
    env.close()
    RuntimeSettings(run_id="hand", hub_port=port).save(run)

    def start(*args: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "hammer.cli", *args], cwd=ROOT, env=ENV,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    hub = start("hub", "--listen", f"tcp/127.0.0.1:{port}")
    roles = [start("learner", "--run-dir", str(run)),
             *(start("local", "--run-dir", str(run), "--agent", str(i)) for i in range(3))]
    try:
        from hammer.protocol.session import HammerSession, TransportConfig

        with HammerSession("hand", TransportConfig.connector(port)) as s:  # start the env host last
            deadline = time.monotonic() + 120
            while not {"learner", "local-0", "local-1", "local-2"} <= s.alive_roles() and time.monotonic() < deadline:
                time.sleep(0.2)
        env = start("env-host", "--run-dir", str(run))
        assert env.wait(timeout=240) == 0
        for p in roles:
            assert p.wait(timeout=60) == 0  # the env host's stop ended every role
    finally:
        for p in [*roles, hub]:
            if p.poll() is None:
                p.terminate()
                p.wait(10)
    with open(run / "metrics.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == CSV_HEADER and len(rows) == 1 + 1
    assert json.loads((run / "summary.json").read_text())["completed"]
