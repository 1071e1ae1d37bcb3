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
    """Every robot external and none started (the README's fleet before its robot runs): SIGTERM to
    `hammer serve --realtime` stops it with exit 0 and a summary that says it was interrupted by
    SIGTERM and is degraded because no robot joined, each robot named as never joined."""
    run = tmp_path / "site"
    serve = subprocess.Popen([*CLI, "serve", str(bundle), "--realtime", "20", "--seconds", "60", "--external", "0,1,2",
                              "--run-dir", str(run)], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        _wait_for(run / "logs" / "central.log", "central alive", serve)
        time.sleep(3)
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
