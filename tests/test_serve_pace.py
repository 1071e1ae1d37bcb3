"""A push pulled in paced chunks: real Zenoh on 127.0.0.1, explicit endpoints, no
scouting, the real policy server and the real weights intake of a local agent.

The policy server announces a pushed version (WeightsAnnounce) instead of publishing it whole; the
agent asks for one chunk at a time (one query outstanding, the next after its step's action), so
no more than one chunk shares a thin link with a step's traffic. A chunk that disagrees with the
announcement is refused and counted; the assembled blob is sha256-checked before it is held. The
whole served path (the env host naming the version once every agent holds it) runs in
tests/test_serve_push.py and tests/test_serve_canary.py, where chunks are the default."""

from __future__ import annotations

import json
import threading
import time

import pytest
from hammer.protocol.codec import encode
from hammer.protocol.schemas import Control, WeightsAnnounce, WeightsChunk
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
from hammer.runtime.settings import RuntimeSettings
from hammer.runtime.weights import WeightsIntake
from hammer.serve.policy_server import PolicyServer

pytestmark = pytest.mark.timeout(120)
CHUNK = 1024
# The served runs that take a push at step 100: 4 env copies, so 1,250 steps. The switch came
# within a few hundred steps of the push (the launcher's tick, the server's history check, ~70 chunks
# of 512 B or one whole-weights query), so the run outlasts it several times over.
PUSH_RUN_EPISODES = 200


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """Two bundles of the cn3 hammer shape: A (served first) and B (pushed), B's local weights
    different bytes from A's (its central network A's)."""
    import shutil

    import numpy as np
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir
    from hammer.learning.trainer import train
    from hammer.serve.bundle import export_bundle
    from safetensors.numpy import load_file, save_file

    root = tmp_path_factory.mktemp("pace")
    cfg = merge_config("cn3", overrides=["num_envs=4", "rollout_steps=25", "epochs=1", "minibatches=1",
                                         "episodes=8", "seed=3"])
    train(cfg, RunDir.create(root / "a", cfg), tensorboard=False)
    shutil.copytree(root / "a", root / "b")
    w = load_file(str(root / "b" / "final" / "local.safetensors"))
    save_file({k: (v + np.float32(0.5)).astype(v.dtype) for k, v in w.items()},
              str(root / "b" / "final" / "local.safetensors"))
    return export_bundle(root / "a", root / "A"), export_bundle(root / "b", root / "B")


@pytest.fixture(scope="module")
def policies(bundles):
    """The two bundles' directories (local.safetensors and central.safetensors each)."""
    return bundles[0].path, bundles[1].path


def _served(tmp_path, b):
    """A run directory whose history pushes B as version 1."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "pushes.json").write_text(json.dumps([{"version": 1, "action": "push", "policy_dir": str(b)}]))
    return run


class _Net:
    """A hub and sessions on it (loopback, explicit endpoints)."""

    def __init__(self, run_id: str) -> None:
        self.run_id, port = run_id, free_loopback_port()
        self.peer = TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[loopback_endpoint(port)])
        self.hub = HammerSession(run_id, TransportConfig(listen=[loopback_endpoint(port)]), sender="launcher").open()
        self.sessions = [self.hub]

    def session(self, sender: str) -> HammerSession:
        s = HammerSession(self.run_id, self.peer, sender=sender).open()
        self.sessions.append(s)
        return s

    def close(self) -> None:
        for s in reversed(self.sessions):
            s.close()


def _serve(net: _Net, policy_dir, run_dir, chunk_bytes=CHUNK) -> tuple[PolicyServer, threading.Thread]:
    settings = RuntimeSettings(run_id="pace", mode="eval", policy_dir=str(policy_dir), weights_chunk_bytes=chunk_bytes)
    server = PolicyServer(net.session("policy"), policy_dir, True, settings, run_dir=run_dir)
    runner = threading.Thread(target=server.run, daemon=True)
    return server, runner


def _pull(intake: WeightsIntake, deadline_s: float = 20.0, step_s: float = 0.02, one_replier: bool = True) -> int:
    """Pump as an agent does after each step's action until a version is held; returns the pumps.
    one_replier: every reply is counted, so with a second replier the bound is not checked."""
    pumps, end = 0, time.monotonic() + deadline_s
    while intake.versions_pulled == 0 and time.monotonic() < end:
        intake.pump()
        assert not one_replier or intake.chunk_queries - intake.chunks_received <= 1  # one outstanding, never more
        pumps += 1
        time.sleep(step_s)
    return pumps


def test_a_push_is_pulled_one_bounded_chunk_at_a_time(policies, tmp_path):
    a, b = policies
    blob = (b / "local.safetensors").read_bytes()
    net = _Net("pace")
    try:
        agent = net.session("local-0")
        loaded: list[int] = []
        intake = WeightsIntake(agent, "local", lambda data, v: loaded.append(v), timeout_s=5.0)
        time.sleep(0.5)  # the subscriptions have reached the hub
        server, runner = _serve(net, a, _served(tmp_path, b))
        runner.start()
        end = time.monotonic() + 10
        while intake.pulling is None and time.monotonic() < end:  # the announcement (version 0 came whole)
            intake.pump()
            time.sleep(0.05)
        assert intake.pulling == 1
        _pull(intake, step_s=0.0)  # pumped as fast as it goes: still one query outstanding at a time
        chunks = -(-len(blob) // CHUNK)
        assert intake.versions_pulled == 1 and intake.chunks_refused == 0
        assert intake.chunk_queries == chunks and intake.chunks_received == chunks  # one query per chunk, no retry
        assert server.counters()["chunks_answered"] == chunks
        intake.take(1)
        assert loaded[-1] == 1 and intake.version == 1 and intake.known == 1
        # what crosses the link per reply: a chunk of at most CHUNK bytes, plus a small header
        asker = net.session("local-1")
        key = asker.keys.weights_chunk("local")

        def ask(params: list[str]) -> list[bytes | None]:
            """One reply payload per query (None: no reply), once the asker reaches the server."""
            got: dict[str, bytes | None] = {}
            end = time.monotonic() + 10
            while time.monotonic() < end and got.get("v=1&i=0") is None:
                got = {}
                for p in ["v=1&i=0", *params]:  # chunk 0 shows that the server was reached
                    replies = asker.zenoh.get(f"{key}?{p}", timeout=2.0)
                    ok = [r.ok.payload.to_bytes() for r in replies if r.ok is not None]
                    got[p] = ok[0] if ok else None
            assert got.get("v=1&i=0") is not None, "the policy server never answered"
            return [got[p] for p in params]

        sizes = [len(r) for r in ask([f"v=1&i={chunks - 1}"]) + ask(["v=1&i=1"])]
        assert all(n <= CHUNK + 64 for n in sizes), sizes
        # nonsense parameters get no reply (the asker is not trusted)
        assert ask(["v=1&i=999", "v=9&i=0", "v=x&i=0", "v=1", "i=" + "9" * 40]) == [None] * 5
        # the announcement itself is small: a few hundred bytes for 35 kB of weights
        assert len(encode(WeightsAnnounce.of("local", 1, blob, CHUNK))) < 64 + 8 * chunks + 200
        net.hub.publish(net.hub.keys.ctl("all"), Control(command="stop"))
        runner.join(timeout=10)
    finally:
        net.close()


def test_a_corrupted_chunk_is_refused_and_counted(policies, tmp_path):
    """A hostile peer answers every chunk query too, with bytes of the right size that are not the
    weights (and with chunks of the wrong size): each of its replies is refused and counted, the
    real chunks are taken, and what is held is exactly version 1's blob (sha256-checked)."""
    a, b = policies
    blob = (b / "local.safetensors").read_bytes()
    net = _Net("pacebad")
    try:
        agent = net.session("local-0")
        held: dict[int, bytes] = {}
        intake = WeightsIntake(agent, "local", lambda data, v: held.__setitem__(v, data), timeout_s=5.0)
        hostile = net.session("evil")

        def forged(params: dict[str, str]) -> WeightsChunk | None:
            if not params.get("i", "").isdecimal():
                return None
            i = int(params["i"])
            size = min(CHUNK, len(blob) - i * CHUNK) if i % 2 else 7  # odd: right size, wrong bytes
            return WeightsChunk(role="local", version=1, index=i, data=b"\x00" * max(size, 1))

        hostile.answer(hostile.keys.weights_chunk("local"), forged, parameters=True)
        time.sleep(0.5)
        _, runner = _serve(net, a, _served(tmp_path, b))
        runner.start()
        _pull(intake, deadline_s=30, one_replier=False)
        assert intake.versions_pulled == 1
        assert intake.chunks_refused >= 1, intake.counters()
        intake.take(1)
        assert held[1] == blob  # the real weights, checked against the announcement's sha256
        net.hub.publish(net.hub.keys.ctl("all"), Control(command="stop"))
        runner.join(timeout=10)
    finally:
        net.close()


def test_a_rollback_to_weights_held_needs_no_pull(policies, tmp_path):
    """A rollback is a new version carrying weights the agent had: the announcement's sha256 names
    bytes it holds, so it is held at once, with no chunk asked for."""
    a, b = policies
    net = _Net("paceroll")
    try:
        agent = net.session("local-0")
        intake = WeightsIntake(agent, "local", lambda data, v: None, timeout_s=5.0)
        time.sleep(0.5)
        run = tmp_path / "run"
        run.mkdir()
        _, runner = _serve(net, a, run)
        runner.start()
        # Version 0 held first, as an agent holds it: the server's first publication, or, when that
        # went out before the new server's session learnt of this subscription (a loaded machine),
        # the query an agent without its version sends. Pushed while it was unheld, it could only
        # be pulled whole later, which is not what this test is about.
        intake.take(0)
        assert intake.version == 0 and intake.chunk_queries == 0
        (run / "pushes.json").write_text(json.dumps([{"version": 1, "action": "push", "policy_dir": str(b)}]))
        _pull(intake)
        asked = intake.chunk_queries
        intake.take(1)
        entries = json.loads((run / "pushes.json").read_text())
        entries.append({"version": 2, "action": "rollback", "policy_dir": str(a)})
        (run / "pushes.json").write_text(json.dumps(entries))
        end = time.monotonic() + 10
        while intake.known < 2 and time.monotonic() < end:
            intake.pump()
            time.sleep(0.05)
        assert intake.known == 2 and intake.chunk_queries == asked  # version 0's bytes, held since the start
        net.hub.publish(net.hub.keys.ctl("all"), Control(command="stop"))
        runner.join(timeout=10)
    finally:
        net.close()


def test_a_push_the_agents_do_not_hold_in_time_is_named_after_the_timeout(bundles, tmp_path):
    """weights_name_timeout_s shorter than any pull: the env host names version 1 before the agents
    hold it (counted as push_named_unheld, logged); each agent then asks for the current weights
    whole (a late joiner's query) at the step that names it, and every agent still switches at one
    step, with no action of the wrong version."""
    import numpy as np
    from hammer.deploy.launcher import launch
    from hammer.serve.push import push
    from hammer.serve.served_settings import serve_settings

    a, b = bundles
    cfg = a.config(episodes=PUSH_RUN_EPISODES, msg_dropout=0.0)
    # 64 B chunks: ~550 of them, one per step, a pull far longer than the timeout even on loopback
    settings, _ = serve_settings(a, "paceearly", runtime=["trace=true", "weights_name_timeout_s=0.001",
                                                          "weights_chunk_bytes=64"])
    run = tmp_path / "served"
    done: list[int] = []

    def update(sup, board) -> None:  # the launcher's tick: push once the run is stepping
        env = board.heartbeats.get("env")
        if not done and env is not None and int(env.counters.get("step", 0)) >= 100:
            push(b.path, run)
            done.append(1)

    res = launch(cfg, settings, run, chaos=update)
    assert res.summary["completed"] and done
    pushes = json.loads((run / "env_summary.json").read_text())["pushes"]
    assert pushes["named"] == 1 and pushes["named_unheld"] == 1, pushes
    trace = dict(np.load(run / "trace.npz"))
    versions = trace["versions"]
    assert set(versions.tolist()) == {0, 1} and np.all(np.diff(versions) >= 0)  # one switch, every agent
    assert res.summary["links"]["off_policy_actions"] == 0


def test_a_push_is_pulled_in_a_secure_run(bundles, tmp_path):
    """Under the secure profile's access rules (protocol/access.py) the announcement reaches the
    agents and the env host, each agent may ask for the chunks and only the policy server answers:
    the push is named once every agent holds it, none by the timeout."""
    import numpy as np
    from hammer.deploy.launcher import launch
    from hammer.serve.push import push
    from hammer.serve.served_settings import serve_settings

    a, b = bundles
    settings, _ = serve_settings(a, "pacesecure", runtime=["trace=true", "secure=true"])
    run = tmp_path / "served"
    done: list[int] = []

    def update(sup, board) -> None:
        env = board.heartbeats.get("env")
        if not done and env is not None and int(env.counters.get("step", 0)) >= 100:
            push(b.path, run)
            done.append(1)

    res = launch(a.config(episodes=PUSH_RUN_EPISODES, msg_dropout=0.0), settings, run, chaos=update)
    assert res.summary["completed"] and done
    pushes = json.loads((run / "env_summary.json").read_text())["pushes"]
    assert pushes["named"] == 1 and pushes["named_unheld"] == 0, pushes
    assert set(np.load(run / "trace.npz")["versions"].tolist()) == {0, 1}
