"""A served run's lifecycle and running it across machines: `hammer serve --listen` on a veth
address with the edge agent started from the command serve prints, in another network namespace; an
edge agent started before its hub waits and says so; SIGTERM ends `hammer serve` cleanly (stop broadcast
to external agents too, summary.json, exit 0); `--stay` makes the edge agent a service across two served
sessions of the same run; `--num-envs` and the manifest checks. Real processes, real Zenoh on 127.0.0.1
(and on a veth pair the test creates and deletes)."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time

import pytest
from hammer.protocol.session import free_loopback_port
from hammer.serve.bundle import BundleError, load_bundle

from tests.runtime_helpers import ENV, ROOT, hammer, netns_reason, trained_bundle

pytestmark = pytest.mark.timeout(240)
CLI = [sys.executable, "-m", "hammer.cli"]
EDGE = [sys.executable, "-m", "hammer"]  # the console script's entry (hammer/entry.py): the edge path


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A briefly trained cn3 team (8 env copies) as a bundle."""
    return trained_bundle(tmp_path_factory.mktemp("team"), episodes=16)


def _start(cmd: list[str], log) -> subprocess.Popen:
    with open(log, "w") as f:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=f, stderr=subprocess.STDOUT)


def _wait_for(what: str, ok, timeout_s: float = 60, procs: tuple = ()) -> None:
    deadline = time.monotonic() + timeout_s
    while not ok():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:.0f} s")
        for p in procs:
            assert p.poll() is None, f"{what}: a process exited early ({p.args})"
        time.sleep(0.2)


def _stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def test_an_edge_agent_started_first_waits_for_its_hub_and_serve_sets_the_env_copies(bundle, tmp_path):
    """The edge agent comes up before `hammer serve`: it logs that it waits for the hub's endpoint, says it
    joined only once it sees the run, acts with the served run's K (`--num-envs 2` on both sides) and ends
    with the run. Serve prints one command for it, with the endpoint and --num-envs filled in."""
    port = free_loopback_port()
    run = tmp_path / "served"
    edge = _start([*EDGE, "local", "--bundle", str(bundle), "--agent", "1", "--run-id", "served", "--connect",
                   f"tcp/127.0.0.1:{port}", "--num-envs", "2"], tmp_path / "edge.log")
    try:
        _wait_for("the edge agent waiting", lambda: "waiting for" in (tmp_path / "edge.log").read_text(), 30, (edge,))
        r = hammer("serve", str(bundle), "--episodes", "4", "--num-envs", "2", "--external", "1", "--runtime",
                   f"hub_port={port}", "--run-dir", str(run), "--no-dashboard", timeout=180)
        edge.wait(30)
    finally:
        _stop(edge)
    log = (tmp_path / "edge.log").read_text()
    assert r.returncode == 0 and r.stdout.startswith("done: 4 episodes"), r.stderr[-2000:]
    assert edge.returncode == 0, log
    assert f"local-1 waiting for tcp/127.0.0.1:{port}" in log and "Traceback" not in log
    assert log.index("waiting for") < log.index("joined run served") < log.index("local-1 alive")
    assert "'steps': 50," in log  # 4 episodes on 2 copies: 2 x 25 steps, every one acted on by the edge agent
    assert json.loads((run / "config.json").read_text())["num_envs"] == 2
    hints = [ln for ln in r.stderr.splitlines() if "hammer local" in ln]
    assert len(hints) == 1, r.stderr  # one command for the one external agent
    assert hints[0].endswith(f"hammer local --bundle {bundle} --agent 1 --run-id served --connect "
                             f"tcp/127.0.0.1:{port} --num-envs 2"), hints


def test_an_unreachable_hub_or_a_bad_endpoint_ends_the_edge_agent_in_one_line(bundle, tmp_path):
    base = [*EDGE, "local", "--bundle", str(bundle), "--agent", "0", "--run-id", "nobody"]
    r = subprocess.run([*base, "--connect", "tcp/192.0.2.1"], cwd=ROOT, env=ENV, capture_output=True, text=True,
                       timeout=60, check=False)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--connect 'tcp/192.0.2.1'" in r.stderr, r.stderr
    port = free_loopback_port()
    r = subprocess.run([*base, "--connect", f"tcp/127.0.0.1:{port}", "--connect-retry-s", "2"], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert f"waiting for tcp/127.0.0.1:{port}" in r.stderr and " alive " not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: local-0: run nobody at tcp/127.0.0.1:")
    # a client of a router that is not up (zenoh.open fails at once there): retried the same way, no ZError
    z = tmp_path / "client.json5"
    z.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                             "scouting": {"multicast": {"enabled": False}}}))
    r = subprocess.run([*base, "--zenoh-config", str(z), "--connect-retry-s", "2"], cwd=ROOT, env=ENV,
                       capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 1 and "Traceback" not in r.stderr and "ZError" not in r.stderr, r.stderr
    assert f"waiting for tcp/127.0.0.1:{port}" in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: local-0: tcp/127.0.0.1:")


def test_sigterm_ends_a_served_run_cleanly_and_a_staying_edge_agent_joins_the_next_session(bundle, tmp_path):
    """SIGTERM to `hammer serve` (what systemd and docker send): every role stops, the external edge agent
    too (it got the stop broadcast), summary.json says so, exit 0. The edge agent (--stay) outlives it,
    joins the next `hammer serve` of the same run directory (same run id) and ends cleanly on SIGTERM."""
    port = free_loopback_port()
    run = tmp_path / "served"
    edge_log = tmp_path / "edge.log"
    edge = _start([*EDGE, "local", "--bundle", str(bundle), "--agent", "1", "--run-id", "served", "--connect",
                   f"tcp/127.0.0.1:{port}", "--stay"], edge_log)
    serve = _start([*CLI, "serve", str(bundle), "--episodes", "100000", "--external", "1", "--runtime",
                    f"hub_port={port}", "--run-dir", str(run), "--no-dashboard"], tmp_path / "serve1.log")
    try:
        def acted() -> bool:
            m = run / "metrics.csv"
            return m.is_file() and len(m.read_text().splitlines()) > 8  # the run is stepping, the edge acting
        _wait_for("the served run stepping", acted, 120, (edge, serve))
        serve.send_signal(signal.SIGTERM)
        assert serve.wait(60) == 0, (tmp_path / "serve1.log").read_text()[-2000:]
        out = (tmp_path / "serve1.log").read_text()
        assert "stopped by SIGTERM:" in out and "Traceback" not in out
        summary = json.loads((run / "summary.json").read_text())
        assert summary["interrupted"] is True and summary["stopped_by"] == "SIGTERM" and not summary["completed"]
        assert summary["episodes"] > 0
        _wait_for("the edge agent told to stop", lambda: "local-1 stopped: stop command from" in edge_log.read_text(),
                  30)
        time.sleep(1.0)
        assert edge.poll() is None, edge_log.read_text()  # --stay: it waits for the next session

        r = hammer("serve", str(bundle), "--episodes", "8", "--external", "1", "--runtime", f"hub_port={port}",
                   "--run-dir", str(run), "--no-dashboard", timeout=180)
        assert r.returncode == 0 and r.stdout.startswith("done: 8 episodes"), r.stderr[-2000:]
        assert json.loads((run / "summary.json").read_text())["completed"] is True
        earlier = list((run / "previous").iterdir())  # the first session's results, set aside
        assert len(earlier) == 1 and json.loads((earlier[0] / "summary.json").read_text())["stopped_by"] == "SIGTERM"
        _wait_for("the second session ended for the edge agent", lambda: edge_log.read_text().count("counters:") == 2,
                  30, (edge,))
        edge.send_signal(signal.SIGTERM)
        assert edge.wait(30) == 0
    finally:
        _stop(edge, serve)
    log = edge_log.read_text()
    assert log.count("joined run served") == 2 and "Traceback" not in log, log
    assert log.count("local-1 stopped: stop command from") == 2  # each session's stop broadcast reached it
    assert "'steps': 25," in log  # 8 episodes on 8 copies: one episode of 25 steps
    assert "stopped by SIGTERM after 2 session(s) of run served; counters: {'steps': " in log


def test_sigterm_stops_a_training_run_resumably_with_what_it_ran(tmp_path):
    """`hammer up` on SIGTERM: every role stopped as on Ctrl-C, what ran in env_summary.json (`stopped_by`),
    no summary.json (that marks a training run finished), the resume command, exit 143."""
    run = tmp_path / "up"
    up = _start([*CLI, "up", "--variant", "il", "--episodes", "100000", "--set", "num_envs=8", "--run-dir", str(run),
                 "--no-dashboard"], tmp_path / "up.log")
    try:
        _wait_for("the run stepping", lambda: (run / "metrics.csv").is_file()
                  and len((run / "metrics.csv").read_text().splitlines()) > 8, 120, (up,))
        up.send_signal(signal.SIGTERM)
        assert up.wait(60) == 128 + signal.SIGTERM
    finally:
        _stop(up)
    out = (tmp_path / "up.log").read_text()
    assert "stopped by SIGTERM:" in out and f"continue it with: hammer up --resume {run}" in out, out[-2000:]
    env = json.loads((run / "env_summary.json").read_text())
    assert env["stopped_by"] == "SIGTERM" and env["interrupted"] and not env["completed"] and env["episodes"] > 0
    assert not (run / "summary.json").exists()


def test_a_hand_edited_manifest_fails_on_load_naming_the_field(bundle, tmp_path):
    b = tmp_path / "b"
    shutil.copytree(bundle, b)
    m = json.loads((b / "manifest.json").read_text())
    cases = [({**m, "num_envs": 1}, "num_envs 1 is not a manifest field", "--num-envs K"),
             ({**m, "config": {**m["config"], "num_envs": 0}}, "config.num_envs 0 must be an integer >= 1", "fix:"),
             ({**m, "config": {**m["config"], "num_envs": "32"}}, "config.num_envs '32'", "--num-envs K"),
             ({**m, "env_spec": {**m["env_spec"], "obs_dim": -1}}, "env_spec.obs_dim -1", "export the bundle again"),
             ({**m, "fallback": {"mode": "sometimes", "k": 3}}, "fallback", "export the bundle again")]
    for manifest, what, fix in cases:
        (b / "manifest.json").write_text(json.dumps(manifest))
        for check_config in (True, False):  # serving, and the edge agent (which builds no RunConfig)
            with pytest.raises(BundleError) as e:
                load_bundle(b, check_config=check_config)
            assert what in str(e.value) and fix in str(e.value) and "\n" not in str(e.value), str(e.value)
    (b / "manifest.json").write_text(json.dumps(m))
    r = hammer("serve", str(b), "--runtime", "num_envs=1")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "fix: pass --num-envs 1" in r.stderr, r.stderr
    r = hammer("serve", str(b), "--listen", "tcp/192.0.2.1:7447", "--run-dir", str(tmp_path / "never"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "refusing to run plain on tcp/192.0.2.1:7447" in r.stderr and "--insecure" in r.stderr
    assert not (tmp_path / "never").exists()  # refused before anything was written




def test_serve_listens_on_a_veth_address_and_the_printed_command_joins_from_another_namespace(bundle, tmp_path):
    """docs/deploy.md's pair of commands across a veth pair (two namespaces, addresses private to them):
    `hammer serve --listen tcp/<its address>:7447 --insecure --external 0` in one namespace, and in the
    other exactly the `hammer local --bundle` command it prints."""
    reason = netns_reason(("ip",))
    if reason:
        pytest.skip(reason)
    from hammer.benchmarks.netns import NetnsUnavailable, topology

    tag = f"l{os.getpid() % 10000}"
    run = tmp_path / "served"
    try:
        with topology(1, tag) as top:
            hub_ns, edge_ns, address = top.hub, top.agents[0], top.links["local-0"][1]
            serve = _start(["ip", "netns", "exec", hub_ns, *CLI, "serve", str(bundle), "--episodes", "16", "--external",
                            "0", "--listen", f"tcp/{address}:7447", "--insecure", "--run-dir", str(run),
                            "--no-dashboard"], tmp_path / "serve.log")
            edge = None
            try:
                log = tmp_path / "serve.log"
                _wait_for("serve printing the agent's command", lambda: "start it by hand with:" in log.read_text(),
                          120, (serve,))
                line = next(ln for ln in log.read_text().splitlines() if "start it by hand with:" in ln)
                cmd = shlex.split(line.split("start it by hand with:", 1)[1])
                assert cmd[:3] == ["hammer", "local", "--bundle"] and f"tcp/{address}:7447" in cmd, cmd
                edge = _start(["ip", "netns", "exec", edge_ns, *EDGE, *cmd[1:]], tmp_path / "edge.log")
                assert serve.wait(180) == 0, log.read_text()[-2000:]
                assert edge.wait(30) == 0, (tmp_path / "edge.log").read_text()
            finally:
                _stop(serve, *([edge] if edge else []))
    except NetnsUnavailable as e:
        pytest.skip(str(e))
    out, edge_log = (tmp_path / "serve.log").read_text(), (tmp_path / "edge.log").read_text()
    assert "done: 16 episodes" in out and out.count("hammer local --bundle") == 1, out
    assert "joined run served" in edge_log and "'steps': 50," in edge_log, edge_log  # 16 episodes / 8 copies
    links = json.loads((run / "links.json").read_text())["links"]
    assert links["local->env"]["defaults"] == 0  # agent 0 acted in time on every step, from the other namespace
    left = subprocess.run(["ip", "netns", "list"], check=False, capture_output=True, text=True).stdout
    assert f"hmr{tag}" not in left  # everything the test created is gone


def test_a_serve_whose_external_agent_never_comes_names_its_real_endpoint_and_blocks_no_report(bundle, tmp_path):
    """No --listen: the hub's port is a free one picked at start, and the printed command names it; the
    startup wait is --runtime startup_timeout_s; the run directory left behind is skipped by `hammer report`
    with a note, not a refusal of the whole folder."""
    import re

    runs = tmp_path / "runs"
    r = subprocess.run([*CLI, "serve", str(bundle), "--episodes", "4", "--out", str(runs), "--no-dashboard"],
                       capture_output=True, text=True, env=ENV, timeout=120, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    r = subprocess.run([*CLI, "serve", str(bundle), "--external", "1", "--runtime", "startup_timeout_s=2", "--out",
                        str(runs), "--no-dashboard"], capture_output=True, text=True, env=ENV, timeout=120, check=False)
    assert r.returncode == 1 and "error: roles not alive after 2s" in r.stderr, r.stderr[-2000:]
    failed = max(runs.iterdir(), key=lambda p: p.stat().st_mtime)
    port = json.loads((failed / "runtime.json").read_text())["hub_port"]
    shown = re.search(r"hammer local --bundle \S+ --agent 1 --run-id \S+ --connect tcp/127\.0\.0\.1:(\d+)", r.stderr)
    assert shown and int(shown.group(1)) == port, r.stderr
    r = subprocess.run([*CLI, "report", str(runs)], capture_output=True, text=True, env=ENV, timeout=60, check=False)
    assert r.returncode == 0 and "| cn N=3" in r.stdout, r.stderr
    assert r.stderr.strip() == f"note: skipped 1 run with no episodes yet: {failed}"
