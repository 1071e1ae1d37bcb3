"""A seed of a seed-batched run (`hammer train --seeds`) is the same run as that seed alone.

Bit-identity is not expected (the batched kernels sum in another order), so the checks are: the
first rollout (taken with the initial weights) is identical, the weights and Adam state after the
first updates agree with the solo run's to a tolerance measured on this machine (largest
difference over every variant of cn3 after two updates, weights and Adam state: 6e-8 absolute;
the test allows 1e-5), every seed's directory is an ordinary run directory that `hammer train --resume` continues,
and over eight seeds the final metrics of batched and solo runs are statistically the same.
Multiwalker (masked losses, seeds finishing apart) and `hammer sweep`'s grouping are checked too.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from hammer.learning.config import ConfigError, merge_config
from hammer.learning.rundir import RunDir
from hammer.learning.seed_batch import parse_seeds, train_seeds
from hammer.learning.trainer import train
from scipy import stats

from tests.runtime_helpers import COMPILE_NETS

VARIANTS = [("hammer", "rl"), ("hammer", "backprop"), ("il", "rl"), ("random", "rl"), ("centralized", "rl")]
SMALL = ["num_envs=8", "checkpoint_every=1", "epochs=4", "minibatches=2"]
TOL = 1e-5


def _cfg(variant: str, mode: str, seed: int, episodes: int, extra: list[str] | None = None):
    return merge_config("cn3", None, SMALL + (extra or []), {"variant": variant, "central_mode": mode,
                                                             "seed": seed, "episodes": episodes})


def _metrics(path: Path) -> list[tuple[str, ...]]:
    with open(path / "metrics.csv", newline="") as f:
        return [tuple(r[:5]) for r in csv.reader(f)][1:]


def _ckpt(path: Path, update: int) -> dict[str, torch.Tensor]:
    return RunDir.load_checkpoint(path / "checkpoints" / f"ckpt_{update:07d}")[0]


@pytest.mark.parametrize(("variant", "mode"), VARIANTS)
def test_batched_seed_matches_solo_run(tmp_path: Path, variant: str, mode: str) -> None:
    _check_batched_matches_solo(tmp_path, variant, mode)


@pytest.mark.parametrize("mode", ["rl", "backprop"])
def test_batched_seed_matches_solo_run_with_the_set_central_net(tmp_path: Path, mode: str) -> None:
    _check_batched_matches_solo(tmp_path, "hammer", mode, ["central_net=set"])


def _check_batched_matches_solo(tmp_path: Path, variant: str, mode: str, extra: list[str] | None = None,
                                seeds: list[int] | None = None, solo_eager: bool = False) -> None:
    seeds = seeds or [0, 1, 2]
    cfgs = [_cfg(variant, mode, s, 24, extra) for s in seeds]  # 8 episodes per update: updates 0, 1, 2
    train_seeds(cfgs, [RunDir.create(tmp_path / f"b{s}", c) for s, c in zip(seeds, cfgs)], tensorboard=False)
    for s, cfg in zip(seeds, cfgs):
        solo_cfg = cfg.model_copy(update={"compile": False}) if solo_eager else cfg
        train(solo_cfg, RunDir.create(tmp_path / f"s{s}", solo_cfg), tensorboard=False)
        batched, solo = tmp_path / f"b{s}", tmp_path / f"s{s}"
        assert sorted(p.name for p in batched.iterdir()) == sorted(p.name for p in solo.iterdir())
        assert _metrics(batched)[:8] == _metrics(solo)[:8]  # the first rollout: initial weights
        for update in (1, 2):
            b, o = _ckpt(batched, update), _ckpt(solo, update)
            assert sorted(b) == sorted(o)
            worst = max(float((b[k].double() - o[k].double()).abs().max()) for k in b)
            assert worst < TOL, (s, update, worst)
    # the seeds really are different runs
    assert _metrics(tmp_path / "b0") != _metrics(tmp_path / "b1")


@pytest.mark.slow
@pytest.mark.parametrize(("variant", "mode", "scope"), [("il", "rl", "step"), ("hammer", "rl", "epoch")])
def test_compiled_batched_seed_matches_its_solo_run(tmp_path: Path, variant: str, mode: str, scope: str) -> None:
    """compile=true: the batch acts through the fused acting graph under vmap and updates through
    the compiled graph over the stacked parameters, so a seed is its solo run up to rounding. Each
    compile_scope once: one graph per epoch (its shuffle and minibatch slices over the stacked
    seeds) on hammer, whose graph holds both networks; one per minibatch step on il, the cheaper
    compile. The solo runs are eager: a solo compiled run is its eager run up to
    rounding (tests/test_learning_compile.py, tests/test_fused_acting.py), so compiling them too
    would build two more graphs for nothing this check needs, and TOL covers both roundings. Two
    seeds, not three: what a third seed adds, stacking beyond a pair, the eager batches check."""
    _check_batched_matches_solo(tmp_path, variant, mode, ["compile=true", f"compile_scope={scope}", *COMPILE_NETS],
                                seeds=[0, 1], solo_eager=True)


def test_batched_seed_resumes_alone(tmp_path: Path) -> None:
    seeds = [3, 4]
    cfgs = [_cfg("hammer", "rl", s, 24) for s in seeds]
    train_seeds(cfgs, [RunDir.create(tmp_path / f"b{s}", c) for s, c in zip(seeds, cfgs)], tensorboard=False)
    rd, cfg = RunDir.open(tmp_path / "b4")
    cfg = merge_config(None, None, ["episodes=40"], base=cfg.model_dump(mode="json"))
    rd.write_config(cfg)
    summary = train(cfg, rd, resume=True, tensorboard=False)
    assert summary["episodes"] == 40 and len(_metrics(tmp_path / "b4")) == 40
    assert (tmp_path / "b4" / "final" / "local.safetensors").is_file()


def test_seed_batch_resumes_together(tmp_path: Path) -> None:
    """A batch stopped at its budget and resumed with a larger one continues every seed."""
    seeds = [0, 1]
    cfgs = [_cfg("il", "rl", s, 16) for s in seeds]
    dirs = [RunDir.create(tmp_path / f"b{s}", c) for s, c in zip(seeds, cfgs)]
    train_seeds(cfgs, dirs, tensorboard=False)
    cfgs = [merge_config(None, None, ["episodes=32"], base=c.model_dump(mode="json")) for c in cfgs]
    for rd, c in zip(dirs, cfgs):
        rd.write_config(c)
    summaries = train_seeds(cfgs, [RunDir(tmp_path / f"b{s}") for s in seeds], resume=True, tensorboard=False)
    assert [s["episodes"] for s in summaries] == [32, 32]


def test_seed_batch_rejects_configs_that_differ_beyond_the_seed(tmp_path: Path) -> None:
    cfgs = [_cfg("il", "rl", 0, 16), _cfg("il", "rl", 1, 16, ["lr_local=1e-3"])]
    with pytest.raises(ConfigError, match="lr_local"):
        train_seeds(cfgs, [RunDir.create(tmp_path / f"b{i}", c) for i, c in enumerate(cfgs)], tensorboard=False)


def test_parse_seeds() -> None:
    assert parse_seeds("0-3,8") == [0, 1, 2, 3, 8]
    assert parse_seeds("5") == [5]
    for bad in ("3-1", "a", ""):
        with pytest.raises(ConfigError, match="--seeds"):
            parse_seeds(bad)


@pytest.mark.slow
def test_batched_and_solo_final_metrics_are_indistinguishable(tmp_path: Path) -> None:
    """Eight seeds of a short hammer-rl run, batched and solo: a Welch t-test and a two-sample KS
    test on the final metric (mean paper metric of the last 32 episodes) must not tell them apart
    (p > 0.05), and the batched runs must have learned as the solo ones did: better than the first
    rollout's metric."""
    seeds = list(range(8))
    cfgs = [_cfg("hammer", "rl", s, 96, ["checkpoint_every=50"]) for s in seeds]
    train_seeds(cfgs, [RunDir.create(tmp_path / f"b{s}", c) for s, c in zip(seeds, cfgs)], tensorboard=False)
    for s, cfg in zip(seeds, cfgs):
        train(cfg, RunDir.create(tmp_path / f"s{s}", cfg), tensorboard=False)

    def final(path: Path) -> float:
        return float(np.mean([float(r[2]) for r in _metrics(path)[-32:]]))

    def first(path: Path) -> float:
        return float(np.mean([float(r[2]) for r in _metrics(path)[:32]]))

    b = np.array([final(tmp_path / f"b{s}") for s in seeds])
    o = np.array([final(tmp_path / f"s{s}") for s in seeds])
    assert stats.ttest_ind(b, o, equal_var=False).pvalue > 0.05
    assert stats.ks_2samp(b, o).pvalue > 0.05
    start = np.array([first(tmp_path / f"b{s}") for s in seeds])
    assert b.mean() > start.mean()


def test_sweep_batches_points_that_differ_only_in_seed(tmp_path: Path) -> None:
    """Two seeds of one setting: one seed-batched process, two ordinary run directories; a second
    sweep skips them; a seed whose summary is lost resumes alone."""
    from hammer.experiments.sweep import expand, run_sweep, state_of

    pts = expand(["cn3"], ["il"], [0, 1], [("num_envs", ["4"]), ("rollout_steps", ["25"])])
    events: list[tuple[str, str]] = []
    res = run_sweep(pts, tmp_path, jobs=2, episodes=8, seed_batch=4, on_event=lambda k, n: events.append((k, n)))
    assert sorted(res.done) == sorted(p.name for p in pts) and not res.failed
    assert all(state_of(tmp_path / p.name) == "done" for p in pts)
    logs = [p.name for p in pts if "seed batch: log in" in (tmp_path / p.name / "train.log").read_text()]
    assert logs == [pts[1].name]  # the second seed points at its batch's log
    assert [k for k, _ in events].count("start") == 2 and len(events) == 4
    solo = pts[0]
    cfg = merge_config("cn3", None, ["num_envs=4", "rollout_steps=25"], {"variant": "il", "seed": 0, "episodes": 8})
    train(cfg, RunDir.create(tmp_path / "solo", cfg), tensorboard=False)
    assert _metrics(tmp_path / solo.name) == _metrics(tmp_path / "solo")  # first rollout: initial weights
    (tmp_path / solo.name / "summary.json").unlink()
    res2 = run_sweep(pts, tmp_path, jobs=2, episodes=8, seed_batch=4)
    assert res2.done == [solo.name] and res2.skipped == [pts[1].name]


@pytest.mark.parametrize("mode,workers", [("rl", 0), ("backprop", 2)])
def test_batched_mw_seed_matches_solo_run(tmp_path: Path, monkeypatch, mode: str, workers: int) -> None:
    """Multiwalker (walkers fall and drop out: masked losses, seeds finishing at different
    updates) batched vs alone, in both central modes and through the env worker pool: the same
    first rollout, the same weights and Adam state after updates 1 and 2.

    Measured (2026-12-03): worst difference 3e-8 after update 1 in both modes; it then grows by
    roughly 10x per update in backprop mode (5.7e-7, 4e-6, 3e-4, 2.7e-3 after updates 2-5) and
    far slower in rl mode (1.7e-6 after update 5): rounding amplified by training, which is why
    the check is at the first updates, as for cn (bit-identity is not expected)."""
    orig = RunDir.save_checkpoint
    monkeypatch.setattr(RunDir, "save_checkpoint", lambda self, *a, **k: orig(self, *a, **{**k, "keep": 100}))
    seeds = [0, 1]
    cfgs = [merge_config("mw3", None, ["num_envs=2", "rollout_steps=60", "checkpoint_every=1", "epochs=2",
                                       f"env_workers={workers}"],
                         {"variant": "hammer", "central_mode": mode, "seed": s, "episodes": 4}) for s in seeds]
    train_seeds(cfgs, [RunDir.create(tmp_path / f"b{s}", c) for s, c in zip(seeds, cfgs)], tensorboard=False)
    train(cfgs[1], RunDir.create(tmp_path / "s1", cfgs[1]), tensorboard=False)
    b, o = _metrics(tmp_path / "b1"), _metrics(tmp_path / "s1")
    assert len(b) == len(o) == 4
    first = [r for r in o if int(r[1]) <= 2 * 60]  # episodes that ended in the first rollout
    assert b[: len(first)] == first
    for update in (1, 2):
        cb, co = _ckpt(tmp_path / "b1", update), _ckpt(tmp_path / "s1", update)
        assert max(float((cb[k].double() - co[k].double()).abs().max()) for k in cb) < TOL, update


def test_bench_seeds_measures_solo_and_batched() -> None:
    from hammer.benchmarks.seeds_bench import grid_estimate, run_bench

    rows = run_bench(("cn3",), (4,), updates=1)
    assert [(r["mode"], r["seeds"]) for r in rows] == [("solo", 1), ("batched", 4)]
    assert all(r["env_steps_per_s"] > 0 and r["seconds"] > 0 for r in rows)
    # the bench prints the ratio to two decimals: equal up to that rounding, whatever its size
    assert rows[1]["ratio"] == pytest.approx(rows[1]["env_steps_per_s"] / rows[0]["env_steps_per_s"], abs=0.005)
    grid = grid_estimate(rows)
    assert grid["solo_s"] > 0 and grid["batched_s"] > 0
