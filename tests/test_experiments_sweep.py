"""The sweep runs real `hammer train` processes, skips finished runs and resumes interrupted ones."""

import csv
import json
import os

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


def test_a_lock_whose_pid_now_belongs_to_another_process_is_stale(tmp_path):
    """A lock outlives its sweep (the machine's session ends), and the kernel gives its pids to other
    processes: a lock names each holder with its start time, so a live process that took over a pid
    does not hold the point ("busy" for a run nobody runs); a bare pid (older locks) still counts."""
    from hammer.experiments.sweep import LOCK, _held, _holder, _lock

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    me = _holder(os.getpid())
    assert me.startswith(f"{os.getpid()}@")
    (run_dir / LOCK).write_text(me)
    assert _held(run_dir)
    pid, start = me.split("@")
    (run_dir / LOCK).write_text(f"{pid}@{int(start) - 1}")  # this pid, another process's start
    assert not _held(run_dir)
    assert _lock(run_dir) and (run_dir / LOCK).read_text() == me  # taken over as stale
    (run_dir / LOCK).write_text(pid)
    assert _held(run_dir)


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


# Two episodes an update and a checkpoint after each: a 4-episode run's last checkpoint is at episode 2,
# so its extension computes episodes 3-4 again (as `hammer train --resume` does) before going on.
EXTEND_GRID = [("num_envs", ["2"]), ("rollout_steps", ["25"]), ("checkpoint_every", ["1"])]


def _metrics(run_dir):
    """Every column but wall_time (the only one that may differ between two runs of one point)."""
    return [{k: v for k, v in row.items() if k != "wall_time"} for row in _rows(run_dir)]


def _tree(d):
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """A finished 4-episode hammer rl run in a sweep directory, and the point at 4 and at 8 episodes."""
    tmp = tmp_path_factory.mktemp("extend")
    short = expand(["cn3"], ["hammer-rl"], [0], EXTEND_GRID, episodes=4)
    long = expand(["cn3"], ["hammer-rl"], [0], EXTEND_GRID, episodes=8)
    assert run_sweep(short, tmp / "short", jobs=1, seed_batch=1).done == [short[0].name]
    return tmp / "short", short, long


def test_extend_from_continues_shorter_runs_as_train_resume_does(short_run, tmp_path):
    """A sweep at 8 episodes with --extend-from a sweep of the same point at 4 continues that run from its
    last checkpoint: the same metrics as `hammer train --resume COPY --episodes 8`, its first rows the
    source's; through --snapshot it continues from an archive alone (a fresh clone); the source is untouched."""
    import shutil

    from hammer.experiments.archive import is_archived, latest_checkpoint, partial_dir
    from hammer.experiments.sweep import sweep_status
    from typer.testing import CliRunner

    from hammer.cli import app

    short_dir, short, long = short_run
    src = short_dir / short[0].name
    assert latest_checkpoint(src).name == "ckpt_0000001" and len(_rows(src)) == 4
    before = _tree(short_dir)

    ref = tmp_path / "ref"
    shutil.copytree(src, ref)
    # the CLI's own path in this process (the sweep's runs are the processes under test)
    resumed = CliRunner().invoke(app, ["train", "--resume", str(ref), "--episodes", "8", "--quiet"])
    assert resumed.exit_code == 0, resumed.output
    assert len(_rows(ref)) == 8

    events = []
    res = run_sweep(long, tmp_path / "long", jobs=1, archive=tmp_path / "arch", extend_from=short_dir,
                    on_event=lambda k, n: events.append((k, n)))
    run = tmp_path / "long" / long[0].name
    assert res.extended == [long[0].name] and res.done == [long[0].name] and not res.failed
    assert events[0][0] == "extend" and "ckpt_0000001, 2 episodes" in events[0][1]
    assert _metrics(run) == _metrics(ref) and _metrics(run)[:4] == _metrics(src)
    assert json.loads((run / "config.json").read_text())["episodes"] == 8
    assert json.loads((run / "summary.json").read_text())["episodes"] == 8
    assert is_archived(tmp_path / "arch", long[0].name) and _tree(short_dir) == before
    # Done now: the source folder is not even looked for.
    again = run_sweep(long, tmp_path / "long", jobs=1, archive=tmp_path / "arch", extend_from=tmp_path / "nowhere")
    assert again.skipped == [long[0].name] and not again.extended

    # A fresh clone: --snapshot --extend-from commits the continuation to the archive's _partial/, and a sweep
    # with that archive alone (no run directory, no source folder) restores and finishes it, the same run.
    grid = ["--presets", "cn3", "--variants", "hammer-rl", "--seeds", "0", "--episodes", "8",
            *[a for k, v in EXTEND_GRID for a in ("--grid", f"{k}={v[0]}")]]
    cli = CliRunner().invoke(app, ["sweep", "--out", str(tmp_path / "prep"), "--archive", str(tmp_path / "arch2"),
                                   *grid, "--extend-from", str(short_dir), "--snapshot"])
    assert cli.exit_code == 0, cli.output
    assert "extend" in cli.output and "update 1, 2 episodes" in cli.output
    assert partial_dir(tmp_path / "arch2", long[0].name).is_dir()
    assert [r.state for r in sweep_status(long, tmp_path / "clone", tmp_path / "arch2")] == ["snapshot"]
    res = run_sweep(long, tmp_path / "clone", jobs=1, archive=tmp_path / "arch2", extend_from=tmp_path / "nowhere")
    assert res.restored == [long[0].name] and res.done == [long[0].name]
    assert _metrics(tmp_path / "clone" / long[0].name) == _metrics(ref)
    assert _tree(short_dir) == before


def test_extend_from_refuses_runs_it_cannot_continue(short_run, tmp_path):
    """A source differing in anything but episodes, without a checkpoint, not shorter, or doubled, and a
    missing folder: refused in one line naming the fix, before anything is copied or run."""
    import shutil

    from hammer.experiments.sweep import ExtendError
    from typer.testing import CliRunner

    from hammer.cli import app

    short_dir, short, long = short_run
    src = short_dir / short[0].name

    def refused(src_dir, match, points=long):
        out = tmp_path / "out"
        with pytest.raises(ExtendError, match=match) as e:
            run_sweep(points, out, jobs=1, extend_from=src_dir)
        assert "\n" not in str(e.value) and "fix:" in str(e.value)
        assert not (out / points[0].name).exists()  # nothing copied, nothing run
        return str(e.value)

    other = tmp_path / "other" / src.name
    shutil.copytree(src, other)
    cfg = json.loads((other / "config.json").read_text())
    (other / "config.json").write_text(json.dumps(dict(cfg, lr_local=cfg["lr_local"] * 2)))
    refused(other.parent, "differs from .* in lr_local")
    shutil.rmtree(other / "checkpoints")
    (other / "config.json").write_text(json.dumps(cfg))
    refused(other.parent, "no checkpoint.*fix: point --extend-from at the sweep directory")
    longer = tmp_path / "longer" / long[0].name
    shutil.copytree(src, longer)
    (longer / "config.json").write_text(json.dumps(dict(cfg, episodes=8)))
    refused(longer.parent, "runs 8 episodes, not fewer than .*'s 4", points=short)
    shutil.copytree(src, tmp_path / "twice" / src.name)
    shutil.copytree(src, tmp_path / "twice" / src.name.replace("-ep4-", "-ep6-"))
    refused(tmp_path / "twice", "all continue to")
    refused(tmp_path / "nowhere", "no such directory")

    res = CliRunner().invoke(app, ["sweep", "--out", str(tmp_path / "o"), "--presets", "cn3", "--variants", "hammer-rl",
                                   "--seeds", "0", "--episodes", "8", "--extend-from", str(other.parent),
                                   *[a for k, v in EXTEND_GRID for a in ("--grid", f"{k}={v[0]}")]])
    assert res.exit_code == 2 and "no checkpoint" in res.output and "Traceback" not in res.output
