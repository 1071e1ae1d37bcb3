"""The local view (`envs.local_view`): what local agents may see of cn, the central agent unchanged."""

from __future__ import annotations

import csv
import itertools
import json

import numpy as np
import pytest
from hammer.envs.local_view import LocalView, SpreadRadiusView, local_view_for
from hammer.envs.registry import make_vec_env
from hammer.envs.spread import VecSimpleSpread
from hammer.learning.config import merge_config
from hammer.learning.sampling import ActingStreams
from hammer.learning.team import Team

from tests.runtime_helpers import CN3_RL, CN3_SET_VIEW, UP_CN3_SET_VIEW, trained_run, up_run


def _expected_mask(env: VecSimpleSpread, radius: float) -> np.ndarray:
    """(K, N, 2N-1) visibility computed from the world state itself (landmarks, then others in
    index order), independently of the observation layout the view reads."""
    p, lm = env.pos.astype(np.float32), env.landmarks.astype(np.float32)  # obs are float32 casts
    k, n = p.shape[:2]
    vis = np.zeros((k, n, 2 * n - 1), dtype=bool)
    for i in range(n):
        d_lm = np.linalg.norm((lm - p[:, i:i + 1]).astype(np.float64), axis=-1)
        others = [j for j in range(n) if j != i]
        d_ag = np.linalg.norm((p[:, others] - p[:, i:i + 1]).astype(np.float64), axis=-1)
        vis[:, i] = np.concatenate([d_lm, d_ag], axis=1) < radius
    return vis


@pytest.mark.parametrize("radius", [0.0, 0.4, 0.9, 1.6])
def test_radius_view_masks_exactly_the_far_landmarks_and_agents(radius):
    k, n = 16, 3
    env = VecSimpleSpread(k, n_agents=n, obs_radius=radius)
    obs, _ = env.reset(5)
    rng = np.random.default_rng(0)
    view = SpreadRadiusView(n, radius)
    seen_some = seen_hidden = False
    for _ in range(30):  # crosses an auto-reset
        vis = _expected_mask(env, radius)
        masked = view(obs)
        assert masked.shape == obs.shape and masked.dtype == np.float32
        np.testing.assert_array_equal(masked[..., :4], obs[..., :4])  # own velocity and position
        np.testing.assert_array_equal(masked[..., 4 + 2 * (2 * n - 1):], 0.0)  # comm slots stay 0
        rel, mrel = obs[..., 4:4 + 2 * (2 * n - 1)].reshape(k, n, -1, 2), masked[..., 4:4 + 2 * (2 * n - 1)].reshape(
            k, n, -1, 2)
        # the float64 distance from the state and the view's float32 reading agree except at the border
        border = np.abs(np.linalg.norm(rel.astype(np.float64), axis=-1) - radius) < 1e-5
        np.testing.assert_array_equal(mrel[vis & ~border], rel[vis & ~border])
        np.testing.assert_array_equal(mrel[~vis & ~border], 0.0)
        seen_some |= bool(vis.any())
        seen_hidden |= bool((~vis).any())
        np.testing.assert_array_equal(view(masked), masked)  # idempotent
        obs = env.step(rng.integers(0, 5, (k, n))).obs
    assert seen_hidden
    assert seen_some == (radius > 0)


def test_off_and_huge_radius_are_the_full_view():
    env = VecSimpleSpread(4, n_agents=3)
    obs, _ = env.reset(1)
    off = local_view_for("cn", 3, {})
    assert type(off) is LocalView and off(obs) is obs  # the default path does not even copy
    np.testing.assert_array_equal(SpreadRadiusView(3, 100.0)(obs), obs)
    assert type(local_view_for("cn", 3, {"obs_radius": 0.5}, joint_obs=True)) is LocalView  # centralised


def test_bad_radius_names_the_option():
    with pytest.raises(ValueError, match="obs_radius"):
        VecSimpleSpread(2, n_agents=3, obs_radius=-1.0)
    with pytest.raises(ValueError, match="observe_others"):
        VecSimpleSpread(2, n_agents=3, obs_radius=0.5, observe_others=False)
    with pytest.raises(Exception, match="obs_radius"):
        make_vec_env("cn", 3, 2, env_kwargs={"obs_radius": "far"})


def test_team_masks_local_inputs_but_not_the_central_state():
    """With obs_radius the central agent's global state is built from the full observations, and
    the local policy acts exactly as it would on the masked observations."""
    base = merge_config(preset="cn3", extra={"variant": "hammer", "num_envs": 8})
    radius = merge_config(preset="cn3", extra={"variant": "hammer", "num_envs": 8,
                                               "env_kwargs": {"obs_radius": 0.5}})
    env = make_vec_env("cn", 3, 8, env_kwargs=dict(radius.env_kwargs))
    obs, _ = env.reset(3)
    t_full, t_view = Team(base, env.spec), Team(radius, env.spec)  # same seed: same weights
    prev = t_full.zero_prev_actions(8)
    s_full, s_view = t_full.global_state(obs, prev), t_view.global_state(obs, prev)
    np.testing.assert_array_equal(s_view, s_full)
    assert s_view[:, : env.spec.obs_dim].tolist() == obs[:, 0].tolist()  # agent 0's full obs, unmasked
    masked = t_view.local_view(obs)
    assert not np.array_equal(masked, obs)
    msg = np.zeros((8, 3, t_full.msg_dim), dtype=np.float32)
    a_view = t_view.local_act(obs, msg, ActingStreams(0, 3))
    a_ref = t_full.local_act(masked, msg, ActingStreams(0, 3))
    for x, y in zip(a_view, a_ref, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(t_view.local_values(obs, msg), t_full.local_values(masked, msg))


def _metric_column(run_dir) -> list[float]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [float(r["paper_metric"]) for r in csv.DictReader(f)]


def test_up_with_a_local_view_completes_and_matches_the_trainer(tmp_path):
    """The env host masks what it sends each local agent as the trainer masks its local inputs: the
    distributed run's episodes equal the in-process trainer's; and the view changes the run. The run
    is the session's UP_CN3_SET_VIEW (also test_runtime_up's set-net run: the set net is only the
    central agent's forward, whose state the view leaves full), so the full view's reference is the
    trainer with the set net."""
    up = up_run(tmp_path / "up", UP_CN3_SET_VIEW)
    assert json.loads((up / "config.json").read_text())["env_kwargs"]["obs_radius"] == 0.6
    # the trainer in process as the CLI runs it, with the view and without it
    tr = trained_run(tmp_path / "train", (*CN3_SET_VIEW, "episodes=70"))
    full = trained_run(tmp_path / "full", (*CN3_RL, "central_net=set", "episodes=70"))
    links = json.loads((up / "summary.json").read_text())["links"]
    assert links["msg_fallback_copies"] == 0 and links["default_actions"] == 0
    a, b, c = _metric_column(up), _metric_column(tr), _metric_column(full)
    assert len(a) == len(b) == len(c) == 70
    assert a == pytest.approx(b, abs=1e-5)
    assert a[32:] != pytest.approx(c[32:], abs=1e-3)  # after the first update the masked team acts differently
    # every run's summary says which CPU path computed it (learning.host_info)
    host = json.loads((tr / "summary.json").read_text())["host"]
    assert host["cpu"]["logical_cpus"] >= 1 and host["numpy"]["version"]
    assert host["torch"]["version"].startswith("2.") and host["torch"]["num_threads"] == 1
    up_host = json.loads((up / "summary.json").read_text())["host"]
    assert up_host["torch"] is None  # the env host never loads torch; the learner reports it
    assert json.loads((up / "learner_summary.json").read_text())["host"]["torch"]["cpu_capability"]


def test_hidden_fraction_is_the_fixed_x_axis_of_the_plan():
    from hammer.envs.local_view import spread_hidden_fraction

    h = [spread_hidden_fraction(r, copies=64, steps=25) for r in (100.0, 1.5, 1.0, 0.6, 0.3, 0.0)]
    assert h[0] == 0.0 and h[-1] == 1.0
    assert all(a < b for a, b in itertools.pairwise(h))  # more hidden as the radius shrinks
