"""The central server acts in numpy, without torch, and sends what the trainer's torch Team sends.

Both paths share `learning.central_acting.CentralActing` (the sampling and its stream draws); only
the forward pass differs (torch `CentralAgent` vs `NumpyCentralAgent` loaded from the safetensors
blob the learner publishes), so messages agree to float32 tolerance and every stream ends at the
same position.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from hammer.envs.registry import make_vec_env
from hammer.learner.worker import weights_blob
from hammer.learning.config import merge_config
from hammer.learning.numpy_policy import NumpyCentralAgent, NumpySetCentralAgent, numpy_central
from hammer.learning.sampling import ActingStreams
from hammer.learning.team import Team
from hammer.protocol.schemas import CentralMsg, Control, ExperienceChunk, GlobalState, Weights
from hammer.protocol.session import HammerSession, TransportConfig
from safetensors.numpy import load as load_safetensors

from tests.runtime_helpers import ROOT

STEPS = 6
K = 8


def _cfg(n: int, variant: str, mode: str, dropout: float, net: str = "concat"):
    return merge_config(f"cn{n}", overrides=[f"num_envs={K}", f"msg_dropout={dropout}", f"central_net={net}"],
                        extra={"variant": variant, "central_mode": mode, "seed": 7})


def _states(team: Team, n: int, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(obs, prev_actions) of a real cn env driven by random actions, as the env host sends them."""
    env = make_vec_env("cn", n, K)
    obs, _ = env.reset(3)
    prev = team.zero_prev_actions(K)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(steps):
        out.append((obs.astype(np.float32), prev))
        action = rng.integers(0, team.act_dim, (K, n))
        st = env.step(action)
        obs, prev = st.obs, team.encode_actions(action, st.active)
    return out


def _team(cfg) -> Team:
    """A Team whose central weights are all nonzero (fresh biases are zero: a bias bug would hide)."""
    import torch

    team = Team(cfg, make_vec_env("cn", cfg.n_agents, 1).spec)
    if team.central is not None:
        g = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for p in team.central.parameters():
                p.add_(0.1 * torch.randn(p.shape, generator=g))
    return team


def _numpy_net(team: Team) -> NumpyCentralAgent | NumpySetCentralAgent | None:
    if team.central is None:
        return None
    net = numpy_central(load_safetensors(weights_blob(team.central.export_numpy())))
    assert net.kind == team.cfg.central_net
    return net


CASES = [("hammer", "rl", 0.0), ("hammer", "backprop", 0.0), ("random", "rl", 0.0), ("hammer", "rl", 0.3),
         ("hammer", "backprop", 0.3), ("random", "rl", 0.3), ("il", "rl", 0.0), ("centralized", "rl", 0.0)]


@pytest.mark.parametrize("n", [3, 5])
@pytest.mark.parametrize(("variant", "mode", "dropout"), CASES)
def test_numpy_acting_equals_the_torch_team(n, variant, mode, dropout):
    _check_acting(_cfg(n, variant, mode, dropout))


@pytest.mark.parametrize("n", [3, 5])
@pytest.mark.parametrize(("mode", "dropout"), [("rl", 0.0), ("backprop", 0.0), ("rl", 0.3)])
def test_numpy_acting_equals_the_torch_team_with_the_set_net(n, mode, dropout):
    _check_acting(_cfg(n, "hammer", mode, dropout, net="set"))


def _check_acting(cfg) -> None:
    n, variant, dropout = cfg.n_agents, cfg.variant, cfg.msg_dropout
    team = _team(cfg)
    net = _numpy_net(team)
    torch_streams, np_streams = ActingStreams(cfg.seed, n), ActingStreams(cfg.seed, n)
    dropped = 0
    for obs, prev in _states(team, n, STEPS):
        state = team.global_state(obs, prev)
        np.testing.assert_array_equal(team.acting.global_state(obs, prev), state)
        a = team.central_messages(state, torch_streams, cfg.msg_dropout)
        b = team.acting.messages(state, np_streams, cfg.msg_dropout, net.message_mean if net else None,
                                 net.values if team.central_rl else None)
        for field in ("sent", "mean", "raw", "logp", "value"):
            x, y = getattr(a, field), getattr(b, field)
            assert x.shape == y.shape and x.dtype == y.dtype == np.float32, field
            np.testing.assert_allclose(y, x, atol=2e-5, rtol=0, err_msg=field)
        np.testing.assert_array_equal(b.keep, a.keep)
        dropped += int((~a.keep).sum())
        m = cfg.effective_msg_dim
        assert a.sent.shape == (K, n, m)
        if m and variant == "hammer":
            assert np.abs(a.mean).max() > 0.01  # a real forward, not zeros on both sides
        if team.central_rl:
            assert np.abs(a.value).max() > 0 and not np.allclose(a.raw, a.mean)
    assert (dropped > 0) == (dropout > 0 and cfg.effective_msg_dim > 0)
    assert json.dumps(np_streams.state()) == json.dumps(torch_streams.state())


_SERVER = """
import json, sys
from hammer.envs.base import EnvSpec
from hammer.learning.config import build_config
from hammer.protocol.session import HammerSession, TransportConfig
from hammer.central_agent.central_server import CentralServer
from hammer.runtime.settings import RuntimeSettings

args = json.loads(sys.argv[1])
cfg = build_config(args["cfg"])
spec = args["spec"]
spec["agent_ids"] = tuple(spec["agent_ids"])
with HammerSession(args["run"], TransportConfig.connector(args["port"]), sender="central") as s:
    settings = RuntimeSettings(run_id=args["run"], weights_timeout_s=args["weights_timeout_s"])
    server = CentralServer(s, cfg, EnvSpec(**spec), settings, idle_exit_s=30.0)
    server.run()
print(json.dumps({"torch": "torch" in sys.modules, "counters": server.counts.as_dict()}))
"""


class _Server:
    """`CentralServer` in a fresh interpreter connected to this test's Zenoh session on 127.0.0.1."""

    def __init__(self, cfg, spec, weights_timeout_s: float = 30.0) -> None:
        from dataclasses import asdict

        t = TransportConfig.listener()
        port = int(t.listen[0].rsplit(":", 1)[1])
        self.arg = json.dumps({"cfg": cfg.model_dump(mode="json"), "spec": asdict(spec), "run": "cnp",
                               "port": port, "weights_timeout_s": weights_timeout_s})
        self.session = HammerSession("cnp", t, sender="launcher")
        self.n = cfg.n_agents

    def __enter__(self):
        s = self.session.__enter__()
        watch = s.watch_alive()
        self.msg_subs = [s.subscribe(s.keys.msg(i), CentralMsg) for i in range(self.n)]
        self.exp_sub = s.subscribe(s.keys.exp("central"), ExperienceChunk)
        self.proc = subprocess.Popen([sys.executable, "-c", _SERVER, self.arg], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        ev = watch.get(60.0)
        if ev is None or ev.role != "central" or not ev.alive:
            self.__exit__(None, None, None)
            raise AssertionError(f"the central server did not come up: {ev}")
        time.sleep(0.3)  # let the server's subscriptions reach this session
        return self

    def weights(self, team: Team, version: int) -> None:
        blob = weights_blob(team.central.export_numpy())
        self.session.publish(self.session.keys.weights("central"), Weights.from_blob("central", version, blob))

    def state(self, step: int, obs: np.ndarray, prev: np.ndarray, version: int) -> None:
        self.session.publish(self.session.keys.state(), GlobalState(
            step=step, env_idx=np.arange(K, dtype=np.int64), obs=obs, prev_actions=prev,
            active=np.ones((K, self.n), bool), policy_version=version))

    def stop(self) -> dict:
        """Stop the server; returns whether it had imported torch and its counters."""
        self.session.publish(self.session.keys.ctl("all"), Control(command="stop", target="central"))
        out, err = self.proc.communicate(timeout=60)
        assert self.proc.returncode == 0, err[-2000:]
        return json.loads(out.strip().splitlines()[-1])

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()
        self.session.__exit__(*exc)


@pytest.mark.parametrize(("mode", "net"), [("rl", "concat"), ("backprop", "concat"), ("rl", "set")])
def test_the_server_process_acts_without_torch_and_matches_the_team(mode, net):
    """The real server loop in a fresh interpreter, over real Zenoh on 127.0.0.1: it never imports
    torch, and the messages and records it publishes are the torch Team's for the same weights."""
    n = 3
    cfg = _cfg(n, "hammer", mode, 0.25, net)
    team = _team(cfg)
    with _Server(cfg, team.spec) as srv:
        srv.weights(team, 0)
        streams = ActingStreams(cfg.seed, n)
        for step, (obs, prev) in enumerate(_states(team, n, STEPS)):
            srv.state(step, obs, prev, 0)
            want = team.central_messages(team.global_state(obs, prev), streams, cfg.msg_dropout)
            for i, sub in enumerate(srv.msg_subs):
                m = sub.get(30.0)
                assert m is not None and m.step == step and m.agent == i
                np.testing.assert_allclose(m.msg, want.sent[:, i], atol=2e-5, rtol=0)
            rec = srv.exp_sub.get(30.0)
            assert rec is not None and rec.step == step
            np.testing.assert_array_equal(rec.arrays["keep"], want.keep)
            np.testing.assert_allclose(rec.arrays["msg_raw"], want.raw, atol=2e-5, rtol=0)
            np.testing.assert_allclose(rec.arrays["c_logp"], want.logp, atol=2e-5, rtol=0)
            np.testing.assert_allclose(rec.arrays["c_values"], want.value, atol=2e-5, rtol=0)
        res = srv.stop()
    assert res["torch"] is False
    assert res["counters"]["steps"] == STEPS and res["counters"]["weights_loaded"] == 1


def test_the_server_without_weights_sends_nothing_then_serves_once_they_come():
    """No central weights after the wait (a learner that never published): the step is not served,
    so the local agents act on their fallback, and the server keeps running; the first weights
    that arrive are used, and the unserved step drew nothing from the central stream."""
    n = 3
    cfg = _cfg(n, "hammer", "rl", 0.0)
    team = _team(cfg)
    (obs0, prev0), (obs1, prev1) = _states(team, n, 2)
    with _Server(cfg, team.spec, weights_timeout_s=0.5) as srv:
        srv.state(0, obs0, prev0, 0)
        time.sleep(1.5)  # > the weights wait: the server gave up on step 0
        assert all(sub.get(0.0) is None for sub in srv.msg_subs) and srv.exp_sub.get(0.0) is None
        srv.weights(team, 1)
        srv.state(1, obs1, prev1, 1)
        want = team.central_messages(team.global_state(obs1, prev1), ActingStreams(cfg.seed, n))
        for i, sub in enumerate(srv.msg_subs):
            m = sub.get(30.0)
            assert m is not None and m.step == 1 and m.policy_version == 1
            np.testing.assert_allclose(m.msg, want.sent[:, i], atol=2e-5, rtol=0)
        res = srv.stop()
    c = res["counters"]
    assert (c["states_no_policy"], c["weights_wait_timeouts"], c["steps"], c["weights_loaded"]) == (1, 1, 1, 1)


def test_the_server_fails_on_weights_of_the_other_central_network():
    """A set-net run's server given concat weights (another run's learner) stops with a one-line reason
    naming central_net, instead of sending messages from a network the run did not train."""
    n = 3
    cfg = _cfg(n, "hammer", "rl", 0.0, "set")
    concat_team = _team(_cfg(n, "hammer", "rl", 0.0, "concat"))
    (obs, prev), = _states(concat_team, n, 1)
    with _Server(cfg, concat_team.spec) as srv:
        srv.weights(concat_team, 0)
        srv.state(0, obs, prev, 0)
        _, err = srv.proc.communicate(timeout=60)
        assert srv.proc.returncode != 0
        assert all(sub.get(0.0) is None for sub in srv.msg_subs)
    assert "(central_net, state_dim, n_agents, msg_dim, critic) = ('concat'" in err and "('set'" in err, err[-1500:]
