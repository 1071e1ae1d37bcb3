"""The central agent of a fleet: its state built from the robots' own uplinks, messages on its own clock.

Why apart from `central_server.CentralServer`: in training the central agent is one step of a lock-stepped
loop, fed the simulator's global state. A fleet has no such state and no shared step: each robot
uplinks what its sensors saw and the action it took (`agent/up/<i>`, serve/edge_agent.py), when it
can. So this role keeps each robot's latest uplink with its arrival time, and at every tick of its
clock builds the state the central network was trained on, o_1 ⊕ … ⊕ o_N ⊕ a_1 ⊕ … ⊕ a_N, from them.

The missing rule (one, declared: `MISSING_RULE`): a robot silent for longer than `missing_after_s`
is missing, and its part of the state is zeros (observation and action): `CentralActing.global_state`
with `present`, the same function a training run with `missing_prob` > 0 uses to simulate robots
going missing, so a team can learn to act well while one is away. Each robot's joins,
leaves (goes missing) and rejoins are log lines with its name and a counter, and heartbeat counters.

Messages go out at every tick to every robot (`central/msg/<i>`) through reliable publishers with
congestion control DROP: a robot whose link is down loses its own messages and holds up no one.
The wire carries no send time or sequence number, so a robot dates a message by arrival and takes
the newest.

Whose clock: a simulated fleet's world (env_host/world.py) is its clock. It sends the state of each
of its ticks (`env/state`: every robot's observation, the actions it just applied, who it hears)
over the serving machine's loopback, and this role answers each at once, its messages stamped with
the world's tick, which the world puts into the robots' observations of that tick (one message down
per robot per tick). Its robots send no uplinks: the world already holds what they would say. A
robot that uplinks (the SDK on a robot with its own sensors) has its row from its uplinks while
they come (within `missing_after_s`), and reads its messages from `central/msg/<i>` itself. Until a
world is heard (none at all: robots on the SDK only), this role ticks on its own clock at `hz`,
stamped with its own tick count (from 0 at its start: a restarted central agent starts again at 0);
once one is, it serves the world's ticks only (the world's end is the fleet's). A robot counts as
heard when its uplink arrives or a state of the world says the world hears it (the world's `hold_s`).

The site feed (docs/fleet.md, "The site feed"): a team whose rows have central-only columns [L, D)
(rware's requested shelves and goals) gets them from the site (`site/state`, a `SiteState` from the
site's own identity: a warehouse management system on `hammer.site.SiteFeed`, or in simulation the
world as the site), not from any robot, so this role puts the newest feed into those columns of every
row. The silent rule (one, declared: `SITE_SILENT_RULE = "zeros"`): a feed silent for longer than
`site_hold_s` is held no longer, and the columns are zeros, as in a training run that simulates the
feed's absence (`site_missing_prob`); its silences and returns are log lines and counters
(`site.absent_max_s`, `site.joined`, `site_silent_ticks`), named in the fleet's verdict.

Hot updates (`hammer push` to a fleet): the fleet's policy server publishes a pushed version's central
network whole (this role's link is on the server side). No step names versions in a fleet: each
robot switches as soon as it holds the pushed local policy (it pulls it in chunks, seconds on a
paced link), and this role switches at a tick once every robot present holds it (their heartbeats'
`policy_held`), or after `hold_timeout_s` (counted, logged). So while a push spreads, robots already
on the new local policy act on the old central network's messages, which the push checked the new
bundle declares it works with (serve/push.py), and no robot acts with the old local policy on the new
central network's messages but one that is late past the timeout. Loading never waits. A (re)started
central agent holding nothing from the run asks for the current version, as a late joiner of a
served run does.
"""

from __future__ import annotations

import time

import numpy as np
from hammer.envs.base import EnvSpec
from hammer.learning.central_acting import CentralActing, encode_actions
from hammer.learning.config import RunConfig
from hammer.learning.numpy_policy import numpy_central
from hammer.learning.sampling import ActingStreams
from hammer.protocol.dims import Dims
from hammer.protocol.schemas import CentralMsg, GlobalState, Heartbeat, SiteState, Uplink
from hammer.protocol.session import HammerSession
from hammer.runtime.clock import SITE_HOLD_S, Clock
from hammer.runtime.presence import Presence, flat_member_rejections, rejections_by_member
from hammer.runtime.role import Role
from hammer.runtime.weights import WeightsIntake

MISSING_RULE = "zeros"  # a missing robot's observation and action in the state
SITE_SILENT_RULE = "zeros"  # a silent site feed's columns in the state
HOLD_TIMEOUT_S = 20.0  # a pushed central network is taken this long after it came even if a robot lacks its local one


class FleetCentral(Role):
    """Uplinks in, one message per robot out at `hz`; `central_weights`: the bundle's central.safetensors."""

    def __init__(self, session: HammerSession, cfg: RunConfig, spec: EnvSpec, central_weights: bytes | None,
                 hz: float, missing_after_s: float, hold_timeout_s: float = HOLD_TIMEOUT_S,
                 site_hold_s: float = SITE_HOLD_S) -> None:
        super().__init__(session, "central")
        self.cfg, self.spec, self.n = cfg, spec, cfg.n_agents
        self.acting = CentralActing.from_config(cfg)
        self.streams = ActingStreams(cfg.seed, cfg.n_agents)
        self.net = numpy_central(_safetensors(central_weights)) if self.acting.has_network else None
        self.version, self.switches = 0, 0  # the bundle's network is the run's first version (0)
        self.weights = (WeightsIntake(session, "central", self._load, timeout_s=0.0, reject=self._rejected)
                        if self.acting.has_network else None)
        self.weights_rejected = 0
        self.hold_timeout_s, self.switched_unheld = hold_timeout_s, 0
        self.held = np.full(self.n, -1, np.int64)  # each robot's newest version held (its heartbeat's policy_held)
        self._due: tuple[int, float] | None = None  # a newer central version received, and since when
        self.beats = ([session.subscribe(self.keys.heartbeat(f"local-{i}"), Heartbeat) for i in range(self.n)]
                      if self.weights is not None else [])
        self.clock = Clock(hz)
        self.poll_s = min(self.poll_s, self.clock.period)
        self.obs = np.zeros((1, self.n, spec.obs_dim), np.float32)
        self.prev = np.zeros((1, self.n, spec.action_dim), np.float32)  # each robot's last action, encoded
        self.uplinked = np.full(self.n, -np.inf)  # when each robot's latest uplink arrived
        self.missing_after_s = missing_after_s
        self.presence = Presence([f"local-{i}" for i in range(self.n)], missing_after_s, self.log)
        # a robot of a team with a site feed uplinks its own columns [0, L) only (local_obs_dim)
        local = spec.local_obs_dim if spec.local_obs_dim not in (None, spec.obs_dim) else None
        self.up_dim = local or spec.obs_dim
        self.uplinks = session.subscribe_latest(
            self.keys.up("*"), Uplink, Dims(num_envs=1, n_agents=self.n, obs_dim=self.up_dim,
                                            action_dim=spec.action_dim, discrete=spec.discrete))
        self.states = session.subscribe_latest(
            self.keys.state(), GlobalState, Dims(num_envs=1, n_agents=self.n, obs_dim=spec.obs_dim,
                                                 action_dim=spec.action_dim))
        # the site feed: the central-only columns [L, D) of every row (None: the robots observe whole rows)
        self.local_dim = spec.local_obs_dim if spec.local_obs_dim not in (None, spec.obs_dim) else None
        self.site = self.site_presence = None
        self.site_cols = None
        self.site_silent_ticks = 0
        if self.local_dim is not None:
            self.site = session.subscribe_latest(self.keys.site_state(), SiteState,
                                                 Dims(num_envs=1, site_dim=spec.obs_dim - self.local_dim))
            self.site_presence = Presence(["site"], site_hold_s, self.log)
            self.site_cols = np.zeros(spec.obs_dim - self.local_dim, np.float32)
        self.world_t = -np.inf  # when the world's latest state arrived
        self.ticks = self.world_ticks = 0  # ticks served (all; on a state of the world)
        self.pubs = [session.publisher(self.keys.msg(i), express=True, block=False) for i in range(self.n)]
        self.env_idx = np.zeros(1, np.int64)
        self.sent = 0
        self.stall_what = "states of the world or robot uplinks"

    def counters(self) -> dict[str, int]:
        return {"ticks": self.ticks, "world_ticks": self.world_ticks, "ticks_skipped": self.clock.skipped,
                "msgs_sent": self.sent, "states_superseded": self.states.superseded,
                "uplinks": self.uplinks.stats.delivered, "uplinks_superseded": self.uplinks.superseded,
                "policy_switches": self.switches, "weights_rejected": self.weights_rejected,
                "policy_switched_unheld": self.switched_unheld, **self.site_counters(),
                # per robot, the 8 longest absent and the 8 largest refusals: a heartbeat holds 64 counters
                **self.presence.counters(), **self.presence.member_counters(limit=8),
                **flat_member_rejections(rejections_by_member(self.session.rejections_by_key(), self.presence.names),
                                         limit=8)}

    def site_counters(self) -> dict[str, float]:
        """The site feed's: states taken, ticks on zeros (silent), its silences, its longest silence
        (`site.absent_max_s`) and whether it was ever heard (`site.joined`); none without a feed."""
        if self.site is None:
            return {}
        p = self.site_presence
        return {"site_states": self.site.stats.delivered, "site_silent_ticks": self.site_silent_ticks,
                "site_silences": p.leaves, **p.member_counters(limit=1)}

    def gauges(self) -> dict[str, int]:
        held = self.version if self.weights is None else max(self.version, self.weights.known)
        return {"policy_version": self.version, "policy_held": held, "robots_present": self.presence.present_count()}

    def _load(self, blob: bytes, version: int) -> None:
        """Act with the central network of `version` from the next tick on."""
        self.net = numpy_central(_safetensors(blob))
        if version != self.version:
            self.log.info("central: acting with policy version %d (was %d)", version, self.version)
            self.switches += 1
            self.heartbeat_soon()
        self.version = version

    def _rejected(self, reason: str, what: str) -> None:
        self.weights_rejected += 1
        self.log.warning("rejected (%s): %s", reason, what)

    def take_weights(self, now: float) -> None:
        """The newest central network received, loaded once every robot present holds its version
        (or `hold_timeout_s` after it came); nothing held from the run yet: ask."""
        if self.weights is None:
            return
        for i, sub in enumerate(self.beats):
            for h in sub.drain():
                self.held[i] = int(h.gauges.get("policy_held", h.gauges.get("policy_version", -1)))
        if self.weights.known < 0:
            self.weights.fetch()  # at most once every FETCH_EVERY_S
        newest = self.weights.receive()
        if newest <= self.version:  # the version acted with (a late joiner's first answer): no one to wait for
            self.weights.take_newest()
            return
        if self._due is None or self._due[0] != newest:
            self._due = (newest, now)
        lacking = [f"local-{i}" for i in np.flatnonzero(self.presence.present & (self.held < newest))]
        waited = now - self._due[1]
        if lacking and waited < self.hold_timeout_s:
            return
        if lacking:
            self.switched_unheld += 1
            self.log.warning("central: taking policy version %d although %s do not hold it after %.1f s",
                             newest, ", ".join(lacking), waited)
        self._due = None
        self.weights.take_newest()

    def poll(self, timeout: float) -> bool:
        """Serve each state of the world at once; with no world, a tick of the own clock when due."""
        self.take_uplinks()
        if self.world_t > -np.inf:  # a world drives this fleet: its ticks, and only they (its end is the run's)
            if not self.states.wait(timeout):
                return False
            due = False
        else:
            due = not self.states.wait(0) and self.clock.due(timeout)
        self.take_uplinks()  # what arrived while this waited is the freshest
        now = time.monotonic()
        step = self.take_state()
        if step is None:
            if not due:
                return False  # a state refused (counted), or none
            step = self.clock.ticks
        else:
            self.clock.next = now + self.clock.period  # the world's tick stands for the own clock's
        self.take_weights(now)
        self.tick(now, step)
        return True

    def take_uplinks(self) -> None:
        for up, t in self.uplinks.take():
            self.obs[0, up.agent, :self.up_dim] = up.obs[0]
            if up.action is not None:
                self.prev[0, up.agent] = encode_actions(self.spec, up.action[None], np.ones((1, 1), bool))[0, 0]
            self.uplinked[up.agent] = t
            self.presence.seen(up.agent, t)

    def take_state(self) -> int | None:
        """The world's newest state: the rows of the robots it hears and that send no uplinks of their
        own; its tick (None: no new state)."""
        got = self.states.take()
        if not got:
            return None
        state, t = got[-1]
        self.world_t, self.world_ticks = t, self.world_ticks + 1
        heard = state.active[0] & (t - self.uplinked > self.missing_after_s)
        self.obs[0, heard] = state.obs[0, heard]
        self.prev[0, heard] = state.prev_actions[0, heard]
        for i in np.flatnonzero(heard):
            self.presence.seen(int(i), t)
        return state.step

    def take_site(self, now: float) -> None:
        """The site's columns into every row: the newest feed while it is no older than `site_hold_s`,
        else zeros (the silent rule, SITE_SILENT_RULE; each silence a log line and a counter)."""
        for got, t in self.site.take():
            self.site_cols = got.cols[0]
            self.site_presence.seen(0, t)
        was = bool(self.site_presence.present[0])
        heard = bool(self.site_presence.update(now)[0])
        if was and not heard:
            self.log.warning("central: the site feed is silent (> site_hold_s %.2f s): its columns are %s in the "
                             "state until it is back", self.site_presence.bound, SITE_SILENT_RULE)
        if heard:
            self.obs[0, :, self.local_dim:] = self.site_cols
        else:
            self.obs[0, :, self.local_dim:] = 0.0
            self.site_silent_ticks += 1

    def tick(self, now: float, step: int) -> None:
        """One message per robot, stamped `step`, from the state of the latest rows (missing robots as
        zeros) and the site's columns (a silent feed as zeros)."""
        if self.site is not None:
            self.take_site(now)
        present = self.presence.update(now)[None]  # (1, N)
        state = self.acting.global_state(self.obs, self.prev, present)  # the missing rule: zeros
        net = self.net
        out = self.acting.messages(state, self.streams, 0.0, net.message_mean if net is not None else None,
                                   net.values if self.acting.rl else None)
        for i, pub in enumerate(self.pubs):
            pub.publish(CentralMsg(step=step, env_idx=self.env_idx, agent=i,
                                   msg=np.ascontiguousarray(out.sent[:, i])))
        self.sent += self.n
        self.ticks += 1
        if present.any():
            self.progressed()


def _safetensors(blob: bytes | None) -> dict[str, np.ndarray]:
    from hammer.learning.numpy_policy import params_from_blob

    if blob is None:
        raise ValueError("this team's central agent has a network: its central.safetensors is needed")
    return params_from_blob(blob)
