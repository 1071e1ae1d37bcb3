"""The shared role loop (`runtime.role.Role`) and weights intake (`runtime.weights.WeightsIntake`)
over real Zenoh on 127.0.0.1 (explicit endpoints, multicast scouting off): what every role
process relies on for stopping, idling out, reporting, and acting with the right policy version."""

from __future__ import annotations

import threading
import time

import pytest
from hammer.protocol.schemas import Control, Heartbeat, Weights
from hammer.protocol.session import HammerSession, TransportConfig
from hammer.runtime.role import Role
from hammer.runtime.weights import WeightsIntake


@pytest.fixture
def hub_and_role_session():
    """Two sessions of one run: the test's `hub` listens, the role's session connects to it."""
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    with HammerSession("rl", t, sender="launcher") as hub, \
            HammerSession("rl", TransportConfig.connector(port), sender="ticker") as s:
        yield hub, s


def _settle() -> None:
    time.sleep(0.3)  # let subscriber declarations reach the publisher's side


TICK = Heartbeat(role="test", pid=1, status="running")  # any message will do as a tick


class Ticker(Role):
    """The smallest role: counts the ticks (messages on the bench channel) it receives."""

    def __init__(self, session: HammerSession, **kw) -> None:
        super().__init__(session, "ticker", **kw)
        self.ticks = session.subscribe(self.keys.bench("tick"), Heartbeat)
        self.received = 0
        self.started = self.stopped = False

    def counters(self) -> dict[str, int]:
        return {"ticks": self.received}

    def on_start(self) -> None:
        self.started = True

    def poll(self, timeout: float) -> bool:
        tick = self.ticks.get(timeout=timeout)
        if tick is None:
            return False
        self.received += 1
        return True

    def on_stop(self) -> None:
        self.stopped = True


def _start(role: Role) -> threading.Thread:
    thread = threading.Thread(target=role.run, daemon=True)
    thread.start()
    return thread


def test_role_stops_on_a_stop_addressed_to_it_and_not_on_one_for_another_role(hub_and_role_session):
    hub, s = hub_and_role_session
    role = Ticker(s)
    thread = _start(role)
    _settle()
    hub.publish(hub.keys.ctl("all"), Control(command="stop", target="central"))
    time.sleep(0.8)
    assert thread.is_alive() and role.stop_reason is None
    hub.publish(hub.keys.ctl("all"), Control(command="stop", target="ticker"))
    thread.join(timeout=5.0)
    assert not thread.is_alive()
    assert role.started and role.stopped
    assert role.stop_reason == "stop command from launcher"


def test_role_stops_on_a_stop_for_everyone(hub_and_role_session):
    hub, s = hub_and_role_session
    role = Ticker(s)
    thread = _start(role)
    _settle()
    hub.publish(hub.keys.ctl("all"), Control(command="stop"))  # target "*"
    thread.join(timeout=5.0)
    assert not thread.is_alive() and role.stop_reason.startswith("stop command")


def test_role_exits_after_idle_exit_s_without_input_and_not_while_input_comes(hub_and_role_session):
    hub, s = hub_and_role_session
    role = Ticker(s, idle_exit_s=0.8)
    t0 = time.monotonic()
    thread = _start(role)
    _settle()
    while time.monotonic() - t0 < 2.0:  # input keeps it alive past idle_exit_s
        hub.publish(hub.keys.bench("tick"), TICK)
        time.sleep(0.1)
    assert thread.is_alive()
    thread.join(timeout=5.0)
    assert not thread.is_alive() and role.stopped
    assert role.stop_reason == "no input for 0.8 s"
    assert role.received >= 10


def test_role_says_it_is_alive_and_heartbeats_carry_its_counters(hub_and_role_session):
    hub, s = hub_and_role_session
    beats = hub.subscribe(hub.keys.heartbeat("ticker"), Heartbeat)
    alive = hub.watch_alive()
    _settle()
    role = Ticker(s)
    thread = _start(role)
    ev = alive.get(5.0)
    assert ev is not None and ev.role == "ticker" and ev.alive
    first = beats.get(timeout=5.0)  # published at once, before any input
    assert first is not None and first.role == "ticker" and first.counters["ticks"] == 0
    for _ in range(3):
        hub.publish(hub.keys.bench("tick"), TICK)
    deadline, ticks = time.monotonic() + 5.0, 0
    while ticks < 3 and time.monotonic() < deadline:
        hb = beats.get(timeout=0.5)
        if hb is not None:
            ticks = hb.counters["ticks"]
    assert ticks == 3
    hub.publish(hub.keys.ctl("all"), Control(command="stop", target="ticker"))
    thread.join(timeout=5.0)
    assert not thread.is_alive()


def test_heartbeat_is_rate_limited_and_carries_only_the_role_counters(hub_and_role_session):
    hub, s = hub_and_role_session
    beats = hub.subscribe(hub.keys.heartbeat("ticker"), Heartbeat)
    _settle()
    role = Ticker(s, report_faults=False)
    role.heartbeat()
    hb = beats.get(timeout=5.0)
    assert hb is not None and hb.counters == {"ticks": 0}
    role.heartbeat()  # within heartbeat_every_s of the last one: nothing sent
    assert beats.get(timeout=0.3) is None


def _publish_versions(hub: HammerSession, versions: list[int]) -> None:
    for v in versions:
        hub.publish(hub.keys.weights("local"), Weights.from_blob("local", v, f"weights v{v}".encode()))


def test_weights_intake_loads_the_version_a_step_names_not_a_newer_one(hub_and_role_session):
    hub, s = hub_and_role_session
    loads: list[tuple[bytes, int]] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append((blob, v)), timeout_s=5.0)
    _settle()
    _publish_versions(hub, [0, 1, 2])
    intake.take(1)
    assert intake.version == 1 and loads[-1] == (b"weights v1", 1)
    assert intake.wait_timeouts == 0
    _publish_versions(hub, [3])
    time.sleep(0.3)
    intake.take(None)  # no step named (an idle evaluation server): the newest received, without waiting
    assert intake.version == 3 and loads[-1] == (b"weights v3", 3)
    assert intake.loaded == len(loads)


def test_weights_intake_times_out_on_a_version_that_never_comes(hub_and_role_session):
    hub, s = hub_and_role_session
    loads: list[int] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=0.5)
    _settle()
    _publish_versions(hub, [0])
    t0 = time.monotonic()
    intake.take(3)
    waited = time.monotonic() - t0
    assert intake.wait_timeouts == 1 and intake.version == 0 and loads == [0]
    assert 0.4 < waited < 3.0
    intake.take(0)  # a version already loaded: no wait, no timeout
    assert intake.wait_timeouts == 1


def test_a_restarted_role_whose_first_version_is_gone_takes_the_next_one(hub_and_role_session):
    """A role restarted mid-run holds no policy; its first steps name the version current when it
    joined, and only newer ones are published after it (each version once). It must not wait out the
    timeout and then act without a policy (a pool crashed so); a role that holds a policy still waits
    for exactly the version its step names."""
    hub, s = hub_and_role_session
    loads: list[int] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=30.0)
    _settle()
    _publish_versions(hub, [5, 6])
    t0 = time.monotonic()
    intake.take(4)
    assert time.monotonic() - t0 < 10.0 and intake.version == 5 and loads == [5]
    assert intake.versions_passed == 1 and intake.wait_timeouts == 0
    intake.take(6)
    assert intake.version == 6
    waiting = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=0.5, version=3)
    _settle()
    _publish_versions(hub, [5])
    waiting.take(4)  # holds version 3: never jumps ahead of what the step names
    assert waiting.version == 3 and waiting.wait_timeouts == 1 and waiting.versions_passed == 0


def test_weights_intake_preloads_the_oldest_version_held(hub_and_role_session):
    hub, s = hub_and_role_session
    loads: list[int] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=1.0)
    _settle()
    assert not intake.preload_oldest()
    _publish_versions(hub, [4, 5])
    time.sleep(0.3)
    assert intake.preload_oldest() and loads == [4] and intake.version == 4


def _stop_from(session: HammerSession, sender: str) -> None:
    """A stop command whose header names `sender` (plain profile: the header is whatever the peer writes)."""
    from hammer.protocol.codec import encode

    data = encode(Control(command="stop"), stamp={"sender": sender})
    session.put_bytes(session.keys.ctl("all"), data)


@pytest.mark.parametrize("obeyed", ["launcher", "env"])
def test_a_stop_from_the_launcher_or_the_env_host_is_obeyed_from_anyone_else_counted_and_ignored(
        hub_and_role_session, obeyed):
    hub, s = hub_and_role_session
    role = Ticker(s)
    thread = _start(role)
    _settle()
    others = ("ticker", "local-0", "central", "learner", "hub", "Launcher")
    for sender in others:
        _stop_from(s, sender)
    deadline = time.monotonic() + 5.0
    while role.rejected["control_sender"] < len(others) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert thread.is_alive() and role.stop_reason is None
    assert role.rejection_counters() == {"rejected.control_sender": len(others)}
    _stop_from(hub, obeyed)
    thread.join(timeout=5.0)
    assert not thread.is_alive() and role.stop_reason == f"stop command from {obeyed}"


def test_a_role_that_stops_progressing_says_so_in_its_heartbeat(hub_and_role_session):
    hub, s = hub_and_role_session
    beats = hub.subscribe(hub.keys.heartbeat("ticker"), Heartbeat)
    _settle()
    role = Ticker(s, report_faults=False)
    role.stall_warn_s, role.stall_what = 0.3, "ticks"
    role.heartbeat()
    assert beats.get(timeout=5.0).detail == ""  # no progress yet: not armed (a role waiting to start)
    role.progressed()
    time.sleep(0.5)
    role._last_heartbeat = 0.0
    role.heartbeat()
    hb = beats.get(timeout=5.0)
    assert hb.detail.startswith("stalled: no progress for") and "ticks" in hb.detail
    role.progressed()
    role._last_heartbeat = 0.0
    role.heartbeat()
    assert beats.get(timeout=5.0).detail == ""


def test_weights_intake_rejects_a_version_further_ahead_than_the_learner_can_be(hub_and_role_session):
    hub, s = hub_and_role_session
    loads: list[int] = []
    refused: list[str] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=1.0,
                           reject=lambda reason, what: refused.append(reason), max_policy_lag=1)
    _settle()
    _publish_versions(hub, [0, 2**62, 2, 1, 3])  # 2^62: forged; 2 and 3 are within the lag bound
    time.sleep(0.3)
    intake.take(1)
    assert intake.version == 1 and refused == ["weights_ahead"]
    assert intake.ahead(2**62) and not intake.ahead(4)
    intake.take(3)
    assert intake.version == 3 and 2**62 not in loads


def test_a_forged_first_weights_version_is_refused_when_the_run_version_is_known(hub_and_role_session):
    """Before any weights are held, the run's known version is the reference: a forged 2^62 first is
    refused (before: adopted, and every later bound was void); the real version 0 after it is loaded."""
    hub, s = hub_and_role_session
    loads: list[int] = []
    refused: list[str] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=1.0,
                           reject=lambda reason, what: refused.append(reason), start_version=0)
    from hammer.runtime.bounds import FIRST_VERSION_SLACK

    assert intake.ahead(2**62) and not intake.ahead(1)  # a step naming a version, before any weights
    assert intake.ahead(FIRST_VERSION_SLACK + 2) and not intake.ahead(FIRST_VERSION_SLACK + 1)
    _settle()
    _publish_versions(hub, [2**62, 0])
    time.sleep(0.3)
    intake.take(0)
    assert loads == [0] and refused == ["weights_ahead"] and intake.known == 0
    assert intake.ahead(2**62 - 1)  # the bound holds from the real version on
    no_start = WeightsIntake(s, "local", lambda blob, v: None, timeout_s=1.0)  # an edge agent from a bundle
    assert not no_start.ahead(2**62)  # no known version: the first weights set the reference (as before)


def test_weights_intake_follows_a_real_versions_stream_beyond_its_bound(hub_and_role_session):
    """A role restarted with a stale hint (or paused while the learner moved on) sees real versions far
    above what it holds; once they have been its only weights for resync_s and continue (or repeat, as
    a policy server republishes), it follows them. One forged version never does."""
    hub, s = hub_and_role_session
    loads: list[int] = []
    intake = WeightsIntake(s, "local", lambda blob, v: loads.append(v), timeout_s=0.2,
                           reject=lambda reason, what: None, start_version=0, resync_s=0.3)
    _settle()
    _publish_versions(hub, [0, 1])
    time.sleep(0.2)
    intake.take(None)
    assert intake.known == 1
    _publish_versions(hub, [40])
    time.sleep(0.2)
    intake.take(None)
    assert intake.known == 1  # alone: refused
    time.sleep(0.4)
    _publish_versions(hub, [40, 41])  # the stream repeats and continues after resync_s of nothing else
    time.sleep(0.3)
    intake.take(None)
    assert intake.known == 41 and loads[-1] in (40, 41)
    restarted = WeightsIntake(s, "local", lambda blob, v: None, timeout_s=0.2, start_version=3)
    _publish_versions(hub, [7])  # the learner moved on while the role restarted: inside the slack, taken
    time.sleep(0.2)
    restarted.take(None)
    assert restarted.known == 7


def test_step_window_rejects_a_far_step_once_and_follows_a_stream_that_moved_on():
    from hammer.runtime.bounds import StepWindow

    w = StepWindow(width=100, resync_s=0.2)
    assert not w.ahead(5, -1)  # nothing acted on yet: the first step anchors
    assert w.ahead(2**63, 5) and not w.ahead(6, 5)  # one forged step: rejected, the real stream goes on
    time.sleep(0.3)
    assert w.ahead(2**63, 6)  # alone after a quiet spell: still rejected (nothing continues it)
    assert not w.ahead(7, 6)
    time.sleep(0.3)
    assert w.ahead(5000, 7)  # a real stream beyond the window (a role paused for long) ...
    assert not w.ahead(5001, 7)  # ... is followed once it continues after resync_s of nothing else


def test_step_window_refuses_a_forged_first_step_beyond_the_runs_known_step():
    from hammer.runtime.bounds import StepWindow

    w = StepWindow(width=100, resync_s=0.2, start=40)
    assert w.ahead(2**64 - 1, -1)  # before the role's first real step: refused, not adopted
    assert w.ahead(141, -1) and not w.ahead(41, -1)  # the bound is the known step + the width
    assert not StepWindow(width=100, start=None).ahead(2**64 - 1, -1)  # no known step: the first one anchors


def test_step_window_follows_a_steady_stream_below_an_anchor_it_never_followed():
    from hammer.runtime.bounds import MIN_STREAM, StepWindow

    assert MIN_STREAM == 3
    w = StepWindow(width=100, resync_s=0.2, start=0)
    assert not w.ahead(99, -1)  # a forged step inside the bound became the anchor (last = 99)
    assert w.stale(1, 99) and w.stale(2, 99) and w.stale(3, 99)  # a stream, but resync_s has not passed
    time.sleep(0.3)
    assert w.stale(1, 99)  # out of order (a duplicate): the stream starts again from one
    assert w.stale(2, 99)  # two in order: not yet a stream
    assert not w.stale(3, 99)  # three, after resync_s with nothing accepted: followed, the caller acts on it
    assert not w.ahead(3, 99)  # accepted in the window of the old anchor; the caller's last moves down to 3
    assert w.stale(3, 3) and w.stale(2, 3)  # duplicates right after it are stale again (just accepted)
    assert w.stale(3, 3)


def test_a_role_the_launcher_starts_mid_run_knows_the_env_hosts_step(tmp_path, monkeypatch):
    """The launcher hands every role it (re)starts the env host's last reported step; the role's
    first-step bound starts there (not at 0, where a restart after step_window would refuse the
    real stream) and never below the run's own start."""
    from hammer.deploy.launcher import Launcher
    from hammer.runtime.bounds import RUN_STEP_ENV, known_step

    launcher = Launcher([], tmp_path, startup_timeout_s=1.0)
    launcher.on_heartbeat(Heartbeat(role="env", pid=1, status="running", counters={"step": 12_345}))
    hint = launcher.sup._env[RUN_STEP_ENV]  # what the next started role gets in its environment
    monkeypatch.setenv(RUN_STEP_ENV, hint)
    assert known_step(None) == 12_345 and known_step(20_000) == 20_000
    monkeypatch.setenv(RUN_STEP_ENV, "junk")
    assert known_step(None) == 0 and known_step(7) == 7
    monkeypatch.delenv(RUN_STEP_ENV)
    assert known_step(None) == 0


def test_a_role_the_launcher_starts_mid_run_knows_the_runs_policy_version(tmp_path, monkeypatch):
    """The same for weights: the env host's last reported policy version bounds a (re)started role's
    first weights; never below the run's resume update."""
    from hammer.deploy.launcher import Launcher
    from hammer.runtime.bounds import RUN_VERSION_ENV, known_version

    launcher = Launcher([], tmp_path, startup_timeout_s=1.0)
    launcher.on_heartbeat(Heartbeat(role="env", pid=1, status="running", counters={"step": 5}, gauges={"policy_version": 17}))
    monkeypatch.setenv(RUN_VERSION_ENV, launcher.sup._env[RUN_VERSION_ENV])
    assert known_version(None) == 17 and known_version(30) == 30
    monkeypatch.setenv(RUN_VERSION_ENV, "-3")
    assert known_version(None) == 0


def test_actions_echo_their_message_only_where_the_env_host_records_it():
    """Training records the message each action used (the rollout), and so does a trace; serving
    records neither, and the message stays off the wire. The env host requires the echo exactly where
    it records, and says so in every observation (LocalObs.echo): an agent needs no setting of its own."""
    from hammer.runtime.settings import RuntimeSettings

    assert RuntimeSettings(run_id="r").echo
    assert not RuntimeSettings(run_id="r", mode="eval", policy_dir="p").echo
    assert RuntimeSettings(run_id="r", mode="eval", policy_dir="p", trace=True).echo
