"""The seeded fault layer: rates and delays as configured, reproducible from the seed."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hammer.protocol.fault_injection import FaultInjector, FaultRule, FaultSpec, key_matches
from hammer.protocol.schemas import LocalObs
from hammer.protocol.session import HammerSession, TransportConfig
from hammer.protocol.structs import SettingsError, parse


def _run(spec: FaultSpec, n: int, key: str = "agent/act/0", pace_s: float = 0.0
         ) -> tuple[list[int], FaultInjector, list[float]]:
    """Submit n numbered payloads; return the order they came out, the injector and their delays."""
    out: list[int] = []
    sent_at: dict[int, float] = {}
    delays: list[float] = []
    lock = threading.Lock()

    def send(p: bytes) -> None:
        i = int.from_bytes(p, "little")
        with lock:
            out.append(i)
            delays.append(time.monotonic() - sent_at[i])

    inj = FaultInjector(spec)
    for i in range(n):
        sent_at[i] = time.monotonic()
        inj.submit(key, i.to_bytes(4, "little"), send)
        if pace_s:
            time.sleep(pace_s)  # a steady stream like a step loop, not one burst
    assert inj.wait_idle(10.0)
    inj.close()
    return out, inj, delays


def test_drop_and_duplicate_rates_match_configuration():
    spec = FaultSpec(seed=1, rules=[FaultRule(match="agent/act/*", drop=0.2, duplicate=0.1)])
    out, inj, _ = _run(spec, 4000)
    c = inj.counters[0]
    assert c.matched == 4000
    assert abs(c.dropped / 4000 - 0.2) < 0.03
    assert abs(c.duplicated / (4000 - c.dropped) - 0.1) < 0.03
    assert c.sent == len(out) == 4000 - c.dropped + c.duplicated
    # Each surviving payload arrives once or twice, in order (no delay, no reorder configured).
    assert out == sorted(out)


def test_delay_distribution_matches_configuration():
    spec = FaultSpec(seed=3, rules=[FaultRule(delay_ms=20.0, jitter_ms=10.0)])
    out, inj, delays = _run(spec, 2000, pace_s=0.0002)
    d = np.array(delays) * 1e3
    assert inj.counters[0].delayed == 2000 and len(out) == 2000
    # Uniform on [10, 30] ms: mean 20, std 10/sqrt(3) = 5.8; scheduling adds a little latency.
    assert 19.0 < d.mean() < 23.0, d.mean()
    assert 4.5 < d.std() < 7.5, d.std()
    assert np.percentile(d, 1) > 9.5 and np.percentile(d, 50) < 25.0


def test_same_seed_same_faults_different_seed_different():
    rule = FaultRule(drop=0.1, duplicate=0.05, reorder=0.05, reorder_window=2)
    a, ia, _ = _run(FaultSpec(seed=7, rules=[rule]), 3000)
    b, ib, _ = _run(FaultSpec(seed=7, rules=[rule]), 3000)
    c, ic, _ = _run(FaultSpec(seed=8, rules=[rule]), 3000)
    assert ia.report() == ib.report() and a == b
    assert ia.report() != ic.report() and a != c
    assert ia.counters[0].reordered > 0 and a != sorted(a)  # some messages really overtaken


def test_streams_are_per_key_and_first_rule_wins():
    spec = FaultSpec(seed=0, rules=[FaultRule(match="agent/act/0", drop=1.0), FaultRule(match="**", drop=0.5)])
    inj = FaultInjector(spec)
    got: list[bytes] = []
    for _ in range(1000):
        inj.submit("agent/act/0", b"a", got.append)
        inj.submit("agent/act/1", b"b", got.append)
        inj.submit("env/state", b"c", got.append)
    inj.close()
    assert b"a" not in got and inj.counters[0].dropped == 1000
    assert inj.counters[1].matched == 2000
    # Interleaving other keys does not change a key's stream: act/1 alone gives the same drops.
    solo = FaultInjector(spec)
    solo_got: list[bytes] = []
    for _ in range(1000):
        solo.submit("agent/act/1", b"b", solo_got.append)
    assert solo_got.count(b"b") == got.count(b"b")


def test_key_matching_and_rule_validation():
    assert key_matches("agent/act/*", "agent/act/3")
    assert not key_matches("agent/act/*", "agent/act/3/x")
    assert key_matches("**", "env/state") and key_matches("agent/**", "agent/act/1")
    assert key_matches("**/act/*", "agent/act/1") and not key_matches("central/**", "agent/act/1")
    for bad in [{"drop": 1.5}, {"duplicate": -0.1}, {"delay_ms": -1}, {"match": "a//b"},
                {"match": "a/b*"}, {"reorder_window": 0}, {"unknown": 1}]:
        with pytest.raises(SettingsError):
            parse(FaultRule, bad)
    with pytest.raises(SettingsError, match="drop: should be a number <= 1"):
        FaultRule(drop=2)
    assert not FaultSpec().enabled and not FaultSpec(rules=[FaultRule()]).enabled
    assert FaultSpec(rules=[FaultRule(drop=0.1)]).enabled


def test_faults_through_zenoh_drop_rate():
    """Drops configured on the publisher side are what the remote subscriber misses."""
    n = 1500
    t = TransportConfig.listener()
    port = int(t.listen[0].rsplit(":", 1)[1])
    spec = FaultSpec(seed=5, rules=[FaultRule(match="env/obs/*", drop=0.3)])
    with HammerSession("faulty", t, faults=spec) as pub_s, \
         HammerSession("faulty", TransportConfig.connector(port)) as sub_s:
        sub = sub_s.subscribe(sub_s.keys.obs("*"), LocalObs, maxsize=0)  # read after the whole burst
        time.sleep(0.3)
        obs = np.zeros((1, 18), np.float32)
        for step in range(n):
            pub_s.publish(pub_s.keys.obs(0), LocalObs(step=step, env_idx=np.arange(1), agent=0, obs=obs,
                                                     active=np.ones(1, bool)))
        pub_s.publish(pub_s.keys.obs(1), LocalObs(step=n, env_idx=np.arange(1), agent=1, obs=obs,
                                                 active=np.ones(1, bool)))  # another agent, same rule
        got = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            m = sub.get(0.5)
            if m is None:
                break
            got.append(m.step)
        report = pub_s.fault_report()["0:env/obs/*"]
    assert report["matched"] == n + 1
    assert len(got) == report["sent"] == n + 1 - report["dropped"]
    assert abs(report["dropped"] / (n + 1) - 0.3) < 0.04
    assert sub.stats.rejected_total == 0
