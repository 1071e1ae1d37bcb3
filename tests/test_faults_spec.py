"""Link fault specs, chaos schedules and per-link counters (no processes)."""

from __future__ import annotations

import signal
from types import SimpleNamespace

import pytest
from hammer.faults.chaos import ChaosScheduler, ChaosSpecError, parse_chaos
from hammer.faults.links import degraded_reasons, flat_fault_counters, link_of_pattern, link_table, rejections
from hammer.faults.spec import FaultSpecError, build_plan, parse_link_fault
from hammer.protocol.fault_injection import FaultInjector, key_matches


def test_link_fault_maps_to_the_link_keys_with_optional_agent():
    lf = parse_link_fault("central->local:agent=1,drop=0.2,delay_ms=5ms,jitter_ms=2")
    assert (lf.match, lf.drop, lf.delay_ms, lf.jitter_ms) == ("central/msg/1", 0.2, 5.0, 2.0)
    assert parse_link_fault("local->env:drop=5%").match == "agent/act/*"
    assert parse_link_fault("env->central:duplicate=0.1").match == "env/state"
    assert key_matches(parse_link_fault("env->local:reorder=0.3").match, "env/obs/2")
    assert "agent 1" in lf.describe() and "drop 20%" in lf.describe()


@pytest.mark.parametrize("text, fragment", [
    ("radio->local:drop=0.1", "link"),
    ("central->local:drop=1.5", "drop"),
    ("central->local:loss=0.1", "unknown field 'loss'"),
    ("central->local:drop", "not FIELD=VALUE"),
    ("env->central:agent=1,drop=0.1", "agent"),
])
def test_bad_link_faults_name_the_problem(text, fragment):
    with pytest.raises(FaultSpecError, match=fragment):
        parse_link_fault(text)


def test_plan_puts_agent_rules_first_and_merges_yaml_and_cli():
    plan = build_plan(["central->local:agent=2,drop=0.9"], seed=7,
                      section={"seed": 1, "links": ["central->local:drop=0.1", {"link": "local->env", "drop": 0.05}]})
    spec = plan.to_spec()
    assert spec.seed == 7  # the CLI seed wins
    assert [r.match for r in spec.rules] == ["central/msg/2", "central/msg/*", "agent/act/*"]
    assert build_plan([]).to_spec() is None


def test_same_seed_same_faults_other_seed_other_faults():
    def counts(seed: int) -> list[dict]:
        spec = build_plan(["central->local:drop=0.3,duplicate=0.2"], seed=seed).to_spec()
        inj = FaultInjector(spec)
        sent: list[bytes] = []
        for step in range(400):
            for i in range(3):
                inj.submit(f"central/msg/{i}", f"{step}/{i}".encode(), sent.append)
        inj.close()
        return [inj.report(), sent]

    a, b, c = counts(7), counts(7), counts(8)
    assert a == b
    assert a[0] != c[0]
    assert 0.2 < a[0]["0:central/msg/*"]["dropped"] / 1200 < 0.4


def test_flat_counters_per_link_and_link_table():
    report = {"0:central/msg/1": {"matched": 10, "sent": 9, "dropped": 2, "duplicated": 1, "delayed": 0, "reordered": 0},
              "1:central/msg/*": {"matched": 20, "sent": 20, "dropped": 1, "duplicated": 1, "delayed": 3, "reordered": 0}}
    flat = flat_fault_counters(report)
    assert flat["fault.central_local.dropped"] == 3 and flat["fault.central_local.delayed"] == 3
    assert link_of_pattern("**") is None and link_of_pattern("agent/act/*") == "local->env"
    roles = {"env": {"step": 10, "actions_on_time": 30, "default_actions": 0},
             "central": {"steps": 10, **flat},
             **{f"local-{i}": {"steps": 10, "msgs_on_time": 9, "msgs_late": 1, "fallback_copies": 16} for i in range(3)}}
    t = link_table(roles, 3, True)
    assert t["central->local"]["sent"] == 30 and t["central->local"]["dropped"] == 3
    assert t["central->local"]["late"] == 3 and t["central->local"]["fallbacks"] == 48
    assert t["local->env"]["delivered"] == 30
    assert all("unreported" not in row for row in t.values())


def test_a_sender_whose_count_lags_its_receivers_is_raised_and_says_so():
    # central was SIGKILLed 4 steps after its last heartbeat: the local agents got 12 more messages
    roles = {"env": {"step": 14, "actions_on_time": 42},
             "central": {"steps": 10},
             **{f"local-{i}": {"steps": 14, "msgs_on_time": 14} for i in range(3)}}
    row = link_table(roles, 3, True)["central->local"]
    assert row["sent"] == row["delivered"] == 42 and row["unreported"] == 12


def test_degraded_reasons_name_defaults_fallbacks_and_rejections():
    links = {"local->env": {"defaults": 10}, "central->local": {"fallbacks": 600}}
    roles = {"env": {"rejected.step_ahead": 2}, "local-0": {"rejected.size": 1, "rejected.other": 0}}
    assert rejections(roles) == {"env": {"step_ahead": 2}, "local-0": {"size": 1}}
    reasons = degraded_reasons(roles, links, agent_steps=3000, fraction=0.05, max_rejections=0)
    assert len(reasons) == 2 and reasons[0].startswith("fallback messages 600 of 3,000 agent-steps (20.0% > 5.0%)")
    assert reasons[1] == "3 messages rejected (env step_ahead 2; local-0 size 1)"
    assert degraded_reasons({}, links, agent_steps=3000, fraction=0.25, max_rejections=0) == []


def test_chaos_parse_and_schedule():
    assert parse_chaos("pause:local-1@t=10s,for=3s").duration_s == 3.0
    assert parse_chaos("kill:central@step=2000").at_step == 2000
    for bad, frag in [("explode:central@step=1", "unknown"), ("kill:env@step=5", "only central"),
                      ("kill:central@when=5", "when"), ("restart:central@step=5,for=2", "for=")]:
        with pytest.raises(ChaosSpecError, match=frag):
            parse_chaos(bad)

    class FakeSup:  # records signals; the launcher's Supervisor is exercised in the runtime tests
        def __init__(self):
            self.sent, self.roles = [], {}

        def signal(self, name, sig):
            self.sent.append((name, sig))

    sup = FakeSup()
    board = SimpleNamespace(heartbeats={"env": SimpleNamespace(counters={"step": 5})}, held=set(), chaos_log=[])
    sched = ChaosScheduler.from_strings(["kill:local-1@step=10", "pause:central@step=3,for=0"])
    sched(sup, board)
    assert sup.sent == [("central", signal.SIGSTOP), ("central", signal.SIGCONT)]
    board.heartbeats["env"].counters["step"] = 10
    sched(sup, board)
    sched(sup, board)  # fires once
    assert sup.sent[-1] == ("local-1", signal.SIGKILL) and len(sup.sent) == 3
    assert board.held == {"local-1"}
    with pytest.raises(ChaosSpecError, match="no role"):
        ChaosScheduler.from_strings(["kill:local-7@step=1"]).validate_roles({"central", "local-0"})


def test_sweep_results_read_back_typed_and_aggregate(tmp_path):
    """sweep.csv round-trips to the same PointResults, so analyses of a finished sweep (e.g.
    docs/results/faults_ownobs.py) reuse `aggregate` instead of parsing the CSV again."""
    from hammer.experiments.fault_sweep import PointResult, aggregate, read_results, write_outputs

    results = [PointResult(team=f"hammer-s{s}", variant="hammer", train_msg_dropout=0.0, drop=d, delay_ms=0.0,
                           seed=e, episodes=500, paper_metric=-19.0 - d - 0.1 * e - 0.01 * s, msgs_sent=100,
                           msgs_dropped=int(100 * d), msgs_late=0, msg_fallback_rate=d, default_actions=0, wall_s=9.5)
               for s in range(2) for d in (0.0, 1.0) for e in range(2)]
    write_outputs(results, tmp_path, msg_deadline_ms=50.0, episodes=500)
    back = read_results(tmp_path / "sweep.csv")
    assert back == results and isinstance(back[0].seed, int) and isinstance(back[0].drop, float)
    agg = aggregate(back)
    assert agg[("hammer-s1", 1.0, 0.0)]["mean"] == pytest.approx(-20.06) and agg[("hammer-s1", 1.0, 0.0)]["n"] == 2
