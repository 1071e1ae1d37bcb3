"""A local agent loads its first policy while it waits for work (real Zenoh on 127.0.0.1), so the
first step is not slowed by loading weights and the env host can wait for every agent to be ready
before an evaluation starts (`EnvHost._wait_actors_ready`)."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
from hammer.local_agent.client import AgentSpec, LocalAgentClient
from hammer.protocol.schemas import Heartbeat, Weights
from hammer.protocol.session import HammerSession, TransportConfig
from hammer.runtime.settings import RuntimeSettings
from safetensors.numpy import save


def _policy_blob(in_dim: int, act_dim: int) -> bytes:
    rng = np.random.default_rng(0)
    p = {}
    for net, out in (("actor", act_dim), ("critic", 1)):
        dims = [in_dim, 8, out]
        for i, (a, b) in enumerate(itertools.pairwise(dims)):
            p[f"{net}.layers.{i}.weight"] = rng.standard_normal((b, a)).astype(np.float32)
            p[f"{net}.layers.{i}.bias"] = np.zeros(b, np.float32)
    return save(p)


def test_agent_holds_the_policy_before_its_first_observation():
    spec = AgentSpec(agent=0, n_agents=3, obs_dim=6, msg_dim=2, discrete=True, action_dim=5, seed=0)
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    with HammerSession("pre", t, sender="launcher") as hub, \
            HammerSession("pre", TransportConfig.connector(port), sender="local-0") as s:
        hb = hub.subscribe(hub.keys.heartbeat("local-0"), Heartbeat)
        client = LocalAgentClient(s, spec, 4, RuntimeSettings(run_id="pre", fallback="zeros", fallback_k=1,
                                                       msg_deadline_ms=20.0, weights_timeout_s=5.0), idle_exit_s=4.0)
        agent = threading.Thread(target=client.run, daemon=True)
        agent.start()
        first = hb.get(timeout=5.0)  # announced before any weights: no policy yet
        assert first is not None and first.gauges["policy_version"] == -1
        hub.publish(hub.keys.weights("local"), Weights.from_blob("local", 0, _policy_blob(8, 5)))
        t0, version = time.monotonic(), -1
        while version < 0 and time.monotonic() - t0 < 3.0:
            m = hb.get(timeout=0.5)
            if m is not None:
                version = m.gauges["policy_version"]
        # No observation was ever sent, and the news came well before the 1 s heartbeat period.
        assert version == 0 and time.monotonic() - t0 < 0.9
        agent.join(timeout=10.0)
        assert not agent.is_alive()
