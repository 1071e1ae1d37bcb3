"""A world that does not wait: the simulator of a fleet, stepping at a fixed real-time rate.

Why apart from `host.EnvHost`: in training the env host waits for every agent's action before it
steps (that is what makes `hammer up` reproduce `hammer train`). A real world does not wait for a
slow robot. This role steps at `hz` whatever arrives, and applies each robot's latest action as
physics would: the last action received is held while the robot is present; a robot silent for
longer than `hold_s` gets the env's declared default action (counted per robot), as a robot that
stopped. After every step it sends each robot its observation (`env/obs/<i>`: the robot's own
sensors, in simulation) through reliable publishers with congestion control DROP, so a robot whose
link is down costs the others nothing.

One message down per robot per tick: a robot's link carries a packet per message, and the
headers of a packet (Ethernet, IP, TCP, TLS: 88-110 B) outweigh a step's numbers (57 B for cn3).
So a team with a central agent gets the state of the tick first (`env/state`: every robot's
observation, the actions just applied, who is present; on the serving machine's loopback), the
world waits for the central agent's messages of that tick for at most `msg_wait_s`, and each
robot's observation carries its message (`LocalObs.msg`). A message that misses the wait goes with
the next tick's observations if that tick's own misses too (`msgs_late`); with none the robot acts
on the message it holds, or on its fallback once that is older than its `max_msg_age_s`, as when the
central agent is away (`msgs_missed`). A central agent not heard for `CENTRAL_QUIET_S` is not
waited for. `msg_wait_s` = 0: never wait, every observation carries the message of the tick before.

The site (docs/fleet.md, "The site feed"): a team whose rows have central-only columns [L, D)
(rware's requested shelves and goals) has them from the site, not from any robot. So the world
hands the env's current columns to `site` (an object with `publish(cols)` and `counter`, its count's name) at every tick before the
state: the site feed SDK `serve/site_feed.SiteFeed` on its own session and identity, which the world
command opens (the world is the site), or, when the site runs elsewhere, `WarehouseRecord` (a file
in the run directory that site reads, as a management system reads its database); a robot's observation holds its own columns [0, L) only (the site's would be
zeros: bytes on its link for nothing), and the state's rows have zeros there: the central agent
composes its state from the robots' rows and the feed, as with a real site.

What it measures is what a fleet is judged by: per robot, the actions that arrived (its control
rate) and their age when applied; the ticks it overran; the episodes' paper metric. `timeline`: a
file that gets one JSON line a second (wall time, ticks, per-robot totals, episodes ended and their
paper metric's running sum), for a bench to cut by outage.
"""

from __future__ import annotations

import collections
import json
import time
from pathlib import Path

import numpy as np
from hammer.envs.base import VecEnv
from hammer.learning.central_acting import encode_actions
from hammer.protocol.dims import Dims
from hammer.protocol.schemas import Action, CentralMsg, GlobalState, LocalObs
from hammer.protocol.session import HammerSession
from hammer.runtime.clock import MSG_WAIT_S, Clock
from hammer.runtime.presence import Presence, rejections_by_member
from hammer.runtime.role import Role

AGES_KEPT = 4096  # per robot: the ages of the latest actions applied (bounded, for percentiles)
CENTRAL_QUIET_S = 1.0  # a central agent silent this long is not waited for (it is away: no message)


class RealtimeWorld(Role):
    """Steps `env` at `hz` on the robots' latest actions until `episodes` episodes or `seconds` s."""

    def __init__(self, session: HammerSession, env: VecEnv, hz: float, hold_s: float, seed: int,
                 episodes: int | None = None, seconds: float | None = None, startup_s: float = 30.0,
                 timeline: Path | None = None, msg_dim: int = 0, central: bool = False,
                 msg_wait_s: float = MSG_WAIT_S, site=None) -> None:
        super().__init__(session, "env")
        self.env, self.spec, self.k, self.n = env, env.spec, env.num_envs, env.spec.n_agents
        self.clock = Clock(hz)
        self.poll_s = min(self.poll_s, self.clock.period)
        self.episodes_budget, self.seconds = episodes, seconds
        self.actions = self.spec.default_actions(self.k)
        self.arrived = np.full(self.n, -np.inf)  # when each robot's latest action arrived
        self.new_action = np.zeros(self.n, bool)  # one came since the last tick
        self.presence = Presence([f"local-{i}" for i in range(self.n)], hold_s, self.log)
        # every size declared (an action may echo the team's message, msg_dim): a payload larger than a
        # valid action is refused on arrival, uncopied, so a flood on a robot's key costs no memory
        self.acts = session.subscribe_latest(
            self.keys.act("*"), Action, Dims(num_envs=self.k, n_agents=self.n, action_dim=self.spec.action_dim,
                                             discrete=self.spec.discrete, msg_dim=msg_dim))
        self.obs_pubs = [session.publisher(self.keys.obs(i), express=True, block=False) for i in range(self.n)]
        # the central agent's side of a tick, over the serving machine's loopback (module docstring)
        if not msg_wait_s >= 0:
            raise ValueError(f"msg_wait_s: must be >= 0 s, got {msg_wait_s}")
        self.msg_wait_s = msg_wait_s
        self.state_pub = session.publisher(self.keys.state(), express=True, block=False) if central else None
        self.msgs = (session.subscribe_latest(self.keys.msg("*"), CentralMsg,
                                              Dims(num_envs=self.k, n_agents=self.n, msg_dim=msg_dim))
                     if central else None)
        self.prev = np.zeros((self.k, self.n, self.spec.action_dim), np.float32)  # the actions applied, encoded
        self.central_t = -np.inf  # when the central agent's latest message arrived
        self.msgs_attached = self.msgs_missed = self.msgs_late = 0  # robot-ticks with / without; after their tick
        self.env_idx = np.arange(self.k, dtype=np.int64)
        self.applied = np.zeros(self.n, np.int64)  # robot-ticks on an action that robot sent
        self.fresh = np.zeros(self.n, np.int64)  # ... on one that arrived since the previous tick
        self.defaults = np.zeros(self.n, np.int64)  # robot-ticks on the default action (robot missing)
        self.ages: list[collections.deque] = [collections.deque(maxlen=AGES_KEPT) for _ in range(self.n)]
        # the loop's latency per robot: from a tick's start (the step, then its observations go out) to
        # the arrival of the robot's action on that tick's observation; its first only
        self.loop_s: list[collections.deque] = [collections.deque(maxlen=AGES_KEPT) for _ in range(self.n)]
        self.tick_t, self.obs_tick, self.answered = 0.0, -1, np.zeros(self.n, bool)
        self.episodes = 0  # running totals, not lists: a world that runs for days stays flat
        self.metric_sum = self.return_sum = 0.0
        self.recent: collections.deque[float] = collections.deque(maxlen=100)
        local = self.spec.local_obs_dim
        self.local_dim = local if local not in (None, self.spec.obs_dim) else None  # [L, D): the site's columns
        self.site, self.site_published = (site if self.local_dim is not None else None), 0
        # the feed's publisher counts as the world's publishing; a site elsewhere's record as what it handed on
        self.site_counter = site.counter if self.site is not None else ""
        self.obs, self.active = self._site_split(*env.reset(seed))
        self.startup_s = startup_s
        self.timeline = None if timeline is None else open(timeline, "a", buffering=1)  # noqa: SIM115 - closed in on_stop
        self._timeline_t = 0.0
        self.running = False  # the clock starts once every robot has acted (or after startup_s)
        self.started = time.monotonic()
        self.stall_what = "the clock"

    def counters(self) -> dict[str, int]:
        per_robot = {f"local_{i}.{what}": int(a[i]) for i in range(self.n)
                     for what, a in (("applied", self.applied), ("fresh", self.fresh), ("defaults", self.defaults))}
        return {"ticks": self.clock.ticks, "ticks_skipped": self.clock.skipped, "episodes": self.episodes,
                "default_actions": int(self.defaults.sum()), "msgs_attached": self.msgs_attached,
                "msgs_missed": self.msgs_missed, "msgs_late": self.msgs_late, **self.presence.counters(), **per_robot,
                **({self.site_counter: self.site_published} if self.site is not None else {})}

    def gauges(self) -> dict[str, float]:
        return {"paper_metric_100": float(np.mean(self.recent)) if self.recent else 0.0,
                "robots_present": self.presence.present_count()}

    def on_start(self) -> None:
        self.started = time.monotonic()
        self.publish_obs(0)

    def poll(self, timeout: float) -> bool:
        self.take_actions()
        if not self.running:
            return self.wait_for_robots(timeout)
        if not self.clock.due(timeout):
            return False
        self.take_actions()  # what arrived while the clock slept is the freshest
        self.tick(time.monotonic())
        return True

    def take_actions(self) -> None:
        for a, t in self.acts.take():
            self.actions[a.env_idx, a.agent] = a.action
            self.arrived[a.agent] = t
            self.new_action[a.agent] = True
            self.presence.seen(a.agent, t)
            if self.running and a.step == self.obs_tick and not self.answered[a.agent]:
                self.answered[a.agent] = True
                self.loop_s[a.agent].append(t - self.tick_t)

    def wait_for_robots(self, timeout: float) -> bool:
        """Before the first tick: offer the first observation until every robot has answered it (a
        world's time starts with its fleet; the measurements then hold no start-up gap), or until
        `startup_s`, after which the absent robots are missing like any other."""
        now = time.monotonic()
        if self.presence.present.all() or now - self.started >= self.startup_s:
            self.running = True
            self.log.info("world clock starts at %g Hz: %d of %d robots present", 1 / self.clock.period,
                          self.presence.present_count(), self.n)
            self.started = self.clock.next = now
            self.presence.start_clock(now)
            self.new_action[:] = False
            return True
        time.sleep(min(timeout, 0.1))
        self.publish_obs(0)
        return False

    def tick(self, now: float) -> None:
        """Apply every robot's latest action (the default for a missing one), step, send the observations."""
        present = self.presence.update(now)
        self.tick_t = now
        self.answered[:] = False
        actions = self.actions.copy()
        if not present.all():
            actions[:, ~present] = self.spec.default_actions(self.k)[:, ~present]
        self.defaults += ~present
        self.applied += present
        self.fresh += present & self.new_action
        for i in np.flatnonzero(present):
            self.ages[i].append(now - self.arrived[i])
        self.new_action[:] = False
        step = self.env.step(self.spec.env_action(actions))
        self.obs, self.active = self._site_split(step.obs, step.next_active)
        if self.state_pub is not None:
            self.prev = encode_actions(self.spec, actions, present[None])
        for e in step.episodes:
            self.episodes += 1
            self.metric_sum += e.paper_metric
            self.return_sum += e.team_return
            self.recent.append(e.paper_metric)
        self.publish_obs(self.clock.ticks)
        self.obs_tick = self.clock.ticks
        self.progressed()
        if self.timeline is not None and now - self._timeline_t >= 1.0:
            self._timeline_t = now
            self.timeline.write(json.dumps({"t": round(time.time(), 3), "ticks": self.clock.ticks,
                                            "fresh": self.fresh.tolist(), "defaults": self.defaults.tolist(),
                                            # the episodes ended and their paper metric's running sum
                                            "episodes": self.episodes, "metric": round(self.metric_sum, 6)}) + "\n")
        if self.episodes_budget is not None and self.episodes >= self.episodes_budget:
            self.stop_reason = f"{self.episodes} episodes done"
        elif self.seconds is not None and now - self.started >= self.seconds:
            self.stop_reason = f"{self.seconds:g} s done"

    def _site_split(self, obs: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rows with the site's columns zeroed (no robot observes them), kept for the site feed
        (copy 0's: a fleet's world is one warehouse; identical in every row)."""
        if self.local_dim is None:
            return obs, active
        self.site_cols = obs[0, 0, self.local_dim:].copy()
        obs = obs.copy()
        obs[..., self.local_dim:] = 0.0
        return obs, active

    def on_stop(self) -> None:
        # while the session is open: the report is written after it closes
        self._refused = self.refusals()
        if self.timeline is not None:
            self.timeline.close()

    def refusals(self) -> tuple[dict[str, int], dict[str, dict[str, int]]]:
        """What this world refused, by reason, and per robot whose keys it came on."""
        return ({k.split(".", 1)[1]: n for k, n in self.rejection_counters().items()},
                rejections_by_member(self.session.rejections_by_key(), self.presence.names))

    def publish_obs(self, tick: int) -> None:
        """Each robot its observation of `tick`, with the central agent's message for it if it came in time."""
        if self.site is not None:  # first: the central agent composes this tick's state with it
            self.site_published += bool(self.site.publish(self.site_cols))
        msgs = self.central_messages(tick) if self.state_pub is not None else [None] * self.n
        width = self.local_dim or self.spec.obs_dim  # a team with a site feed: a robot's own columns only
        for i, pub in enumerate(self.obs_pubs):
            pub.publish(LocalObs(step=tick, env_idx=self.env_idx, agent=i,
                                 obs=np.ascontiguousarray(self.obs[:, i, :width]),
                                 active=np.ascontiguousarray(self.active[:, i]), msg=msgs[i]))

    def central_messages(self, tick: int) -> list[np.ndarray | None]:
        """The state of `tick` to the central agent, then its message for each robot, waiting for them
        at most `msg_wait_s` (not at all for a central agent not heard for CENTRAL_QUIET_S)."""
        present = np.broadcast_to(self.presence.present, (self.k, self.n))
        self.state_pub.publish(GlobalState(step=tick, env_idx=self.env_idx, obs=self.obs, prev_actions=self.prev,
                                           active=np.ascontiguousarray(present)))
        got: list[np.ndarray | None] = [None] * self.n
        late: list[np.ndarray | None] = [None] * self.n  # of the tick before, which came after its observations
        start = time.monotonic()
        deadline = start + (self.msg_wait_s if start - self.central_t < CENTRAL_QUIET_S else 0.0)
        waiting = self.n
        while True:
            for m, t in self.msgs.take():
                self.central_t = t
                if m.step == tick and got[m.agent] is None:
                    got[m.agent] = m.msg
                    waiting -= 1
                elif m.step == tick - 1:
                    late[m.agent] = m.msg
            left = deadline - time.monotonic()
            if waiting == 0 or left <= 0:
                break
            self.msgs.wait(left)
        self.msgs_attached += self.n - waiting
        for i in range(self.n):
            if got[i] is None and late[i] is not None:
                got[i] = late[i]
                self.msgs_late += 1
        self.msgs_missed += sum(g is None for g in got)
        return got

    def report(self) -> dict:
        """What the run is judged by (the launcher writes it to summary.json)."""
        elapsed = max(time.monotonic() - self.started, 1e-9)
        refused = getattr(self, "_refused", None) or self.refusals()
        robots = {}
        for i in range(self.n):
            ages = np.asarray(self.ages[i]) * 1e3
            loop = np.asarray(self.loop_s[i]) * 1e3
            robots[f"local-{i}"] = {
                "applied": int(self.applied[i]), "fresh": int(self.fresh[i]), "defaults": int(self.defaults[i]),
                "control_hz": round(self.fresh[i] / elapsed, 2),
                "action_age_ms_p50": round(float(np.percentile(ages, 50)), 2) if ages.size else None,
                "action_age_ms_p99": round(float(np.percentile(ages, 99)), 2) if ages.size else None,
                "step_to_action_ms_p50": round(float(np.percentile(loop, 50)), 2) if loop.size else None,
                "step_to_action_ms_p99": round(float(np.percentile(loop, 99)), 2) if loop.size else None}
        return {"hz": round(1 / self.clock.period, 3), "seconds": round(elapsed, 3), "ticks": self.clock.ticks,
                "ticks_skipped": self.clock.skipped, "episodes": self.episodes,
                "msgs_attached": self.msgs_attached, "msgs_missed": self.msgs_missed, "msgs_late": self.msgs_late,
                **({self.site_counter: self.site_published} if self.site is not None else {}),
                "paper_metric_mean": self.metric_sum / self.episodes if self.episodes else None,
                "team_return_mean": self.return_sum / self.episodes if self.episodes else None,
                "presence": self.presence.counters(), "absences": self.presence.absences(),
                "rejected": refused[0], "rejected_on": refused[1],
                "events": list(self.presence.events), "robots": robots}
