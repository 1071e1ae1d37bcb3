"""A trained team as a fleet: the robot SDK (serve/edge_agent.py), the fleet-fed central
agent (central_agent/fleet_central.py), the realtime world (env_host/world.py) and their launcher
(deploy/fleet_launch.py). Real Zenoh on 127.0.0.1, a real trained cn3 team, real processes for the fleet.
Rates and ages are figures of `hammer bench fleet`, not asserted here; what is asserted is who acted
on what (defaults, fallbacks, fresh messages) and that outages are named."""

from __future__ import annotations

import contextlib
import json
import logging
import re
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from hammer.central_agent.fleet_central import FleetCentral
from hammer.deploy.fleet_launch import FleetPlan, run_fleet
from hammer.protocol.binding import rule_for
from hammer.protocol.schemas import Uplink
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
from hammer.runtime.presence import Presence
from hammer.serve.bundle import CENTRAL, load_bundle
from hammer.serve.edge_agent import EdgeAgent

from tests.runtime_helpers import ENV, ROOT, netns_reason, run_block_beside_serve, trained_bundle

pytestmark = pytest.mark.timeout(240)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return trained_bundle(tmp_path_factory.mktemp("fleet"), episodes=48)


def _wait(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_an_uplink_is_bound_to_its_robot():
    r = rule_for("agent/up/2")
    assert (r.type, r.agent, r.sender, r.agent_pool) == ("uplink", 2, "local-2", 2)
    with pytest.raises(ValueError, match="obs"):
        Uplink(agent=0, env_idx=np.zeros(1, np.int64), obs=np.zeros((2, 3), np.float32))


def test_presence_names_leaves_and_rejoins_and_forgives_its_own_stall(caplog):
    p = Presence(["local-0", "local-1"], 0.5, logging.getLogger("test.presence"))
    with caplog.at_level(logging.INFO, "test.presence"):
        p.seen(0, 10.0)
        p.seen(1, 10.0)
        assert p.update(10.2).all() and p.joins == 2
        p.seen(0, 10.4)
        assert list(p.update(10.7)) == [True, False] and p.leaves == 1  # local-1 silent 0.7 s
        p.seen(1, 12.0)
        assert p.present.all() and p.rejoins == 1 and p.longest_absence_s == pytest.approx(2.0)
        # the observer itself stalled for 3 s: nobody is judged missing on that turn ...
        assert p.update(15.0).all() and p.observer_stalls == 1 and p.leaves == 1
        # ... but one who stays silent is, at the next turn
        p.seen(0, 15.05)
        assert list(p.update(15.1)) == [True, False]
    text = caplog.text
    assert "local-1 missing" in text and "local-1 rejoined after 2.0 s silent (rejoin 1)" in text


def test_the_missing_rule_is_one_function_that_training_simulates():
    """A missing robot is zeros in the central state (observation and previous action), whether a
    fleet's central agent found it silent or training took it away (missing_prob): one function;
    training's absences last whole windows, hit the asked share, and agree for any subset of copies."""
    from hammer.learning.central_acting import CentralActing, missing_mask
    from hammer.learning.config import merge_config

    cfg = merge_config("cn3", overrides=["num_envs=4", "missing_prob=0.25", "missing_window=5"])
    acting = CentralActing.from_config(cfg)
    rng = np.random.default_rng(0)
    obs, prev = rng.normal(size=(4, 3, 18)).astype(np.float32), rng.normal(size=(4, 3, 5)).astype(np.float32)
    present = np.array([[True, False, True]] * 4)
    state = acting.global_state(obs, prev, present).reshape(4, -1)
    assert (state[:, 18:36] == 0).all() and (state[:, 54 + 5:54 + 10] == 0).all()  # robot 1: obs and action
    assert np.array_equal(state[:, :18], obs[:, 0]) and np.array_equal(state[:, 36:54], obs[:, 2])
    assert np.array_equal(acting.global_state(obs, prev, np.ones((4, 3), bool)), acting.global_state(obs, prev))
    m = np.stack([missing_mask(cfg.seed, s, np.arange(16), 3, 0.25, 5) for s in range(1, 1001)])
    assert 0.22 < m.mean() < 0.28 and (m[:5] == m[0]).all() and (m[5:10] == m[5]).all() and (m[5] != m[0]).any()
    assert np.array_equal(missing_mask(cfg.seed, 7, np.array([2, 9]), 3, 0.25, 5), m[6][[2, 9]])
    assert acting.training_presence(7, np.arange(16)).tolist() == (~m[6]).tolist()
    assert CentralActing.from_config(merge_config("cn3")).training_presence(7, np.arange(4)) is None


@contextlib.contextmanager
def _central_agent(port: int, b, bundle):
    """A fleet's central agent (50 Hz) in a thread of this process, with a session of its own."""
    s = HammerSession("fleet-sdk", TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[loopback_endpoint(port)]),
                      sender="central")
    with s:
        central = FleetCentral(s, b.config(num_envs=1), b.env_spec(), (bundle / CENTRAL).read_bytes(), hz=50,
                               missing_after_s=0.5)
        t = threading.Thread(target=central.run, daemon=True)
        t.start()
        try:
            yield central
        finally:
            central.stop_reason = "test over"
            t.join(5)
        assert not t.is_alive()


def test_the_sdk_acts_at_once_on_the_freshest_message_or_the_fallback(bundle):
    """A robot's act() before the central agent exists (fallback, counted), while it serves (fresh
    messages, and the central agent's state holds the robot's uplinked observation), after it
    stopped (the last message grows stale: fallback), and when a central agent starts again (fresh
    again: the robot outlives a server restart without doing anything)."""
    port = free_loopback_port()
    b = load_bundle(bundle)
    with HammerSession("fleet-sdk", TransportConfig(listen=[loopback_endpoint(port)]), sender="hub"):
        robot = EdgeAgent(bundle, 1, run_id="fleet-sdk", connect=loopback_endpoint(port), max_msg_age_s=0.3,
                          wait=True)
        with robot:
            obs = np.linspace(-1, 1, robot.obs_dim).astype(np.float32)
            a = robot.act(obs)
            assert a.dtype == np.int64 and 0 <= int(a) < b.env_spec_data["action_dim"]
            assert robot.counts.msg_none == 1 and robot.counts.uplinks_sent == 1
            with pytest.raises(ValueError, match="expected 18 finite floats"):
                robot.act(np.zeros(5))
            with pytest.raises(ValueError, match="NaN"):
                robot.act(np.full(robot.obs_dim, np.nan))
            def fresh():
                robot.act(obs)
                return robot.last_fresh

            with _central_agent(port, b, bundle) as central:
                assert _wait(fresh), "no fresh central message reached the robot"
                assert _wait(lambda: np.array_equal(central.obs[0, 1], obs))
                assert central.presence.joins == 1 and central.uplinks.stats.rejected_total == 0
                assert robot.counts.msg_fresh >= 1 and robot.counts.msgs_received >= 1
            time.sleep(0.4)
            robot.act(obs)
            assert not robot.last_fresh and robot.counts.msg_stale >= 1
            # a central agent started again (a server restart): the same robot is on fresh messages again
            with _central_agent(port, b, bundle):
                assert _wait(fresh), "the robot did not take up the restarted central agent's messages"
                assert robot.counts.stale_periods == 1  # one stale period, logged, then fresh again


def test_a_realtime_fleet_keeps_going_while_a_robot_and_the_central_agent_are_away(bundle, tmp_path):
    """Every robot its own process on the torch-free path; local-1 paused for 3 s, then the central
    agent for 2 s. The world never waits: the paused robot gets the default action and is named
    missing and back; the others never do; every robot acts on its fallback while the central agent
    is away and on fresh messages otherwise."""
    run = tmp_path / "fleet-run"
    plan = FleetPlan(bundle=bundle, hz=20, seconds=10, hold_s=2.0, missing_after_s=2.0, max_msg_age_s=0.5,
                     max_absence_s=1.5, chaos=["pause:local-1@t=2,for=3", "pause:central@t=6,for=2"])
    s = run_fleet(plan, run)
    assert s["completed"], s
    assert s == json.loads((run / "summary.json").read_text())
    robots, world = s["robots"], s["world"]
    assert world["ticks"] > 0 and world["presence"]["robot_leaves"] >= 1 and world["presence"]["robot_rejoins"] >= 1
    assert robots["local-1"]["defaults"] > 0
    # the outage is named: who, how long, and the run is degraded for it (3 s > max_absence_s 1.5 s)
    assert list(s["absences"]) == ["local-1"] and s["absences"]["local-1"]["longest_absence_s"] > 1.5
    assert s["degraded"] and "local-1 was missing" in s["degraded_reasons"][0]
    assert [e["event"] for e in s["world"]["events"] if e["member"] == "local-1"] == ["missing", "rejoined"]
    assert robots["local-0"]["defaults"] == 0 and robots["local-2"]["defaults"] == 0
    for name, r in robots.items():
        assert r["msg_stale"] > 0, name  # the central agent's pause
        assert r["msg_fresh"] > r["msg_stale"], name
    # one message down per robot per tick: each observation carries the central message of its tick
    # (the world waited for it over loopback), and the robots send no uplinks (the world holds their
    # observations and actions, and gives them to the central agent)
    assert world["msgs_attached"] > 0.5 * len(robots) * world["ticks"], world
    assert s["central"]["uplinks"] == 0 and s["central"]["world_ticks"] >= 0.5 * world["ticks"], s["central"]
    env_log = (run / "logs" / "env.log").read_text()
    assert "local-1 missing" in env_log and "local-1 rejoined" in env_log
    assert "local-0 missing" not in env_log and "local-2 missing" not in env_log
    # the fleet's run directory holds what `hammer push` checks a push against, as a served run's does;
    # no push came, so every robot acted with the bundle's version throughout
    assert json.loads((run / "runtime.json").read_text())["mode"] == "eval"
    assert (run / "config.json").is_file() and (run / "env_spec.json").is_file()
    assert s["pushes"] == [] and s["policy_server"]["policy_version"] == 0
    assert all(r["policy_version"] == 0 and r["version_switches"] == [] for r in robots.values()), robots


@pytest.fixture(scope="module")
def team_b(bundle):
    """Team B: the fleet's team with a random, sharp action head and another central message head (so
    it acts and messages differently), exported declaring that its local policy works with the
    fleet's central network (`--works-with`); and B alone, without that declaration."""
    from hammer.serve.bundle import export_bundle
    from safetensors.numpy import load_file, save_file

    root = bundle.parent
    shutil.copytree(root / "run", root / "run-b")
    final = root / "run-b" / "final"
    w = load_file(str(final / "local.safetensors"))
    last = max(int(k.split(".")[2]) for k in w if k.startswith("actor.layers."))
    head = f"actor.layers.{last}.weight"
    w[head] = np.random.default_rng(0).normal(0.0, 3.0, w[head].shape).astype(np.float32)
    save_file(w, str(final / "local.safetensors"))
    c = load_file(str(final / "central.safetensors"))
    c["head_weight"] = np.random.default_rng(1).normal(0.0, 1.0, c["head_weight"].shape).astype(np.float32)
    save_file(c, str(final / "central.safetensors"))
    paired = export_bundle(root / "run-b", root / "B", works_with=(root / "run" / "final",)).path
    alone = export_bundle(root / "run-b", root / "B-alone").path
    return paired, alone


def test_a_fleet_takes_a_push_and_a_rollback_each_robot_on_its_own(bundle, team_b, tmp_path):
    """`hammer push` to a running 20 Hz fleet, then `hammer rollback`: the policy server announces
    each version, every robot pulls the push in chunks paced by its own acts and switches as soon as
    it holds it (the rollback's bytes are the bundle's: held without a pull), the central agent takes
    B's central network whole once every robot holds the push; no robot goes missing and the world keeps its rate. Then what a fleet
    refuses: a staged rollout, and a local policy that does not declare the running central network."""
    from hammer.serve.bundle import BundleError
    from hammer.serve.push import push, rollback

    paired, alone = team_b
    run = tmp_path / "fleet-push"
    members = ["local-0", "local-1", "local-2", "central"]
    done: dict[str, float] = {}
    watch: dict[str, object] = {}

    def update(board, t: float) -> None:  # the launcher's tick: push ~2 s in, roll back ~3 s after all hold it
        if "session" not in watch:  # the robots' actions to the world, watched from outside
            from hammer.protocol.schemas import Action

            s = watch["session"] = HammerSession(run.name, TransportConfig(
                listen=["tcp/127.0.0.1:0"], connect=[json.loads((run / "fleet.json").read_text())["hub"]]),
                sender="watcher").open()
            watch["acts"] = s.subscribe(s.keys.act("*"), Action, maxsize=100_000)
        world = board.heartbeats.get("env")
        if world is None or world.counters.get("ticks", 0) < 40:
            return
        if "push" not in done:
            push(paired, run)
            done["push"] = t
        elif "all_1" not in done and all(board.versions.get(m) == 1 for m in members):
            done["all_1"] = t
        elif "all_1" in done and "rollback" not in done and t - done["all_1"] >= 3.0:
            rollback(run)
            done["rollback"] = t
        elif "rollback" in done and "all_2" not in done and all(board.versions.get(m) == 2 for m in members):
            done["all_2"] = t

    plan = FleetPlan(bundle=bundle, hz=20, seconds=16, max_absence_s=5)
    try:
        s = run_fleet(plan, run, on_tick=update)
        acted = [(a.agent, a.policy_version) for a in watch["acts"].drain()]
    finally:
        if "session" in watch:
            watch["session"].close()
    # each robot's actions name the version that acted: the bundle's, the push's, the rollback's, in order
    for i in range(3):
        versions = [v for agent, v in acted if agent == i]
        assert versions and versions == sorted(versions) and {0, 1, 2} <= set(versions), (i, sorted(set(versions)))
    assert s["completed"], s
    assert list(done) == ["push", "all_1", "rollback", "all_2"], done
    assert [p["action"] for p in s["pushes"]] == ["push", "rollback"] and s["pushes"][1]["restores_version"] == 0
    assert s["policy_server"]["policy_version"] == 2 and s["policy_server"]["chunks_answered"] > 0
    for name in members[:3]:
        r = s["robots"][name]
        assert [(x["from"], x["to"]) for x in r["version_switches"]] == [(0, 1), (1, 2)], (name, r)
        assert r["policy_version"] == r["policy_held"] == 2 and r["policy_switches"] == 2, (name, r)
        assert r["chunk_queries"] > 1 and r["chunks_refused"] == 0 and r["weights_rejected"] == 0, (name, r)
        assert r["version_switches"][0]["t_s"] - done["push"] < 10.0, (name, r, done)  # 77 chunks, ~4 s at 20 Hz
        assert r["defaults"] == 0, (name, r)
    c = s["central"]
    assert [(x["from"], x["to"]) for x in c["version_switches"]] == [(0, 1), (1, 2)] and c["policy_version"] == 2, c
    assert c["policy_switched_unheld"] == 0, c  # it waited for the robots to hold each version ...
    last_robot = max(s["robots"][m]["version_switches"][0]["t_s"] for m in members[:3])
    assert c["version_switches"][0]["t_s"] >= last_robot, (c, s["robots"])  # ... so it switched after them
    assert s["absences"] == {} and not s["degraded"], s["absences"]
    world = s["world"]
    assert world["ticks_skipped"] <= 0.02 * world["ticks"], world
    assert all(f"acting with policy version {v}" in (run / "logs" / f"{m}.log").read_text()
               for m in members for v in (1, 2))
    # what a fleet refuses, in one line each
    with pytest.raises(BundleError, match=r"realtime fleet takes no staged rollout \(--canary\).*fix: push without"):
        push(paired, run, agents=[0])
    with pytest.raises(BundleError, match=r"does not declare the fleet's running central network.*--works-with"):
        push(alone, run)
    assert len(json.loads((run / "pushes.json").read_text())) == 2


def test_a_secure_fleet_gives_a_stolen_robot_key_that_robot_s_job_only(bundle, tmp_path):
    """`hammer serve --realtime --secure`: every role on mutual TLS with its own identity and the run's
    access rules. Robot 0 is external and never starts; a hostile peer holding robot 1's stolen
    identity joins the fleet's hub and floods uplinks and actions for robot 0 (well formed, each
    stamped as robot 0's) while listening for robot 0's and robot 1's central messages. It gets robot
    1's messages (it is linked in: a stolen key does its robot's job), never robot 0's; neither the
    world nor the central agent ever hears of robot 0."""
    from hammer.protocol.identity import identity_dir
    from hammer.protocol.schemas import Action, CentralMsg
    from hammer.runtime.settings import RuntimeSettings

    b = load_bundle(bundle)
    n, obs_dim = b.env_spec_data["n_agents"], b.env_spec_data["obs_dim"]
    run = tmp_path / "fleet-secure"
    plan = FleetPlan(bundle=bundle, hz=20, seconds=10, secure=True, external=[0], max_absence_s=60)
    got, out = {0: 0, 1: 0}, {"sent": 0}

    def thief() -> None:  # the launcher takes the main thread (it handles SIGTERM)
        assert _wait(lambda: (run / "fleet.json").is_file(), 60), "the fleet did not start"
        fleet = json.loads((run / "fleet.json").read_text())
        out["fleet"] = fleet
        # a client of the fleet's router, as every robot is, with the fleet's rules and robot 1's key
        stolen = RuntimeSettings(run_id=run.name, secure=True, secure_hub=True).secured(
            TransportConfig(mode="client", connect=["tcp/" + fleet["hub"].split("/", 1)[1]]),
            "local-1", None, n, identity_directory=identity_dir(run))
        with HammerSession(run.name, stolen, sender="local-1") as s:
            k = s.keys
            msgs = {i: s.subscribe(k.msg(i), CentralMsg) for i in (0, 1)}
            up0, act0 = s.publisher(k.up(0), block=False), s.publisher(k.act(0), block=False)
            # its own robot's keys: the access rules let it, only the receivers' bounds stop it
            flood = [s.publisher(key, reliable=False) for key in (k.up(1), k.act(1))]
            big = bytes(4 << 20)
            one = np.zeros(1, np.int64)
            # the router is up before the roles (fleet.json is written then): flood once robot 1 is served
            _wait(lambda: bool(msgs[1].drain()), 60)
            end = time.monotonic() + 6
            while time.monotonic() < end:
                up0.publish(Uplink(agent=0, env_idx=one, obs=np.ones((1, obs_dim), np.float32), action=one))
                act0.publish(Action(step=0, env_idx=one, agent=0, action=one, fallback=np.array([False])))
                if out["sent"] % 10 == 0:
                    for p in flood:
                        p.put_bytes(big)
                out["sent"] += 1
                for i in (0, 1):
                    got[i] += len(msgs[i].drain())
                time.sleep(0.02)

    t = threading.Thread(target=thief, daemon=True)
    t.start()
    s = run_fleet(plan, run)
    t.join(30)
    fleet = out["fleet"]
    assert fleet["hub"].startswith("tls/127.0.0.1:") and "--identity" in fleet["commands"]["local-1"]
    # the external robot's command names the router's real endpoint and its identity files
    port = fleet["hub"].rsplit(":", 1)[1]
    assert f"--connect tcp/127.0.0.1:{port} --identity {run / 'identity'}" in fleet["robot_commands"]["local-0"]
    assert json.loads((run / "runtime.json").read_text())["hub_port"] == int(port)
    sent = out["sent"]
    assert sent > 100 and got[1] > 0, (sent, got)  # linked in and doing robot 1's job
    assert got[0] == 0
    robots = s["robots"]
    assert robots["local-0"]["applied"] == 0 and robots["local-0"]["defaults"] > 0, robots["local-0"]
    assert robots["local-1"]["fresh"] > 0 and robots["local-1"]["msg_fresh"] > 0
    assert s["world"]["presence"]["robot_joins"] == n - 1, s["world"]  # the world never heard robot 0 ...
    assert s["central"]["robot_joins"] == n - 1, s["central"]  # ... nor did the central agent
    # the verdict names what happened: robot 0 never joined; robot 1's keys carried a flood its
    # thief sent (refused by size at both receivers), which no one should read as a link failure
    reasons = s["degraded_reasons"]
    assert s["degraded"] and any(r.startswith("local-0 never joined") for r in reasons), reasons
    assert s["rejected_on"]["local-1"]["env"]["size"] > 0 and s["rejected_on"]["local-1"]["central"]["size"] > 0, s
    assert any("refused on local-1's own keys" in r and "stolen" in r for r in reasons), reasons
    assert "local-0" in s["absences"] and s["absences"]["local-0"]["never_joined"]


def test_the_docs_secure_fleet_commands_join_a_robot_from_another_namespace(bundle, tmp_path):
    """docs/fleet.md's pair of commands for a robot on another machine, as written (the TEST-NET
    address replaced by a veth address private to the test's namespaces, the run shortened): `hammer
    serve --realtime 20 --external 1 --listen ... --secure` in one namespace; in the other, robot 1
    from its own folder holding only the bundle and its copy of its three identity files."""
    import os
    import shlex

    reason = netns_reason(("ip",))
    if reason:
        pytest.skip(reason)
    from hammer.benchmarks.netns import NetnsUnavailable, topology

    text = (ROOT / "docs" / "fleet.md").read_text()
    serve_cmd = shlex.split(re.search(r"^(hammer serve bundles/cn3 --realtime .*--secure.*)$", text, re.MULTILINE)[1])
    robot_cmd = shlex.split(re.search(r"^(hammer local --bundle bundles/cn3 .*--identity .*)$", text, re.MULTILINE)[1])
    tag = f"f{os.getpid() % 10000}"
    run = tmp_path / "runs" / "site-a"
    robot_home = tmp_path / "robot"
    shutil.copytree(bundle, tmp_path / "bundles" / "cn3")
    shutil.copytree(bundle, robot_home / "bundles" / "cn3")
    cli = [sys.executable, "-P", "-m", "hammer.cli"]
    edge = [sys.executable, "-P", "-m", "hammer"]

    def fill(cmd: list[str], address: str) -> list[str]:
        cmd = [x.replace("192.0.2.1", address) for x in cmd]
        return [("12" if cmd[i - 1] == "--seconds" else x) for i, x in enumerate(cmd)]

    try:
        with topology(1, tag) as top:
            address = top.links["local-0"][1]
            with open(tmp_path / "serve.log", "w") as f:
                serve = subprocess.Popen(["ip", "netns", "exec", top.hub, *cli, *fill(serve_cmd, address)[1:]],
                                         cwd=tmp_path, env=ENV, stdout=f, stderr=subprocess.STDOUT)
            robot = None
            try:
                key = run / "identity" / "local-1.key"
                assert _wait(lambda: key.is_file() or serve.poll() is not None, 60), "no identities made"
                (robot_home / "identity").mkdir()
                for name in ("ca.pem", "local-1.pem", "local-1.key"):
                    shutil.copy(run / "identity" / name, robot_home / "identity" / name)
                with open(tmp_path / "robot.log", "w") as f:
                    robot = subprocess.Popen(["ip", "netns", "exec", top.agents[0], *edge,
                                              *fill(robot_cmd, address)[1:]],
                                             cwd=robot_home, env=ENV, stdout=f, stderr=subprocess.STDOUT)
                assert serve.wait(150) == 0, (tmp_path / "serve.log").read_text()[-2000:]
                robot.wait(30)
            finally:
                for p in (serve, robot):
                    if p is not None and p.poll() is None:
                        p.kill()
                        p.wait(10)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    s = json.loads((run / "summary.json").read_text())
    robot_log = (tmp_path / "robot.log").read_text()
    assert json.loads((run / "fleet.json").read_text())["hub"].startswith("tls/")
    assert "joined run site-a" in robot_log, robot_log[-2000:]
    one = s["robots"]["local-1"]
    assert one["fresh"] > 0 and one["msg_fresh"] > 0, one  # it acted, on fresh messages, across the veth, over TLS
    assert s["world"]["presence"]["robot_joins"] == 3


@pytest.mark.timeout(420)
def test_a_secure_fleet_across_namespaces_keeps_its_recovery_contract(bundle, tmp_path):
    """The documented secure fleet on a LAN of namespaces (the serving machine, a switch, one namespace
    per robot, each robot from its own folder with its copy of its identity): robot 0's switch port
    down 8 s (within Zenoh's lease), then robot 1's down 30 s (past it). In each: the healthy robots
    keep >= 0.98 of their control rate while it is down, and the cut robot acts on fresh central
    messages, the world and the central agent hear it again, <= 1.5 s after the port is back."""
    reason = netns_reason(("ip",))
    if reason:
        pytest.skip(reason)
    from hammer.benchmarks.fleet_bench import run_trials, trial_line, trial_ok
    from hammer.benchmarks.netns import NetnsUnavailable

    try:
        r = run_trials(bundle, tmp_path, [("port", 8.0, 1), ("port", 30.0, 1)], hz=20, secure=True,
                       results=tmp_path / "trials.jsonl", progress=lambda line: None)
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    trials = r["trials"]
    assert [(t["kind"], t["seconds"], t["cut"]) for t in trials] == [("port", 8.0, ["local-0"]),
                                                                        ("port", 30.0, ["local-1"])], trials
    for t in trials:
        assert trial_ok(t) or _kept_what_the_machine_gave(t), trial_line(t)
    assert r["fleets"][0]["summary"]["ticks"] > 0, r["fleets"]


def _kept_what_the_machine_gave(t: dict) -> bool:
    """The contract with the healthy robots' rate judged against their own rate in the seconds before
    the cut, for a loaded test machine where CPU contention already holds them under 0.98 with every
    link up. What the contract guards against (healthy robots at 0 Hz for the seconds around a cut
    robot's lease expiry) costs far more than the slack allowed here; recovery is judged unchanged."""
    from hammer.benchmarks.fleet_bench import CONTRACT

    during, before = t["healthy_min_fraction"], t.get("healthy_min_fraction_before")
    return (not t["stranded"] and t["back_max_s"] <= CONTRACT["back_s"] and during is not None
            and before is not None and before < CONTRACT["healthy_fraction"] and during >= before - 0.03)


def test_robots_are_back_at_once_after_the_serving_machine_stalls(bundle, tmp_path):
    """A secure fleet on this machine (`hammer serve --realtime --secure`, three robots), its launcher,
    whose session is the fleet's router, stopped for 4 s (SIGSTOP: the CPU starved), then let go. Every
    link's lease expires meanwhile, and every client keeps dialling the stopped router, whose kernel
    still completes the connections. Each robot must act on the world's observations again within the
    recovery contract's 1.5 s of the router running again, and the router refuse no handshake: with
    attempts given up after 0.5 s, Zenoh's TLS listener (100 ms after each handshake that fails) took
    the dead ones first come first served and admitted no one for the rest of the run."""
    from hammer.benchmarks.fleet_bench import CONTRACT, robot_back

    run = tmp_path / "stalled"
    log = (tmp_path / "serve.log").open("wb")
    serve = subprocess.Popen([sys.executable, "-P", "-m", "hammer.cli", "serve", str(bundle), "--realtime", "20",
                              "--seconds", "16", "--secure", "--run-dir", str(run)], cwd=tmp_path, env=ENV,
                             stdout=log, stderr=subprocess.STDOUT)
    try:
        env_log = run / "logs" / "env.log"
        assert _wait(lambda: env_log.is_file() and "world clock starts" in env_log.read_text(), 120), \
            (tmp_path / "serve.log").read_text()
        time.sleep(3)
        down = time.time()
        serve.send_signal(signal.SIGSTOP)
        time.sleep(4)
        serve.send_signal(signal.SIGCONT)
        up = time.time()
        assert serve.wait(120) == 0
    finally:
        if serve.poll() is None:
            serve.send_signal(signal.SIGCONT)
            serve.kill()
            serve.wait()
    s = json.loads((run / "summary.json").read_text())
    backs = {name: robot_back(run / "logs" / f"{name}.log", 4, down, up) for name in s["robots"]}
    assert len(backs) == 3 and all(b is not None and b <= CONTRACT["back_s"] for b in backs.values()), \
        (backs, s["degraded_reasons"])
    assert not any("connections refused" in r for r in s["degraded_reasons"]), s["degraded_reasons"]


def test_the_sdk_loads_no_torch(bundle):
    code = f"""
import sys
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
from hammer.serve.edge_agent import EdgeAgent
port = free_loopback_port()
with HammerSession("r", TransportConfig(listen=[loopback_endpoint(port)]), sender="hub"):
    with EdgeAgent({str(bundle)!r}, 0, run_id="r", connect=loopback_endpoint(port)) as robot:
        robot.act([0.0] * robot.obs_dim)
print("torch" in sys.modules, "torch.nn" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-P", "-c", code], check=False, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["False", "False"]


def test_the_readme_robot_example_runs_against_a_served_fleet(bundle, tmp_path):
    """The README's "On a robot" block, as it stands (only the port made free), against the command the
    README names, from a folder of the user's own; then SIGTERM to `hammer serve`: a summary, exit 0."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("### On a robot"):]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    command = re.search(r"`(hammer serve bundles/lib-cn3 --realtime [^`]*)`", section).group(1)
    port = str(free_loopback_port())
    shutil.copytree(bundle, tmp_path / "bundles" / "lib-cn3")
    r, serve, out = run_block_beside_serve(command, code, tmp_path, "site-a", port)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.split() == ["True", "True"]
    assert serve.returncode == 0, out[-2000:]
    s = json.loads((tmp_path / "runs" / "site-a" / "summary.json").read_text())
    assert s["interrupted"] is True and s["stopped_by"] == "SIGTERM" and "local-0" not in s["restarts"]


def test_the_readme_robot_example_runs_with_no_fleet_at_all(bundle, tmp_path):
    """The same README block with nothing listening at its endpoint (a robot started before its fleet):
    it acts on the fallback all along and its last line prints, with no message age to report."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("### On a robot"):]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    shutil.copytree(bundle, tmp_path / "bundles" / "lib-cn3")
    code = code.replace("7447", str(free_loopback_port())) + \
        "print(robot.age_gauges(), robot.counts.msg_none, robot.counts.acts)\n"
    r = subprocess.run([sys.executable, "-P", "-c", code], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                       timeout=120, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    first, last = r.stdout.strip().splitlines()
    assert first.split() == ["False", "False"]
    assert last == "{'msg_age_p50_ms': None, 'msg_age_p99_ms': None} 60 60"


def test_the_lease_and_the_reconnect_period_are_settings(tmp_path):
    """`zenoh_lease_s` and `reconnect_max_s` reach the Zenoh config of every session a run builds; a
    --zenoh-config file keeps its own retry periods unless one is set; a bad value names the field."""
    from hammer.protocol.structs import SettingsError
    from hammer.runtime.settings import RuntimeSettings

    s = RuntimeSettings(run_id="r", hub_port=free_loopback_port(), zenoh_lease_s=30, reconnect_max_s=0.2)
    c = s.transport().to_zenoh()
    assert json.loads(c.get_json("transport/link/tx/lease")) == 30000
    assert json.loads(c.get_json("connect/retry"))["period_max_ms"] == 200
    with HammerSession("r", s.hub_transport(), sender="hub"), HammerSession("r", s.transport(), sender="env"):
        pass  # Zenoh takes them
    plain = RuntimeSettings(run_id="r", hub_port=7447).hub_transport().to_zenoh()
    assert json.loads(plain.get_json("transport/link/tx/lease")) == 10000
    assert json.loads(plain.get_json("connect/retry"))["period_max_ms"] == 500
    f = tmp_path / "client.json5"
    f.write_text('{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7447"], retry: {period_max_ms: 3000}}}')
    s2 = RuntimeSettings(run_id="r", zenoh_config_file=str(f))
    assert json.loads(s2.transport().to_zenoh().get_json("connect/retry"))["period_max_ms"] == 3000
    s3 = RuntimeSettings(run_id="r", zenoh_config_file=str(f), reconnect_max_s=1.0)
    assert json.loads(s3.transport().to_zenoh().get_json("connect/retry"))["period_max_ms"] == 1000
    with pytest.raises(SettingsError, match="reconnect_max_s"):
        RuntimeSettings(run_id="r", reconnect_max_s=0.01)
    # a fleet's links (a robot, a role: clients of the router) take the fleet's defaults unless given
    fleet = RuntimeSettings(run_id="r").transport_to("tcp/127.0.0.1:7447", client=True).to_zenoh()
    assert json.loads(fleet.get_json("mode")) == "client"
    assert json.loads(fleet.get_json("transport/link/tx/lease")) == 1200
    # over loopback no SYN is lost, and an attempt must wait for a stalled router's turn
    assert json.loads(fleet.get_json("transport/unicast/open_timeout")) == 10000
    away = RuntimeSettings(run_id="r").transport_to("tcp/192.0.2.1:7447", client=True).to_zenoh()
    assert json.loads(away.get_json("transport/unicast/open_timeout")) == 500
    assert json.loads(fleet.get_json("connect/retry"))["period_max_ms"] == 100
    given = RuntimeSettings(run_id="r", zenoh_lease_s=3, zenoh_open_timeout_s=2, reconnect_max_s=0.3)
    c = given.transport_to("tcp/127.0.0.1:7447", client=True).to_zenoh()
    assert [json.loads(c.get_json(k)) for k in ("transport/link/tx/lease", "transport/unicast/open_timeout")] == \
        [3000, 2000] and json.loads(c.get_json("connect/retry"))["period_max_ms"] == 300
    assert json.loads(s.transport().to_zenoh().get_json("transport/unicast/open_timeout")) == 10000  # not a fleet


def test_a_fleet_takes_its_settings_from_the_command_line_and_refuses_bad_ones_in_one_line(bundle, tmp_path):
    """`hammer serve --realtime` takes `--runtime`: the bounds go to the plan, the link settings to
    every role's command and the printed robot command, a bad item is one line naming the field."""
    from hammer.deploy.fleet_launch import apply_runtime, robot_command, role_specs
    from typer.testing import CliRunner

    from hammer.cli import app

    plan = apply_runtime(FleetPlan(bundle=bundle, hub_port=7447, external=[1], listen=["tcp/0.0.0.0:7500"]),
                         ["hold_s=1.5", "zenoh_lease_s=3", "weights_chunk_bytes=1024"])
    assert plan.hold_s == 1.5 and plan.runtime == {"zenoh_lease_s": 3, "weights_chunk_bytes": 1024}
    cmd = robot_command(plan, 1, tmp_path / "site-a")
    assert "--connect 'tcp/<this host>:7500' --insecure --runtime zenoh_lease_s=3 --fleet" in cmd, cmd
    world = role_specs(plan, "site-a", "tcp/127.0.0.1:7447", 3, True, tmp_path)[0].args
    assert world[world.index("--runtime") + 1] == "zenoh_lease_s=3" and world[world.index("--hold-s") + 1] == "1.5"
    for item, says in (("zenoh_lease_s=0.1", "zenoh_lease_s: should be a number >= 0.5"),
                       ("hold_s=abc", "hold_s takes seconds"), ("hub_port=5", "set by --listen"),
                       ("nosuch=1", "nosuch: unknown field")):
        res = CliRunner().invoke(app, ["serve", str(bundle), "--realtime", "20", "--seconds", "2", "--runtime", item,
                                       "--run-dir", str(tmp_path / "never")])
        assert res.exit_code == 2 and says in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not (tmp_path / "never").exists()


def test_the_fleet_soak_bench_samples_every_process(bundle, tmp_path, capsys):
    from hammer.benchmarks.fleet_bench import main

    out = tmp_path / "soak.json"
    # 9 s, a sample a second: every role sampled does not depend on the soak's length
    assert main([str(bundle), "--soak-minutes", "0.15", "--work", str(tmp_path), "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert set(r["growth_pct"]) == {"world", "central", "local-0", "local-1", "local-2"}
    assert r["world"]["ticks"] > 0 and len(r["samples"]) >= 1
    assert "RSS growth" in capsys.readouterr().out
