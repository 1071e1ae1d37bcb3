"""What a served run puts on the wire, watched from outside by a session of the test's own: an edge
agent started exactly with the command `hammer serve` prints (a bundle and a run id, no settings)
sends actions without the echoed message (the env host's observations say it records none), every
role's last heartbeat says `stopped` with its final counters (which is all an external agent leaves
the launcher), and the central agent sends no learner record (a served run has no learner). Real
processes, real Zenoh on 127.0.0.1."""

from __future__ import annotations

import collections
import json
import shlex
import subprocess
import sys
import threading

import pytest
from hammer.protocol import codec
from hammer.protocol.schemas import Action, Heartbeat
from hammer.protocol.session import HammerSession, TransportConfig

from tests.runtime_helpers import ENV, ROOT, trained_bundle

pytestmark = pytest.mark.timeout(300)
K = 32


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return trained_bundle(tmp_path_factory.mktemp("team"), episodes=16)


def test_an_edge_agent_started_as_printed_sends_compact_actions_and_every_role_says_it_stopped(bundle, tmp_path):
    run = tmp_path / "served"
    serve = subprocess.Popen([sys.executable, "-m", "hammer.cli", "serve", str(bundle), "--episodes", str(2 * K),
                              "--num-envs", str(K), "--external", "1", "--run-dir", str(run), "--no-dashboard"],
                             cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    printed = threading.Event()

    def read() -> None:
        for line in serve.stderr:
            lines.append(line)
            if "start it by hand with: hammer local --bundle" in line:
                printed.set()

    threading.Thread(target=read, daemon=True).start()
    edge = None
    try:
        assert printed.wait(120), "".join(lines)[-3000:]
        command = next(ln for ln in lines if "start it by hand with:" in ln).split("start it by hand with: ", 1)[1]
        args = shlex.split(command)
        assert args[:3] == ["hammer", "local", "--bundle"] and "--settings" not in args, command
        assert args[args.index("--num-envs") + 1] == str(K)
        hub = args[args.index("--connect") + 1]
        with HammerSession(run.name, TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[hub]),
                           sender="watcher") as s:
            acts = s.subscribe_raw(s.keys.act("1"), maxsize=100_000)
            records = s.subscribe_raw(s.keys.exp("central"), maxsize=100_000)
            beats = s.subscribe(s.keys.heartbeat("*"), Heartbeat, maxsize=100_000)
            with open(tmp_path / "edge.log", "w") as log:  # the child keeps its own copy of the descriptor
                edge = subprocess.Popen([sys.executable, "-m", "hammer", *args[1:]], cwd=ROOT, env=ENV,
                                        stdout=subprocess.DEVNULL, stderr=log)
            assert serve.wait(240) == 0, "".join(lines)[-3000:]
            assert edge.wait(60) == 0, (tmp_path / "edge.log").read_text()[-3000:]
            sizes, flagged = [], []
            while (data := acts.get(timeout=0.5)) is not None:
                a = codec.decode(data, Action)
                assert a.msg is None
                (flagged if a.fallback.any() else sizes).append(len(data))
            central_records = 0
            while records.get(timeout=0.1) is not None:
                central_records += 1
            last: dict[str, Heartbeat] = {}
            statuses = collections.defaultdict(list)
            for h in beats.drain():
                last[h.role] = h
                statuses[h.role].append(h.status)
    finally:
        for p in (serve, edge):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(10)
    summary = json.loads((run / "summary.json").read_text())
    steps = summary["step"]
    assert summary["completed"] and steps == 2 * 25  # two episodes of 25 steps on each of the K copies
    # item: an action at K = 32 carries 32 one-byte ids and its header, not the message it acted on;
    # one acted on a late message's fallback also carries its K flags (a busy machine makes some late)
    assert len(sizes) + len(flagged) == steps and sizes, (len(sizes), len(flagged))
    assert max(sizes) <= 50 and max(flagged, default=0) <= 50 + K + 8, (sorted(set(sizes)), sorted(set(flagged)))
    assert central_records == 0  # no learner listens in a served run
    # every role's last heartbeat says stopped; the external agent's carries its final counters
    assert set(last) == {"env", "central", "policy", "local-0", "local-1", "local-2"}, sorted(last)
    assert {r: h.status for r, h in last.items()} == dict.fromkeys(last, "stopped"), dict(statuses)
    assert last["local-1"].counters["steps"] == steps
    links = json.loads((run / "links.json").read_text())
    assert links["roles"]["local-1"]["steps"] == steps
