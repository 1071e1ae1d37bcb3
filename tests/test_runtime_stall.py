"""No single message can stall a role, and a degraded run says so.

Real `hammer up` runs of cn3 on 127.0.0.1 (real processes, Zenoh, env and torch), plain profile:
a peer sends each message that used to freeze a role or end the run (tests/stall_peer.py) into a
live run; the run completes with the metrics of an undisturbed run (the in-process trainer's, which
an undisturbed `hammer up` equals: test_runtime_up) and every attempt is in the rejection counters
the roles persist. A run whose central->local link drops everything is reported degraded, on stdout
and in summary.json; an undisturbed one is not (test_runtime_up).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from hammer.deploy.launcher import launch
from hammer.learning.config import merge_config
from hammer.protocol.session import TransportConfig
from hammer.runtime.settings import RuntimeSettings

from tests.runtime_helpers import CN3_RL, hammer, trained_run
from tests.stall_peer import EarlyStallPeer, StallPeer


def _metrics_without_wall_time(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


def _attacked_run(run_dir: Path) -> SimpleNamespace:
    """One run of the calm run's config, attacked twice: an `EarlyStallPeer` from the moment the
    launcher's hub listens until the first real step, then a `StallPeer` once the run is live."""
    # 20 updates: the live peer starts at the first heartbeat of a live run and must get its
    # attempts in while the run is live, also on an idle machine where a rollout takes a fraction of
    # a second (weights that arrive while the env host steps are checked at its next wait or at the end).
    cfg = merge_config("cn3", overrides=[*CN3_RL, "episodes=640"])  # the calm run's config
    # Generous deadlines: the comparison is about forged traffic, so a loaded host must not turn a
    # slow message into a fallback.
    settings = RuntimeSettings(run_id="stall-attacked", msg_deadline_ms=5000, act_deadline_ms=10000)
    early, peers = EarlyStallPeer(run_dir), []

    def chaos(sup, board) -> None:
        env = board.heartbeats.get("env")
        # The live peer copies real messages of the run, so it subscribes only once the early peer,
        # whose forgeries travel on the same keys, has seen the first real step and sends no more.
        if not peers and early.first_real_step is not None and env is not None and env.counters.get("step", 0) >= 1:
            rt = RuntimeSettings.load(run_dir)
            peer = StallPeer(rt.run_id, TransportConfig(listen=["tcp/127.0.0.1:0"],
                                                        connect=[f"tcp/127.0.0.1:{rt.hub_port}"]), cfg.n_agents)
            peer.start()
            peers.append(peer)

    early.start()  # it waits for the run files and the launcher's hub
    try:
        res = launch(cfg, settings, run_dir, chaos=chaos)
    finally:
        for peer in [*peers, early]:
            peer.stop_event.set()
            peer.join(10)
    return SimpleNamespace(dir=run_dir, res=res, early=early, peer=peers[0] if peers else None)


@pytest.fixture(scope="module")
def calm(tmp_path_factory):
    """The undisturbed run, the reference of the attacked one: the same config and seed trained in
    process (the session's team cache), whose episodes an undisturbed `hammer up` reproduces."""
    return _metrics_without_wall_time(trained_run(tmp_path_factory.mktemp("stall") / "calm", (*CN3_RL, "episodes=640")))


@pytest.fixture(scope="module")
def attacked(tmp_path_factory):
    """The attacked run both tests below judge, each its own attack (one run: a `hammer up` costs
    its processes' start-up, whatever it is attacked with)."""
    return _attacked_run(tmp_path_factory.mktemp("stall") / "attacked")


def test_stall_messages_are_rejected_counted_and_change_nothing(attacked, calm):
    peer = attacked.peer
    assert peer is not None, f"the live peer never started (early peer: {attacked.early.error})"
    assert peer.error is None, peer.error
    assert peer.sent.get("oversize") == 1, f"the peer did not get through its attempts: {peer.sent}"
    assert attacked.res.summary["completed"]
    assert len(calm) == 640 and calm == _metrics_without_wall_time(attacked.dir)
    # every attempt is in the counters the roles persisted (links.json <- counters/*.json)
    roles = json.loads((attacked.dir / "links.json").read_text())["roles"]
    got = {(role, k[9:]) for role, c in roles.items() for k, v in c.items() if k.startswith("rejected.") and v}
    want = {("local-0", "step_ahead"), ("local-1", "step_ahead"), ("central", "step_ahead"),
            ("local-0", "version_ahead"), ("local-0", "weights_ahead"), ("central", "weights_ahead"),
            ("env", "weights_ahead"), ("env", "step_ahead"), ("local-2", "size"),
            *((r, "control_sender") for r in ("env", "central", "learner", "local-0", "local-1", "local-2"))}
    assert want <= got, f"missing: {sorted(want - got)}"
    assert roles["env"]["rejected.step_ahead"] == 2  # both future-step actions (the early peer sends the env none)
    summary = json.loads((attacked.dir / "summary.json").read_text())
    assert summary["degraded"] is True and "messages rejected" in summary["degraded_reasons"][0]
    assert summary["rejected"]["local-2"]["size"] == 1  # the 50 MB payload, counted once, never queued


def test_stall_messages_before_the_first_step_are_rejected_too(attacked, calm):
    """Before a role's first real step there is no step to measure against; the run's known step
    (runtime.json, or the env host's last reported one for a restarted role) stands in for it, so
    the forged first step is refused instead of anchoring the window (runtime/bounds.py): the run's
    episodes are the undisturbed run's. The live peer's forged steps land in the same counters, so
    each role must have rejected more step_ahead messages than the live peer sent it."""
    early, res = attacked.early, attacked.res
    assert early.error is None, early.error
    assert early.first_real_step == 1, "the peer never saw the run start: it proves nothing"
    assert res.summary["completed"]
    assert len(calm) == 640 and calm == _metrics_without_wall_time(attacked.dir)
    live = attacked.peer.sent if attacked.peer is not None else {}
    live_step_ahead = {"local-0": live.get("obs_step_local-0", 0), "local-1": live.get("obs_step_local-1", 0),
                       "central": live.get("state_step", 0)}
    rejected = res.summary["rejected"]
    for role in ("local-0", "local-1", "local-2", "central", "learner"):
        got = rejected.get(role, {}).get("step_ahead", 0)
        assert got >= 1 + live_step_ahead.get(role, 0), (role, rejected, early.sent, live)
    assert res.summary["degraded"] is True  # and the run says it was attacked


def test_a_run_whose_messages_never_arrive_is_reported_degraded(tmp_path):
    run = tmp_path / "dropped"
    res = hammer("up", "--episodes", "40", "--run-dir", str(run), "--no-dashboard",
                 "--runtime", "msg_deadline_ms=20", "--fault", "central->local:drop=1.0")
    assert res.returncode == 0, res.stderr[-2000:]
    assert "degraded: fallback messages" in res.stdout  # the verdict is on stdout, next to the done line
    assert "done: 40 episodes" in res.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert summary["completed"] and summary["degraded"] is True
    assert summary["degraded_reasons"][0].startswith("fallback messages")


def test_a_learner_that_dies_names_its_last_log_lines_and_the_resume_command(tmp_path):
    import os
    import signal

    import pytest
    from hammer.deploy.launcher import UpError

    cfg = merge_config("cn3", overrides=["episodes=2000", "variant=il"])
    killed: list[int] = []

    def chaos(sup, board) -> None:
        env = board.heartbeats.get("env")
        if not killed and env is not None and env.counters.get("step", 0) >= 1:
            killed.append(sup.pid("learner"))
            os.kill(killed[0], signal.SIGKILL)

    with pytest.raises(UpError) as err:
        launch(cfg, RuntimeSettings(run_id="learner-death"), tmp_path / "run", chaos=chaos)
    msg = str(err.value)
    assert killed and msg.startswith(f"learner exited with code {-signal.SIGKILL}: ")
    assert "learner alive" in msg  # the tail of learner.log
    assert msg.endswith(f"hammer up --resume {tmp_path / 'run'}")
