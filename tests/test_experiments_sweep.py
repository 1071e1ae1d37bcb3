"""The sweep runs real `hammer train` processes, skips finished runs and resumes interrupted ones."""

import csv
import json

import pytest
from hammer.experiments.sweep import expand, parse_grid_overrides, parse_seeds, run_sweep, state_of


def _rows(run_dir):
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_grid_expansion_and_parsing():
    pts = expand(["cn3"], ["hammer-rl", "il"], parse_seeds("0-1"), parse_grid_overrides(["msg_dim=2,4"]))
    assert len(pts) == 8
    assert pts[0].name == "cn3-hammer-rl-msg_dim=2-s0"
    short = expand(["mw3"], ["il"], [1], episodes=2000)[0]
    assert short.name == "mw3-il-ep2000-s1" and "2000" in short.train_args("d", short.episodes)
    args = pts[0].train_args(pts[0].name, 10)
    assert args[args.index("--central-mode") + 1] == "rl" and "msg_dim=2" in args
    with pytest.raises(ValueError, match="seeds"):
        parse_seeds("a-b")
    with pytest.raises(ValueError, match="KEY=V1"):
        parse_grid_overrides(["msg_dim"])
    with pytest.raises(ValueError, match="variant"):
        expand(["cn3"], ["hammr"], [0])


def test_sweep_skips_finished_and_resumes_interrupted(tmp_path):
    pts = expand(["cn3"], ["il"], [0, 1], [("num_envs", ["4"]), ("rollout_steps", ["25"]),
                                           ("checkpoint_every", ["2"])])
    res = run_sweep(pts, tmp_path, jobs=2, episodes=24)
    assert sorted(res.done) == sorted(p.name for p in pts) and not res.failed
    first = tmp_path / pts[0].name
    assert len(_rows(first)) == 24 and state_of(first) == "done"
    # Interrupt one run after the fact: drop its summary (as if killed after its last checkpoint).
    (first / "summary.json").unlink()
    assert state_of(first) == "resume"
    res2 = run_sweep(pts, tmp_path, jobs=2, episodes=24)
    assert res2.skipped == [pts[1].name] and res2.done == [pts[0].name]
    assert len(_rows(first)) == 24
    assert json.loads((first / "summary.json").read_text())["episodes"] == 24


def test_archived_runs_survive_a_fresh_sweep_directory(tmp_path):
    """A sweep archived into the repository continues from a clean clone (no run directories)."""
    from hammer.experiments.archive import is_archived

    pts = expand(["cn3"], ["il"], [0], [("num_envs", ["4"]), ("rollout_steps", ["25"])])
    archive = tmp_path / "archive"
    res = run_sweep(pts, tmp_path / "a", jobs=1, episodes=8, archive=archive)
    assert res.done == [pts[0].name] and is_archived(archive, pts[0].name)
    # The trained weights come along, byte for byte: the archived team can be evaluated from a clone.
    final = tmp_path / "a" / pts[0].name / "final"
    assert sorted(f.name for f in (archive / pts[0].name / "final").iterdir()) == ["local.safetensors"]
    assert (archive / pts[0].name / "final" / "local.safetensors").read_bytes() == (final / "local.safetensors").read_bytes()
    res2 = run_sweep(pts, tmp_path / "fresh", jobs=1, episodes=8, archive=archive)
    assert res2.skipped == [pts[0].name] and not res2.done
    assert not (tmp_path / "fresh" / pts[0].name).exists()


def test_a_point_held_by_a_live_sweep_is_not_run_twice(tmp_path):
    """Two sweeps on one directory: a point locked by a live process is skipped as busy; a lock
    whose processes are gone is stale and taken over."""
    import subprocess
    import sys

    from hammer.experiments.sweep import LOCK

    pts = expand(["cn3"], ["il"], [0], [("num_envs", ["4"]), ("rollout_steps", ["25"])])
    run_dir = tmp_path / pts[0].name
    run_dir.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (run_dir / LOCK).write_text(str(holder.pid))
        res = run_sweep(pts, tmp_path, jobs=1, episodes=8)
        assert res.skipped == [pts[0].name] and not res.done and not (run_dir / "metrics.csv").exists()
    finally:
        holder.kill()
        holder.wait()
    res = run_sweep(pts, tmp_path, jobs=1, episodes=8)  # the holder is gone: a stale lock
    assert res.done == [pts[0].name] and not (run_dir / LOCK).exists()


def test_points_that_differ_only_in_a_field_their_variant_ignores_are_named():
    """The centralised wiring never reads the local view's radius: its runs at two radii are one run."""
    from hammer.experiments.sweep import duplicate_points, expand

    pts = expand(["cn3"], ["centralized", "il"], [0, 1], [("env_kwargs.obs_radius", ["0.3", "0.6"])])
    assert [(p.name, f) for p, f in duplicate_points(pts)] == [
        ("cn3-centralized-env_kwargs_obs_radius=0.6-s0", "env_kwargs.obs_radius"),
        ("cn3-centralized-env_kwargs_obs_radius=0.6-s1", "env_kwargs.obs_radius")]
    assert duplicate_points(expand(["cn3"], ["il", "hammer-rl"], [0], [("env_kwargs.obs_radius", ["0.3", "0.6"])])) == []


def _contend(root: str, rounds: int, start_at: float, out) -> None:
    """One competing sweep: try every round's fresh directory once; report the rounds it won."""
    import time as t
    from pathlib import Path as P

    from hammer.experiments.sweep import _lock

    while t.time() < start_at:
        pass
    out.put([r for r in range(rounds) if _lock(P(root) / f"r{r}")])


def test_competing_sweeps_never_both_take_a_point(tmp_path):
    """Four sweep processes race for the lock of each of 300 fresh points at once: each point is taken
    exactly once (a lock used to appear empty for a moment, and a competitor read that as stale and
    took it over)."""
    import multiprocessing as mp
    import time

    rounds = 300
    for r in range(rounds):
        (tmp_path / f"r{r}").mkdir()
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    start_at = time.time() + 3.0  # every process imported and spinning before the first round
    procs = [ctx.Process(target=_contend, args=(str(tmp_path), rounds, start_at, out)) for _ in range(4)]
    for p in procs:
        p.start()
    won = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(30)
    taken = sorted(r for w in won for r in w)
    assert taken == list(range(rounds)), f"{len(taken) - len(set(taken))} points taken twice"
