"""The numpy warehouse (`envs.rware_numpy`, env_kwargs impl="numpy") is rware 2.0.0 step for step.

The reference is rware's own `Warehouse` (real package, no mocks), one per copy, seeded seed + k and
stepped with the same actions. At every step the test compares, bit for bit: every robot's position,
direction, load and has_delivered flag, every shelf's position, the request queue slot by slot, the
step counter, the whole observation row (rware's flattened view plus the central columns) and the
rewards; the time limit and the unseeded resets that follow it must match too.

Rollouts, for every size (tiny, small, medium, large) and difficulty (easy, normal, hard) that the
`rware-<size>-<N>ag[-easy|-hard]` names can take, crowded grids, and rware's two_stage and global
rewards and a 5x5 window through the bare `rware` name:
  random   uniform actions;
  push     mostly forward, so robots queue into chains and contest cells;
  seek     robots steer to a goal or a requested shelf and toggle loads there, so loaded robots are
           cancelled against standing shelves, deliveries refill the queue from rware's generator;
  staged   every few steps each copy is rearranged (on both sides, `set_state`) into 2x2 and 2x3
           rotations (cycles of 4 and 6: a 3-cycle cannot happen, grid graphs are bipartite), head-on
           swaps, chains and 2-4 robots facing one free cell, then driven mostly forward.
Counters of what happened (moved rotations, swaps, contested cells, ties that networkx broke,
chains, cancelled loaded moves, deliveries) are asserted so the comparison cannot pass vacuously.

CI runs ~12,100 copy-steps. The long check (>= 100,000 copy-steps, same cases scaled up):
    RWARE_EXACT_STEPS=100000 .venv/bin/python -m pytest -q tests/test_rware_exact.py
"""

from __future__ import annotations

import math
import os
from collections import Counter

import numpy as np
import pytest
from hammer.envs.description import EnvDescription
from hammer.envs.registry import make_vec_env
from hammer.envs.rware_numpy import DX, DY, NumpyRwareVecEnv
from hammer.envs.rware_vec import central_columns, settings_from
from rware.warehouse import Direction

# (name, n_agents, copies, steps per copy in CI, max_steps): every size x difficulty, crowds on tiny
CASES = [
    ("rware-tiny-2ag", 2, 1, 520, 500),
    ("rware-tiny-4ag", 4, 1, 520, 500),
    ("rware-tiny-4ag-easy", 4, 2, 100, 60),
    ("rware-tiny-3ag-hard", 3, 2, 100, 60),
    ("rware-tiny-12ag", 12, 2, 100, 60),
    ("rware-tiny-24ag-hard", 24, 1, 100, 60),
    ("rware-small-4ag", 4, 1, 100, 60),
    ("rware-small-6ag-easy", 6, 1, 100, 60),
    ("rware-small-2ag-hard", 2, 1, 100, 60),
    ("rware-medium-6ag", 6, 1, 100, 60),
    ("rware-medium-10ag-easy", 10, 1, 100, 60),
    ("rware-medium-4ag-hard", 4, 1, 100, 60),
    ("rware-large-8ag", 8, 1, 100, 60),
    ("rware-large-16ag-easy", 16, 1, 100, 60),
    ("rware-large-6ag-hard", 6, 1, 100, 60),
    # rware's other reward types and a wider window, through the bare name's env_kwargs
    ("rware", 4, 2, 100, 60, {"reward_type": "two_stage", "sensor_range": 2}),
    ("rware", 3, 2, 100, 60, {"reward_type": "global", "size": "small", "difficulty": "easy"}),
]
POLICIES = ("random", "push", "seek", "staged")
LONG = int(os.environ.get("RWARE_EXACT_STEPS", "0"))  # the long check's total copy-steps
CI_TOTAL = sum(case[2] * case[3] for case in CASES) * len(POLICIES)
SCALE = max(1.0, LONG / CI_TOTAL)


# ---- the reference's state, read and written in rware's own objects ------------------------------
def ref_state(wh) -> dict:
    ids = {id(s): j for j, s in enumerate(wh.shelfs)}
    return {"x": [int(a.x) for a in wh.agents], "y": [int(a.y) for a in wh.agents],
            "dir": [a.dir.value for a in wh.agents],
            "carry": [ids[id(a.carrying_shelf)] if a.carrying_shelf is not None else -1 for a in wh.agents],
            "delivered": [bool(a.has_delivered) for a in wh.agents],
            "shelf_x": [int(s.x) for s in wh.shelfs], "shelf_y": [int(s.y) for s in wh.shelfs],
            "requests": [ids[id(s)] for s in wh.request_queue], "t": int(wh._cur_steps)}


def set_ref_state(wh, st: dict) -> None:
    for i, a in enumerate(wh.agents):
        a.x, a.y, a.dir = int(st["x"][i]), int(st["y"][i]), Direction(int(st["dir"][i]))
        a.carrying_shelf = wh.shelfs[st["carry"][i]] if st["carry"][i] >= 0 else None
        a.has_delivered = bool(st["delivered"][i])
    for j, s in enumerate(wh.shelfs):
        s.x, s.y = int(st["shelf_x"][j]), int(st["shelf_y"][j])
    wh.request_queue = [wh.shelfs[j] for j in st["requests"]]
    wh._cur_steps = int(st["t"])
    wh._recalc_grid()


def full_rows(wh, local_obs, d: int) -> np.ndarray:
    local = np.stack(local_obs)
    central = np.zeros(d - local.shape[1], dtype=np.float32)
    central_columns(wh, central)
    return np.concatenate([local, np.broadcast_to(central, (len(local), len(central)))], axis=1)


def assert_same_state(ours: dict, ref: dict, where) -> None:
    for key, value in ref.items():
        assert np.array_equal(np.asarray(ours[key]), np.asarray(value)), (where, key, ours[key], value)


# ---- adversarial policies --------------------------------------------------------------------------
def steer(env: NumpyRwareVecEnv, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Forward when facing the larger offset to (tx, ty), else turn right (1 forward, 3 right)."""
    dx, dy = tx - env.x, ty - env.y
    want = np.where(np.abs(dx) >= np.abs(dy), np.where(dx < 0, 2, 3), np.where(dy < 0, 0, 1))
    return np.where((dx == 0) & (dy == 0), 4, np.where(env.dir == want, 1, 3))


def policy_actions(name: str, env: NumpyRwareVecEnv, rng: np.random.Generator, staged: np.ndarray) -> np.ndarray:
    k, n = env.num_envs, env.n
    if name == "random":
        return rng.integers(0, 5, (k, n))
    if name == "push":
        return rng.choice(5, size=(k, n), p=[0.05, 0.7, 0.1, 0.1, 0.05])
    if name == "seek":
        g = env.goals[np.arange(n) % len(env.goals)][None]  # each robot keeps its goal and request slot
        req = env.req[:, np.arange(n) % env.q]
        loaded = env.carry >= 0
        # a loaded robot inside a shelf block first steps sideways to the nearest vertical highway
        in_block = loaded & ~env.highway[env.y, env.x]
        aisle = np.where(env.x % 3 <= 1, env.x - env.x % 3, np.minimum(env.x - env.x % 3 + 3, env.w - 1))
        tx = np.where(in_block, aisle, np.where(loaded, g[..., 0], env.sx[env.kk, req]))
        ty = np.where(in_block, env.y, np.where(loaded, g[..., 1], env.sy[env.kk, req]))
        acts = steer(env, tx, ty)
        noise = rng.random((k, n))
        acts = np.where(noise < 0.1, rng.integers(0, 5, (k, n)), acts)
        return np.where(noise > 0.96, 4, acts)
    acts = rng.choice(5, size=(k, n), p=[0.1, 0.5, 0.15, 0.15, 0.1])
    return np.where(staged & (rng.random((k, n)) < 0.9), 1, acts)


def stage(env: NumpyRwareVecEnv, c: int, rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """A rearranged copy c: robots put down their shelves where they stand, then 2-6 of them form a
    rotation, a swap, a chain or a contest, the rest go to random free cells."""
    st = env.get_state(c)
    n, h, w = env.n, env.h, env.w
    scene: list[tuple[int, int, int]] = []  # (x, y, direction) per staged robot
    x0, y0 = int(rng.integers(1, w - 3)), int(rng.integers(1, h - 3))
    kind = rng.choice(["rot4", "rot6", "swap", "chain", "contest"]) if n >= 6 else \
        rng.choice(["rot4", "swap", "chain", "contest"]) if n >= 4 else rng.choice(["swap", "contest"])
    up, down, left, right = 0, 1, 2, 3
    if kind == "rot4":
        spin = [(x0, y0, right), (x0 + 1, y0, down), (x0 + 1, y0 + 1, left), (x0, y0 + 1, up)]
        scene = spin if rng.random() < 0.5 else [(x0, y0, down), (x0, y0 + 1, right), (x0 + 1, y0 + 1, up),
                                                   (x0 + 1, y0, left)]
    elif kind == "rot6":
        scene = [(x0, y0, right), (x0 + 1, y0, right), (x0 + 2, y0, down), (x0 + 2, y0 + 1, left),
                 (x0 + 1, y0 + 1, left), (x0, y0 + 1, up)]
    elif kind == "swap":
        scene = [(x0, y0, right), (x0 + 1, y0, left)]
    elif kind == "chain":
        scene = [(x0 + j, y0, right) for j in range(min(n, 4))]
    else:  # robots around one free cell (x0+1, y0+1), all facing it
        around = [(x0 + 1, y0, down), (x0 + 1, y0 + 2, up), (x0, y0 + 1, right), (x0 + 2, y0 + 1, left)]
        scene = [around[j] for j in rng.permutation(4)[:int(rng.integers(2, min(n, 4) + 1))]]
    taken = {(sx, sy) for sx, sy, _ in scene}
    if kind == "contest":
        taken.add((x0 + 1, y0 + 1))
    free = [(xx, yy) for yy in range(h) for xx in range(w) if (xx, yy) not in taken]
    rest = [free[j] for j in rng.choice(len(free), n - len(scene), replace=False)]
    order = rng.permutation(n)  # which robot ids get the scene, so ties see every id order
    cells = scene + [(xx, yy, int(rng.integers(0, 4))) for xx, yy in rest]
    st["carry"] = np.full(n, -1)
    for j, i in enumerate(order):
        st["x"][i], st["y"][i], st["dir"][i] = cells[j]
    staged = np.zeros(n, dtype=bool)
    staged[order[:len(scene)]] = True
    return st, staged


# ---- what happened, so the comparison is not vacuous ------------------------------------------------
def count_events(env: NumpyRwareVecEnv, before: dict, acts: np.ndarray, after_x, after_y, c: int, ev: Counter) -> None:
    x, y, d = np.asarray(before["x"]), np.asarray(before["y"]), np.asarray(before["dir"])
    fwd = acts == 1
    tx = np.where(fwd, np.clip(x + DX[d], 0, env.w - 1), x)
    ty = np.where(fwd, np.clip(y + DY[d], 0, env.h - 1), y)
    start = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(x, y))}
    moving = (tx != x) | (ty != y)
    moved = (after_x != x) | (after_y != y)
    targets = Counter((int(a), int(b)) for a, b, m in zip(tx, ty, moving) if m)
    ev["contested"] += sum(1 for v in targets.values() if v >= 2)
    shelves = {(int(a), int(b)) for a, b in zip(before["shelf_x"], before["shelf_y"])}
    for i in np.flatnonzero(moving):
        j = start.get((int(tx[i]), int(ty[i])))
        if before["carry"][i] >= 0 and (int(tx[i]), int(ty[i])) in shelves and (j is None or before["carry"][j] < 0):
            ev["cancelled"] += 1
        if j is None:
            continue
        if (int(tx[j]), int(ty[j])) == (int(x[i]), int(y[i])) and moving[j]:
            ev["swap"] += 1
        elif moved[i] and moved[j]:
            ev["chain"] += 1
        seen, p = {i}, j  # a moved rotation: following "the robot at my target" comes back to me
        while p is not None and p not in seen and moving[p]:
            seen.add(p)
            p = start.get((int(tx[p]), int(ty[p])))
        if p == i and len(seen) >= 3 and moved[i]:
            ev[f"rotation{len(seen)}"] += 1


def lockstep(name: str, n: int, k: int, steps: int, max_steps: int, policy: str, seed: int,
             kwargs: dict | None = None) -> Counter:
    settings = settings_from(EnvDescription(name, n, {"impl": "numpy", "max_steps": max_steps, **(kwargs or {})}))
    env = NumpyRwareVecEnv(settings, k)
    obs, _ = env.reset(seed)
    d = env.spec.obs_dim
    refs = [settings.warehouse() for _ in range(k)]
    for c, ref in enumerate(refs):
        local, _ = ref.reset(seed=seed + c)
        assert np.array_equal(obs[c], full_rows(ref, local, d)), (name, "reset", c)
        assert_same_state(env.get_state(c), ref_state(ref), (name, "reset", c))
    rng = np.random.default_rng(seed + 1000)
    staged = np.zeros((k, n), dtype=bool)
    ev: Counter = Counter()
    for t in range(1, steps + 1):
        if policy == "staged" and t % 6 == 1:
            for c, ref in enumerate(refs):
                st, staged[c] = stage(env, c, rng)
                ours = env.set_state(c, **st)
                set_ref_state(ref, st)
                assert np.array_equal(ours, full_rows(ref, [ref._make_obs(a) for a in ref.agents], d)), (name, t, c)
        acts = policy_actions(policy, env, rng, staged)
        before = [env.get_state(c) for c in range(k)]
        fallbacks = env.fallback_copies
        out = env.step(acts)
        ev["networkx_ties"] += env.fallback_copies - fallbacks
        for c, ref in enumerate(refs):
            local, rew, done, _, _ = ref.step(acts[c].tolist())
            where = (name, policy, t, c)
            assert np.array_equal(out.final_obs[c], full_rows(ref, local, d)), where
            assert np.array_equal(out.reward[c], np.asarray(rew, dtype=np.float32)), (where, out.reward[c], rew)
            assert bool(out.done[c]) == done == (ref._cur_steps >= max_steps), where
            ref_st = ref_state(ref)
            count_events(env, before[c], acts[c], np.asarray(ref_st["x"]), np.asarray(ref_st["y"]), c, ev)
            ev["deliveries"] += int(np.count_nonzero(rew))
            ev["half_rewards"] += int(np.count_nonzero(np.asarray(rew) == 0.5))  # two_stage
            if done:
                ev["episodes"] += 1
                local, _ = ref.reset()
                assert np.array_equal(out.obs[c], full_rows(ref, local, d)), (where, "auto-reset")
            else:
                assert np.array_equal(out.obs[c], out.final_obs[c]), where
            assert_same_state(env.get_state(c), ref_state(ref), where)
            ev["copy_steps"] += 1
        assert np.array_equal(out.truncated, np.repeat(out.done[:, None], n, axis=1)) and not out.terminated.any()
    return ev


@pytest.mark.parametrize("policy", POLICIES)
def test_numpy_warehouse_is_rware(policy: str) -> None:
    total: Counter = Counter()
    for j, (name, n, k, steps, max_steps, *kwargs) in enumerate(CASES):
        total += lockstep(name, n, k, math.ceil(steps * SCALE), max_steps, policy, seed=100 * j + POLICIES.index(policy),
                          kwargs=kwargs[0] if kwargs else None)
    print(policy, dict(total))
    assert total["episodes"] >= len(CASES)  # every case crossed a time limit and an unseeded reset
    if policy in ("push", "staged"):
        assert total["contested"] >= 20 and total["networkx_ties"] >= 10 and total["chain"] >= 20
    if policy == "staged":
        assert total["rotation4"] >= 10 and total["rotation6"] >= 3 and total["swap"] >= 20
    if policy == "seek":
        assert total["deliveries"] >= 20 and total["cancelled"] >= 20 and total["half_rewards"] >= 3


def test_batched_env_equals_the_plain_adapter() -> None:
    """The registry's two implementations give the same VecStep stream (obs, final_obs, rewards, flags,
    episode records) with a slice offset, across time limits."""
    kw = {"max_steps": 40}
    plain = make_vec_env("rware-tiny-4ag", 4, 3, env_kwargs={**kw, "impl": "rware"})
    fast = make_vec_env("rware-tiny-4ag", 4, 3, env_kwargs={**kw, "impl": "numpy"})
    assert type(fast).__name__ == "NumpyRwareVecEnv" and fast.spec == plain.spec
    a, b = plain.reset(5), fast.reset(5)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))
    rng = np.random.default_rng(2)
    episodes = 0
    for _ in range(130):
        acts = rng.integers(0, 5, (3, 4))
        p, f = plain.step(acts), fast.step(acts)
        for field in ("obs", "reward", "terminated", "truncated", "active", "next_active", "final_obs", "done"):
            assert np.array_equal(getattr(p, field), getattr(f, field)), field
        assert p.episodes == f.episodes
        episodes += len(f.episodes)
    assert episodes == 9


def test_slices_and_errors() -> None:
    """A worker's slice (index_offset) is that slice of the whole batch, subprocess workers step it
    alike; bad input is refused."""
    whole = make_vec_env("rware-tiny-2ag", 2, 4, env_kwargs={"impl": "numpy"})
    part = NumpyRwareVecEnv(whole.settings, 2, index_offset=2)
    o_whole, _ = whole.reset(9)
    o_part, _ = part.reset(9)
    assert np.array_equal(o_whole[2:], o_part)
    acts = np.random.default_rng(0).integers(0, 5, (50, 4, 2))
    for a in acts:
        assert np.array_equal(whole.step(a).obs[2:], part.step(a[2:]).obs)
    workers = make_vec_env("rware-tiny-2ag", 2, 4, env_kwargs={"impl": "numpy"}, workers=2)
    try:
        whole.reset(9)
        assert np.array_equal(workers.reset(9)[0], o_whole)
        for a in acts[:20]:
            w, s = workers.step(a), whole.step(a)
            assert np.array_equal(w.obs, s.obs) and np.array_equal(w.reward, s.reward)
    finally:
        workers.close()
    with pytest.raises(ValueError, match="shape"):
        whole.step(np.zeros((4, 3), dtype=np.int64))
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        whole.step(np.full((4, 2), 5))
    with pytest.raises(RuntimeError, match="reset"):
        NumpyRwareVecEnv(whole.settings, 1).step(np.zeros((1, 2), dtype=np.int64))
    with pytest.raises(ValueError, match="unknown field 'speed'"):
        whole.set_state(0, speed=1)
    from hammer.envs.description import EnvConfigError

    with pytest.raises(EnvConfigError, match="env_kwargs.impl must be one of rware, numpy"):
        make_vec_env("rware-tiny-2ag", 2, 1, env_kwargs={"impl": "jax"})


def test_hammer_train_is_the_same_run_with_either_impl(tmp_path) -> None:
    """The trainer (in process, as `hammer train` runs it) on the preset with the same seed gives the
    same metrics.csv (all but wall_time) and, after its PPO updates, the same weights bit for bit with
    impl=numpy and impl=rware. Rewards are sparse in short episodes, so the weights are the sharp
    check: one different observation value or action anywhere in the run would move them."""
    import csv

    from safetensors.numpy import load as load_safetensors

    from tests.runtime_helpers import trained_run

    runs = {impl: trained_run(tmp_path / impl, ("variant=hammer", "seed=3", "episodes=12", "env_kwargs.max_steps=100",
                                                "num_envs=4", "rollout_steps=50", f"env_kwargs.impl={impl}",
                                                "torch_threads=1"), preset="rware-tiny-4ag")
            for impl in ("numpy", "rware")}

    def rows(run):
        with open(run / "metrics.csv", newline="") as f:
            return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]

    a, b = rows(runs["numpy"]), rows(runs["rware"])
    assert len(a) == 12 and a == b
    for part in ("local", "central"):
        wa = load_safetensors((runs["numpy"] / "final" / f"{part}.safetensors").read_bytes())
        wb = load_safetensors((runs["rware"] / "final" / f"{part}.safetensors").read_bytes())
        assert wa.keys() == wb.keys() and wa
        for key in wa:
            np.testing.assert_array_equal(wa[key], wb[key], err_msg=f"{part}/{key}")
