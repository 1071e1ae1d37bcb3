"""The edge entry (hammer/entry.py -> hammer/commands/edge.py -> serve/edge_entry.py): `hammer local --bundle` starts without the CLI
framework or the training config, takes the served run's runtime settings, and joins a secure run with
only its three identity files (no run directory). Real processes, real Zenoh on 127.0.0.1. The served
runs go twice: a team of 32 env copies (the numpy agent) and of one (K=1: the lite agent, which never
imports numpy, local_agent/lite.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time

import pytest
from hammer.benchmarks.edge_bench import make_team
from hammer.deploy.launcher import launch
from hammer.protocol.session import free_loopback_port
from hammer.runtime.settings import RuntimeSettings
from hammer.serve.edge_entry import edge_inputs
from hammer.serve.served_settings import serve_settings

from tests.runtime_helpers import ENV, ROOT

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    bundle, _, cfg, _ = make_team(tmp_path_factory.mktemp("team"))
    return bundle, cfg


@pytest.fixture(scope="module")
def team1(tmp_path_factory):
    """The same team on one env copy: the edge agent acts without numpy."""
    bundle, _, cfg, _ = make_team(tmp_path_factory.mktemp("team1"), overrides=("num_envs=1",))
    return bundle, cfg


# (team fixture, episodes of 25 steps giving 50 vector steps, what the edge agent logs about its acting)
SERVED = {"k32-numpy": ("team", 64, "acts with numpy (K=32 env copies)"),
          "k1-lite": ("team1", 2, "acts in plain Python, without numpy")}


def test_the_edge_entry_loads_neither_the_cli_framework_nor_the_training_config(team):
    bundle, _ = team
    r = subprocess.run([sys.executable, "-X", "importtime", "-m", "hammer", "local", "--bundle", str(bundle.path),
                        "--agent", "7", "--run-id", "x", "--connect", "tcp/127.0.0.1:9"],
                       check=False, capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=60)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and lines[-1] == "error: --agent 7: this team has agents 0..2", lines[-1]
    loaded = {ln.split("|")[-1].strip() for ln in lines if ln.startswith("import time:")}
    assert "hammer.serve.edge_entry" in loaded and "hammer.protocol.session" in loaded
    assert not loaded & {"typer", "rich", "hammer.learning.config", "torch", "hammer.cli", "yaml"}, loaded & {
        "typer", "rich", "hammer.learning.config", "torch", "hammer.cli", "yaml"}


_WHO_IMPORTS_PYDANTIC = """
import builtins, json, sys
importers = set()
real = builtins.__import__
def hook(name, globals=None, locals=None, fromlist=(), level=0):
    who = (globals or {}).get("__name__", "?")
    if level == 0 and name.split(".")[0] in ("pydantic", "pydantic_core") and not who.startswith("pydantic"):
        importers.add(who)
    return real(name, globals, locals, fromlist, level)
builtins.__import__ = hook
from pathlib import Path
from hammer.commands.edge import parser
from hammer.serve.edge_entry import edge_inputs
import hammer.faults.steplog, hammer.local_agent.client, hammer.runtime.process, hammer.serve.edge_agent
bundle, settings = sys.argv[1:3]
parser().parse_args(["--bundle", bundle, "--agent", "0"])
s, t, spec, k = edge_inputs(Path(bundle), 0, None, "tcp/127.0.0.1:7447", None, None, settings_file=Path(settings),
                            runtime=["fallback_k=5", "msg_deadline_ms=20"])
assert s.faults.enabled and s.fallback_k == 5 and t.connect == ["tcp/127.0.0.1:7447"]
print(json.dumps({"importers": sorted(importers), "loaded": "pydantic" in sys.modules}))
"""


def test_the_edge_agents_settings_load_no_pydantic(team, tmp_path):
    """RuntimeSettings, TransportConfig, FaultSpec, the link faults: the edge agent reads them (runtime.json with
    faults, --runtime items) as msgspec Structs (protocol/structs.py), like the wire messages: no module of the
    edge path imports pydantic (its memory and start time: docs/deploy.md "Footprint")."""
    import json

    bundle, _ = team
    RuntimeSettings(run_id="served-x", mode="eval", policy_dir=str(bundle.path), hub_port=7447,
                    faults={"seed": 3, "rules": [{"match": "agent/act/*", "drop": 0.1}]}).save(tmp_path)
    r = subprocess.run([sys.executable, "-c", _WHO_IMPORTS_PYDANTIC, str(bundle.path), str(tmp_path / "runtime.json")],
                       check=False, capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=60)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["importers"] == [] and out["loaded"] is False, out


def test_the_served_runs_runtime_json_and_runtime_items_set_the_edge_agent(team, tmp_path):
    bundle, _ = team
    RuntimeSettings(run_id="served-x", msg_deadline_ms=12, fallback="last", step_window=77, hub_port=7447,
                    mode="eval", policy_dir=str(bundle.path)).save(tmp_path)
    settings, transport, spec, k = edge_inputs(bundle.path, 1, None, "tcp/127.0.0.1:7447", None, None,
                                               settings_file=tmp_path / "runtime.json", runtime=["fallback_k=5"])
    assert (settings.run_id, settings.msg_deadline_ms, settings.fallback, settings.fallback_k, settings.step_window) \
        == ("served-x", 12, "last", 5, 77)
    assert transport.connect == ["tcp/127.0.0.1:7447"] and (spec.agent, spec.obs_dim, spec.msg_dim, k) == (1, 18, 4, 32)
    s, _, _, _ = edge_inputs(bundle.path, 0, "plain", "tcp/127.0.0.1:7448", None, 5)
    assert (s.fallback, s.msg_deadline_ms) == ("zeros", 50.0)  # no settings: the bundle's fallback, defaults
    with pytest.raises(ValueError, match="--run-id"):
        edge_inputs(bundle.path, 0, None, "tcp/127.0.0.1:7447", None, None)
    with pytest.raises(ValueError, match="msg_deadline_ms"):
        edge_inputs(bundle.path, 0, "x", "tcp/127.0.0.1:7447", None, None, runtime=["msg_deadline_ms=-1"])
    with pytest.raises(ValueError, match="refusing to run plain on .*--identity DIR.*--insecure"):  # a LAN hub, plain
        edge_inputs(bundle.path, 0, "plain", "tcp/192.0.2.1:7447", None, None)
    _, t, _, _ = edge_inputs(bundle.path, 0, "plain", "tcp/192.0.2.1:7447", None, None, insecure=True)
    assert t.connect == ["tcp/192.0.2.1:7447"] and t.listen == ["tcp/0.0.0.0:0"]
    # no Zenoh shared-memory pool (mapped, and counted in the RSS, once a peer on the same host sends)
    assert t.shared_memory is False and t.to_zenoh().get_json("transport/shared_memory/enabled") == "false"
    RuntimeSettings(run_id="sec", secure=True).save(tmp_path)
    with pytest.raises(ValueError, match="--identity"):  # a secure run without the agent's identity files
        edge_inputs(bundle.path, 0, None, "tcp/127.0.0.1:7447", None, None, settings_file=tmp_path / "runtime.json")


def _join_when_ready(run, bundle, port, ids, out: dict, agent: int = 2) -> None:
    """What a person does on the edge machine: copy the agent's three identity files and runtime.json
    from the launcher's run directory, then start the agent from the bundle."""
    deadline = time.monotonic() + 60
    while not (run / "identity" / f"local-{agent}.key").is_file() and time.monotonic() < deadline:
        time.sleep(0.05)
    ids.mkdir()
    for name in ("ca.pem", f"local-{agent}.pem", f"local-{agent}.key"):
        shutil.copy(run / "identity" / name, ids / name)
    shutil.copy(run / "runtime.json", ids.parent / "served-runtime.json")
    env = {k: v for k, v in ENV.items()}
    out["proc"] = subprocess.Popen([sys.executable, "-m", "hammer", "local", "--bundle", str(bundle.path), "--agent",
                                    str(agent),
                                    "--settings", str(ids.parent / "served-runtime.json"), "--identity", str(ids),
                                    "--connect", f"tcp/127.0.0.1:{port}"], cwd=ROOT, env=env,
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@pytest.mark.parametrize("served", SERVED)
def test_a_secure_served_run_takes_an_edge_agent_with_only_its_identity_files(served, request, tmp_path):
    fixture, episodes, acting = SERVED[served]
    bundle, _ = request.getfixturevalue(fixture)
    port = free_loopback_port()
    settings, _ = serve_settings(bundle, "secure-edge", runtime=[f"hub_port={port}", "secure=true"])
    run, out = tmp_path / "served", {}
    joiner = threading.Thread(target=_join_when_ready, args=(run, bundle, port, tmp_path / "edge" / "id", out))
    (tmp_path / "edge").mkdir()
    joiner.start()
    try:
        res = launch(bundle.config(episodes=episodes, msg_dropout=0.0), settings, run, external_agents=(2,))
        joiner.join(timeout=30)
        text, _ = out["proc"].communicate(timeout=30)
    finally:
        joiner.join(timeout=30)
        if "proc" in out and out["proc"].poll() is None:
            out["proc"].kill()
    assert res.summary["completed"] and res.summary["episodes"] == episodes
    assert out["proc"].returncode == 0, text
    assert acting in text, text
    assert "tls/" in text and "'steps': 50," in text  # over TLS, every step of the run (25-step episodes)
    assert res.links["local->env"]["defaults"] == 0


@pytest.mark.parametrize("served", SERVED)
def test_a_thief_of_the_edge_agents_files_is_that_agent_and_nothing_more(served, request, tmp_path):
    """A stolen identity in the served profile: the real agent 1 on the edge entry with its three files, and a
    thief holding the same three files attacking through agent 1's own keys (tests/own_key_thief.py).
    The run completes with no default action, every attempt refused and named in the summary."""
    from hammer.protocol.session import TransportConfig
    from hammer.runtime.settings import RuntimeSettings as RS

    from tests.own_key_thief import OwnKeyThief

    fixture, episodes, acting = SERVED[served]
    bundle, _ = request.getfixturevalue(fixture)
    port = free_loopback_port()
    settings, _ = serve_settings(bundle, "secure-thief", runtime=[f"hub_port={port}", "secure=true",
                                                                  "msg_deadline_ms=5000", "act_deadline_ms=10000"])
    run, out, thieves = tmp_path / "served", {}, []
    joiner = threading.Thread(target=_join_when_ready, args=(run, bundle, port, tmp_path / "edge" / "id", out, 1))
    (tmp_path / "edge").mkdir()
    joiner.start()

    def chaos(sup, board) -> None:
        if not thieves and "local-1" in board.alive:
            rt = RS.load(run)
            stolen = rt.secured(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]),
                                "local-1", None, 3, identity_directory=tmp_path / "edge" / "id")
            thieves.append(OwnKeyThief(rt.run_id, stolen, agent=1))
            thieves[0].start()

    try:
        res = launch(bundle.config(episodes=episodes, msg_dropout=0.0), settings, run, chaos=chaos,
                     external_agents=(1,))
        joiner.join(timeout=30)
        text, _ = out["proc"].communicate(timeout=30)
    finally:
        for t in thieves:
            t.stop_event.set()
            t.join(10)
        joiner.join(timeout=30)
        if "proc" in out and out["proc"].poll() is None:
            out["proc"].kill()
    thief = thieves[0]
    assert thief.error is None, thief.error
    assert thief.obs_seen > 0 and all(n > 0 for n in thief.sent.values()), thief.sent
    assert res.summary["completed"] and res.summary["episodes"] == episodes
    assert out["proc"].returncode == 0, text
    assert acting in text, text
    assert res.links["local->env"]["defaults"] == 0 and res.links["local->env"]["duplicate"] == 0
    rejected = res.summary["rejected"]
    assert {"key_mismatch", "size"} <= rejected["env"].keys(), rejected
    # an external agent may come and go, but no more than 8 processes of it count; falling counters never
    assert {"key_mismatch", "field", "counters_fell", "heartbeat_processes"} <= rejected["launcher"].keys(), rejected
    assert res.summary["degraded"] is True


@pytest.fixture(scope="module")
def lite_push_run(team1, tmp_path_factory):
    """One served run of the K=1 team, signed, that the two tests below check: its agent 0 is the lite
    edge agent started from the signed bundle with --trust (its memory maps read every 50 ms while it
    runs), and the run takes a push mid-run (a bundle of the same team with other local weights)."""
    import numpy as np
    from hammer.serve.bundle import export_bundle
    from hammer.serve.push import push
    from hammer.serve.signing import new_key
    from safetensors.numpy import load_file, save_file

    bundle, _ = team1
    tmp = tmp_path_factory.mktemp("lite")
    _, public = new_key(tmp / "keys" / "site")
    signed = export_bundle(bundle.path.parent / "run", tmp / "signed", sign=tmp / "keys" / "site.key")
    src = tmp / "b-run"
    shutil.copytree(bundle.path.parent / "run", src)
    w = load_file(str(src / "final" / "local.safetensors"))
    save_file({k: (v + np.float32(0.25)).astype(v.dtype) for k, v in w.items()}, str(src / "final" / "local.safetensors"))
    b = export_bundle(src, tmp / "B")
    port = free_loopback_port()
    settings, _ = serve_settings(signed, "lite-push", runtime=[f"hub_port={port}"])
    run, out, pushed = tmp / "served", {"maps": 0, "numpy": []}, []

    def edge() -> None:
        proc = out["proc"] = subprocess.Popen(
            [sys.executable, "-m", "hammer", "local", "--bundle", str(signed.path), "--agent", "0", "--run-id",
             settings.run_id, "--connect", f"tcp/127.0.0.1:{port}", "--trust", str(public)],
            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        while proc.poll() is None:
            try:
                maps = open(f"/proc/{proc.pid}/maps").read()  # noqa: SIM115 - read at once while it runs
            except OSError:
                break
            out["maps"] += 1
            out["numpy"] += [ln for ln in maps.splitlines() if "numpy" in ln][:3]
            time.sleep(0.05)

    def chaos(sup, board) -> None:  # push once the run is stepping
        env = board.heartbeats.get("env")
        if not pushed and env is not None and int(env.counters.get("step", 0)) >= 25:
            push(b.path, run)
            pushed.append(True)

    watcher = threading.Thread(target=edge)
    watcher.start()
    try:
        res = launch(signed.config(episodes=24, msg_dropout=0.0), settings, run, chaos=chaos, external_agents=(0,))
        watcher.join(timeout=30)
        text, _ = out["proc"].communicate(timeout=30)
    finally:
        if "proc" in out and out["proc"].poll() is None:
            out["proc"].kill()
        watcher.join(timeout=30)
    return res, out, text, run, pushed


def test_a_k1_edge_agent_from_a_signed_bundle_acts_without_ever_loading_numpy(lite_push_run):
    """The lite edge agent of a discrete K=1 team, from a signed bundle it checks with
    --trust, acts every step of a served run and never maps numpy (its memory maps are read while it
    acts, so an import anywhere on the acting path, lazy or not, would show), a push's pull included."""
    res, out, text, _, _ = lite_push_run
    assert res.summary["completed"] and res.summary["episodes"] == 24
    assert out["proc"].returncode == 0, text
    assert "acts in plain Python, without numpy" in text and "'steps': 600," in text, text  # 24 episodes of 25 steps
    assert res.links["local->env"]["defaults"] == 0
    assert out["maps"] >= 3 and out["numpy"] == [], out["numpy"]


def test_a_push_reaches_a_lite_edge_agent_in_chunks_and_is_named_once_held(lite_push_run):
    """A paced push to the lite edge agent: a served run whose agent 0 is the lite edge agent (K=1, no
    numpy) takes a push mid-run; the agent pulls the new weights in paced chunks like the numpy
    agents, says it holds them, and the env host names the version for every agent only then."""
    res, out, text, run, pushed = lite_push_run
    assert res.summary["completed"] and pushed
    assert out["proc"].returncode == 0, text
    assert "acts in plain Python, without numpy" in text, text
    env_summary = json.loads((run / "env_summary.json").read_text())
    assert env_summary["pushes"]["named"] == 1 and env_summary["pushes"]["named_unheld"] == 0, env_summary["pushes"]
    assert res.links["local->env"]["defaults"] == 0
