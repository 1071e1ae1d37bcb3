"""A buggy or hostile peer in the plain profile that tries, once each, every message that used to
stall or silence a role: absurd step numbers, a far-future weights version, a stop from
a non-launcher, actions for future steps, a policy version no learner has published, and a 50 MB
payload. It copies real messages of the live run and changes one header, so each forged message
is well formed and passes validation: only the roles' bounds (runtime/bounds.py) stand in the way.
"""

from __future__ import annotations

import numpy as np
from hammer.protocol.schemas import Action, CentralMsg, Control, GlobalState, LocalObs, Weights
from hammer.protocol.session import HammerSession, TransportConfig
from msgspec.structs import replace

from tests.peer_thread import PeerThread

HUGE_OBS_STEP = 2**64 - 1
HUGE_STATE_STEP = 2**63
HUGE_VERSION = 2**62


class StallPeer(PeerThread):
    def __init__(self, run_id: str, transport: TransportConfig, n_agents: int) -> None:
        super().__init__("stall-peer")
        self.run_id, self.transport, self.n = run_id, transport, n_agents
        self.sent: dict[str, int] = {}

    def _send(self, what: str, publish, msg) -> None:
        publish(msg)
        self.sent[what] = self.sent.get(what, 0) + 1

    def _attack(self) -> None:
        with HammerSession(self.run_id, self.transport, sender="local-1") as s:
            k = s.keys
            state_in = s.subscribe(k.state(), GlobalState)
            obs_in = [s.subscribe(k.obs(i), LocalObs) for i in range(2)]
            msg_in = s.subscribe(k.msg(0), CentralMsg)  # its width: a training action echoes its message
            state = obs0 = obs1 = msg0 = None
            while not self.stop_event.is_set() and (state is None or obs0 is None or obs1 is None or msg0 is None):
                state = state or state_in.get(timeout=0.1)
                obs0, obs1 = obs0 or obs_in[0].get(timeout=0.05), obs1 or obs_in[1].get(timeout=0.05)
                msg0 = msg0 or msg_in.get(timeout=0.05)
            if self.stop_event.is_set():
                return
            now = max(state.step, obs0.step)
            junk = np.random.default_rng(0).bytes(4096)
            for i, o in enumerate((obs0, obs1)):
                self._send(f"obs_step_local-{i}", lambda m, i=i: s.publish(k.obs(i), m),
                           replace(o, step=HUGE_OBS_STEP))
            self._send("state_step", lambda m: s.publish(k.state(), m), replace(state, step=HUGE_STATE_STEP))
            # a step inside the window, naming a policy version no learner has published
            self._send("obs_version", lambda m: s.publish(k.obs(0), m),
                       replace(obs0, step=now + 50, policy_version=HUGE_VERSION))
            for net in ("local", "central"):
                self._send(f"weights_{net}", lambda m, net=net: s.publish(k.weights(net), m),
                           Weights.from_blob(net, HUGE_VERSION, junk))
            self._send("stop", lambda m: s.publish(k.ctl("all"), m), Control(command="stop"))
            env_idx = np.arange(len(obs0.env_idx), dtype=np.int64)
            for step in (now + 1000, HUGE_VERSION):  # never current in a run this short
                self._send("future_action", lambda m: s.publish(k.act(0), m),
                           Action(agent=0, step=step, env_idx=env_idx, action=np.zeros(len(env_idx), np.int64),
                                  msg=np.zeros((len(env_idx), msg0.msg.shape[1]), np.float32)))
            s.put_bytes(k.obs(2), b"\0" * (50 * 2**20))  # 50 MB where a LocalObs (cap 4 MiB) is expected
            self.sent["oversize"] = 1
            self.stop_event.wait(3.0)  # stay joined while the big payload is delivered


class EarlyStallPeer(PeerThread):
    """The same stall messages before the run's first step, when no role has a step to measure them
    against: from the moment the launcher's hub listens until the env host's first observation, it
    sends every 50 ms a `LocalObs` of step 2^64-1 to every local agent, a `GlobalState` of step
    2^63 to the central agent and a rollout chunk of step 2^63 to the learner (well formed, with
    the run's dimensions, version 0). The roles subscribe seconds before step 1 (the env host waits
    for the learner, which loads torch), so each receives some of them before its first real step."""

    def __init__(self, run_dir, timeout_s: float = 120.0) -> None:
        super().__init__("early-stall-peer")
        self.run_dir, self.timeout_s = run_dir, timeout_s
        self.sent: dict[str, int] = {}
        self.first_real_step: int | None = None

    def _wait_for_run_files(self) -> tuple:
        import json
        import time

        from hammer.learning.config import build_config
        from hammer.runtime.settings import RuntimeSettings, read_env_spec

        deadline = time.monotonic() + self.timeout_s
        while not (self.run_dir / "env_spec.json").is_file():  # written after runtime.json and config.json
            if time.monotonic() > deadline or self.stop_event.wait(0.05):
                raise TimeoutError("no run files appeared")
        return (RuntimeSettings.load(self.run_dir), build_config(json.loads((self.run_dir / "config.json").read_text())),
                read_env_spec(self.run_dir))

    def _forgeries(self, keys, cfg, spec) -> list[tuple[str, str, object]]:
        from hammer.local_agent.client import AgentSpec
        from hammer.protocol.rollout_layout import CHUNK, RolloutLayout
        from hammer.protocol.schemas import ExperienceChunk

        k, n = cfg.num_envs, cfg.n_agents
        idx = np.arange(k, dtype=np.int64)
        out = [(f"obs_local-{i}", keys.obs(i), LocalObs(
            step=HUGE_OBS_STEP, env_idx=idx, agent=i, active=np.ones(k, bool),
            obs=np.zeros((k, AgentSpec.from_config(cfg, spec, i).obs_dim), np.float32))) for i in range(n)]
        out.append(("state", keys.state(), GlobalState(
            step=HUGE_STATE_STEP, env_idx=idx, obs=np.zeros((k, n, spec.obs_dim), np.float32),
            prev_actions=np.zeros((k, n, spec.action_dim), np.float32), active=np.ones((k, n), bool))))
        out.append(("chunk", keys.exp("team"), ExperienceChunk(
            step=HUGE_STATE_STEP, env_idx=idx, role="team", policy_version=0,
            arrays=RolloutLayout.from_config(cfg, spec).allocate(CHUNK))))
        return out

    def _attack(self) -> None:
        settings, cfg, spec = self._wait_for_run_files()
        transport = TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{settings.hub_port}"])
        with HammerSession(settings.run_id, transport, sender="env") as s:
            real = s.subscribe(s.keys.obs(0), LocalObs)
            forged = self._forgeries(s.keys, cfg, spec)
            while not self.stop_event.is_set() and self.first_real_step is None:
                for what, key, msg in forged:
                    self._send(what, lambda m, key=key: s.publish(key, m), msg)
                o = real.get(timeout=0.05)
                if o is not None and o.step != HUGE_OBS_STEP:
                    self.first_real_step = o.step
            self.stop_event.wait(1.0)  # stay joined while the last ones are delivered

    _send = StallPeer._send
