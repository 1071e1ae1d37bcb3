"""Hot update and rollback of a served team (serve/push.py): real role processes, real Zenoh on 127.0.0.1,
real cn3. A push and a rollback land mid-run; the env host's trace shows every step, the version each
was acted with, and what the agents did, which is replayed with the bundles' weights."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from hammer.deploy.launcher import launch
from hammer.learning.central_acting import CentralActing, encode_actions, zero_prev_actions
from hammer.learning.numpy_policy import NumpyCentralAgent
from hammer.learning.sampling import ActingStreams
from hammer.local_agent.client import AgentSpec, LocalAgent
from hammer.runtime.settings import RuntimeSettings
from hammer.serve.bundle import BundleError, export_bundle
from hammer.serve.push import push, read_history, rollback
from hammer.serve.served_settings import serve_settings
from safetensors.numpy import load_file, save_file
from typer.testing import CliRunner

from hammer.cli import app
from tests.runtime_helpers import SHORT_RUN, trained_run

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """Team A (a short real training run) and team B: A with a random, sharp action head (a briefly
    trained head is near uniform) and another central message head, so B acts and messages clearly
    differently on the same inputs."""
    root = tmp_path_factory.mktemp("teams")
    trained_run(root / "a", (*SHORT_RUN, "episodes=24", "seed=6"))
    shutil.copytree(root / "a", root / "b")
    w = load_file(str(root / "b" / "final" / "local.safetensors"))
    last = max(int(k.split(".")[2]) for k in w if k.startswith("actor.layers."))
    head = f"actor.layers.{last}.weight"
    w[head] = np.random.default_rng(0).normal(0.0, 3.0, w[head].shape).astype(np.float32)
    save_file(w, str(root / "b" / "final" / "local.safetensors"))
    c = load_file(str(root / "b" / "final" / "central.safetensors"))
    c["head_weight"] = np.random.default_rng(1).normal(0.0, 1.0, c["head_weight"].shape).astype(np.float32)
    save_file(c, str(root / "b" / "final" / "central.safetensors"))
    return export_bundle(root / "a", root / "A"), export_bundle(root / "b", root / "B")


def _replay(bundle_of_version: dict, cfg, spec, trace) -> np.ndarray:
    """Each local agent's actions on the recorded observations and messages, with the weights of the
    version each step names, drawing its own random stream step by step as the client does."""
    blobs = {v: (b.path / "local.safetensors").read_bytes() for v, b in bundle_of_version.items()}
    agents = [LocalAgent(AgentSpec.from_config(cfg, spec, i)) for i in range(cfg.n_agents)]
    out = np.zeros(trace["actions"].shape, np.int64)
    for t, v in enumerate(trace["versions"]):
        for i, a in enumerate(agents):
            if a.version != v:
                a.load_weights(blobs[int(v)], int(v))
            out[t, :, i] = a.act(trace["obs"][t, :, i], trace["msgs"][t, :, i])
    return out


def _central_replay(bundle_of_version: dict, cfg, spec, trace) -> np.ndarray:
    """The central agent's messages on the recorded observations and actions, with the central weights
    of the version each step names, drawing its stream step by step as the central server does."""
    acting, streams = CentralActing.from_config(cfg), ActingStreams(cfg.seed, cfg.n_agents)
    nets = {v: NumpyCentralAgent(load_file(str(b.path / "central.safetensors"))) for v, b in bundle_of_version.items()}
    out = np.zeros(trace["msgs"].shape, np.float32)
    k = trace["actions"].shape[1]
    for t, (step, v) in enumerate(zip(trace["steps"], trace["versions"])):
        first = (int(step) - 1) % spec.max_steps == 0  # every cn copy starts an episode together
        prev = zero_prev_actions(spec, k) if first else encode_actions(spec, trace["actions"][t - 1],
                                                                        np.ones((k, cfg.n_agents), bool))
        net = nets[int(v)]
        out[t] = acting.messages(acting.global_state(trace["obs"][t], prev), streams, 0.0, net.message_mean,
                                 net.values if acting.rl else None).sent
    return out


def test_push_and_rollback_switch_every_agent_at_one_step(bundles, tmp_path):
    a, b = bundles
    cfg = a.config(episodes=640, msg_dropout=0.0)
    settings, _ = serve_settings(a, "pushed", runtime=["trace=true"])
    run = tmp_path / "served"
    done: list[str] = []

    def update(sup, board) -> None:  # the launcher's tick: push at ~step 300, roll back ~400 steps later
        env = board.heartbeats.get("env")
        step = int(env.counters.get("step", 0)) if env else 0
        version = int(env.gauges.get("policy_version", 0)) if env else 0
        if not done and step >= 300:
            push(b.path, run)
            done.append("push")
        elif done == ["push"] and version == 1 and step >= 700:
            rollback(run)
            done.append("rollback")

    res = launch(cfg, settings, run, chaos=update)
    assert res.summary["completed"] and done == ["push", "rollback"]
    trace = dict(np.load(run / "trace.npz"))
    steps, versions = trace["steps"], trace["versions"]
    assert np.array_equal(steps, np.arange(1, len(steps) + 1))  # no step missed
    # An action past the act deadline (a loaded machine) is replaced by the default; the agent still
    # acted (its random stream moved on), so the replay below skips only those entries.
    ok = ~trace["defaulted"]
    assert ok.mean() > 0.99, f"default actions at steps {steps[~ok.all(axis=(1, 2))]}"
    assert res.summary["links"]["off_policy_actions"] == 0  # no action of another version than its step's
    assert np.all(np.diff(versions) >= 0) and set(versions.tolist()) == {0, 1, 2}
    assert (versions == 1).sum() > 50 and (versions == 2).sum() > 50
    assert [e["action"] for e in read_history(run)] == ["push", "rollback"]
    # Both were named only once every agent held them (pulled in chunks; the rollback's bytes were held)
    pushes = json.loads((run / "env_summary.json").read_text())["pushes"]
    assert pushes["named"] == 2 and pushes["named_unheld"] == 0, pushes
    spec = a.env_spec()
    acted = trace["actions"]
    replay = _replay({0: a, 1: b, 2: a}, cfg, spec, trace)
    assert np.array_equal(replay[ok], acted[ok])  # each step acted by one version; rollback: A's behaviour exactly
    only_a = _replay({0: a, 1: a, 2: a}, cfg, spec, trace)
    in_b = ok & (versions == 1)[:, None, None]
    assert (only_a[in_b] != acted[in_b]).mean() > 0.3  # B did act differently in its window
    # The central agent switched at the same steps: its messages are B's central network's in B's window.
    sent = ~trace["fallback"] & ~trace["defaulted"]  # what the central agent sent and an agent acted on
    msgs = _central_replay({0: a, 1: b, 2: a}, cfg, spec, trace)
    assert np.allclose(msgs[sent], trace["msgs"][sent], atol=1e-6)
    a_msgs = _central_replay({0: a, 1: a, 2: a}, cfg, spec, trace)
    b_sent = sent & (versions == 1)[:, None, None]
    assert np.abs(a_msgs[b_sent] - trace["msgs"][b_sent]).mean() > 0.05  # B's messages, not A's


def test_push_checks_and_cli(bundles, tmp_path):
    a, _ = bundles
    runner = CliRunner()
    r = runner.invoke(app, ["rollback", str(tmp_path)])
    assert r.exit_code == 2 and "error:" in r.output and "runtime.json" in r.output
    settings, _ = serve_settings(a, "checks")
    run = tmp_path / "run"
    run.mkdir()
    settings.save(run)
    (run / "config.json").write_text(__import__("json").dumps(a.config_data))
    (run / "env_spec.json").write_text(__import__("json").dumps(a.env_spec_data))
    r = runner.invoke(app, ["rollback", str(run)])
    assert r.exit_code == 2 and "nothing to roll back" in r.output
    cn5 = tmp_path / "cn5"
    shutil.copytree(a.path, cn5)
    with pytest.raises(BundleError):  # a bundle whose manifest no longer matches its files
        (cn5 / "manifest.json").write_text((cn5 / "manifest.json").read_text().replace('"n_agents": 3', '"n_agents": 5'))
        push(cn5, run)
    from hammer.serve.bundle import MANIFEST
    from hammer.serve.signing import new_key, sign_manifest

    _, pub = new_key(tmp_path / "keys" / "site")
    r = runner.invoke(app, ["push", str(a.path), "--to", str(run), "--trust", str(pub)])
    assert r.exit_code == 2 and "not signed" in r.output and not (run / "pushes.json").exists()
    signed = tmp_path / "signed"
    shutil.copytree(a.path, signed)
    sign_manifest(signed / MANIFEST, tmp_path / "keys" / "site.key")
    r = runner.invoke(app, ["push", str(signed), "--to", str(run), "--trust", str(pub)])
    assert r.exit_code == 0 and "policy version 1" in r.output
    r = runner.invoke(app, ["rollback", str(run)])
    assert r.exit_code == 0 and "version 2 serves the policy of version 0" in r.output


def test_the_policy_server_publishes_once_and_a_late_joiner_asks(bundles):
    """A policy crosses each link once per version: the policy server publishes version 0 once (a
    role subscribed from the start gets exactly one copy in 6 s); a role that joins later asks for it
    (runtime/weights.py: a query the server answers) and loads it, and nobody else receives a copy.
    With weights_republish_s > 0 it republishes, backing off (0, 0.5, 1.5, 3.5 s: not every 0.5 s)."""
    import threading
    import time

    from hammer.protocol.schemas import Control, Weights
    from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port, loopback_endpoint
    from hammer.runtime.weights import WeightsIntake
    from hammer.serve.policy_server import PolicyServer

    a, _ = bundles
    for republish_s in (0.0, 0.5):
        port = free_loopback_port()
        peer = TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[loopback_endpoint(port)])
        with HammerSession("once", TransportConfig(listen=[loopback_endpoint(port)]), sender="launcher") as hub, \
                HammerSession("once", peer, sender="policy") as s, HammerSession("once", peer, sender="local-1") as w:
            got = w.subscribe(w.keys.weights("local"), Weights)
            time.sleep(0.5)  # the subscription has reached the other sessions
            settings = RuntimeSettings(run_id="once", mode="eval", policy_dir=str(a.path), weights_republish_s=republish_s,
                                       weights_republish_max_s=4.0)
            server = PolicyServer(s, a.path, True, settings)
            runner = threading.Thread(target=server.run, daemon=True)
            t0 = time.monotonic()
            runner.start()
            time.sleep(1.0)
            with HammerSession("once", peer, sender="local-0") as j:  # a role that joins late
                loaded: list[int] = []
                intake = WeightsIntake(j, "local", lambda blob, v, loaded=loaded: loaded.append(v), timeout_s=5.0)
                end = time.monotonic() + 5
                while not loaded and time.monotonic() < end:
                    intake.preload_oldest()
                    time.sleep(0.05)
            arrivals = []
            while time.monotonic() - t0 < 6.0:
                if got.get(timeout=0.05) is not None:
                    arrivals.append(time.monotonic() - t0)
            hub.publish(hub.keys.ctl("all"), Control(command="stop"))
            runner.join(timeout=10)
        assert loaded == [0] and intake.fetches >= 1, (loaded, intake.fetches)
        if republish_s == 0:
            assert len(arrivals) == 1, arrivals  # published once; the joiner's copy went to the joiner only
            assert server.counters()["weights_answered"] >= 1
        else:
            assert 3 <= len(arrivals) <= 5, arrivals  # a fixed 0.5 s period would have sent 12


def test_a_push_or_rollback_to_a_served_run_that_has_ended_is_refused_in_one_line(bundles, tmp_path):
    """`hammer serve` run to its budget, then `hammer push`: real processes, as a user types them."""
    import subprocess
    import sys

    from tests.runtime_helpers import ENV

    a, b = bundles
    run = tmp_path / "served"
    r = subprocess.run([sys.executable, "-m", "hammer", "serve", str(a.path), "--episodes", "8", "--run-dir", str(run)],
                       capture_output=True, text=True, env=ENV, timeout=150, check=False)
    assert r.returncode == 0 and (run / "summary.json").is_file(), r.stderr[-2000:]
    for args in (["push", str(b.path), "--to", str(run)], ["rollback", str(run)]):
        r = subprocess.run([sys.executable, "-m", "hammer", *args], capture_output=True, text=True, env=ENV,
                           timeout=60, check=False)
        assert r.returncode == 2 and r.stdout == "" and r.stderr.count("\n") == 1, (r.stdout, r.stderr)
        assert "the served run has ended (it spent its budget; summary.json)" in r.stderr
        assert f"hammer serve BUNDLE --run-dir {run}" in r.stderr
        assert not (run / "pushes.json").exists() and not (run / "policies").exists()
