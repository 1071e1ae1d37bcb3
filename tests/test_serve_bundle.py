"""Bundles of trained teams (serve/bundle.py): export from a real run, every check a loader makes, and a
served run an edge agent joins from the bundle alone (real processes, real Zenoh on 127.0.0.1)."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from hammer.deploy.launcher import launch
from hammer.envs.registry import make_vec_env
from hammer.learning.config import merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import train
from hammer.protocol.session import free_loopback_port
from hammer.serve.bundle import BUNDLE_FORMAT, BundleError, export_bundle, load_bundle, seal
from hammer.serve.served_settings import serve_settings
from typer.testing import CliRunner

from hammer.cli import app
from tests.runtime_helpers import ENV, ROOT, SHORT_RUN, trained_run

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A short real cn3 HAMMER (rl mode) training run: final/ has a local and a central policy."""
    return trained_run(tmp_path_factory.mktemp("team") / "run", (*SHORT_RUN, "episodes=48", "seed=4"))


def _copy(bundle, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(bundle, dst)
    return dst


def test_export_writes_a_checked_bundle(trained, tmp_path):
    b = export_bundle(trained, tmp_path / "b")
    m = b.manifest
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["central.safetensors", "local.safetensors",
                                                                  "manifest.json"]
    assert m["bundle_format"] == BUNDLE_FORMAT and m["variant"] == "hammer" and m["central_mode"] == "rl"
    assert m["env"]["id"] == "cn" and m["env_spec"]["obs_dim"] == 18 and m["msg_dim"] == 4
    assert m["source"]["run"] == "run" and m["source"]["episodes"] == 48
    summary = json.loads((trained / "summary.json").read_text())
    assert m["source"]["final_paper_metric_last500"] == summary["final_paper_metric_last500"]
    assert b.config().seed == 4 and b.env_spec().n_agents == 3
    with pytest.raises(BundleError, match="exists"):
        export_bundle(trained, tmp_path / "b")


def test_a_set_central_net_travels_in_the_bundle(tmp_path):
    """central_net=set: the manifest says so, the bundle's central file loads into the numpy set net that
    equals the trained torch net, and a manifest that names the other network fails on load."""
    import torch
    from hammer.learning.numpy_policy import numpy_central
    from hammer.learning.team import Team
    from safetensors.numpy import load as load_safetensors

    run = tmp_path / "set"
    cfg = merge_config("cn3", overrides=["num_envs=8", "epochs=1", "minibatches=2", "episodes=16", "central_net=set"])
    train(cfg, RunDir.create(run, cfg), tensorboard=False)
    b = export_bundle(run, tmp_path / "b")
    assert b.manifest["central_net"] == "set" and b.config().wiring.set_central
    params = load_safetensors((b.path / "central.safetensors").read_bytes())
    net = numpy_central(params)
    team = Team(b.config(), b.env_spec())
    team.central.load_state_dict({k: torch.from_numpy(v) for k, v in params.items()})
    s = np.random.default_rng(0).normal(size=(4, team.state_dim)).astype(np.float32)
    with torch.no_grad():
        np.testing.assert_allclose(net.message_mean(s), team.central.message_mean(torch.from_numpy(s)).numpy(), atol=2e-6)
    m = json.loads((b.path / "manifest.json").read_text())
    m["config"]["central_net"] = "concat"
    m["seal"] = seal(m)  # a manifest consistent with itself but not with its weights
    (b.path / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="holds the set central network but the config says central_net=concat"):
        load_bundle(b.path)


def test_a_corrupted_file_fails_on_its_hash(trained, tmp_path):
    b = _copy(export_bundle(trained, tmp_path / "b").path, tmp_path)
    data = bytearray((b / "central.safetensors").read_bytes())
    data[-1] ^= 0x01  # one bit of one weight
    (b / "central.safetensors").write_bytes(bytes(data))
    with pytest.raises(BundleError, match="central.safetensors: sha256 differs"):
        load_bundle(b)


def test_a_newer_format_or_wire_schema_fails(trained, tmp_path):
    b = _copy(export_bundle(trained, tmp_path / "b").path, tmp_path)
    m = json.loads((b / "manifest.json").read_text())
    (b / "manifest.json").write_text(json.dumps({**m, "bundle_format": BUNDLE_FORMAT + 1}))
    with pytest.raises(BundleError, match="newer than this hammer reads"):
        load_bundle(b)
    (b / "manifest.json").write_text(json.dumps({**m, "schema_version": 999}))
    with pytest.raises(BundleError, match="schema_version 999"):
        load_bundle(b)


def test_weights_that_do_not_fit_the_env_fail(trained, tmp_path):
    b = _copy(export_bundle(trained, tmp_path / "b").path, tmp_path)
    m = json.loads((b / "manifest.json").read_text())
    m["env_spec"]["obs_dim"] = 26  # what cn5 observes: the first layer takes 22 inputs
    m["seal"] = seal(m)
    (b / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="takes 22 inputs"):
        load_bundle(b)
    env = make_vec_env("cn", 5, 1)
    try:
        with pytest.raises(BundleError, match="n_agents 3 \\(env has 5\\)"):
            load_bundle(tmp_path / "b").check_env(env.spec)
    finally:
        env.close()


def test_cli_export_and_serve_errors_are_one_line(trained, tmp_path):
    runner = CliRunner()
    r = runner.invoke(app, ["export", str(trained), "--out", str(tmp_path / "b")])
    assert r.exit_code == 0, r.output
    assert "message length 4" in r.output
    r = runner.invoke(app, ["export", str(tmp_path / "nowhere"), "--out", str(tmp_path / "c")])
    assert r.exit_code == 2 and r.output.count("\n") == 1 and "error:" in r.output and "config.json" in r.output
    (tmp_path / "b" / "local.safetensors").write_bytes(b"x")
    r = runner.invoke(app, ["serve", str(tmp_path / "b"), "--episodes", "4"])
    assert r.exit_code == 2 and r.output.count("\n") == 1 and "sha256 differs" in r.output


def _metrics(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def test_an_edge_agent_from_the_bundle_joins_a_served_run(trained, tmp_path):
    """The same served run twice: every role launched, then local-1 started by hand from the bundle alone
    (no run directory): both complete with the same episodes, so the edge agent acted exactly as the
    launched one did."""
    bundle = export_bundle(trained, tmp_path / "b")
    cfg = bundle.config(episodes=8, msg_dropout=0.0)
    settings, _ = serve_settings(bundle, "served-all")
    launch(cfg, settings, tmp_path / "all")
    port = free_loopback_port()
    settings, _ = serve_settings(bundle, "served-edge", runtime=[f"hub_port={port}"])
    edge = subprocess.Popen([sys.executable, "-m", "hammer.cli", "local", "--bundle", str(bundle.path), "--agent", "1",
                             "--run-id", "served-edge", "--connect", f"tcp/127.0.0.1:{port}"],
                            cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        res = launch(cfg, settings, tmp_path / "edge", external_agents=(1,))
        out, _ = edge.communicate(timeout=30)
    finally:
        if edge.poll() is None:
            edge.kill()
    assert res.summary["completed"] and edge.returncode == 0, out
    assert "'steps': 25," in out and "'weights_loaded': 1" in out  # 8 copies x 1 episode of 25 steps, one policy
    assert _metrics(tmp_path / "edge") == _metrics(tmp_path / "all")


def test_play_renders_the_team_with_its_messages(trained, tmp_path, monkeypatch):
    from PIL import Image, ImageSequence

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    export_bundle(trained, tmp_path / "b")
    runner = CliRunner()
    r = runner.invoke(app, ["play", str(tmp_path / "b"), "--out", str(tmp_path / "team.gif"), "--episodes", "1",
                            "--max-steps", "6"])
    assert r.exit_code == 0, r.output
    frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(tmp_path / "team.gif"))]
    assert len(frames) == 6 and frames[0].shape[1] > frames[0].shape[0]  # the env's frame with the panel beside it
    half = frames[0].shape[1] * 2 // 3
    assert not np.array_equal(frames[0][:, half:], frames[3][:, half:])  # the messages panel changes
    r = runner.invoke(app, ["play", str(tmp_path / "b"), "--out", str(tmp_path / "team.mp4")])
    assert r.exit_code == 2 and "error:" in r.output and "GIF" in r.output


@pytest.fixture(scope="module")
def served_secure_float16(trained, tmp_path_factory):
    """One `hammer serve --secure --runtime weights_float16=true` of the team (16 episodes): the served
    run both tests below check, the secure profile's and float16 weights' (neither changes what the
    other checks: the identities and access rules, the bytes the policy server sends)."""
    from tests.runtime_helpers import hammer

    tmp = tmp_path_factory.mktemp("served")
    bundle = export_bundle(trained, tmp / "b")
    run = tmp / "secure"
    res = hammer("serve", str(bundle.path), "--episodes", "16", "--run-dir", str(run), "--no-dashboard", "--secure",
                 "--runtime", "weights_float16=true")
    return bundle, run, res


def test_hammer_serve_secure_serves_the_team_over_mutual_tls(served_secure_float16):
    """`hammer serve --secure` is the secure profile of `hammer up --secure`: identities in RUN/identity/,
    runtime.json says secure, and the served run completes."""
    _, run, res = served_secure_float16
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.startswith("done: 16 episodes")
    assert json.loads((run / "runtime.json").read_text())["secure"] is True
    assert (run / "identity" / "policy.key").is_file() and not (run / "identity" / "hub.key").exists()
    assert not (run / "identity" / "learner.key").exists()  # a served run has a policy server, no learner
    assert len(_metrics(run)) == 16


@pytest.mark.parametrize(("preset", "overrides", "steps"), [("mw3", (), 3), ("cn3", ("env_kwargs.observe_others=false",), 4)])
def test_play_renders_multiwalker_and_own_observation_teams(tmp_path, monkeypatch, preset, overrides, steps):
    """Smoke test of the other renderers: SISL multiwalker (continuous actions), and cn whose local agents
    see only their own position and the landmarks (mpe2's observation without its tail)."""
    from hammer.benchmarks.edge_bench import make_team
    from PIL import Image, ImageSequence

    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    bundle, *_ = make_team(tmp_path / "team", preset, overrides)
    r = CliRunner().invoke(app, ["play", str(bundle.path), "--out", str(tmp_path / "team.gif"), "--episodes", "1",
                                 "--max-steps", str(steps)])
    assert r.exit_code == 0, r.output
    frames = list(ImageSequence.Iterator(Image.open(tmp_path / "team.gif")))
    assert len(frames) == steps and f"{steps} frames" in r.output


def test_faults_eval_and_sweep_serve_a_bundle_with_its_fallback(trained, tmp_path):
    """`hammer faults eval/sweep` given a bundle run it as `hammer serve` does (serve_settings), so the
    fallback in its manifest applies; a run directory keeps the default."""
    from hammer.experiments.fault_sweep import Point, point_settings

    b = tmp_path / "b"
    export_bundle(trained, b)
    m = json.loads((b / "manifest.json").read_text())
    m["fallback"] = {"mode": "last_k", "k": 2}
    m["seal"] = seal(m)  # as exported so (the seal covers every field)
    (b / "manifest.json").write_text(json.dumps(m))
    s = point_settings(Point(team="t", run=str(b), drop=0.5, delay_ms=0.0, seed=1), 20.0)
    assert (s.mode, s.fallback, s.fallback_k, s.msg_deadline_ms) == ("eval", "last_k", 2, 20.0)
    assert s.faults is not None and s.fault_links[0]["drop"] == 0.5 and s.policy_dir == str(b)
    s = point_settings(Point(team="t", run=str(trained), drop=0.0, delay_ms=0.0, seed=1), 20.0)
    assert (s.fallback, s.policy_dir) == ("zeros", str(trained / "final"))
    r = CliRunner().invoke(app, ["faults", "eval", str(b), "--episodes", "8", "--run-dir", str(tmp_path / "ev"),
                                 "--fault", "central->local:drop=1.0"])
    assert r.exit_code == 0, r.output
    rt = json.loads((tmp_path / "ev" / "runtime.json").read_text())
    assert (rt["fallback"], rt["fallback_k"], rt["mode"]) == ("last_k", 2, "eval")
    links = json.loads((tmp_path / "ev" / "links.json").read_text())["links"]
    assert links["central->local"]["dropped"] > 0  # the fault of the command line applied too


def test_serve_says_policy_server_and_gives_external_agents_the_seed(trained, tmp_path, caplog):
    """The start-up lines of a served run: no learner runs (the policy server does), and the one command each
    external agent needs (the launcher shows it as it waits) carries --seed when one was given (its sampling
    stream must be the run's) and the hub's endpoint."""
    export_bundle(trained, tmp_path / "b")
    r = CliRunner().invoke(app, ["serve", str(tmp_path / "b"), "--episodes", "8", "--seed", "3", "--external",
                                 "1,central", "--runtime", "startup_timeout_s=3", "--run-dir", str(tmp_path / "s"),
                                 "--no-dashboard"])
    assert r.exit_code == 1 and "local-1 (external: start it by hand)" in r.output, r.output  # nobody joined
    hints = [m for m in caplog.messages if "start it by hand with:" in m]
    assert len(hints) == 2, hints  # local-1 and central, once each
    local = next(m for m in hints if "local-1" in m)
    assert "--agent 1 --run-id s --connect tcp/127.0.0.1:" in local and local.endswith("--seed 3"), local
    assert any("hammer central --run-dir" in m and "--connect tcp/127.0.0.1:" in m for m in hints), hints
    line = next(ln for ln in r.output.splitlines() if ln.startswith("will run:"))
    assert "policy server" in line and "learner" not in line and "--resume" not in line and "external" in line


def test_a_hand_edit_with_a_plausible_value_fails_on_the_seal(trained, tmp_path):
    """The seal covers the whole manifest, the config included: a change no field check can call
    wrong (another seed, another fallback) is still caught, in one line."""
    b = _copy(export_bundle(trained, tmp_path / "b").path, tmp_path)
    m = json.loads((b / "manifest.json").read_text())
    assert m["bundle_format"] == 2 and m["seal"] == seal(m)
    for edit in ({**m, "config": {**m["config"], "seed": 5}}, {**m, "fallback": {"mode": "last", "k": 3}}):
        (b / "manifest.json").write_text(json.dumps(edit))
        with pytest.raises(BundleError, match="the manifest changed after export") as e:
            load_bundle(b, check_config=False)
        assert "\n" not in str(e.value)
    legacy = {k: v for k, v in m.items() if k != "seal"}  # a format-1 bundle (before seals) still loads
    (b / "manifest.json").write_text(json.dumps({**legacy, "bundle_format": 1}))
    assert load_bundle(b).manifest["bundle_format"] == 1


def test_signed_bundles_load_only_against_a_trusted_key(trained, tmp_path):
    """`hammer keygen`, `hammer export --sign`, `hammer sign`, as a user runs them; then what an edge
    agent given --trust does with a signed, a tampered, a foreign-signed and an unsigned bundle."""
    from hammer.serve.signing import SignatureError

    keys = tmp_path / "keys"
    for name in ("site", "other"):
        r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", "keygen", str(keys / name)], env=ENV,
                           capture_output=True, text=True, timeout=120, check=False)
        assert r.returncode == 0, r.stderr
    assert oct((keys / "site.key").stat().st_mode & 0o777) == "0o600"
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", "keygen", str(keys / "site")], env=ENV,
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 2 and "exists" in r.stderr and r.stderr.count("\n") == 1  # never overwritten silently
    signed = tmp_path / "signed"
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", "export", str(trained), "--out", str(signed),
                        "--sign", str(keys / "site.key")], env=ENV, capture_output=True, text=True, timeout=300,
                       check=False)
    assert r.returncode == 0 and "signed with" in r.stdout, r.stderr
    site, other = keys / "site.pub", keys / "other.pub"
    assert load_bundle(signed, trust=[site]).manifest["seal"]
    assert load_bundle(signed, trust=[other, site])  # any trusted key will do
    with pytest.raises(SignatureError, match="does not verify against the trusted key"):
        load_bundle(signed, trust=[other])
    # tampered: a field changed and the seal made to match (a tamperer can compute a sha256, not a signature)
    forged = _copy(signed, tmp_path)
    m = json.loads((forged / "manifest.json").read_text())
    m["fallback"] = {"mode": "last", "k": 3}
    m["seal"] = seal(m)
    (forged / "manifest.json").write_text(json.dumps(m, indent=1))
    assert load_bundle(forged).manifest["fallback"]["mode"] == "last"  # nothing else could tell
    with pytest.raises(SignatureError, match="changed after signing") as e:
        load_bundle(forged, trust=[site])
    assert "\n" not in str(e.value)
    # weights swapped under a signed manifest: the signature holds, the file's sha256 does not
    swapped = tmp_path / "swapped"
    shutil.copytree(signed, swapped)
    data = bytearray((swapped / "local.safetensors").read_bytes())
    data[-1] ^= 0x01
    (swapped / "local.safetensors").write_bytes(bytes(data))
    with pytest.raises(BundleError, match="local.safetensors: sha256 differs"):
        load_bundle(swapped, trust=[site])
    unsigned = export_bundle(trained, tmp_path / "unsigned").path
    with pytest.raises(SignatureError, match="not signed"):
        load_bundle(unsigned, trust=[site])
    r = subprocess.run([sys.executable, "-P", "-m", "hammer.cli", "sign", str(unsigned), "--key",
                        str(keys / "site.key")], env=ENV, capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    assert load_bundle(unsigned, trust=[site])
    # the edge agent (the console script's torch-free path) refuses the forged bundle in one line, before joining
    port = free_loopback_port()
    for bundle, what in ((forged, "changed after signing"), (export_bundle(trained, tmp_path / "u2").path, "not signed")):
        r = subprocess.run([sys.executable, "-P", "-m", "hammer", "local", "--bundle", str(bundle), "--agent", "0",
                            "--run-id", "x", "--connect", f"tcp/127.0.0.1:{port}", "--trust", str(site)],
                           env=ENV, capture_output=True, text=True, timeout=120, check=False)
        assert r.returncode == 2 and what in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_weights_sent_as_float16_halve_the_bytes_and_serve(served_secure_float16):
    """`weights_float16`: the policy server sends half the bytes; every receiver computes in float32
    (learning.numpy_policy.params_from_blob), and a served run completes with no default action."""
    from hammer.learning.numpy_policy import float16_blob, params_from_blob
    from safetensors.numpy import load

    b, run, r = served_secure_float16
    blob = (b.path / "local.safetensors").read_bytes()
    half = float16_blob(blob)
    assert len(half) < 0.55 * len(blob)
    exact, got = load(blob), params_from_blob(half)
    assert set(got) == set(exact) and all(got[k].dtype == np.float32 for k in got)
    assert max(float(np.abs(got[k] - exact[k]).max()) for k in got) < 1e-2
    assert all(np.array_equal(params_from_blob(blob)[k], exact[k]) for k in exact)  # float32 untouched
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads((run / "runtime.json").read_text())["weights_float16"] is True
    # every agent acted on every step, with the float16 weights it loaded (whether a central message
    # was late on a busy machine is timing, not the weights: the agent then acts on its fallback)
    links = json.loads((run / "summary.json").read_text())["links"]
    assert links["default_actions"] == 0, links
