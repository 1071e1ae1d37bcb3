"""A hostile peer for the security tests: joins a live run and forges what the issue's attacks did.

It answers agent 0's observations before the real agent (if it can read them), floods actions
for agent 0 at guessed steps, publishes well-formed weights one version ahead of the learner's
newest (zeroed copies of the real ones, inside every role's version bound) for both networks, and
sends `stop` commands whose header names the launcher and the env host. Each forgery passes every
check a role makes itself (validation, step window, version bound, control sender), so in the
secure profile, where it joins with a stolen role identity (e.g. local-1's) and is linked into
the run, only Zenoh's access control stands between it and the other roles.
"""

from __future__ import annotations

import time

import numpy as np
from hammer.protocol.codec import encode
from hammer.protocol.schemas import Action, Control, LocalObs, Weights
from hammer.protocol.session import HammerSession, TransportConfig

from tests.peer_thread import PeerThread

FORGED_STOP_SENDERS = ("launcher", "env")  # the senders every role obeys (runtime.role.STOP_SENDERS)


def zeroed(blob: bytes) -> bytes:
    """The same safetensors file with every tensor zeroed: well formed, the right names and shapes."""
    from safetensors.numpy import load, save

    return save({k: np.zeros_like(v) for k, v in load(blob).items()})


class HostilePeer(PeerThread):
    def __init__(self, run_id: str, transport: TransportConfig, num_envs: int, agent: int = 0,
                 templates: dict[str, bytes] | None = None, msg_dim: int = 0) -> None:
        """`templates`: weights blobs of the run's architecture (the code is public), forged from
        until real weights are read, so the forgery never waits on catching a publication; `msg_dim`:
        the run's message length (a training action carries the message it acted on)."""
        super().__init__("hostile-peer")
        self.run_id, self.transport, self.k, self.agent = run_id, transport, num_envs, agent
        self.echo = np.zeros((num_envs, msg_dim), np.float32) if msg_dim else None
        self.forged = {net: zeroed(blob) for net, blob in (templates or {}).items()}
        self.sent = {"answers": 0, "blind_actions": 0, "weights": 0, "control": 0}
        self.obs_seen = 0
        self.weights_seen = -1  # the newest real version it read (local-1 may read the local weights)
        self.max_peers = 0
        self.timeline: dict[str, float] = {"started": time.monotonic()}  # for a failure's message

    def _attack(self) -> None:
        with HammerSession(self.run_id, self.transport, sender="launcher") as s:
            self.timeline["open"] = time.monotonic()
            k = s.keys
            obs = s.subscribe(k.obs(self.agent), LocalObs)
            real_weights = s.subscribe(k.weights("local"), Weights)
            act = s.publisher(k.act(self.agent), express=True)
            last_blind = 0.0
            guess = 0
            while not self.stop_event.is_set():
                peers = len(list(s.zenoh.info.peers_zid()))
                if peers > self.max_peers:
                    self.max_peers = peers
                    self.timeline[f"peers={peers}"] = time.monotonic()
                for o in obs.drain():
                    self.obs_seen += 1
                    act.publish(Action(agent=self.agent, step=o.step, env_idx=o.env_idx,
                                       action=np.zeros(len(o.env_idx), np.int64), policy_version=o.policy_version,
                                       msg=None if self.echo is None else self.echo[:len(o.env_idx)]))
                    self.sent["answers"] += 1
                for w in real_weights.drain():
                    if w.version > self.weights_seen:
                        self.weights_seen, self.forged["local"] = w.version, zeroed(w.blob)
                if time.monotonic() - last_blind > 0.02:
                    last_blind = time.monotonic()
                    guess = self._blind_actions(act, guess)
                    self._weights(s)
                    self._stops(s)
                time.sleep(0.002)
            self.timeline["stopped"] = time.monotonic()

    def _blind_actions(self, act, guess: int) -> int:
        """Actions for agent 0 at 50 guessed steps (the real agent's are the ones that count)."""
        env_idx = np.arange(self.k, dtype=np.int64)
        for step in range(guess, guess + 50):
            act.publish(Action(agent=self.agent, step=step, env_idx=env_idx, action=np.zeros(self.k, np.int64),
                               msg=self.echo))
        self.sent["blind_actions"] += 50
        return (guess + 50) % 20_000

    def _weights(self, s: HammerSession) -> None:
        """Version newest + 1: what the learner publishes next, inside every bound (runtime/bounds.py);
        before any real version is read, a guess among the first 20."""
        version = self.weights_seen + 1 if self.weights_seen >= 0 else 1 + (self.sent["weights"] // 2) % 20
        for net, blob in self.forged.items():
            s.publish(s.keys.weights(net), Weights.from_blob(net, version, blob))
            self.sent["weights"] += 1

    def _stops(self, s: HammerSession) -> None:
        for sender in FORGED_STOP_SENDERS:
            data = encode(Control(command="stop"), stamp={"sender": sender})
            s.put_bytes(s.keys.ctl("all"), data)
            self.sent["control"] += 1
