"""A `hammer hub` router relays typed messages between client-mode sessions (the multi-machine
layout), here on 127.0.0.1."""

import subprocess
import sys
import time

from hammer.protocol.schemas import Heartbeat
from hammer.protocol.session import HammerSession, TransportConfig, free_loopback_port


def test_hub_router_relays_between_clients():
    port = free_loopback_port()
    hub = subprocess.Popen([sys.executable, "-m", "hammer.cli", "hub", "--listen", f"tcp/127.0.0.1:{port}"],
                           stderr=subprocess.PIPE, text=True)
    try:
        assert "listening" in hub.stderr.readline()
        client = TransportConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"])
        with HammerSession("r1", client) as a, HammerSession("r1", client) as b:
            sub = b.subscribe(b.keys.heartbeat("x"), Heartbeat)
            time.sleep(0.5)
            for i in range(5):
                a.publish(a.keys.heartbeat("x"), Heartbeat(role="x", pid=i, status="running"))
            got = [sub.get(timeout=5) for _ in range(5)]
            assert [h.pid for h in got] == [0, 1, 2, 3, 4]
            assert sub.stats.rejected_total == 0
    finally:
        hub.terminate()
        assert hub.wait(10) is not None
