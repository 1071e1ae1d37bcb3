"""The multi-robot warehouse (`envs.rware_vec`): the real rware package, no mocks.

What is pinned: the local columns are exactly rware's own observations (same seeds, same actions,
across auto-resets), the central-only columns carry the warehouse the robots cannot see and never
reach a local policy, config mistakes name the field, and `hammer train` / `hammer up` run it alike.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from hammer.envs.description import EnvConfigError
from hammer.envs.registry import make_vec_env
from hammer.learning.config import merge_config
from hammer.learning.team import Team
from rware.warehouse import RewardType, Warehouse
from typer.testing import CliRunner

from hammer.cli import app
from tests.runtime_helpers import DISPATCH, hammer, processes_mentioning, trained_run

LOCAL = 71  # rware's flattened view at sensor_range 1: 8 own values + 9 cells x 7
SHELVES, GOALS = 32, 2  # the tiny layout


def _reference(n: int, seed: int) -> Warehouse:
    """rware's own tiny-<n>ag, as its gym id rware-tiny-<n>ag-v2 registers it."""
    wh = Warehouse(shelf_columns=3, column_height=8, shelf_rows=1, n_agents=n, msg_bits=0, sensor_range=1,
                   request_queue_size=n, max_inactivity_steps=None, max_steps=500,
                   reward_type=RewardType.INDIVIDUAL)
    wh.reset(seed=seed)
    return wh


def test_spec_and_shapes():
    env = make_vec_env("rware-tiny-4ag", 4, 3)
    s = env.spec
    assert (s.n_agents, s.discrete, s.action_dim, s.max_steps) == (4, True, 5, 500)
    assert s.local_obs_dim == LOCAL and s.obs_dim == LOCAL + 3 * SHELVES + 2 * GOALS
    obs, active = env.reset(seed=0)
    assert obs.shape == (3, 4, s.obs_dim) and obs.dtype == np.float32 and active.all()
    st = env.step(np.zeros((3, 4), dtype=np.int64))
    assert st.reward.shape == (3, 4) and st.reward.dtype == np.float32
    # central-only columns are the same warehouse in every robot's row, and differ from copy to copy
    assert (obs[:, :, LOCAL:] == obs[:, :1, LOCAL:]).all()
    assert not (obs[0, 0, LOCAL:] == obs[1, 0, LOCAL:]).all()
    assert make_vec_env("rware", 2, 1, env_kwargs={"sensor_range": 2}).spec.local_obs_dim == 8 + 25 * 7


def test_local_columns_are_rware_itself_across_episodes():
    """Two copies for two whole episodes against two plain rware envs seeded seed + k: every local
    observation and reward bit for bit, the time limit reported as truncation, and after the
    auto-reset our copy continues rware's own unseeded stream."""
    k, n, seed = 2, 2, 7
    env = make_vec_env("rware-tiny-2ag", n, k)
    obs, _ = env.reset(seed=seed)
    refs = [_reference(n, seed + c) for c in range(k)]
    for c, ref in enumerate(refs):
        assert np.array_equal(obs[c, :, :LOCAL], np.stack([ref._make_obs(r) for r in ref.agents]))
    rng = np.random.default_rng(0)
    ended, delivered = 0, 0.0
    for t in range(1, 1001):
        acts = rng.integers(0, 5, (k, n))
        st = env.step(acts)
        for c, ref in enumerate(refs):
            r_obs, r_rew, r_done, _, _ = ref.step(acts[c].tolist())
            assert np.array_equal(st.final_obs[c, :, :LOCAL], np.stack(r_obs)), (t, c)
            assert np.array_equal(st.reward[c], np.asarray(r_rew, np.float32))
            delivered += float(np.sum(r_rew))
            assert st.done[c] == r_done == (t % 500 == 0)
            if r_done:
                ended += 1
                r_obs, _ = ref.reset()
            assert np.array_equal(st.obs[c, :, :LOCAL], np.stack(r_obs))
        assert np.array_equal(st.truncated, np.repeat(st.done[:, None], n, axis=1)) and not st.terminated.any()
    assert ended == 4 and [e.length for e in st.episodes] == [500, 500]


def _team(obs_env, variant: str = "hammer") -> Team:
    cfg = merge_config(preset="rware-tiny-2ag", extra={"variant": variant, "num_envs": obs_env.num_envs})
    return Team(cfg, obs_env.spec)


def test_central_state_carries_what_the_local_view_lacks():
    """Two warehouses equal in everything a robot can see but with a different requested shelf far
    from both robots: the local policies' inputs are identical, the central agent's states are not,
    and they differ exactly in those two shelves' requested flags."""
    a, b = make_vec_env("rware-tiny-2ag", 2, 1), make_vec_env("rware-tiny-2ag", 2, 1)
    a.reset(seed=3)
    b.reset(seed=3)
    wa, wb = a.envs[0], b.envs[0]
    near = {(r.x + dx, r.y + dy) for r in wa.agents for dx in (-1, 0, 1) for dy in (-1, 0, 1)}
    far = [j for j, s in enumerate(wb.shelfs) if (s.x, s.y) not in near and s not in wb.request_queue]
    old = next(j for j, s in enumerate(wb.shelfs) if s in wb.request_queue and (s.x, s.y) not in near)
    wb.request_queue[wb.request_queue.index(wb.shelfs[old])] = wb.shelfs[far[0]]
    noop = np.zeros((1, 2), dtype=np.int64)
    oa, ob = a.step(noop).obs, b.step(noop).obs
    team = _team(a)
    assert np.array_equal(team.local_view(oa), team.local_view(ob))  # what the robots get
    assert (team.local_view(oa)[..., LOCAL:] == 0).all()
    prev = team.zero_prev_actions(1)
    sa, sb = team.global_state(oa, prev), team.global_state(ob, prev)
    assert sa.shape == (1, team.state_dim) == (1, 2 * (LOCAL + 3 * SHELVES + 2 * GOALS) + 2 * 5)
    diff = np.flatnonzero(sa[0] != sb[0])
    flags = {LOCAL + 3 * j + 2 for j in (old, far[0])}  # robot 0's row; robot 1's row repeats them
    row = LOCAL + 3 * SHELVES + 2 * GOALS
    assert set(diff) == flags | {f + row for f in flags}
    assert team.local_view(oa)[0, 0, :LOCAL].any()  # the view itself is not blanked


def test_acting_applies_the_local_view():
    """The trainer's local forward sees the masked row: central-only columns do not move the
    local policy's output, a local column does."""
    env = make_vec_env("rware-tiny-2ag", 2, 2)
    obs, _ = env.reset(seed=0)
    team = _team(env, "il")
    msg = np.zeros((2, 2, 0), dtype=np.float32)
    base = team.local_values(obs, msg)
    noisy = obs.copy()
    noisy[..., LOCAL:] = 99.0
    assert np.array_equal(team.local_values(noisy, msg), base)
    noisy[..., 0] += 3.0
    assert not np.allclose(team.local_values(noisy, msg), base)


@pytest.mark.parametrize(("name", "n", "kwargs", "match"), [
    ("rware", 2, {"sensor_rang": 1}, "unknown env_kwargs field 'sensor_rang'; valid fields: column_height"),
    ("rware-tiny-2ag", 4, {}, r"n_agents: env 'rware-tiny-2ag' has 2 robots but n_agents=4; set n_agents=2"),
    ("rware-tiny-2ag", 2, {"size": "small"}, "env_kwargs.size is set by the name"),
    ("rware", 2, {"size": "huge"}, "env_kwargs.size must be one of tiny, small, medium, large"),
    ("rware", 2, {"max_steps": 0}, "env_kwargs.max_steps must be an int >= 1"),
    ("rware-tiny-two", 2, {}, "unknown name 'rware-tiny-two'"),
])
def test_config_errors_name_the_field(name, n, kwargs, match):
    with pytest.raises(EnvConfigError, match=match):
        make_vec_env(name, n, 1, env_kwargs=kwargs)


def test_workers_equal_in_process():
    a = make_vec_env("rware-tiny-2ag", 2, 4)
    b = make_vec_env("rware-tiny-2ag", 2, 4, workers=2, parent_slice=True)
    try:
        oa, _ = a.reset(seed=5)
        ob, _ = b.reset(seed=5)
        assert np.array_equal(oa, ob)
        rng = np.random.default_rng(1)
        for _ in range(520):  # across one auto-reset
            acts = rng.integers(0, 5, (4, 2))
            sa, sb = a.step(acts), b.step(acts)
            for f in ("obs", "final_obs", "reward", "truncated", "done"):
                assert np.array_equal(getattr(sa, f), getattr(sb, f)), f
            assert sa.episodes == sb.episodes
    finally:
        b.close()


# 100-step episodes, 4 copies, 50-step rollouts: a checkpoint (and env reseed) every 2 updates = 1 episode
_SHORT_FIELDS = ("env_kwargs.max_steps=100", "num_envs=4", "rollout_steps=50", "checkpoint_every=2")
_SHORT = [a for field in _SHORT_FIELDS for a in ("--set", field)]


def _metrics(run) -> list[dict[str, str]]:
    with open(run / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_hammer_train_runs_a_few_episodes(tmp_path):
    run = tmp_path / "train"
    # the CLI's own path in this process: what is checked is the rware run it starts, not the process
    res = CliRunner().invoke(app, ["train", "--preset", "rware-tiny-2ag", "--episodes", "8", *_SHORT, "--run-dir",
                                   str(run), "--quiet"])
    assert res.exit_code == 0, res.output[-2000:]
    rows = _metrics(run)
    assert len(rows) == 8 and {r["length"] for r in rows} == {"100"}
    summary = json.loads((run / "summary.json").read_text())
    # 4 rollouts of 50 steps; the budget is spent in the 4th, before its update
    assert summary["env"] == "rware" and summary["episode_length"] == 100 and summary["updates"] == 3


@pytest.mark.parametrize("dispatch", ["default", "baseline kernels"])
def test_up_equals_train(tmp_path, dispatch):
    """The same config through every `hammer up` role and through `hammer train` (the trainer in
    process where the kernels are this CPU's own, a `hammer train` process under others): the same
    episodes and, after 5 PPO updates, the same weights bit for bit, with the kernels this CPU
    picks and with the ones an older CPU would run (`DISPATCH`: numpy, OpenBLAS, ATen, MKL, libm).
    Rewards are sparse here (most short episodes deliver nothing), so the weights are the sharp
    check: one different action, a central agent fed other columns, a local agent fed unmasked
    rows, or one value computed by another library in one runner (torch's central forward against
    the central server's numpy one once moved 128 weights by 1.8e-4) would move them."""
    from safetensors.numpy import load as load_safetensors

    if dispatch not in DISPATCH:
        pytest.skip(f"no '{dispatch}' setting on this machine (x86-64 only)")
    env = DISPATCH[dispatch]
    up, tr = tmp_path / "up", tmp_path / "train"
    common = ["--preset", "rware-tiny-2ag", "--central-mode", "rl", "--episodes", "12", *_SHORT]
    r1 = hammer("up", *common, "--run-dir", str(up), "--no-dashboard",
                "--runtime", "msg_deadline_ms=5000", "--runtime", "act_deadline_ms=10000", env=env)
    assert r1.returncode == 0, r1.stderr[-2000:]
    if env:  # the kernels are chosen at a process's start: a `hammer train` of its own under them
        r2 = hammer("train", *common, "--variant", "hammer", "--run-dir", str(tr), "--quiet", env=env)
        assert r2.returncode == 0, r2.stderr[-2000:]
    else:  # this process's own kernels: the trainer in process, as `hammer train` runs it
        trained_run(tr, ("variant=hammer", "central_mode=rl", "episodes=12", *_SHORT_FIELDS, "torch_threads=1"),
                    preset="rware-tiny-2ag")
    links = json.loads((up / "summary.json").read_text())["links"]
    assert links["msg_fallback_copies"] == 0 and links["default_actions"] == 0
    a, b = _metrics(up), _metrics(tr)
    assert [(r["length"], r["team_return"]) for r in a] == [(r["length"], r["team_return"]) for r in b]
    for part in ("local", "central"):
        wa = load_safetensors((up / "final" / f"{part}.safetensors").read_bytes())
        wb = load_safetensors((tr / "final" / f"{part}.safetensors").read_bytes())
        assert wa.keys() == wb.keys()
        for key in wa:
            np.testing.assert_array_equal(wa[key], wb[key], err_msg=f"{part}/{key}")
    assert processes_mentioning(str(up)) == []


def test_pilot_rule_judges_only_finished_seeds():
    """The plan's rule (experiments.rware_pilot): all 3 finished seeds above floor mean + 3 s.e."""
    from hammer.experiments.rware_pilot import verdicts

    floor = {2: {"threshold": 0.064}}

    def row(variant: str, seed: int, final: float, finished: bool = True) -> dict:
        return {"variant": variant, "n": 2, "seed": seed, "final": final, "finished": finished}

    rows = [row("il", s, 0.5) for s in range(3)] + [row("hammer-rl", 0, 0.5), row("hammer-rl", 1, 0.05),
                                                    row("hammer-rl", 2, 0.9)]
    rows += [row("random", 0, 0.9), row("random", 1, 0.9, finished=False)]
    assert verdicts(rows, floor) == {("hammer-rl", 2): "does not learn", ("il", 2): "learns",
                                     ("random", 2): "not judged (1 of 3 seeds finished)"}
