"""The message analysis on warehouse teams (rware; plan-messages.md, addendum of 2026-12-03): real rware,
an archived trained team of the warehouse comparison, real weights.

The targets are checked against rware's own objects (robots, shelves, request queue, what each robot
carries), not against the observation they are read from; a planted central agent whose message is the
other robot's cell shows the probe finds a signal that is there and the trained team's message, which
says nothing measurable about it (the smoke test of the plan's addendum), does not.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hammer.envs.registry import make_vec_env
from hammer.experiments.messages import (
    TeamActor,
    WarehouseLayout,
    analyse_team,
    probe_recording,
    warehouse_targets,
)
from safetensors.numpy import save_file

ROOT = Path(__file__).resolve().parents[1]
TEAM = ROOT / "docs/results/runs/rware-cmp/rware-tiny-2ag-hammer-rl-ep2000-s0"
pytestmark = pytest.mark.timeout(180)


def _expected(wh, i: int, sr: int) -> dict:
    """H_shelf, V and H_agents of robot i from rware's objects (plan-messages.md, the addendum)."""
    me = wh.agents[i]
    carried = {a.carrying_shelf.id for a in wh.agents if a.carrying_shelf is not None}
    free = [s for s in wh.shelfs if s in wh.request_queue and s.id not in carried]
    out = {}
    if free and me.carrying_shelf is None:
        near = min(free, key=lambda s: (np.hypot(s.x - me.x, s.y - me.y), wh.shelfs.index(s)))
        rel = (near.x - me.x, near.y - me.y)
        out["H_shelf" if max(map(abs, rel)) > sr else "V"] = rel
    out["H_agents"] = [((a.x - me.x, a.y - me.y), max(abs(a.x - me.x), abs(a.y - me.y)) > sr)
                       for a in wh.agents if a is not me]
    return out


def test_warehouse_targets_match_rwares_own_state():
    n, k = 4, 8
    env = make_vec_env("rware", n, k, env_kwargs={"size": "tiny"})
    layout = WarehouseLayout(env.local_dim, env.n_shelves, env.n_goals, env.settings.sensor_range)
    obs, _ = env.reset(3)
    rng = np.random.default_rng(3)
    seen = {"H_shelf": 0, "V": 0, "carrying": 0, "far": 0, "near": 0}
    for _ in range(120):
        obs = env.step(rng.integers(0, 5, (k, n))).obs
        tg = warehouse_targets(obs, layout)
        for c, wh in enumerate(env.envs):
            for i in range(n):
                want = _expected(wh, i, layout.sensor_range)
                seen["carrying"] += wh.agents[i].carrying_shelf is not None
                for name in ("H_shelf", "V"):
                    assert tg[name].mask[c, i, 0] == (name in want), (name, c, i)
                    if name in want:
                        np.testing.assert_array_equal(tg[name].values[c, i, 0], want[name])
                        seen[name] += 1
                for slot, (rel, hidden) in enumerate(want["H_agents"]):
                    np.testing.assert_array_equal(tg["H_agents"].values[c, i, slot], rel)
                    assert tg["H_agents"].mask[c, i, slot] == hidden
                    seen["far" if hidden else "near"] += 1
    env.close()
    assert min(seen.values()) > 0, seen  # every case happened: the comparison is not vacuous


def _plant_other_robot(run: Path, dst: Path) -> Path:
    """The archived N = 2 team with its central agent replaced by one whose message to robot i is
    tanh(0.05 × cell) of both robots (x, y each), read off the global state (robot k's cell at columns
    k·D, k·D + 1), sent deterministically (backprop mode: the mean is what is sent)."""
    shutil.copytree(run, dst)
    cfg = json.loads((dst / "config.json").read_text())
    cfg["central_mode"] = "backprop"
    (dst / "config.json").write_text(json.dumps(cfg))
    n, d, m = 2, 171, 4
    enc = np.zeros((2 * n, n * d + n * 5), np.float32)
    for r in range(n):
        enc[2 * r, r * d] = enc[2 * r + 1, r * d + 1] = 0.05
    heads = np.tile(np.eye(2 * n, m, dtype=np.float32), (n, 1, 1))
    save_file({"encoder.layers.0.weight": enc, "encoder.layers.0.bias": np.zeros(2 * n, np.float32),
               "head_weight": heads, "head_bias": np.zeros((n, m), np.float32)}, str(dst / "final/central.safetensors"))
    return dst


def test_the_probe_finds_a_planted_robot_and_not_what_the_trained_team_does_not_say(tmp_path):
    actor = TeamActor(TEAM)
    layout = actor.view()
    assert layout == WarehouseLayout(71, 32, 2, 1)
    planted = TeamActor(_plant_other_robot(TEAM, tmp_path / "planted"))
    got = probe_recording(planted.rollout(0, 16, record=True), layout)
    real = probe_recording(actor.rollout(0, 16, record=True), layout)
    assert got["H_agents"]["gain"] > 0.3, got["H_agents"]
    assert abs(real["H_agents"]["gain"]) < 0.05, real["H_agents"]


def test_a_warehouse_team_is_analysed_with_its_targets_and_cuts():
    res = analyse_team(TEAM, [1], 16)
    assert set(res["probes"]) == {"H_agents", "H_shelf", "V"}
    assert set(res["cut"]) == {"agent 0", "agent 1", "all"} and res["episodes"] == 16
    assert all(np.isfinite(res["probes"][t]["gain"]) for t in ("H_agents", "H_shelf"))
    assert {"probes_mean", "probes_initial"} <= set(res)  # hammer rl: the exploratory references too
