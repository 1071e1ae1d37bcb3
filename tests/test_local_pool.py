"""Agent pools (local_agent/pool.py): many local agents in one process, each its own agent on the
wire. Real processes, real Zenoh on 127.0.0.1 (explicit endpoints, scouting off), real envs and
torch in the learner; the secure checks use real TLS identities and Zenoh's access control."""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from hammer.deploy.launcher import launch, role_specs
from hammer.learning.config import merge_config
from hammer.learning.numpy_policy import NumpyLocalPolicy
from hammer.local_agent.pool import LocalAgentPool, parse_agents
from hammer.protocol.access import grants, pool_name, role_names, secure_link
from hammer.protocol.identity import create_identities
from hammer.protocol.keys import Keys
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port
from hammer.runtime.settings import RuntimeSettings, auto_agents_per_process

from tests.runtime_helpers import UP_CN3_BACKPROP, processes_mentioning, trained_run, up_run


def _metrics_without_wall_time(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def _run(run_dir: Path, agents_per_process: int, mode: str = "backprop", preset: str = "cn3", episodes: int = 100,
         **extra):
    cfg = merge_config(preset, overrides=[f"episodes={episodes}", "variant=hammer", f"central_mode={mode}"])
    # Generous deadlines: equality without faults is the point; a slow message on a loaded machine
    # must not become a fallback (fallbacks under pools: test_faults_runtime-style runs, not here).
    settings = RuntimeSettings(run_id=f"pool{agents_per_process}-{mode}-{time.monotonic_ns() % 10**6}",
                               agents_per_process=agents_per_process, msg_deadline_ms=5000, act_deadline_ms=10000,
                               **extra)
    return launch(cfg, settings, run_dir)


@pytest.fixture(scope="module")
def one_per_process(tmp_path_factory) -> Path:
    """What `_run(run, 1)` makes, by the `hammer up` CLI: the session's run that test_runtime_up
    compares with the trainer (the same config, seed and deadlines), run once."""
    run = up_run(tmp_path_factory.mktemp("solo") / "run", UP_CN3_BACKPROP)
    assert json.loads((run / "summary.json").read_text())["completed"]
    return run


@pytest.fixture(scope="module")
def pooled(tmp_path_factory) -> SimpleNamespace:
    """`hammer up --secure` of cn3 with agents_per_process=2: agents 0 and 1 in one pool process,
    agent 2 alone, each with its own identity. Both tests below judge this one run: the secure
    profile changes the transport and its access rules, not one value of the run, and pools in the
    plain profile run in the pool-of-five and pool-killing tests."""
    run = tmp_path_factory.mktemp("pooled") / "run"
    return SimpleNamespace(dir=run, res=_run(run, 2, secure=True))


def test_a_pooled_run_writes_the_same_metrics_as_one_process_per_agent(one_per_process, pooled):
    """agents_per_process=2 on cn3: agents 0 and 1 in one pool process, agent 2 alone. Same seed,
    no faults: metrics.csv is identical (every column but wall_time) to one process per agent, and
    every agent still reports as itself (counters, heartbeats, the link table)."""
    run, res = pooled.dir, pooled.res
    assert res.summary["completed"] and not res.summary["degraded"]
    a, b = _metrics_without_wall_time(one_per_process), _metrics_without_wall_time(run)
    assert len(a) == 100 and a == b
    assert len({r["paper_metric"] for r in a}) > 50  # real, varied episodes
    assert sorted(p.name for p in (run / "logs").glob("local*.log")) == ["local-2.log", "locals-0-1.log"]
    counters = sorted(p.name.rsplit("-", 1)[0] for p in (run / "counters").glob("local-*.json"))
    assert counters == ["local-0", "local-1", "local-2"]
    roles = json.loads((run / "links.json").read_text())["roles"]
    solo = json.loads((one_per_process / "links.json").read_text())["roles"]
    for i in range(3):
        assert roles[f"local-{i}"]["steps"] == solo[f"local-{i}"]["steps"] == res.summary["step"]
        assert roles[f"local-{i}"]["msgs_on_time"] == res.summary["step"]
        assert roles[f"local-{i}"]["tx_msgs"] >= res.summary["step"]  # its own actions (+ heartbeats)
    links = res.summary["links"]
    assert links["default_actions"] == 0 and links["msg_fallback_copies"] == 0
    log = (run / "logs" / "locals-0-1.log").read_text()
    assert "stacked" in log or "forwards" in log
    assert processes_mentioning(str(run)) == []


def test_a_secure_pool_holds_exactly_its_agents_grants_and_runs_like_the_others(one_per_process, pooled):
    """`hammer up --secure` with pools of 2 (cn3: a pool of agents 0 and 1, agent 2 alone): the
    pool's identity is granted exactly its agents' keys (agent 2's own identity holds the rest),
    and the run reproduces the plain one-process-per-agent run."""
    run, res = pooled.dir, pooled.res
    assert res.summary["completed"] and res.summary["rejected"] == {}
    assert _metrics_without_wall_time(run) == _metrics_without_wall_time(one_per_process)
    assert (run / "identity" / "locals-0-1.key").is_file() and (run / "identity" / "local-2.key").is_file()


def test_a_pool_of_five_with_batched_bursts_matches_the_trainer(tmp_path):
    """cn5, rl mode: five agents in one pool against the in-process trainer, whose episodes one
    process per agent reproduces bit for bit (test_runtime_stall, test_runtime_up). Bursts of five
    puts go out batched (the env host's observations, the central agent's messages;
    protocol.session.BATCH_MIN) and the pool's five actions too: the episodes are the same."""
    pooled = tmp_path / "pooled"
    b = _run(pooled, 5, mode="rl", preset="cn5", episodes=64)
    solo = trained_run(tmp_path / "train", ("variant=hammer", "central_mode=rl", "episodes=64"), preset="cn5")
    assert b.summary["completed"]
    assert b.summary["links"]["msg_fallback_copies"] == 0 and b.summary["links"]["default_actions"] == 0
    rows = _metrics_without_wall_time(pooled)
    assert len(rows) == 64 and rows == _metrics_without_wall_time(solo)
    roles = json.loads((pooled / "links.json").read_text())["roles"]
    assert roles["locals-0-4"]["stacked_forwards"] > 0  # the five agents did act together


def test_pool_identity_cannot_act_or_listen_for_an_agent_outside_the_pool(tmp_path):
    """Real TLS + access control, N=3, pool locals-0-1: it publishes agents 0 and 1's actions, not
    agent 2's (dropped at the receiver), and its subscriber on agent 2's observation gets nothing."""
    keys, n, pools = Keys("poolsec"), 3, (("locals-0-1", (0, 1)),)
    create_identities(tmp_path, role_names(n, pools=pools))
    port = free_loopback_port()

    def tls(role: str, listen: bool = False) -> TransportConfig:
        return TransportConfig(listen=[f"tls/127.0.0.1:{port if listen else 0}"],
                               connect=[] if listen else [f"tls/127.0.0.1:{port}"],
                               security=secure_link(tmp_path, role, keys, n, pools))

    g = grants(keys, n, pools)["locals-0-1"]
    assert set(g.publish) == {keys.act(0), keys.act(1), keys.heartbeat("local-0"), keys.heartbeat("local-1")}
    assert keys.obs(2) not in g.subscribe and keys.act(2) not in g.publish
    with HammerSession("poolsec", tls("env", listen=True), sender="env") as env, \
            HammerSession("poolsec", tls("locals-0-1"), sender="locals-0-1") as pool:
        acts = env.subscribe_raw(keys.act("*"))
        spy = pool.subscribe_raw(keys.obs(2))
        mine = pool.subscribe_raw(keys.obs(1))
        time.sleep(0.8)  # peers meet, declarations propagate
        pool.put_bytes(keys.act(2), b"forged")
        env.put_bytes(keys.obs(2), b"o2")
        for i in (0, 1):
            pool.put_bytes(keys.act(i), f"a{i}".encode())
        env.put_bytes(keys.obs(1), b"o1")
        got, deadline = [], time.monotonic() + 5
        while len(got) < 2 and time.monotonic() < deadline:
            if (b := acts.get(0.05)) is not None:
                got.append(b)
        assert sorted(got) == [b"a0", b"a1"]
        assert mine.get(5.0) == b"o1"
        time.sleep(0.3)
        assert acts.get(0) is None and spy.get(0) is None


def test_stacked_forward_equals_one_forward_per_agent_bit_for_bit():
    """The pool's one (agents, K, d) forward gives exactly the floats of one forward per agent
    (a flat (agents*K, d) matmul does not: BLAS blocks it differently)."""
    rng = np.random.default_rng(1)
    d, h, a = 22, 64, 5
    params = {"actor.layers.0.weight": rng.standard_normal((h, d)), "actor.layers.0.bias": rng.standard_normal(h),
              "actor.layers.1.weight": rng.standard_normal((a, h)), "actor.layers.1.bias": rng.standard_normal(a),
              "critic.layers.0.weight": rng.standard_normal((1, d)), "critic.layers.0.bias": rng.standard_normal(1)}
    policy = NumpyLocalPolicy({k: v.astype(np.float32) for k, v in params.items()})
    xs = [rng.standard_normal((32, d)).astype(np.float32) for _ in range(50)]

    member = SimpleNamespace(agent=SimpleNamespace(policy=policy))  # what LocalAgentPool._forward reads
    pool = LocalAgentPool.__new__(LocalAgentPool)  # only _forward's state: no session needed for this maths
    pool.members, pool.forwards, pool.stacked_forwards = [member], 0, 0
    stacked = pool._forward(xs)
    assert pool.stacked_forwards == 1
    for x, out in zip(xs, stacked, strict=True):
        assert np.array_equal(out, policy.actor_out(x))


def test_agent_ranges_pools_and_the_default_per_machine(tmp_path):
    assert parse_agents("0-3,7", 10) == [0, 1, 2, 3, 7]
    for bad, what in (("3-1", "FIRST-LAST"), ("x", "not an agent"), ("0-12", "agent 0..9")):
        with pytest.raises(ValueError, match=what):
            parse_agents(bad, 10)
    assert pool_name([0, 1, 2]) == "locals-0-2" and pool_name([0, 2]) == "locals-0_2"
    assert [auto_agents_per_process(n, 2) for n in (3, 5, 20, 50)] == [1, 2, 7, 17]
    assert auto_agents_per_process(50, 32) == 1
    cfg = merge_config("cn5", overrides=["episodes=10"])
    s = RuntimeSettings(run_id="x", agents_per_process=2, external=["local-1"])
    names = [(r.name, r.members) for r in role_specs(cfg, tmp_path, s) if r.name.startswith("local")]
    assert names == [("locals-0_2", ("local-0", "local-2")), ("local-1", ()), ("locals-3-4", ("local-3", "local-4"))]
    s.save(tmp_path)
    assert json.loads((tmp_path / "runtime.json").read_text())["agents_per_process"] == 2
    RuntimeSettings(run_id="x", agents_per_process=1).save(tmp_path)
    assert "agents_per_process" not in json.loads((tmp_path / "runtime.json").read_text())


def test_killing_a_pool_takes_down_its_agents_and_the_supervisor_restarts_it(tmp_path):
    """Chaos acts on processes: SIGKILL of the pool serving agents 0 and 1 is an outage of both
    (the env host steps on their declared default actions), the launcher restarts the pool as it
    restarts a single agent, and the run completes."""
    import os
    import signal

    from hammer.faults.chaos import ChaosScheduler

    cfg = merge_config("cn3", overrides=["episodes=960", "variant=il"])
    settings = RuntimeSettings(run_id="poolkill", act_deadline_ms=100, agents_per_process=2)
    specs = role_specs(cfg, tmp_path, settings)
    scheduled = ChaosScheduler.from_strings(["kill:local-1@step=100"])
    scheduled.bind_pools(specs)
    assert scheduled.events[0].role == "locals-0-1"  # an agent's event names its pool's process
    killed: list[int] = []

    def chaos(sup, board) -> None:
        env = board.heartbeats.get("env")
        if not killed and env is not None and env.counters.get("episodes", 0) >= 20:
            pid = sup.pid("locals-0-1")
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    res = launch(cfg, settings, tmp_path / "run", chaos=chaos)
    assert killed, "the run ended before the chaos hook fired"
    assert res.restarts["locals-0-1"] == 1 and res.restarts["local-2"] == 0
    assert res.summary["completed"] and res.summary["episodes"] == 960
    assert res.summary["links"]["default_actions"] > 0
    roles = json.loads((tmp_path / "run" / "links.json").read_text())["roles"]
    step = res.summary["step"]
    assert roles["local-2"]["steps"] == step  # the agent outside the pool never missed a step
    assert roles["local-0"]["steps"] < step and roles["local-1"]["steps"] < step
    assert processes_mentioning(str(tmp_path / "run")) == []
