"""The message analysis (experiments/messages.py, `hammer messages`): real env, real weights.

Tiny real training runs (cn3 with observe_others=false, as the teams analysed) give the local
policies; a planted central agent, whose message is by construction the other agents' relative
positions, shows that the probe finds a signal that is there, and a real random-message team that it
finds none where there is none. The cross-validation's split by episode is shown to matter, the
targets are checked against the env's own observation, and the in-process acting against the
runtime's published evaluation of an archived team.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hammer.envs.local_view import SpreadRadiusView
from hammer.envs.spread import VecSimpleSpread
from hammer.experiments.messages import (
    TeamActor,
    analyse_team,
    hidden_targets,
    initial_central_weights,
    probe_recording,
    recording_targets,
)
from hammer.experiments.probes import Moments, cv_r2, episode_folds, r2_of, ridge
from hammer.learning.config import merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import train
from safetensors.numpy import load_file, save_file
from typer.testing import CliRunner

from hammer.cli import app

ROOT = Path(__file__).resolve().parents[1]
OWNOBS = ROOT / "docs/results/runs/cn3-ownobs"
pytestmark = pytest.mark.timeout(120)


def _train(d: Path, variant: list[str], env: str = "env_kwargs.observe_others=false") -> Path:
    cfg = merge_config("cn3", overrides=["num_envs=8", "rollout_steps=25", "epochs=1", "minibatches=2",
                                         "episodes=16", "seed=0", env, *variant])
    train(cfg, RunDir.create(d, cfg), tensorboard=False)
    return d


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Two real trained teams (a few updates each): HAMMER backprop mode and random messages."""
    root = tmp_path_factory.mktemp("teams")
    return {"backprop": _train(root / "bp", ["variant=hammer", "central_mode=backprop"]),
            "random": _train(root / "random", ["variant=random"])}


def _plant(run: Path, dst: Path, obs_dim: int = 10) -> Path:
    """The backprop team with its central agent replaced: agent i's message is tanh of 0.2 × (p_j − p_i)
    for its two others j (x, y each), read off the global state (each agent's observation holds its own
    position at columns 2:4), so the message carries H_agents by construction, nearly linearly."""
    shutil.copytree(run, dst)
    cfg = json.loads((run / "config.json").read_text())
    n, d, m = 3, obs_dim, 4
    state_dim = n * d + n * 5  # observations + one-hot previous actions
    enc = np.zeros((2 * n, state_dim), np.float32)
    for k in range(n):
        enc[2 * k, k * d + 2] = enc[2 * k + 1, k * d + 3] = 0.2  # h = tanh(0.2 p_k)
    heads = np.zeros((n, 2 * n, m), np.float32)
    for i in range(n):
        for slot, j in enumerate(j for j in range(n) if j != i):
            for c in range(2):
                heads[i, 2 * j + c, 2 * slot + c] += 1.0
                heads[i, 2 * i + c, 2 * slot + c] -= 1.0
    save_file({"encoder.layers.0.weight": enc, "encoder.layers.0.bias": np.zeros(2 * n, np.float32),
               "head_weight": heads, "head_bias": np.zeros((n, m), np.float32)}, str(dst / "final/central.safetensors"))
    assert cfg["central_mode"] == "backprop"  # deterministic messages: the mean is what is sent
    return dst


def test_probe_finds_a_planted_message_and_nothing_in_random_messages(runs, tmp_path):
    planted = TeamActor(_plant(runs["backprop"], tmp_path / "planted")).rollout(0, 40, record=True)
    acts = recording_targets(planted, None)["X_actions"].values.reshape(40, 25, 3, 2, 2)
    assert not acts[:, 0].any() and set(np.abs(acts[:, 1:]).sum(-1).ravel()) == {0.0, 1.0}  # no-op or one axis
    got = probe_recording(planted, None)["H_agents"]
    assert got["u"] > 0.9 and got["gain"] > 0.3, got  # the receiver's own observation lacks it
    rnd = probe_recording(TeamActor(runs["random"]).rollout(0, 40, record=True), None)
    for target in ("H_agents", "H_landmark", "V"):
        assert abs(rnd[target]["gain"]) < 0.02 and rnd[target]["u"] < 0.02, (target, rnd[target])


def test_the_untrained_reference_is_the_runs_own_initialisation(runs):
    """The exploratory untrained central agent is the run's checkpoint 0 (written before any update)."""
    cfg = merge_config(base=json.loads((runs["backprop"] / "config.json").read_text()))
    ckpt = load_file(str(runs["backprop"] / "checkpoints/ckpt_0000000.safetensors"))
    init = initial_central_weights(cfg)
    assert init and all(np.array_equal(v, ckpt[f"central/{k}"]) for k, v in init.items())
    on_gpu = initial_central_weights(cfg.model_copy(update={"device": "cuda"}))  # a GPU run, analysed anywhere
    assert all(np.array_equal(v, on_gpu[k]) for k, v in init.items())
    final = load_file(str(runs["backprop"] / "final/central.safetensors"))
    assert not all(np.array_equal(v, final[k]) for k, v in init.items())  # training moved it


def test_cv_splits_by_episode_and_a_row_split_would_leak():
    """A per-episode constant target and per-episode constant features, unrelated across episodes: a
    near-unpenalised probe memorises its training episodes, so held-out rows of those episodes score
    R² ≈ 1 and only an episode split gives the honest ≤ 0."""
    rng = np.random.default_rng(0)
    episode = np.repeat(np.arange(10), 25)
    x = rng.normal(size=(10, 12))[episode] + 1e-3 * rng.normal(size=(250, 12))
    y = rng.normal(size=10)[episode]
    folds = episode_folds(episode)
    assert sorted(np.concatenate(folds).tolist()) == list(range(250))
    for test in folds:
        assert not set(episode[test]) & set(np.delete(episode, test))
    rows = rng.permutation(250) % 5  # a fold id per row, ignoring episodes
    assert cv_r2(x, y, episode, alphas=(1e-6,), outer=rows) > 0.9
    assert cv_r2(x, y, episode, alphas=(1e-6,)) < 0.1
    assert cv_r2(x, y, episode) < 0.1  # and with alpha chosen by the nested CV


def test_ridge_from_moments_equals_a_direct_fit_on_the_rows():
    """The CV's fits come from summed moments; the same fit made directly on the rows (standardise,
    solve the penalised normal equations, score the held-out rows) must agree."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 6)) * [1, 2, 3, 0.5, 1, 4] + 3
    y = x @ rng.normal(size=(6, 2)) + rng.normal(size=(300, 2))
    train, test = np.arange(200), np.arange(200, 300)
    z = np.concatenate([x, y], axis=1)
    (w, b), = ridge(Moments.of(z[train]), 6, [0.3])
    mu, sd = x[train].mean(0), x[train].std(0)
    xs = (x[train] - mu) / sd
    ws = np.linalg.solve(xs.T @ xs / 200 + 0.3 * np.eye(6), xs.T @ (y[train] - y[train].mean(0)) / 200)
    pred = (x[test] - mu) / sd @ ws + y[train].mean(0)
    np.testing.assert_allclose(x[test] @ w + b, pred, rtol=1e-9, atol=1e-9)
    direct = np.mean(1 - np.square(y[test] - pred).sum(0) / np.square(y[test] - y[test].mean(0)).sum(0))
    assert r2_of(Moments.of(z[test]), 6, w, b) == pytest.approx(direct, abs=1e-9)


def test_targets_from_the_world_state_match_the_observation():
    env = VecSimpleSpread(16, 3)
    obs, _ = env.reset(7)
    rng = np.random.default_rng(7)
    for _ in range(9):
        obs = env.step(rng.integers(0, 5, (16, 3))).obs
    pos, lm = env.pos.copy(), env.landmarks.copy()
    tg = hidden_targets(pos, lm, obs, None)
    np.testing.assert_allclose(tg["H_agents"].values.reshape(16, 3, 4), obs[..., 10:14], atol=1e-6)
    lm_rel = obs[..., 4:10].reshape(16, 3, 3, 2)
    near = np.linalg.norm(lm_rel, axis=-1).argmin(-1)
    np.testing.assert_allclose(tg["V"].values[:, :, 0], np.take_along_axis(lm_rel, near[..., None, None], 2)[:, :, 0],
                               atol=1e-6)
    for k in range(16):
        for i in range(3):
            claimed = {int(near[k, j]) for j in range(3) if j != i}
            free = [l for l in range(3) if l not in claimed]
            want = min(free, key=lambda l: np.linalg.norm(lm_rel[k, i, l]))
            np.testing.assert_allclose(tg["H_landmark"].values[k, i, 0], lm_rel[k, i, want], atol=1e-6)
    seen = SpreadRadiusView(3, 0.6)(obs)[..., 4:14].reshape(16, 3, 5, 2)
    hid = hidden_targets(pos, lm, obs, 0.6)
    np.testing.assert_array_equal(hid["H_agents"].mask, np.all(seen[:, :, 3:] == 0, axis=-1))
    assert hid["H_agents"].mask.any() and not hid["H_agents"].mask.all()


def _published(team: str, drop: float, seed: int) -> float:
    with open(ROOT / "docs/results/faults-ownobs/hammer/sweep.csv", newline="") as f:
        return next(float(r["paper_metric"]) for r in csv.DictReader(f)
                    if r["team"] == team and float(r["drop"]) == drop and int(r["seed"]) == seed)


def test_acting_reproduces_the_runtime_and_a_cut_zeroes_one_message():
    """The archived cn3-ownobs seed-0 team here gives the figure the real multi-process runtime published
    (`hammer faults sweep`, docs/results/faults-ownobs): with messages, and with every message dropped
    (zeros fallback) as a cut of all agents."""
    actor = TeamActor(OWNOBS / "cn3-hammer-rl-env_kwargs_observe_others=false-s0")
    assert actor.rollout(0, 500).mean() == pytest.approx(_published("hammer-s0", 0.0, 0), abs=1e-9)
    assert actor.rollout(0, 500, cut=(0, 1, 2)).mean() == pytest.approx(_published("hammer-s0", 1.0, 0), abs=1e-9)
    full, cut = actor.rollout(1, 32, record=True), actor.rollout(1, 32, cut=(1,), record=True)
    assert not cut.msgs[:, :, 1].any() and full.msgs[:, :, 1].any()
    np.testing.assert_array_equal(cut.msgs[:, 0, [0, 2]], full.msgs[:, 0, [0, 2]])  # same first-step draws


def test_cli_writes_tables_json_figure_and_reuses_results(runs, tmp_path):
    out, fig = tmp_path / "m", tmp_path / "ep.png"
    args = ["messages", str(runs["backprop"]), str(runs["random"]), "--episodes", "10", "--out", str(out),
            "--figure", str(fig)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    md = out.with_suffix(".md").read_text()
    assert "hammer-backprop-m4" in md and "random-m4" in md and "Message cut per agent" in md
    assert json.loads(out.with_suffix(".json").read_text())["episodes"] == 10
    assert fig.stat().st_size > 10_000  # backprop stands in for hammer-rl when a setting has none
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0 and again.output.count("cached") == 2, again.output
    assert out.with_suffix(".md").read_text() == md
    js, part = out.with_suffix(".json"), out.with_suffix(".partial.json")
    assert not part.exists()  # removed once the analysis finished
    js.rename(part)  # as if cut short after both teams: the resumed run computes nothing
    resumed = CliRunner().invoke(app, args)
    assert resumed.exit_code == 0 and resumed.output.count("cached") == 2 and not part.exists(), resumed.output
    assert out.with_suffix(".md").read_text() == md
    parallel = CliRunner().invoke(app, [*args, "--fresh", "--jobs", "2"])  # two processes, recomputed
    assert parallel.exit_code == 0 and parallel.output.count("analysed") == 2, parallel.output
    assert out.with_suffix(".md").read_text() == md
    only = CliRunner().invoke(app, [*args[:-2], "--teams", "random"])
    assert only.exit_code == 0 and only.output.count("cached") == 1, only.output
    assert "hammer-backprop" not in out.with_suffix(".md").read_text()


def test_everything_visible_the_same_planted_message_adds_nothing(tmp_path):
    """The plan's negative reference (cn3, full view): the receiver sees the other agents itself, so the
    planted message that carries their positions adds nothing over its observation."""
    run = _train(tmp_path / "full", ["variant=hammer", "central_mode=backprop"], env="env_kwargs.observe_others=true")
    planted = _plant(run, tmp_path / "planted", obs_dim=18)
    got = probe_recording(TeamActor(planted).rollout(0, 40, record=True), None)["H_agents"]
    assert got["u"] > 0.9 and got["o"] > 0.99 and abs(got["gain"]) < 0.01, got


def test_a_dose_grid_team_is_probed_only_where_the_radius_hides(tmp_path):
    """A team of the dose-response grid (obs_radius): H_agents rows are those the local view masks."""
    run = _train(tmp_path / "dose", ["variant=hammer", "central_mode=rl"], env="env_kwargs.obs_radius=0.6")
    res = analyse_team(run, [0], 10, keep_episode=True)
    rows = res["probes"]["H_agents"]["rows"]
    assert 0 < rows < 10 * 25 * 3 * 2 and np.isfinite(res["probes"]["H_agents"]["gain"])
    assert "env_kwargs.obs_radius=0.6" in res["setting"] and set(res["cut"]) == {
        "agent 0", "agent 1", "agent 2", "all"}


def test_the_plans_comparisons_and_holm_family_over_settings_and_targets():
    """hammer-rl vs random per setting and tested target (never backprop, never the control V), Holm
    across all of them: a second setting doubles the family, so the smallest p is multiplied by 4."""
    from hammer.experiments.messages_report import comparisons

    results = json.loads((ROOT / "docs/results/messages-cn3-ownobs.json").read_text())["results"]
    one = comparisons(results)
    assert [(c.target, c.a, c.b, c.n_a, c.n_b) for c in one] == [
        ("H_agents", "hammer-rl-m4", "random-m4", 10, 5), ("H_landmark", "hammer-rl-m4", "random-m4", 10, 5)]
    two = comparisons(results + [{**r, "setting": r["setting"] + " (copy)"} for r in results])
    assert len(two) == 4
    smallest = min(two, key=lambda c: c.p)
    assert smallest.p_holm == pytest.approx(4 * smallest.p)


def test_the_cut_table_says_which_way_a_cut_matters():
    """A CI below 0 (the team does better without the message, as random-message teams do at full
    view) is not reported as "the cut costs"; the archived full-view and r=0 teams give one of each."""
    from hammer.experiments.messages_report import cut_table

    results = json.loads((ROOT / "docs/results/messages.json").read_text())["results"]
    rows = {(r.split("|")[1].strip(), r.split("|")[2].strip(), r.split("|")[3].strip()): r.split("|")[7].strip()
            for r in cut_table(results)[2:]}
    assert rows[("cn N=3 (env_kwargs.obs_radius=0.0)", "hammer-rl-m4", "all agents (check)")] == "yes: the cut costs"
    assert rows[("cn N=3", "random-m4", "all agents (check)")] == "yes, but the cut helps"


def test_analyse_saves_each_finished_team_so_a_cut_short_analysis_resumes(runs):
    from hammer.experiments.messages_report import analyse

    saved: list[list[str]] = []
    results = analyse([runs["backprop"], runs["random"]], [0], 10, save=lambda done: saved.append(
        [r["run"] for r in done]))
    assert saved == [[str(runs["backprop"])], [str(runs["backprop"]), str(runs["random"])]]
    again = analyse([runs["backprop"], runs["random"]], [0], 10, previous=results[:1],
                    save=lambda done: saved.append(len(done)))
    assert saved[-1] == 2 and len(saved) == 3 and again == results  # one cached, one computed and saved
