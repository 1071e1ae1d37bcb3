"""Every message says what its key says, and intake is bounded before decoding.

Real Zenoh sessions on 127.0.0.1. A peer allowed on its own key (in a secure run, a stolen
identity) must not speak for another agent or role through the payload, must not flood the
receiver into slowness or memory growth, and must not rewrite the counters a run's verdict is
built from.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from hammer.protocol.binding import check_key, pool_agents
from hammer.protocol.codec import decode, encode
from hammer.protocol.dims import Dims
from hammer.protocol.errors import KeyMismatchError, ProtocolError
from hammer.protocol.samples import sample_messages
from hammer.protocol.schemas import (
    Action,
    CentralMsg,
    Control,
    ExperienceChunk,
    GlobalState,
    Heartbeat,
    LocalObs,
    Weights,
)
from hammer.protocol.session import HammerSession, TransportConfig
from hammer.runtime.heartbeats import HeartbeatLedger
from msgspec.structs import replace

K = 4


def _msg(cls, sender: str, **fields):
    """A sample message of `cls` with its sender (as a session stamps it) and the given fields."""
    m = next(m for m in sample_messages() if type(m) is cls)
    return replace(m, sender=sender, **fields)


@pytest.mark.parametrize(("key", "cls", "sender", "fields"), [
    ("env/obs/1", LocalObs, "env", {"agent": 1}),
    ("env/state", GlobalState, "env", {}),
    ("central/msg/2", CentralMsg, "central", {"agent": 2}),
    ("agent/act/0", Action, "local-0", {"agent": 0}),
    ("agent/act/3", Action, "locals-2-5", {"agent": 3}),
    ("agent/act/5", Action, "locals-1_5_9", {"agent": 5}),
    ("learn/team/exp", ExperienceChunk, "env", {"role": "team"}),
    ("learn/central/exp", ExperienceChunk, "central", {"role": "central"}),
    ("learn/local/weights", Weights, "learner", {"role": "local"}),
    ("ctl/hb/env", Heartbeat, "env", {"role": "env"}),
    ("ctl/hb/local-3", Heartbeat, "locals-2-5", {"role": "local-3"}),
])
def test_what_the_key_says_is_accepted(key, cls, sender, fields):
    check_key(_msg(cls, sender, **fields), key)


@pytest.mark.parametrize(("key", "cls", "sender", "fields", "what"), [
    # a stolen local-1 identity on its own keys
    ("agent/act/1", Action, "local-1", {"agent": 0}, "agent"),
    ("agent/act/1", Action, "local-1", {"agent": 2}, "agent"),
    ("ctl/hb/local-1", Heartbeat, "local-1", {"role": "env"}, "role"),
    ("ctl/hb/local-1", Heartbeat, "env", {"role": "local-1"}, "sender"),
    # every other identity a payload carries
    ("agent/act/1", Action, "local-0", {"agent": 1}, "sender"),
    ("agent/act/1", Action, "locals-2-5", {"agent": 1}, "sender"),
    ("env/obs/1", LocalObs, "env", {"agent": 0}, "agent"),
    ("env/obs/1", LocalObs, "central", {"agent": 1}, "sender"),
    ("central/msg/2", CentralMsg, "central", {"agent": 1}, "agent"),
    ("central/msg/2", CentralMsg, "env", {"agent": 2}, "sender"),
    ("env/state", GlobalState, "local-0", {}, "sender"),
    ("learn/team/exp", ExperienceChunk, "env", {"role": "central"}, "role"),
    ("learn/central/exp", ExperienceChunk, "env", {"role": "central"}, "sender"),
    ("learn/local/weights", Weights, "learner", {"role": "central"}, "role"),
    ("learn/local/weights", Weights, "local-0", {"role": "local"}, "sender"),
    ("ctl/hb/local-1", Heartbeat, "locals-2-5", {"role": "local-1"}, "sender"),
    # a message of another type on a key (a receiver expecting several types)
    ("env/obs/1", CentralMsg, "env", {"agent": 1}, "type"),
    ("ctl/all", Heartbeat, "launcher", {"role": "launcher"}, "type"),
])
def test_a_payload_that_claims_more_than_its_key_is_refused(key, cls, sender, fields, what):
    with pytest.raises(KeyMismatchError) as e:
        check_key(_msg(cls, sender, **fields), key)
    assert e.value.reason == "key_mismatch" and e.value.field == what


def test_an_empty_sender_is_the_one_its_key_implies():
    """A publisher sends the sender its key implies as "" (it is not repeated on the wire); the
    receiver takes it from the key. On a key that implies none, "" stays "" (and obeys no stop)."""
    m = _msg(Action, "", agent=1)
    check_key(m, "agent/act/1")
    assert m.sender == "local-1"
    stop = Control(command="stop")
    check_key(stop, "ctl/all")
    assert stop.sender == ""


def test_pool_names_cover_exactly_their_agents():
    assert pool_agents("locals-2-4") == {2, 3, 4} and pool_agents("locals-1_5") == {1, 5}
    assert pool_agents("local-1") == set() and pool_agents("locals-x") == set()


def test_heartbeat_counters_are_non_negative_and_gauges_separate():
    good = sample_messages()[-1]
    assert isinstance(good, Heartbeat) and good.gauges["paper_metric_100"] < 0
    for bad in ({"decode": -6}, {"x": -0.5}, {"x": float("nan")}):
        with pytest.raises(ProtocolError):
            decode(encode(replace(good, counters=bad)), Heartbeat)


@pytest.fixture()
def pair():
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    with HammerSession("r", t, sender="env") as env, \
            HammerSession("r", TransportConfig.connector(port), sender="local-1") as thief:
        yield env, thief


def _settle() -> None:
    time.sleep(0.3)


def _action(agent: int, step: int) -> Action:
    return Action(agent=agent, step=step, env_idx=np.arange(K, dtype=np.int64), action=np.zeros(K, np.int64),
                  msg=np.zeros((K, 2), np.float32))


DIMS = Dims(num_envs=K, n_agents=3, obs_dim=6, msg_dim=2, action_dim=5, discrete=True)


def test_an_action_for_another_agent_on_ones_own_key_is_refused_and_counted(pair):
    env, thief = pair
    acts = env.subscribe(env.keys.act("*"), Action, DIMS)
    _settle()
    thief.publish(thief.keys.act(1), _action(0, 3))  # the attack: agent 0 in the payload
    thief.publish(thief.keys.act(1), _action(2, 3))
    thief.publish(thief.keys.act(1), _action(1, 3))  # its own job
    got = acts.get(5.0)
    assert got is not None and got.agent == 1 and got.sender == "local-1"
    assert acts.get(0.3) is None
    assert acts.stats.rejected == {"key_mismatch": 2}
    assert env.rejection_counts() == {"key_mismatch": 2}


def test_a_flood_on_one_key_is_refused_on_arrival_and_bounded(pair):
    """4 MB payloads on an agent's own key are over what an action of the run's sizes can weigh:
    refused by the subscription's callback without a copy; a flood of valid-size payloads is held
    to the key's queue bound and never delays another key's message beyond it."""
    env, thief = pair
    acts = env.subscribe(env.keys.act("*"), Action, DIMS, maxsize=16)
    assert acts.cap is not None and acts.cap < 4096
    _settle()
    big = encode(_action(1, 0), stamp={"sender": "local-1"}) + bytes(4 << 20)
    for _ in range(25):
        thief.put_bytes(thief.keys.act(1), big)
    small = encode(_action(1, 0), stamp={"sender": "local-1"})
    for _ in range(200):
        thief.put_bytes(thief.keys.act(1), small)
    deadline = time.monotonic() + 5.0
    while acts.stats.rejected["size"] + acts.stats.overflow + acts.pending() < 225 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert acts.stats.rejected["size"] == 25
    assert acts.pending() == 16 and acts.stats.overflow == 200 - 16
    with HammerSession("r", TransportConfig.connector(int(env.transport.listen[0].rsplit(":", 1)[1])),
                       sender="local-0") as honest:
        _settle()
        honest.publish(honest.keys.act(0), _action(0, 1))
        deadline = time.monotonic() + 5.0
        while acts.pending() < 17 and time.monotonic() < deadline:
            time.sleep(0.01)
        got = acts.drain()
    assert [m.agent for m in got] == [1] * 16 + [0]  # agent 0's one action still queued behind the bound


def _hb(role: str, pid: int, **counters) -> Heartbeat:
    return Heartbeat(role=role, pid=pid, status="running", counters=counters, sender=role)


def test_the_ledger_refuses_counters_that_fall_and_pids_it_did_not_start():
    started = {"env": {100}, "local-0": {200, 201}}
    ledger = HeartbeatLedger(started.get, max_processes=2)
    assert ledger.offer(_hb("env", 100, actions_duplicate=80, step=10))
    assert not ledger.offer(_hb("env", 100, actions_duplicate=0, step=11))  # a counter fell
    assert ledger.last[("env", 100)] == {"actions_duplicate": 80, "step": 10}
    assert ledger.offer(_hb("env", 100, step=12))  # one left out keeps its value
    assert ledger.last[("env", 100)] == {"actions_duplicate": 80, "step": 12}
    assert not ledger.offer(_hb("env", 999, step=1))  # env from a pid the launcher never started
    assert ledger.offer(_hb("local-0", 201, steps=1))  # a restart of a started role
    # a role started elsewhere: at most max_processes processes of it are counted
    assert ledger.offer(_hb("local-1", 1, steps=5)) and ledger.offer(_hb("local-1", 2, steps=5))
    assert not ledger.offer(_hb("local-1", 3, steps=5))
    assert ledger.offer(_hb("local-1", 1, steps=6))
    assert ledger.rejected == {"counters_fell": 1, "heartbeat_pid": 1, "heartbeat_processes": 1}
