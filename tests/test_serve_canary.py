"""Staged rollout with health gates (serve/canary.py): real role processes, real Zenoh on 127.0.0.1,
real cn3 (mpe2 simple_spread). One served run takes a canary push of a deliberately worse team (every
local agent of it always moves left, off the landmarks), which the gates roll back on their own, and
then a good one (the same team, re-exported), which is promoted stage by stage; pushes.json, the
env host's health file and the agents' own heartbeats say which version each agent acted with."""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading

import numpy as np
import pytest
from hammer.deploy.launcher import launch
from hammer.serve.bundle import BundleError, export_bundle
from hammer.serve.canary import CanaryError, Gate, Snapshot, judge, parse_gate, parse_stages, staged_push
from hammer.serve.push import check_push, push, read_history, rollback
from hammer.serve.served_settings import serve_settings
from safetensors.numpy import load_file, save_file
from typer.testing import CliRunner

from hammer.cli import app
from tests.runtime_helpers import SHORT_RUN, trained_run

pytestmark = pytest.mark.timeout(240)


def _head(w: dict) -> str:
    last = max(int(k.split(".")[2]) for k in w if k.startswith("actor.layers."))
    return f"actor.layers.{last}"


# The served runs' env copies (the team trained on 8): a window of 128 episodes fills in 4 episode
# lengths, not 16; the gates compare the canary's episodes with the rest's whatever the copies.
COPIES = 32


@pytest.fixture(scope="module")
def teams(tmp_path_factory):
    """A (a short real training run), A again (another export of the same team: as good), a worse
    team (A's local action head replaced by one that always picks action 1, moving left: agents
    leave the landmarks; the central network is A's, so the canary pairing is allowed) and a team
    whose central network differs (a canary of it would pair A's central agent with a local policy
    trained for another)."""
    root = tmp_path_factory.mktemp("canary-teams")
    trained_run(root / "a", (*SHORT_RUN, "episodes=24", "seed=6"))
    for name in ("worse", "other"):
        shutil.copytree(root / "a", root / name)
    w = load_file(str(root / "worse" / "final" / "local.safetensors"))
    h = _head(w)
    w[h + ".weight"] = np.zeros_like(w[h + ".weight"])
    w[h + ".bias"] = np.where(np.arange(w[h + ".bias"].shape[0]) == 1, 30.0, -30.0).astype(np.float32)
    save_file(w, str(root / "worse" / "final" / "local.safetensors"))
    c = load_file(str(root / "other" / "final" / "central.safetensors"))
    c["head_weight"] = c["head_weight"] + 0.5
    save_file(c, str(root / "other" / "final" / "central.safetensors"))
    a = export_bundle(root / "a", root / "A")
    return {"a": a, "good": export_bundle(root / "a", root / "good"), "worse": export_bundle(root / "worse", root / "W"),
            "other": export_bundle(root / "other", root / "O"), "root": root}


def _served_dir(bundle, tmp_path):
    """A run directory as `hammer serve` writes it, without its processes (for the checks)."""
    settings, _ = serve_settings(bundle, "checks")
    run = tmp_path / "run"
    run.mkdir()
    settings.save(run)
    (run / "config.json").write_text(json.dumps(bundle.config_data))
    (run / "env_spec.json").write_text(json.dumps(bundle.env_spec_data))
    return run


def test_options_and_pairing_are_checked(teams, tmp_path):
    a, other = teams["a"], teams["other"]
    assert parse_stages("1,50%,100%", [2], 3) == [[2], [0, 2], [0, 1, 2]]
    assert parse_stages(None, [0, 1], 3) == [[0, 1], [0, 1, 2]]
    for bad, word in (("2,1,3", "must rise"), ("1,50%", "must rise"), ("x,100%", "not a count")):
        with pytest.raises(CanaryError, match=word):
            parse_stages(bad, [0], 3)
    with pytest.raises(CanaryError, match="whole team"):
        parse_stages(None, [0, 1, 2], 3)
    assert parse_gate(["metric_drop=0.3,latency_ms=5"], 10) == Gate(metric_drop=0.3, latency_ms=5, window_episodes=10)
    with pytest.raises(CanaryError, match=r"--gate metric_drop='-1'.*fix"):
        parse_gate(["metric_drop=-1"])
    with pytest.raises(CanaryError, match=r"--gate speed=.*names: window_episodes"):
        parse_gate(["speed=3"])
    with pytest.raises(CanaryError, match="--window-episodes"):
        parse_gate([], 0)
    run = _served_dir(a, tmp_path)
    # Another central network: a canary would pair it with the served one; refused in one line.
    with pytest.raises(BundleError, match="does not declare the served central network.*fix: push without --canary"):
        check_push(other.path, run, agents=[0])
    check_push(other.path, run)  # a plain push switches the central agent too: allowed
    declared = export_bundle(teams["root"] / "other", tmp_path / "declared", works_with=(a.path,))
    check_push(declared.path, run, agents=[0])  # declared compatible with A's central network
    runner = CliRunner()
    r = runner.invoke(app, ["push", str(other.path), "--to", str(run), "--canary", "0"])
    assert r.exit_code == 2 and "does not declare" in r.output and not (run / "pushes.json").exists()
    r = runner.invoke(app, ["push", str(a.path), "--to", str(run), "--stages", "1,100%"])
    assert r.exit_code == 2 and "only with --canary" in r.output
    r = runner.invoke(app, ["push", str(a.path), "--to", str(run), "--canary", "0", "--gate", "crashes=x"])
    assert r.exit_code == 2 and "--gate crashes" in r.output
    r = runner.invoke(app, ["push", str(a.path), "--to", str(run), "--canary", "0"])  # no served process
    assert r.exit_code == 2 and "health.json" in r.output
    (run / "health.json").write_text(json.dumps({"time": 0, "episodes": 0, "agents": []}))  # a run that ended
    r = runner.invoke(app, ["push", str(a.path), "--to", str(run), "--canary", "0"])
    assert r.exit_code == 2 and "not stepping" in r.output and not (run / "pushes.json").exists()
    # An open canary refuses a plain push until its decision; `hammer rollback` ends it.
    push(a.path, run, agents=[0])
    from hammer.deploy.dashboard import rollout_text

    assert rollout_text(run, 3).startswith("canary v1 open; central:0 local-0:1 local-1:0 local-2:0; last: canary v1")
    with pytest.raises(BundleError, match="staged rollout of version 1 is open"):
        push(a.path, run)
    e = rollback(run)
    assert e["restores_version"] == 0 and push(a.path, run)["version"] == 3


def _health(episodes: int, metric: list[float], **per_agent: list[float]) -> Snapshot:
    """A health.json read: 3 agents, 100 actions and 800 env copies each, plus `per_agent` totals."""
    agents = [{"agent": i, "version": 0, "actions": 100, "copies": 800, "defaults": 0, "fallbacks": 0,
               "latency_ms_sum": 300.0, "rejected": 0, "restarts": 0, "leaves": 0} for i in range(3)]
    for key, values in per_agent.items():
        for i, v in enumerate(values):
            agents[i][key] = v
    m = np.array(metric, float)
    return Snapshot({"episodes": episodes, "metric_sum": float(m.sum()), "metric_sq_sum": float((m**2).sum()),
                     "return_sum": 0.0, "return_sq_sum": 0.0, "agents": agents})


def test_each_gate_compares_the_canary_with_the_rest():
    """judge() on two reads of health.json: every per-agent gate fails on its own signal (the
    canary, agent 0, against agents 1-2 over the same window) and the metric fails only when the
    drop is both over its relative limit and over metric_z standard errors."""
    gate, zero = Gate(), _health(0, [])
    rng = np.random.default_rng(0)
    before_eps = rng.normal(-27.0, 7.7, 100)
    before = (before_eps.mean(), before_eps.var(), 100)
    same = _health(100, list(rng.normal(-27.0, 7.7, 100)))
    assert all(c["ok"] for c in judge(gate, before, zero, same, [0], [1, 2]).values())
    for key, values, name in ((("defaults"), [80, 0, 0], "default_rate"), ("fallbacks", [200, 8, 0], "fallback_rate"),
                              ("latency_ms_sum", [2600.0, 300.0, 310.0], "latency_ms"), ("rejected", [1, 0, 0], "rejected"),
                              ("restarts", [1, 0, 0], "crashes"), ("leaves", [1, 0, 0], "crashes")):
        worse = _health(100, list(rng.normal(-27.0, 7.7, 100)), **{key: values})
        checks = judge(gate, before, zero, worse, [0], [1, 2])
        assert [n for n, c in checks.items() if not c["ok"]] == [name], (key, checks)
        on_the_rest = _health(100, list(rng.normal(-27.0, 7.7, 100)), **{key: values[::-1]})
        assert all(c["ok"] for c in judge(gate, before, zero, on_the_rest, [0], [1, 2]).values())  # the rest's trouble
    worse = _health(100, list(rng.normal(-37.0, 7.7, 100)))
    assert not judge(gate, before, zero, worse, [0], [1, 2])["metric_drop"]["ok"]
    noisy = _health(4, [-5.0, -60.0, -5.0, -60.0])  # a 20% drop on 4 wild episodes: within the noise
    drop = judge(gate, before, zero, noisy, [0], [1, 2])["metric_drop"]
    assert drop["value"] > 0.15 and drop["ok"], drop
    assert set(judge(gate, before, zero, same, [0, 1, 2], [])) == {"metric_drop"}  # promoted: no rest to compare


def _serve_and_roll_out(teams, tmp_path, window: int) -> tuple[list[str], list[str], dict, list[dict]]:
    """Serve team A (agents 0-1 pooled, agent 2 alone); once it runs, a canary push of the worse team (agents 0 and 1 first), then of the
    good one in three stages; the run is stopped (SIGINT, a served run's normal end) after both."""
    a = teams["a"]
    cfg = a.config(episodes=10**6, msg_dropout=0.0, num_envs=COPIES)
    # Agents 0 and 1 in one pool (one process, one stacked forward): at the good team's stage 2 the
    # pool holds a canary agent and another, whose steps name two versions (local_agent/pool.py).
    settings, _ = serve_settings(a, "canary", runtime=["agents_per_process=2"])
    run = tmp_path / "served"
    verdicts: list[str] = []
    said: list[str] = []
    errors: list[BaseException] = []

    def drive() -> None:
        try:
            gate = Gate(window_episodes=window, timeout_s=90)
            verdicts.append(staged_push(teams["worse"].path, run, [0, 1], None, gate, say=said.append))
            verdicts.append(staged_push(teams["good"].path, run, [2], "1,2,3", gate, say=said.append))
        except BaseException as e:  # noqa: BLE001 - reported by the test
            errors.append(e)
        finally:
            os.kill(os.getpid(), signal.SIGINT)

    started: list[threading.Thread] = []

    def tick(board) -> None:
        if not started and (run / "health.json").is_file():
            started.append(threading.Thread(target=drive, daemon=True))
            started[0].start()

    res = launch(cfg, settings, run, on_tick=tick, stop_signals=(signal.SIGINT,))
    started[0].join(timeout=10)
    assert not errors, (errors, said)
    assert res.stopped_by == "SIGINT"
    return verdicts, said, res.summary, read_history(run)


def test_a_worse_canary_is_rolled_back_and_a_good_one_promoted(teams, tmp_path):
    verdicts, said, summary, history = _serve_and_roll_out(teams, tmp_path, window=128)
    print("\n".join(said))
    assert verdicts == ["rolled back", "promoted"], said
    actions = [e["action"] for e in history]
    assert actions == ["canary", "rollback", "canary", "stage", "promote", "gate"], history
    bad = history[1]
    assert bad["reason"].startswith("gate metric_drop") and bad["restores_version"] == 0, bad
    drop = bad["decision"]["checks"]["metric_drop"]
    assert drop["value"] > 0.15 and drop["rest"] - drop["canary"] > 2 * drop["stderr"] > 0 and not drop["ok"]
    # The worse team acted only where it was named: agents 0 and 1, never agent 2 nor the central agent.
    assert history[0]["agents"] == [0, 1] and history[0]["base_version"] == 0
    good = history[2:]
    assert [e.get("agents") for e in good[:2]] == [[2], [0, 2]] and good[2]["version"] == good[0]["version"] == 3
    for e in good[1:]:  # every stage's gates passed, each with canary and rest values
        checks = (e.get("decision") or e)["checks"]
        assert all(c["ok"] for c in checks.values()), checks
    assert set(good[1]["decision"]["checks"]) == {"metric_drop", "default_rate", "fallback_rate", "latency_ms",
                                                 "rejected", "crashes"}
    health = json.loads((tmp_path / "served" / "health.json").read_text())
    assert health["central_version"] == 3 and [x["version"] for x in health["agents"]] == [3, 3, 3]
    assert summary["links"]["off_policy_actions"] == 0  # every action came from the version its agent was named


def test_across_namespaces_from_the_command_line(teams, tmp_path):
    """The same two rollouts through `hammer push --canary`, with the team served across network
    namespaces (benchmarks/netns.py: router, `hammer serve`, env host and policy server in the hub
    namespace; the central agent and each edge agent, `hammer local --bundle`, in one of their own,
    joined by veth pairs with 10.213.x addresses); then a third rollout interrupted with Ctrl-C
    (SIGINT) after its canary started, which leaves the run rolled back. Namespaces made and deleted here."""
    import subprocess
    import sys
    import time

    from hammer.benchmarks.netns import (
        PORT,
        NetnsUnavailable,
        Procs,
        _start_central_and_driver,
        _wait_for,
        client_config,
        topology,
    )

    from tests.runtime_helpers import netns_reason

    reason = netns_reason(("ip",))
    if reason:
        pytest.skip(reason)
    a, work = teams["a"], tmp_path
    run = work / "served"
    py = [sys.executable, "-P", "-m", "hammer.cli"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    procs = Procs(work)
    try:
        with topology(3, f"c{os.getpid() % 10000}", central=True) as top:
            try:
                hub = procs.start(top.hub, [*py, "hub", "--listen", f"tcp/0.0.0.0:{PORT}", "--insecure"], "hub.log")
                _wait_for("the hub listening", lambda: b"listening" in (work / "hub.log").read_bytes(), 30, [hub])
                inside = client_config(work / "hub-client.json5", f"tcp/127.0.0.1:{PORT}")
                serve = procs.start(top.hub, [*py, "serve", str(a.path), "--episodes", "1000000", "--num-envs",
                                              str(COPIES), "--external",
                                              "0,1,2,central", "--runtime", f"zenoh_config_file={inside}", "--runtime",
                                              "insecure=true", "--run-dir", str(run), "--no-dashboard"], "serve.log")
                edges = [procs.start(ns, [sys.executable, "-P", "-m", "hammer", "local", "--bundle", str(a.path),
                                          "--agent", str(i), "--run-id", run.name, "--num-envs", str(COPIES),
                                          "--insecure", "--zenoh-config",
                                          str(client_config(work / f"edge{i}.json5",
                                                            f"tcp/{top.links[f'local-{i}'][1]}:{PORT}"))],
                                     f"local-{i}.log") for i, ns in enumerate(top.agents)]
                _start_central_and_driver(procs, top, run, py, None, 0, inside, serve)
                _wait_for("the served run's health.json", lambda: (run / "health.json").is_file(), 120, [serve, *edges])

                def hammer_push(bundle, *args):
                    return subprocess.run(["ip", "netns", "exec", top.hub, *py, "push", str(bundle), "--to", str(run),
                                           "--window-episodes", "128", *args], check=False, capture_output=True,
                                          text=True, timeout=240, env=env)

                worse = hammer_push(teams["worse"].path, "--canary", "0-1")
                assert worse.returncode == 1 and "rolled back (gate failed): gate metric_drop" in worse.stdout, \
                    (worse.stdout, worse.stderr)
                good = hammer_push(teams["good"].path, "--canary", "2", "--stages", "1,2,3")
                assert good.returncode == 0 and "held: version 3 serves every agent" in good.stdout, \
                    (good.stdout, good.stderr)
                p = subprocess.Popen(["ip", "netns", "exec", top.hub, *py, "push", str(teams["worse"].path), "--to",
                                      str(run), "--canary", "1", "--window-episodes", "128"],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
                lines = []
                for line in p.stdout:  # the canary is on agent 1: interrupt before its window's verdict
                    lines.append(line)
                    if "version 4 on agents [1]" in line:
                        p.send_signal(signal.SIGINT)
                assert p.wait(timeout=60) == 130 and "interrupted: rolled back" in "".join(lines), lines
                _wait_for("every agent on the rollback's version", lambda: json.loads(
                    (run / "health.json").read_text())["central_version"] == 5, 60, [serve])
                time.sleep(1.0)  # a few more steps on it
                health = json.loads((run / "health.json").read_text())
                serve.send_signal(signal.SIGINT)  # a served run's normal end
                assert serve.wait(timeout=60) == 0
            finally:
                procs.close()
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    history = read_history(run)
    assert [e["action"] for e in history] == ["canary", "rollback", "canary", "stage", "promote", "gate", "canary",
                                              "rollback"], history
    assert history[1]["decision"]["checks"]["metric_drop"]["ok"] is False
    assert history[-1]["reason"] == "interrupted" and history[-1]["restores_version"] == 3 and history[-1]["version"] == 5
    assert health["central_version"] == 5 and [x["version"] for x in health["agents"]] == [5, 5, 5], health
    # Each edge agent's health came across its own link: actions in time and heartbeats, no crash.
    assert all(x["actions"] > 0 and x["restarts"] == 0 and x["rejected"] == 0 for x in health["agents"]), health
