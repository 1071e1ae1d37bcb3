"""A thief of one agent's identity, attacking through that agent's own keys.

Zenoh's access rules let the holder of `local-1.key` publish on `agent/act/1` and `ctl/hb/local-1`;
everything this peer tries goes there, so only what the receivers check stands in its way:

- for every observation of agent 1 it reads, an action for agent 0 and one for agent 2 on
  agent 1's key (the payload names the other agent); the sender header names local-0 on some;
- heartbeats on `ctl/hb/local-1` that file themselves under `env` (sound counters), with negative
  counters, and as `local-1` from invented pids with counters that rise and then fall;
- a flood of 4 MB payloads on agent 1's key, 25 a second.

It never sends an action for agent 1 itself (the real agent's job), so a run it cannot move ends
with exactly the metrics of a run without it.
"""

from __future__ import annotations

import time

import msgpack
import numpy as np
from hammer.protocol.codec import encode
from hammer.protocol.schemas import SCHEMA_VERSION, Action, Heartbeat, LocalObs
from hammer.protocol.session import HammerSession, TransportConfig

from tests.peer_thread import PeerThread

FLOOD_BYTES = 4 << 20
FLOOD_PER_S = 25


def raw_heartbeat(run: str, role: str, pid: int, counters: dict, sender: str = "local-1", seq: int = 0) -> bytes:
    """A heartbeat as bytes, built by hand: the schema would refuse to build one with negative counters."""
    # [type tag (heartbeat), v, step, env_idx (K = 0), sender, role, pid, status, counters, gauges, detail]
    return msgpack.packb([Heartbeat.TAG, SCHEMA_VERSION, 0, 0, sender, role, pid, "running", counters, {}, ""],
                         use_bin_type=True)


class OwnKeyThief(PeerThread):
    def __init__(self, run_id: str, transport: TransportConfig, agent: int = 1, flood: bool = True,
                 flood_s: float | None = None) -> None:
        super().__init__("own-key-thief")
        self.run_id, self.transport, self.agent, self.flood, self.flood_s = run_id, transport, agent, flood, flood_s
        self.sent = {"other_agent_actions": 0, "forged_sender_actions": 0, "env_heartbeats": 0,
                     "negative_heartbeats": 0, "falling_heartbeats": 0, "flood": 0}
        self.obs_seen = 0

    def _attack(self) -> None:
        with HammerSession(self.run_id, self.transport, sender=f"local-{self.agent}") as s:
            k = s.keys
            obs = s.subscribe(k.obs(self.agent), LocalObs)
            act = s.publisher(k.act(self.agent), express=True)
            hb = s.publisher(k.heartbeat(f"local-{self.agent}"), reliable=False)
            flood_pub = s.publisher(k.act(self.agent), reliable=False)
            big = bytes(FLOOD_BYTES)
            started = last_flood = last_hb = time.monotonic()
            pid = 4_000_000
            while not self.stop_event.is_set():
                for o in obs.drain():
                    self.obs_seen += 1
                    self._other_agents(act, o, s.run_id)
                now = time.monotonic()
                flooding = self.flood and (self.flood_s is None or now - started < self.flood_s)
                if flooding and now - last_flood >= 1 / FLOOD_PER_S:
                    last_flood = now
                    flood_pub.put_bytes(big)
                    self.sent["flood"] += 1
                if now - last_hb >= 0.1:
                    last_hb = now
                    pid += 1
                    self._heartbeats(hb, s.run_id, pid)
                time.sleep(0.002)

    def _other_agents(self, act, o: LocalObs, run: str) -> None:
        """The issue's first attack: its own key, another agent in the payload."""
        zeros = np.zeros(len(o.env_idx), np.int64)
        for other in (0, 2):
            act.publish(Action(agent=other, step=o.step, env_idx=o.env_idx, action=zeros,
                               policy_version=o.policy_version))
            self.sent["other_agent_actions"] += 1
        # its own agent, but a header naming another sender
        act.put_bytes(encode(Action(agent=self.agent, step=o.step, env_idx=o.env_idx, action=zeros,
                                    policy_version=o.policy_version),
                             stamp={"sender": "local-0"}))
        self.sent["forged_sender_actions"] += 1

    def _heartbeats(self, hb, run: str, pid: int) -> None:
        """Filed under env; negative counters; counters that fall (from a pid nobody started)."""
        hb.put_bytes(raw_heartbeat(run, "env", pid, {"step": 1, "actions_duplicate": 80}))
        self.sent["env_heartbeats"] += 1
        hb.put_bytes(raw_heartbeat(run, f"local-{self.agent}", pid, {"rejected.decode": -6, "steps": -80}))
        self.sent["negative_heartbeats"] += 1
        for steps in (10**9, 0):
            hb.put_bytes(raw_heartbeat(run, f"local-{self.agent}", pid, {"steps": steps, "fallback_copies": steps}))
        self.sent["falling_heartbeats"] += 1
