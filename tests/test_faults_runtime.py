"""Communication faults end to end: real role processes, real Zenoh on 127.0.0.1, real cn3 env.

Each test evaluates a frozen policy (mode eval: the learner only serves exported weights) under
seeded link faults or process chaos and checks what the agents actually did, step by step, from
the env host's trace (obs, messages used, actions, fallback masks).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import psutil
import pytest
from hammer.deploy.launcher import launch
from hammer.envs.registry import make_vec_env
from hammer.faults.spec import build_plan
from hammer.learning.config import merge_config
from hammer.local_agent.client import AgentSpec, LocalAgent
from hammer.runtime.settings import RuntimeSettings
from safetensors.numpy import save_file

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def team_policy(tmp_path_factory) -> tuple[Path, object, object]:
    """An exported cn3 HAMMER policy whose actions clearly depend on the message (untrained
    weights, message inputs and central head scaled up), so "acted on zeros" is a real claim."""
    from hammer.learning.team import Team

    cfg = merge_config("cn3", overrides=["variant=hammer", "central_mode=backprop", "seed=3", "num_envs=16"])
    env = make_vec_env(cfg.env, cfg.n_agents, 1)
    spec = env.spec
    env.close()
    team = Team(cfg, spec)
    local = team.local.export_numpy()
    local["actor.layers.0.weight"][:, spec.obs_dim:] *= 40.0
    local["actor.layers.2.weight"] *= 100.0
    central = team.central.export_numpy()
    central["head_weight"] *= 20.0
    d = tmp_path_factory.mktemp("policy")
    save_file(local, str(d / "local.safetensors"))
    save_file(central, str(d / "central.safetensors"))
    return d, cfg, spec


def _eval(tmp: Path, name: str, policy_dir: Path, base_cfg, episodes: int, faults: list[str] | None = None,
          fault_seed: int = 0, chaos: list[str] | None = None, **runtime):
    cfg = base_cfg.model_copy(update={"episodes": episodes, "seed": 5})
    plan = build_plan(faults or [], fault_seed)
    settings = RuntimeSettings(run_id=name, mode="eval", policy_dir=str(policy_dir), trace=True,
                               faults=plan.to_spec(), chaos=chaos or [], **runtime)
    res = launch(cfg, settings, tmp / name)
    assert res.summary["completed"] and res.summary["episodes"] == episodes
    return res, dict(np.load(tmp / name / "trace.npz"))


def _replay_actions(policy_dir: Path, cfg, spec, obs: np.ndarray, msgs: np.ndarray) -> np.ndarray:
    """What each local agent's numpy policy does on these observations and messages, drawing its
    own random stream step by step exactly as the client does."""
    agents = []
    for i in range(cfg.n_agents):
        a = LocalAgent(AgentSpec(agent=i, n_agents=cfg.n_agents, obs_dim=spec.obs_dim, msg_dim=cfg.msg_dim,
                                 discrete=spec.discrete, action_dim=spec.action_dim, seed=5))
        a.load_weights((policy_dir / "local.safetensors").read_bytes(), 0)
        agents.append(a)
    out = np.zeros(obs.shape[:3], np.int64)
    for t in range(obs.shape[0]):
        for i, a in enumerate(agents):
            out[t, :, i] = a.act(obs[t, :, i], msgs[t, :, i])
    return out


def test_same_seed_gives_the_same_fault_counts(tmp_path, team_policy):
    policy, cfg, _ = team_policy
    faults = ["central->local:drop=0.2,duplicate=0.1", "central->local:agent=1,drop=0.5", "env->local:duplicate=0.2"]
    runs = [_eval(tmp_path, f"seed7-{j}", policy, cfg, 60, faults, fault_seed=7, msg_deadline_ms=40)
            for j in range(2)]
    (a, ta), (b, tb) = runs
    fault_cols = ("sent", "dropped", "duplicated")
    for link in a.links:
        assert {c: a.links[link][c] for c in fault_cols} == {c: b.links[link][c] for c in fault_cols}, link
    c2l = a.links["central->local"]
    # ~0.2 x 2/3 + 0.5 x 1/3 of the messages dropped, duplicates arrive and are recognised as such.
    assert 0.2 * c2l["sent"] < c2l["dropped"] < 0.45 * c2l["sent"]
    assert c2l["duplicated"] > 0 and c2l["duplicate"] > 0
    assert a.links["env->local"]["duplicate"] == 0 and a.links["env->local"]["late"] > 0  # stale obs copies ignored
    # Agent 1 (its own rule, drop 0.5) fell back far more often than agents 0 and 2.
    fb = ta["fallback"].mean(axis=(0, 1))
    assert fb[1] > 1.5 * max(fb[0], fb[2]) and min(fb[0], fb[2]) > 0.05
    # Same faults on the same steps: the agents acted on the same messages.
    assert np.array_equal(ta["fallback"], tb["fallback"]) or a.links["central->local"]["late"] + \
        b.links["central->local"]["late"] > 0


def test_drop_rate_one_acts_exactly_like_the_local_policy_on_zero_messages(tmp_path, team_policy):
    policy, cfg, spec = team_policy
    res, tr = _eval(tmp_path, "dropall", policy, cfg, 60, ["central->local:drop=1.0"], msg_deadline_ms=20)
    c2l = res.links["central->local"]
    assert c2l["dropped"] == c2l["sent"] > 0 and c2l["delivered"] == 0
    assert tr["fallback"].all() and not tr["msgs"].any()
    assert np.array_equal(tr["actions"], _replay_actions(policy, cfg, spec, tr["obs"], tr["msgs"]))
    # Not vacuous: with real (non-zero) messages this policy acts differently.
    ones = np.ones_like(tr["msgs"])
    assert (tr["actions"] != _replay_actions(policy, cfg, spec, tr["obs"], ones)).mean() > 0.2


def test_message_later_than_the_deadline_is_late_and_never_applied(tmp_path, team_policy):
    policy, cfg, spec = team_policy
    res, tr = _eval(tmp_path, "delay", policy, cfg, 60, ["central->local:delay_ms=90"], msg_deadline_ms=20,
                    fallback="last")
    c2l = res.links["central->local"]
    # Every message arrived after its step was acted on: counted late, never used, and with
    # fallback=last not even remembered as the "last message" for a later step.
    assert c2l["late"] > 0.8 * c2l["sent"]
    assert tr["fallback"].all() and not tr["msgs"].any()
    assert np.array_equal(tr["actions"], _replay_actions(policy, cfg, spec, tr["obs"], tr["msgs"]))


def test_killed_central_agents_fall_back_and_restart_resumes_messages(tmp_path, team_policy):
    policy, cfg, _ = team_policy
    res, tr = _eval(tmp_path, "chaos", policy, cfg, 640, chaos=["kill:central@step=120", "restart:central@step=300"],
                    msg_deadline_ms=15)
    assert [e["event"] for e in res.chaos_log] == ["kill central at step 120", "restart central at step 300"]
    kill_step, restart_step = (e["step"] for e in res.chaos_log)
    steps, fb = tr["steps"], tr["fallback"].all(axis=(1, 2))
    # Messages before the kill: on a loaded machine a step's message can miss the 15 ms deadline now
    # and then, which is what the deadline is for; the outage below is every step.
    assert fb[steps < 100].mean() < 0.05
    # The logged step is the env host's last heartbeat (<= 0.5 s old): the outage starts after it.
    first = int(steps[fb & (steps >= 100)][0])
    assert kill_step <= first < restart_step
    assert fb[(steps >= first) & (steps <= restart_step)].all()  # local agents kept acting on zeros
    assert fb[-50:].mean() < 0.1  # the restarted central's messages are used again
    assert res.links["central->local"]["fallbacks"] >= (restart_step - first) * cfg.num_envs * cfg.n_agents
    assert res.links["local->env"]["defaults"] == 0  # no agent stopped acting
    assert res.restarts["central"] == 0  # chaos restarted it, not the launcher's crash handling
    # Link counters stay consistent across the restart: nothing is delivered that was not sent.
    for link, row in res.links.items():
        assert row["delivered"] <= row["sent"] + row["duplicated"], (link, row)
    assert not [p for p in psutil.process_iter(["cmdline"]) if str(tmp_path) in " ".join(p.info["cmdline"] or [])]


def _episode_counts(run_dir: Path) -> tuple[list[dict], dict[str, np.ndarray]]:
    from hammer.faults.episode_links import read_episodes, read_step_logs
    from hammer.faults.steplog import STEP_LOG_DIR

    return read_episodes(run_dir / "episode_links.csv"), read_step_logs(run_dir / STEP_LOG_DIR)


def test_per_episode_link_counters_add_up_to_the_run_and_repeat_with_the_seed(tmp_path, team_policy):
    """Per-episode columns (RUN/episode_links.csv) from the roles' step logs: the step logs add up
    to links.json, the episode sums to the step logs weighted by how many recorded episodes cover
    each step, they agree with the env host's own per-copy counts, and repeat with the fault seed."""
    import json

    from hammer.faults.episode_links import EPISODE_EVENTS, step_totals
    from hammer.faults.links import LINK_IDS

    policy, cfg, _ = team_policy
    faults = ["central->local:drop=0.3", "local->env:drop=0.1"]
    # 40 episodes of 16 copies x 25 steps: steps 51..75 carry only the 8 episodes still in budget.
    runs = [_eval(tmp_path, f"ep{j}", policy, cfg, 40, faults, fault_seed=3, msg_deadline_ms=40,
                  act_deadline_ms=80)[0] for j in range(2)]
    n = cfg.n_agents
    per_run = []
    for res in runs:
        episodes, counts = _episode_counts(res.run_dir)
        assert len(episodes) == 40
        links = json.loads((res.run_dir / "links.json").read_text())["links"]
        assert list(links) == list(LINK_IDS)  # variant hammer: all four links
        # 1. The step logs hold every counted event once: their totals are the run's link table.
        totals = step_totals(counts)
        for link, row in links.items():
            for event, want in row.items():
                if event != "delayed":  # not logged per step (see faults.steplog.LoggedPublisher)
                    assert totals.get(link, {}).get(event, 0) == want, (link, event)
        # 2. Summed over episodes, a step's events count once per recorded episode running then.
        top = max(len(a) for a in counts.values())
        cover = np.zeros(top, np.int64)
        for e in episodes:
            cover[e["start_step"]:e["end_step"] + 1] += 1
        assert cover.max() == cfg.num_envs and cover.min() == 0  # the unrecorded tail is not counted
        for link, lid in LINK_IDS.items():
            for event in EPISODE_EVENTS:
                a = counts.get(f"{lid}_{event}", np.zeros(top, np.int64))
                assert sum(e[f"{lid}_{event}"] for e in episodes) == int((a * cover[:len(a)]).sum()), (link, event)
        # 3. Per episode, against what the env host counted for that env copy itself.
        for e in episodes:
            length = e["length"]
            assert e["end_step"] - e["start_step"] + 1 == length == 25
            assert e["env_central_sent"] == length and e["env_local_sent"] == n * length
            assert e["local_env_sent"] == n * length  # every agent acted on every observation
            on_time_actions = e["local_env_delivered"] - e["local_env_late"] - e["local_env_duplicate"]
            assert e["default_actions"] == n * length - on_time_actions
            on_time_msgs = e["central_local_delivered"] - e["central_local_late"] - e["central_local_duplicate"]
            missing = n * length - on_time_msgs  # agent-steps acted on a fallback message
            assert missing - e["default_actions"] <= e["msg_fallbacks"] <= missing
        c2l = sum(e["central_local_dropped"] for e in episodes) / sum(e["central_local_sent"] for e in episodes)
        l2e = sum(e["local_env_dropped"] for e in episodes) / sum(e["local_env_sent"] for e in episodes)
        assert 0.2 < c2l < 0.4 and 0.03 < l2e < 0.2
        per_run.append(episodes)
    # 4. Same fault seed: the same faults on the same episodes (what the senders decided). Not the
    # episodes that end on the run's last step: the stop that follows the budget's last episode
    # races the senders' messages for that step (the env host has acted on fallbacks by then), so
    # whether they were sent, and so decided, is timing, not the seed.
    sender = ["episode", "env_index", "start_step", "end_step",
              *(f"{lid}_{e}" for lid in LINK_IDS.values() for e in ("sent", "dropped", "duplicated"))]
    last = max(e["end_step"] for e in per_run[0])
    a, b = ([{c: e[c] for c in sender} for e in eps if e["end_step"] < last] for eps in per_run)
    assert len(a) == len(b) == 32  # 16 copies x 2 rounds; the 8 episodes of the third end on the last step
    for x, y in zip(a, b, strict=True):
        assert x == y, {c: (x[c], y[c]) for c in sender if x[c] != y[c]} | {"episode": x["episode"]}
