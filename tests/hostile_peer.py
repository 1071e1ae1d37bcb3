"""A hostile peer for the security tests: joins a live run and forges what the issue's attacks did.

It answers agent 0's observations before the real agent (if it can read them), floods actions
for agent 0 at guessed steps, publishes well-formed weights of a far-future version for both
networks, and sends forged `stop` control commands. In the secure profile it joins with a
stolen role identity (e.g. local-1's), so it is linked into the run and only the access rules
stand between it and the other roles.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from protocol.schemas import Action, Control, LocalObs, Weights
from protocol.session import HammerSession, TransportConfig


class HostilePeer(threading.Thread):
    def __init__(self, run_id: str, transport: TransportConfig, num_envs: int, agent: int = 0) -> None:
        super().__init__(daemon=True, name="hostile-peer")
        self.run_id, self.transport, self.k, self.agent = run_id, transport, num_envs, agent
        self.stop_event = threading.Event()
        self.sent = {"answers": 0, "blind_actions": 0, "weights": 0, "control": 0}
        self.obs_seen = 0
        self.max_peers = 0
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._attack()
        except BaseException as e:  # noqa: BLE001 - the test reports it
            self.error = e

    def _attack(self) -> None:
        with HammerSession(self.run_id, self.transport, sender=f"local-{self.agent}") as s:
            k = s.keys
            obs = s.subscribe(k.obs(self.agent), LocalObs)
            act = s.publisher(k.act(self.agent), express=True)
            junk = np.random.default_rng(0).bytes(4096)
            weights = {net: s.publisher(k.weights(net)) for net in ("local", "central")}
            ctl = s.publisher(k.ctl("all"))
            env_idx = np.arange(self.k, dtype=np.int64)
            guess, last_blind = 0, 0.0
            while not self.stop_event.is_set():
                self.max_peers = max(self.max_peers, len(list(s.zenoh.info.peers_zid())))
                for o in obs.drain():
                    self.obs_seen += 1
                    act.publish(Action(agent=self.agent, step=o.step, env_idx=o.env_idx,
                                       action=np.zeros(len(o.env_idx), np.int64), policy_version=o.policy_version))
                    self.sent["answers"] += 1
                if time.monotonic() - last_blind > 0.02:
                    last_blind = time.monotonic()
                    for step in range(guess, guess + 50):
                        act.publish(Action(agent=self.agent, step=step, env_idx=env_idx,
                                           action=np.zeros(self.k, np.int64)))
                    guess = (guess + 50) % 20_000
                    self.sent["blind_actions"] += 50
                    for net, pub in weights.items():
                        pub.publish(Weights.from_blob(net, 2**40, junk))
                        self.sent["weights"] += 1
                    ctl.publish(Control(command="stop"))
                    self.sent["control"] += 1
                time.sleep(0.002)
