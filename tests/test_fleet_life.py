"""A fleet's life at a site: its verdict when robots never join or are attacked, its end on SIGTERM,
identities that outlive a restart, robots that outlive one. Real processes, real Zenoh on 127.0.0.1,
real TLS, a real trained cn3 team."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from tests.runtime_helpers import ENV, trained_bundle

pytestmark = pytest.mark.timeout(300)
CLI = [sys.executable, "-P", "-m", "hammer.cli"]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return trained_bundle(tmp_path_factory.mktemp("fleetlife"), episodes=48)


def _wait_for(path, text: str, proc: subprocess.Popen, timeout: float = 90.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.is_file() and text in path.read_text():
            return
        assert proc.poll() is None, f"exited ({proc.returncode}) before {path.name} said {text!r}"
        time.sleep(0.1)
    raise AssertionError(f"{path} never said {text!r}")


def test_sigterm_ends_a_fleet_no_robot_joined_as_interrupted_and_degraded(bundle, tmp_path):
    """Every robot external and none started (the README's fleet before its robot runs), a secure
    fleet a stranger knocks on with plain bytes: SIGTERM to `hammer serve --realtime` stops it with
    exit 0 and a summary that says it was interrupted by SIGTERM and is degraded because no robot
    joined, each robot named as never joined, and the stranger's connections counted as refused."""
    import socket

    run = tmp_path / "site"
    serve = subprocess.Popen([*CLI, "serve", str(bundle), "--realtime", "20", "--seconds", "60", "--external", "0,1,2",
                              "--secure", "--run-dir", str(run)], env=ENV, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT)
    try:
        _wait_for(run / "logs" / "central.log", "central alive", serve)
        host, port = json.loads((run / "fleet.json").read_text())["hub"].split("/", 1)[1].rsplit(":", 1)
        for _ in range(3):
            with socket.create_connection((host, int(port)), timeout=5) as stranger:
                stranger.sendall(b"GET / HTTP/1.0\r\n\r\n")
                time.sleep(0.3)
        time.sleep(2)
    finally:
        serve.send_signal(signal.SIGTERM)
        out = serve.communicate(timeout=90)[0].decode()
    assert serve.returncode == 0, out[-2000:]
    s = json.loads((run / "summary.json").read_text())
    assert s["interrupted"] is True and s["stopped_by"] == "SIGTERM" and s["completed"] is False, s
    assert s["degraded"] is True
    assert any(r.startswith("no robot joined the fleet") for r in s["degraded_reasons"]), s["degraded_reasons"]
    assert {n for n, a in s["absences"].items() if a.get("never_joined")} == {"local-0", "local-1", "local-2"}
    assert "degraded: no robot joined" in out, out[-2000:]
    assert s["refused_connections"]["launcher"]["tls_plain"] == 3, s["refused_connections"]
    assert any(r.startswith("3 connections refused by launcher (tls_plain 3)") for r in s["degraded_reasons"])


def _serve(bundle, run, site, port, seconds, log):
    return subprocess.Popen([*CLI, "serve", str(bundle), "--realtime", "20", "--seconds", str(seconds), "--external", "1",
                             "--listen", f"tcp/127.0.0.1:{port}", "--secure", "--site", str(site), "--run-dir", str(run)],
                            env=ENV, stdout=log, stderr=subprocess.STDOUT)


def test_a_stay_robot_with_a_site_identity_rejoins_a_restarted_fleet_and_a_revoked_one_cannot(bundle, tmp_path):
    """A site made once (`hammer site init`, `hammer site issue ... local-1`); robot 1 started once
    with `--fleet --stay` and its copy of the site's three files. The fleet is served, stopped, and
    served again on the same run directory: robot 1 joins both sessions with no file copied, then
    exits 0 on SIGTERM. After `hammer site revoke ... local-1`, a third session refuses it at the
    TLS handshake: the robot never joins, the verdict names it and the refused connections."""
    import shutil

    from hammer.protocol.session import free_loopback_port

    site, run, port = tmp_path / "site", tmp_path / "runs" / "site-a", free_loopback_port()
    for args in (["init", str(site)], ["issue", str(site), "local-1"]):
        r = subprocess.run([*CLI, "site", *args], env=ENV, capture_output=True, text=True, timeout=60, check=False)
        assert r.returncode == 0, r.stderr
    assert oct((site / "ca.key").stat().st_mode & 0o777) == "0o600"
    robot_id = tmp_path / "robot" / "identity"  # the robot's own copy, made once
    shutil.copytree(site / "robots" / "local-1", robot_id)
    robot_log = open(tmp_path / "robot.log", "w")  # noqa: SIM115 - closed below
    robot = subprocess.Popen([sys.executable, "-P", "-m", "hammer", "local", "--bundle", str(bundle), "--agent", "1", "--run-id", run.name, "--connect",
                              f"tcp/127.0.0.1:{port}", "--identity", str(robot_id), "--fleet", "--stay"],
                             env=ENV, stdout=robot_log, stderr=subprocess.STDOUT)
    summaries = []
    try:
        for session in range(2):
            with open(tmp_path / f"serve{session}.log", "w") as log:
                serve = _serve(bundle, run, site, port, 8, log)
                assert serve.wait(150) == 0, (tmp_path / f"serve{session}.log").read_text()[-2000:]
            summaries.append(json.loads((run / "summary.json").read_text()))
            assert robot.poll() is None, (tmp_path / "robot.log").read_text()[-2000:]  # outlived the session
        r = subprocess.run([*CLI, "site", "revoke", str(site), "local-1"], env=ENV, capture_output=True, text=True,
                           timeout=60, check=False)
        assert r.returncode == 0, r.stderr
        with open(tmp_path / "serve2.log", "w") as log:
            serve = _serve(bundle, run, site, port, 8, log)
            assert serve.wait(150) == 0, (tmp_path / "serve2.log").read_text()[-2000:]
        summaries.append(json.loads((run / "summary.json").read_text()))
    finally:
        robot.send_signal(signal.SIGTERM)
        code = robot.wait(30)
        robot_log.close()
    for s in summaries[:2]:
        one = s["robots"]["local-1"]
        assert one["fresh"] > 0 and one["msg_fresh"] > 0, one  # it acted, on the team's messages, in each session
        assert "local-1" not in s["absences"] or not s["absences"]["local-1"].get("never_joined"), s["absences"]
    assert code == 0, (tmp_path / "robot.log").read_text()[-2000:]
    assert "staying for the next one" in (tmp_path / "robot.log").read_text()
    revoked = summaries[2]
    assert revoked["robots"]["local-1"]["fresh"] == 0 and revoked["absences"]["local-1"]["never_joined"], revoked
    assert revoked["degraded"]
    # the revoked robot kept dialling: refused at the handshake, counted and named, not a link failure
    refused = sum(r.get("tls_certificate", 0) for r in revoked["refused_connections"].values())
    assert refused > 0, revoked["refused_connections"]
    assert any("connections refused" in r for r in revoked["degraded_reasons"]), revoked["degraded_reasons"]
    assert not any("connections refused" in r for s in summaries[:2] for r in s["degraded_reasons"])


def test_a_robot_without_stay_that_hears_no_fleet_exits_after_its_bound(bundle):
    """A robot out of range when the stop was sent (here: no fleet at all) does not wait for ever:
    after --connect-retry-s with nothing from its fleet it exits 1 with one line saying so."""
    from hammer.protocol.session import free_loopback_port

    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-P", "-m", "hammer", "local", "--bundle", str(bundle), "--agent", "0",
                        "--run-id", "gone", "--connect", f"tcp/127.0.0.1:{free_loopback_port()}", "--fleet",
                        "--connect-retry-s", "3"], env=ENV, capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 1, r.stderr[-2000:]
    assert "error: local-0 lost the fleet: nothing from it for 3 s" in r.stderr.splitlines()[-1], r.stderr[-2000:]
    assert time.monotonic() - t0 < 30


def test_the_verdict_names_a_robot_the_central_agent_lost_while_the_world_heard_it():
    """What the central agent's heartbeat says of a robot (its longest absence, whether it ever joined)
    against the world's view: a robot the world heard throughout but the central agent lost for 40 s
    is a degraded reason of its own; one the central never heard is too; refusals on a robot's keys
    name that robot."""
    from hammer.deploy.fleet_verdict import fleet_verdict

    names = ["local-0", "local-1", "local-2"]
    absences = {"local-2": {"leaves": 1, "longest_absence_s": 2.0, "missing_at_end": False}}
    central = {"local_1.absent_max_s": 40.0, "local_1.joined": 1, "local_2.absent_max_s": 2.5, "local_2.joined": 1,
               "local_0.absent_max_s": 60.0, "local_0.joined": 0, "rejected.size": 7, "local_2.rejected.size": 7}
    v = fleet_verdict(names, absences, {"rejected": {}}, {"central": {"counters": central}}, 10.0)
    text = "\n".join(v["reasons"])
    assert "the central agent lost local-1 for 40.0 s" in text, text
    assert "the central agent never heard from local-0" in text, text
    assert "7 payloads refused on local-2's own keys (central: size 7)" in text, text
    assert "other payloads" not in text  # every refusal is on local-2's keys
    quiet = fleet_verdict(names, {}, {}, {"central": {"counters": {"local_1.absent_max_s": 3.0, "local_1.joined": 1}}},
                          10.0)
    assert quiet["reasons"] == []
    # a robot's own refusals (e.g. forged messages reaching it) are every role's, named; strangers too
    robot = fleet_verdict(names, {}, {}, {"local-2": {"counters": {"rejected.version": 3}},
                                          "env": {"counters": {"refused.tls_plain": 2}}}, 10.0, {"tls_certificate": 5})
    assert robot["rejections"] == {"local-2": {"version": 3}}
    assert robot["refused_connections"] == {"env": {"tls_plain": 2, "total": 2},
                                            "launcher": {"tls_certificate": 5, "total": 5}}
    assert any("3 other payloads refused (local-2: version 3)" in r for r in robot["reasons"]), robot["reasons"]
    assert any("5 connections refused by launcher" in r for r in robot["reasons"]), robot["reasons"]
