"""The robot-side SDK: one local agent of a trained team inside a robot's own control loop.

    from hammer.edge import EdgeAgent
    with EdgeAgent("bundles/cn3", agent=1, run_id="site-a", connect="tcp/192.0.2.1:7447", insecure=True) as robot:
        while running:
            action = robot.act(read_sensors())   # never waits on the network
            drive(action)

Why this shape (docs/fleet.md): a robot owns its sensors and its clock. `act(obs)` sends the
observation up to the central agent (the robot's uplink, `agent/up/<i>`), then acts at once on the
freshest central message it holds, if that is no older than `max_msg_age_s`, else on the team's
fallback (counted). The only waiting is the policy's own forward (tens of µs): the uplink is a
reliable publisher with congestion control DROP, so a dead link drops the uplink instead of
holding up the robot, and a message that arrives late is simply used by a later call.

A message's age is counted from its arrival here (no clock shared with the central agent is
needed); only the newest message is held (`HammerSession.subscribe_latest`). Torch-free: the weights are the
bundle's safetensors, run by numpy (`local_agent.client.LocalAgent`).

Hot updates (`hammer push` / `hammer rollback` to a fleet, docs/fleet.md): the robot holds a
`WeightsIntake` of the local network. Each `act` calls its `pump()` once: a pushed version is pulled
in chunks, one small chunk asked for per act and at most one in flight, so the robot's own control
loop paces what a push puts on its link. A realtime fleet has no step boundary at which all robots
could switch together, so each robot switches on its own, at the first `act` after it holds the
version (checked against the announcement's sha256); loading it is a parse of tens of kB, never a
wait on the network. A robot that holds no version from the run yet (it just started, or restarted
mid-run) asks for the current one (a query, at most once a second, answered whole), as a late
joiner of a served run does.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import numpy as np

log = logging.getLogger("hammer.edge")


@dataclass
class EdgeCounters:
    """What a robot did, as totals (its heartbeat reports them in a served fleet)."""

    acts: int = 0
    msg_fresh: int = 0  # acted on a central message no older than max_msg_age_s
    msg_stale: int = 0  # the newest message held was too old: acted on the team's fallback
    msg_none: int = 0  # no message yet: the fallback
    msgs_received: int = 0
    uplinks_sent: int = 0
    stale_periods: int = 0  # times the messages went stale (each a log line, as is their return)
    policy_switches: int = 0  # times it began acting with another policy version (each a log line)
    weights_rejected: int = 0  # weights or announcements refused (a version too far ahead)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class FleetClient:
    """What every client of a fleet's router shares (a robot, the site feed): its session opened here
    (`wait`) or in the background while it works without one, and a close that the session cannot
    outlive. A subclass sets `name`, `settings`, `transport` and `counts`, and declares what it
    sends and hears in `_join`; `_alone` says what it does while it has no session."""

    _alone = "working without the fleet"

    def _start(self, wait: bool, retry_s: float) -> None:
        self.session = None
        self._closed = threading.Event()
        self._joiner: threading.Thread | None = None
        if wait:
            self._join(retry_s)
        else:
            self._joiner = threading.Thread(target=self._join_quietly, args=(retry_s,), daemon=True,
                                            name=f"{self.name}-join")
            self._joiner.start()

    def _join(self, retry_s: float) -> None:
        raise NotImplementedError

    def _open(self, retry_s: float):
        """The session, or None if closed meanwhile (ConnectionError: no router within `retry_s`)."""
        from hammer.protocol.session import HammerSession

        session = open_fleet_client(HammerSession, self.settings, self.transport, self.name, retry_s, self._closed)
        if session is not None and self._closed.is_set():  # closed while this was opening
            session.close()
            return None
        return session

    def _joined(self) -> None:
        log.info("%s joined run %s (%s)", self.name, self.settings.run_id,
                 ", ".join(self.transport.connect) or self.transport.zenoh_config_file or "-")

    def _join_quietly(self, retry_s: float) -> None:
        try:
            self._join(retry_s)
        except ConnectionError as e:
            log.warning("%s (%s)", e, self._alone)

    def close(self) -> None:
        counts = self.counts.as_dict() if hasattr(self.counts, "as_dict") else self.counts
        log.info("%s leaves run %s: %s", self.name, self.settings.run_id, counts)
        self._closed.set()
        if self._joiner is not None:
            self._joiner.join(30)  # an open under way ends within its open timeout; the session must not outlive us
        if self.session is not None:
            self.session.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EdgeAgent(FleetClient):
    """Agent `agent` of the team in `bundle`, joined to run `run_id` (`act`, `run`, `close`).

    Transport: `connect` (the fleet's router: the robot is a Zenoh client of it, which no other
    process ever dials), or `zenoh_config`; `identity` (a directory with ca.pem, local-<i>.pem, local-<i>.key) for a secure
    run; `insecure` to accept plain traffic beyond loopback. `max_msg_age_s`: the oldest central
    message acted on; `fallback`: the team's own (from the bundle) unless given (zeros, last, last_k).
    `connect_retry_s`: how long to keep trying to reach the fleet's router: in the background while
    `act` acts on the fallback (a robot started before its fleet; a warning when it gives up), or,
    with `wait=True`, in the constructor, then ConnectionError.
    `runtime`: RuntimeSettings items as `hammer local --runtime` takes them (`zenoh_lease_s=30`, ...).
    `trust`: ed25519 public keys (`hammer keygen`'s NAME.pub); given any, the bundle loads only if one
    of them signed it (serve/signing.py), else BundleError.
    `fed_by_world`: a simulated robot (`robot_role`): its sensors are the world's observation, which
    carries the central message (`act_on_world`), so it neither uplinks nor listens to `central/msg/<i>`.
    """

    _alone = "acting on the fallback"

    def __init__(self, bundle: str | Path, agent: int, *, run_id: str, connect: str | None = None,
                 zenoh_config: Path | None = None, identity: Path | None = None, insecure: bool = False,
                 max_msg_age_s: float = 0.5, fallback: str | None = None, seed: int | None = None,
                 connect_retry_s: float = 300.0, runtime: tuple[str, ...] = (),
                 trust: tuple[str | Path, ...] = (), wait: bool = False, fed_by_world: bool = False) -> None:
        from hammer.local_agent.client import LocalAgent, MessageFallback
        from hammer.serve.bundle import LOCAL, load_bundle
        from hammer.serve.edge_entry import agent_spec, edge_settings, edge_transport

        if not max_msg_age_s > 0:
            raise ValueError(f"max_msg_age_s: must be > 0 s, got {max_msg_age_s}")
        b = load_bundle(Path(bundle), check_config=False, trust=tuple(Path(k) for k in trust))
        fleet_check(b)
        self.spec, _ = agent_spec(b, agent, seed)
        env = b.env_spec_data
        self.settings = edge_settings(b, run_id, None, [*runtime, *([f"fallback={fallback}"] if fallback else [])])
        self.transport = edge_transport(self.settings, f"local-{agent}", self.spec.n_agents, connect, zenoh_config,
                                        identity, insecure, client=True)
        self.agent, self.max_msg_age_s, self.fed_by_world = agent, max_msg_age_s, fed_by_world
        self.name = f"local-{agent}"
        self.obs_dim = int(env["obs_dim"])
        cols = site_columns(env)
        self.local_dim = None if cols is None else cols[0]  # the robot's own columns; the rest: the site feed's
        self.row_dim = self.obs_dim if cols is None else cols[0]  # what crosses the robot's link: its own columns
        self.low, self.high = env.get("action_low"), env.get("action_high")
        self.core = LocalAgent(self.spec)
        self._bundle_blob = (b.path / LOCAL).read_bytes()
        self.core.load_weights(self._bundle_blob, 0)
        self.policy_version = 0  # the version acted with: the bundle's is the run's first (0) until one arrives
        self.switches: collections.deque[tuple[float, int, int]] = collections.deque(maxlen=64)  # (time, from, to)
        self.fallback = MessageFallback(self.settings.fallback, self.settings.fallback_k, 1, self.spec.msg_dim)
        self.counts = EdgeCounters()
        self._env_idx = np.zeros(1, np.int64)
        self._prev: np.ndarray | None = None  # the last action taken, for the uplink
        self.last_msg: np.ndarray | None = None  # (1, M) the message the last act used (received or fallback)
        self._msg: np.ndarray | None = None  # the newest central message held ...
        self._msg_t = 0.0  # ... and when it arrived (monotonic)
        self.last_fresh = False
        self._stale_since: float | None = None  # when the messages went stale (None: fresh, or none yet)
        self.ages: collections.deque[float] = collections.deque(maxlen=1024)  # of the messages acted on, s
        # The robot is a client of the fleet's router, whose session opens only once the router
        # answers. `wait`: here, up to connect_retry_s (ConnectionError after); else in the
        # background, while `act` acts on the fallback (a robot started before its fleet).
        self._msgs = self._up = self.weights = None
        self._start(wait, connect_retry_s)

    def _join(self, retry_s: float) -> None:
        """Open the session and declare what the robot sends and hears (ConnectionError: no router)."""
        from hammer.protocol.dims import Dims
        from hammer.protocol.schemas import CentralMsg
        session = self._open(retry_s)
        if session is None:
            return
        try:
            keys = session.keys
            msgs = up = None
            if not self.fed_by_world:
                msgs = session.subscribe_latest(
                    keys.msg(self.agent), CentralMsg,
                    Dims(num_envs=1, n_agents=self.spec.n_agents, msg_dim=self.spec.msg_dim))
                up = session.publisher(keys.up(self.agent), express=True, block=False)
            self.weights = self._intake(session)
            session.declare_alive(self.name)
        except BaseException:
            session.close()
            raise
        self._msgs, self._up = msgs, up
        self.session = session  # last: `act` uses the session once all of it is declared
        self._joined()

    def _intake(self, session):
        """The local network's weights from the run's policy server. Nothing held from the run at
        first (version -1): the first version received, a publication or the answer to this
        robot's query, sets the reference a later version is bounded by (runtime.bounds), since a
        robot started from a bundle does not know which version the run is at."""
        from hammer.runtime.weights import WeightsIntake

        def reject(reason: str, what: str) -> None:
            self.counts.weights_rejected += 1
            log.warning("%s: rejected (%s): %s", self.name, reason, what)

        intake = WeightsIntake(session, "local", self._load, timeout_s=0.0, reject=reject)
        intake.remember(self._bundle_blob)  # a rollback to the bundle's weights is held without a pull
        return intake

    def _load(self, blob: bytes, version: int) -> None:
        """Act with `version` from the next forward on (a log line and a counter when it changes)."""
        self.core.load_weights(blob, version)
        if version != self.policy_version:
            log.info("%s: acting with policy version %d (was %d)", self.name, version, self.policy_version)
            self.switches.append((time.time(), self.policy_version, version))
            self.counts.policy_switches += 1
        self.policy_version = version

    def _take_weights(self) -> None:
        """Once per act: a push's next chunk (pump), then the newest version held, loaded at once.
        A robot holding nothing from the run asks for the current version (the query returns at
        once; its answer is taken by a later act)."""
        w = self.weights
        if w is None or self.session is None:
            return  # not joined yet
        w.pump()
        if w.known < 0:
            w.fetch()  # at most once every FETCH_EVERY_S
        w.take_newest()

    def weight_gauges(self) -> dict[str, int]:
        """The version it acts with and the newest it holds (the heartbeat's `policy_version`,
        `policy_held`), the version being pulled (-1: none)."""
        pulling = None if self.weights is None else self.weights.pulling
        known = -1 if self.weights is None else self.weights.known
        return {"policy_version": self.policy_version, "policy_held": max(known, self.policy_version),
                "policy_pulling": -1 if pulling is None else pulling}

    # ----- the control step -----------------------------------------------------------------------
    def act(self, obs: Any) -> np.ndarray:
        """The action for observation `obs` (the robot's D floats; for a team with a site feed, its own
        L floats, or D of which the rest is ignored): an int64 id (discrete) or a
        float32 vector clipped to the action box. Sends the uplink first; never waits on the network."""
        o = np.asarray(obs, dtype=np.float32).reshape(-1)
        sizes = (self.obs_dim,) if self.local_dim is None else (self.local_dim, self.obs_dim)
        if o.shape[0] not in sizes or not np.isfinite(o).all():
            raise ValueError(f"obs: expected {' or '.join(map(str, sizes))} finite floats, got shape {np.shape(obs)}"
                             f"{'' if np.isfinite(o).all() else ' with NaN/inf'}")
        o = o[None, :self.row_dim]
        self._uplink(o)
        return self._decide(self._row(o))

    def _row(self, o: np.ndarray) -> np.ndarray:
        """(1, D): the robot's own columns, and zeros where a team with a site feed has the site's
        columns (the robot never sees them; its policy was trained on them zeroed)."""
        if self.local_dim is None:
            return o
        row = np.zeros((1, self.obs_dim), np.float32)
        row[:, :self.local_dim] = o[:, :self.local_dim]
        return row

    def act_on_world(self, obs: np.ndarray, msg: np.ndarray | None, arrived: float) -> np.ndarray:
        """The action for a simulated fleet's observation (1, D; a team with a site feed: the robot's own
        (1, L)), `msg` (1, M) the central message it carried (None: none came with it), both arrived at
        `arrived` (time.monotonic()): a message held like one from `central/msg/<i>`; no uplink (the
        world holds what it would say)."""
        if msg is not None:
            self._msg, self._msg_t = msg, arrived
            self.counts.msgs_received += 1
        return self._decide(self._row(obs))

    def _decide(self, o: np.ndarray) -> np.ndarray:
        msg = self.last_msg = self.message()
        self._take_weights()
        action = self.core.act(o, msg)[0]
        if not self.spec.discrete and self.low is not None:
            action = np.clip(action, self.low, self.high).astype(np.float32)
        self._prev = np.asarray(action)
        self.counts.acts += 1
        return self._prev

    def message(self) -> np.ndarray:
        """(1, M) float32: the freshest central message if young enough, else the fallback (counted)."""
        now = time.monotonic()
        for got, t in self._msgs.take() if self._msgs is not None else ():  # at most one, the newest
            self._msg, self._msg_t = got.msg, t
            self.counts.msgs_received += 1
        self.last_fresh = self._msg is not None and now - self._msg_t <= self.max_msg_age_s
        if self._msg is not None:
            self.ages.append(now - self._msg_t)
            self._note_freshness(now)
        if self.last_fresh:
            self.counts.msg_fresh += 1
            self.fallback.received(self._env_idx, self._msg)
            return self._msg
        if self._msg is None:
            self.counts.msg_none += 1
        else:
            self.counts.msg_stale += 1
        return self.fallback.fill(self._env_idx)

    def _note_freshness(self, now: float) -> None:
        """A log line when the central messages go stale and when fresh ones come back (with the gap)."""
        if not self.last_fresh and self._stale_since is None:
            self._stale_since = self._msg_t + self.max_msg_age_s
            self.counts.stale_periods += 1
            log.warning("%s: central messages stale (newest %.2f s old): acting on the fallback (stale %d)",
                        self.name, now - self._msg_t, self.counts.stale_periods)
        elif self.last_fresh and self._stale_since is not None:
            log.warning("%s: fresh central messages again after %.2f s stale", self.name, now - self._stale_since)
            self._stale_since = None

    def _uplink(self, obs: np.ndarray) -> None:
        from hammer.protocol.schemas import Uplink

        if self._up is None:
            return  # not joined yet (nobody to send it to), or fed by the world
        prev = None if self._prev is None else (self._prev.reshape(1) if self.spec.discrete else self._prev[None])
        self._up.publish(Uplink(step=self.counts.acts, env_idx=self._env_idx, agent=self.agent, obs=obs,
                                action=prev))
        self.counts.uplinks_sent += 1

    def age_gauges(self) -> dict[str, float | None]:
        """p50 / p99 age (ms) of the newest central message at the latest acts (stale ones included):
        both keys always, None while no message has been received."""
        if not self.ages:
            return {"msg_age_p50_ms": None, "msg_age_p99_ms": None}
        p50, p99 = np.percentile(np.fromiter(self.ages, float), [50, 99]) * 1e3
        return {"msg_age_p50_ms": round(float(p50), 2), "msg_age_p99_ms": round(float(p99), 2)}

    # ----- a loop for callers that want one -------------------------------------------------------
    def run(self, sense: Callable[[], Any], actuate: Callable[[np.ndarray], None], hz: float,
            should_stop: Callable[[], bool] = lambda: False) -> None:
        """The robot's control loop at `hz`: sense, act, actuate, until `should_stop()` (or Ctrl-C).
        A tick that comes late is served at once and the ones it overran are skipped."""
        from hammer.runtime.clock import Clock

        clock = Clock(hz)
        while not should_stop():
            if clock.due(0.2):
                actuate(self.act(sense()))


def open_fleet_client(session_type, settings, transport, name: str, retry_s: float, closed: threading.Event):
    """A fleet client's session (a robot's, the site feed's: `serve/site_feed.py`), opened as soon as
    the fleet's router answers, trying for `retry_s`; None if `closed` is set meanwhile;
    ConnectionError with the fix when the router never answered."""
    from hammer.protocol.session import OpenTimeout, open_retrying

    try:
        return open_retrying(
            lambda: session_type(settings.run_id, transport, settings.faults, sender=name),
            time.monotonic() + retry_s, closed.is_set,
            lambda reason: log.info("%s waiting for the run's router (%s)", name, reason),
            pause=closed.wait, retry_s=0.5)
    except OpenTimeout as e:
        raise ConnectionError(f"{name}: the run's router not reachable within {retry_s:g} s "
                              f"({e.reason}); fix: check the address and that the router is up") from None


def site_columns(env: dict) -> tuple[int, int] | None:
    """(L, D): the central-only columns [L, D) of a team's observation rows, which a fleet's site feed
    carries (`serve/site_feed.py`); None for a team whose robots observe their whole row."""
    local, d = env.get("local_obs_dim"), int(env["obs_dim"])
    return None if local in (None, d) else (int(local), d)


def fleet_check(bundle) -> None:
    """What a team needs to run as a fleet, in one line: every robot acts on its own observation (not
    the joint one of variant centralized). Central-only columns (rware's requested shelves) come from
    the site feed (`site_columns`, docs/fleet.md "The site feed"), not from any robot."""
    if bundle.wiring().joint_obs:
        raise ValueError(f"bundle {bundle.path}: variant {bundle.manifest['variant']} acts on the joint "
                         "observation of all agents, which no robot has; a fleet runs il or hammer teams")


def robot_role(agent: EdgeAgent, stay: bool = False, lost_exit_s: float | None = None):
    """The robot of a simulated fleet as a role process (`hammer local --bundle ... --fleet`): its
    sensors are the realtime world's observation for it (`env/obs/<i>`), its actuator the world's
    action key (`agent/act/<i>`); in between, `agent.act_on_world` on the observation and the central
    message it carries (one message down per tick; the action is the one message up). An agent made
    `fed_by_world` neither uplinks nor listens to `central/msg/<i>`. A heartbeat carries its counters.

    Losing the fleet (a cut link, a server restarted or stopped): the robot waits, acting on nothing
    (a simulated robot's sensors are the world's). Its Zenoh session keeps dialling the hub, so it acts
    again on the first observation once the fleet is back. `stay=False`: a stop from the launcher ends
    it, and so does hearing nothing for `lost_exit_s` (a robot out of range when the stop was sent
    must not wait for ever): `stop_reason` then starts with "lost". `stay=True`: a service; a stop
    ends only the fleet's session, the robot waits for the next (a restarted `hammer serve` on the
    same run directory) and rejoins on its own; only SIGTERM or Ctrl-C end it."""
    from hammer.protocol.dims import Dims
    from hammer.protocol.schemas import Action, LocalObs
    from hammer.runtime.role import Role

    class Robot(Role):
        def __init__(self) -> None:
            super().__init__(agent.session, agent.name)
            keys = agent.session.keys
            self.sensors = agent.session.subscribe_latest(keys.obs(agent.agent), LocalObs,
                                                          Dims(num_envs=1, obs_dim=agent.row_dim,
                                                               msg_dim=agent.spec.msg_dim))
            self.actuator = agent.session.publisher(keys.act(agent.agent), express=True, block=False)
            self.stall_what = "observations from the world"
            self.last_act: float | None = None
            self.idle_exit_s = None if stay else lost_exit_s
            self.sessions_ended = 0

        def stop_requested(self) -> bool:
            if not super().stop_requested():
                return False
            if not stay:
                return True
            self.sessions_ended += 1
            self.log.info("%s: the fleet's session ended (%s); staying for the next one (--stay)", agent.name,
                          self.stop_reason)
            self.stop_reason = None
            self.heartbeat_soon()
            return False

        def on_stop(self) -> None:
            if self.stop_reason is not None and self.stop_reason.startswith("no input"):
                self.stop_reason = (f"lost the fleet: nothing from it for {self.idle_exit_s:g} s (out of range when it "
                                    "stopped, or its server is gone); exiting (--stay waits for it instead)")
                self.log.warning("%s %s", agent.name, self.stop_reason)

        def alive_names(self) -> list[str]:
            return []  # the EdgeAgent declared it

        def counters(self) -> dict[str, int]:
            return {**agent.counts.as_dict(), **agent.weights.counters()}

        def gauges(self) -> dict[str, float]:
            ages = {k: v for k, v in agent.age_gauges().items() if v is not None}  # a gauge is a number: none yet, unsent
            return {**agent.weight_gauges(), **ages}

        def poll(self, timeout: float) -> bool:
            if not self.sensors.wait(timeout):
                return False
            for obs, t in self.sensors.take():
                switches = agent.counts.policy_switches
                action = agent.act_on_world(obs.obs, obs.msg, t)
                if agent.counts.policy_switches != switches:
                    self.heartbeat_soon()  # the launcher sees the switch now, not a heartbeat later
                if self.last_act is not None and t - self.last_act > 1.0:  # the world was out of reach
                    self.log.warning("%s: observations again after %.2f s (central message %s)", agent.name,
                                     t - self.last_act, "fresh" if agent.last_fresh else "stale")
                self.last_act = t
                self.actuator.publish(Action(step=obs.step, env_idx=obs.env_idx, agent=agent.agent,
                                             action=action.reshape(1, *action.shape[0:]),
                                             policy_version=agent.policy_version,
                                             fallback=np.array([not agent.last_fresh]),
                                             msg=agent.last_msg if obs.echo and agent.spec.msg_dim else None))
                self.progressed()
            return True

    return Robot()
