"""A run in progress survives a lost machine through a committed partial snapshot: a real
`hammer train` is killed mid-run, snapshotted, its run directory deleted, and a sweep in a fresh
directory restores and finishes it with exactly the metrics of an uninterrupted run."""

import csv
import gzip
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from hammer.experiments.archive import PARTIAL, check_partial, is_archived, partial_dir
from hammer.experiments.runs import find_runs
from hammer.experiments.sweep import LOCK, expand, run_sweep, snapshot_sweep, state_of, sweep_status

EPISODES = 120  # 30 updates of 4 episodes; checkpoints every 2 updates


def _metrics(run_dir):
    """Every column but wall_time (the only one that may differ between two runs of one point)."""
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader(f)]


def _interrupted_run(point, run_dir, at_update: int, while_running=None) -> None:
    """Start the point's real `hammer train`, call `while_running()` once its first checkpoint after
    update 0 exists, and SIGKILL it once checkpoint `at_update` is complete."""
    run_dir.mkdir(parents=True)
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", HAMMER_TORCH_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "hammer.cli", *point.train_args(run_dir, EPISODES), "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    first = run_dir / "checkpoints" / "ckpt_0000002.json"
    deadline = time.monotonic() + 60
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if while_running is not None:
        while_running()
    marker = run_dir / "checkpoints" / f"ckpt_{at_update:07d}.json"
    deadline = time.monotonic() + 60
    while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert marker.exists() and state_of(run_dir) == "resume", "the run finished before it could be interrupted"


@pytest.fixture(scope="module")
def snapshotted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("snap")
    pts = expand(["cn3"], ["il"], [0], [("num_envs", ["4"]), ("rollout_steps", ["25"]), ("checkpoint_every", ["2"])],
                 episodes=EPISODES)
    live = []

    def snapshot_while_training():  # the trainer keeps writing checkpoints and rows meanwhile
        live.extend(snapshot_sweep(pts, tmp / "out", tmp / "archive"))
        check_partial(partial_dir(tmp / "archive", pts[0].name), pts[0].expected_config(EPISODES))

    _interrupted_run(pts[0], tmp / "out" / pts[0].name, at_update=6, while_running=snapshot_while_training)
    assert len(live) == 1 and live[0].update >= 2
    events = []
    snaps = snapshot_sweep(pts, tmp / "out", tmp / "archive", on_event=lambda k, n: events.append((k, n)))
    assert len(snaps) == 1 and snaps[0].update >= 6 and snaps[0].episodes == 4 * snaps[0].update
    assert events[0][0] == "snap" and f"update {snaps[0].update}" in events[0][1]
    # Taking it again while nothing changed rewrites nothing.
    again = snapshot_sweep(pts, tmp / "out", tmp / "archive")
    assert again[0].unchanged and again[0].update == snaps[0].update
    shutil.rmtree(tmp / "out")  # the session's machine is gone; only the archive (git) remains
    return tmp, pts, snaps[0]


def test_snapshot_holds_one_checkpoint_and_no_tensorboard(snapshotted):
    tmp, pts, snap = snapshotted
    src = partial_dir(tmp / "archive", pts[0].name)
    files = sorted(str(p.relative_to(src)) for p in src.rglob("*") if p.is_file())
    stem = f"checkpoints/ckpt_{snap.update:07d}"
    assert files == sorted(["config.json", "config.yaml", "metrics.csv.gz", stem + ".json", stem + ".safetensors"])
    check_partial(src, pts[0].expected_config(EPISODES))
    other = expand(["cn3"], ["il"], [1], [("num_envs", ["4"]), ("rollout_steps", ["25"]),
                                          ("checkpoint_every", ["2"])], episodes=EPISODES)[0]
    with pytest.raises(ValueError, match="seed"):
        check_partial(src, other.expected_config(EPISODES))
    # A partial run is never a result: plot/report find nothing in an archive holding only snapshots.
    assert find_runs([tmp / "archive"]) == [] and find_runs([src]) == []
    assert not is_archived(tmp / "archive", pts[0].name)


def test_snapshot_cli(snapshotted, tmp_path):
    """(Runs before the restore test, which consumes the snapshot.) `hammer sweep --snapshot` needs --archive, is a no-op for a grid never run here, and names
    the snapshots it took (here: the kept one, unchanged)."""
    from typer.testing import CliRunner

    from hammer.cli import app

    tmp, pts, snap = snapshotted
    grid = ["--presets", "cn3", "--variants", "il", "--seeds", "0", "--episodes", str(EPISODES),
            "--grid", "num_envs=4", "--grid", "rollout_steps=25", "--grid", "checkpoint_every=2"]
    res = CliRunner().invoke(app, ["sweep", "--out", str(tmp_path / "o"), *grid, "--snapshot"])
    assert res.exit_code == 2 and "--archive" in res.output
    res = CliRunner().invoke(app, ["sweep", "--out", str(tmp_path / "o"), "--archive", str(tmp_path / "a"),
                                   *grid, "--snapshot"])
    assert res.exit_code == 0 and "nothing to snapshot" in res.output and not (tmp_path / "a").exists()
    out = tmp_path / "o"
    run_dir = out / pts[0].name
    shutil.copytree(tmp / "archive" / PARTIAL / pts[0].name, run_dir)  # a run dir at that checkpoint...
    res = CliRunner().invoke(app, ["sweep", "--out", str(out), "--archive", str(tmp_path / "a"), *grid, "--snapshot"])
    assert res.exit_code == 0 and "not snapshotted (metrics.csv is missing)" in res.output  # ...once its CSV is back
    with gzip.open(run_dir / "metrics.csv.gz", "rt", newline="") as f, open(run_dir / "metrics.csv", "w", newline="") as g:
        g.write(f.read())
    res = CliRunner().invoke(app, ["sweep", "--out", str(out), "--archive", str(tmp_path / "a"), *grid, "--snapshot"])
    assert res.exit_code == 0, res.output
    assert f"{pts[0].name}  update {snap.update}, {snap.episodes} episodes" in res.output
    assert partial_dir(tmp_path / "a", pts[0].name).is_dir()


def test_status_reads_every_state_without_changing_anything(snapshotted, tmp_path):
    """`hammer sweep --status`: one real snapshot (seed 0) placed in the states a grid point can be in."""
    from typer.testing import CliRunner

    from hammer.cli import app

    tmp, pts, snap = snapshotted
    grid = [("num_envs", ["4"]), ("rollout_steps", ["25"]), ("checkpoint_every", ["2"])]
    points = expand(["cn3"], ["il"], [0, 1, 2, 3, 4, 5], grid, episodes=EPISODES)
    out, src = tmp_path / "out", partial_dir(tmp / "archive", pts[0].name)
    for p in points[1:3]:  # seeds 1, 2: a run directory at the snapshot's checkpoint
        shutil.copytree(src, out / p.name)
        with gzip.open(src / "metrics.csv.gz", "rt", newline="") as f:
            (out / p.name / "metrics.csv").write_text(f.read() + "9999,1,-1.0,-3.0,25,1.0\n")
    (out / points[2].name / LOCK).write_text(f"{os.getpid()}")  # seed 2: held by a live process
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], check=True, capture_output=True,
                          text=True)
    (out / points[1].name / LOCK).write_text(dead.stdout.strip())  # seed 1: a stale lock
    (out / points[3].name).mkdir()  # seed 3: started, no checkpoint yet
    summary = {"episodes": EPISODES, "final_paper_metric_last500": -12.5}
    (out / points[4].name).mkdir()  # seed 4: finished here, not archived
    (out / points[4].name / "summary.json").write_text(json.dumps(summary))
    before = sorted((str(p), p.stat().st_mtime_ns) for p in tmp_path.rglob("*"))

    rows = sweep_status(points, out, tmp / "archive")
    got = [(r.state, r.episodes, r.budget) for r in rows]
    assert got == [("snapshot", snap.episodes, EPISODES), ("resumable", snap.episodes, EPISODES),
                   ("running", snap.episodes + 1, EPISODES), ("started", None, EPISODES),
                   ("done", EPISODES, EPISODES), ("not started", None, EPISODES)]
    assert rows[4].final == -12.5 and rows[4].note == "not archived yet"
    assert f"checkpoint at {snap.episodes:,}" in rows[2].note
    assert sorted((str(p), p.stat().st_mtime_ns) for p in tmp_path.rglob("*")) == before  # read-only

    args = ["--presets", "cn3", "--variants", "il", "--seeds", "0-5", "--episodes", str(EPISODES),
            *[x for k, v in grid for x in ("--grid", f"{k}={v[0]}")]]
    res = CliRunner().invoke(app, ["sweep", "--out", str(out), "--archive", str(tmp / "archive"), *args,
                                   "--status"], terminal_width=200)
    assert res.exit_code == 0, res.output
    assert "1 snapshot, 1 resumable, 1 running, 1 started, 1 done, 1 not started of 6" in res.output
    assert not (out / points[5].name).exists()  # status ran nothing


def test_restored_run_matches_an_uninterrupted_one_and_broken_snapshot_starts_fresh(snapshotted):
    tmp, pts, snap = snapshotted
    name = pts[0].name
    # A copy of the archive with a truncated safetensors file: the sweep must say why and start fresh.
    shutil.copytree(tmp / "archive", tmp / "broken")
    st = partial_dir(tmp / "broken", name) / "checkpoints" / f"ckpt_{snap.update:07d}.safetensors"
    st.write_bytes(st.read_bytes()[: st.stat().st_size // 2])
    events = []
    fresh = run_sweep(pts, tmp / "fresh", jobs=1, archive=tmp / "broken",
                      on_event=lambda k, n: events.append((k, n)))
    assert fresh.done == [name] and not fresh.restored and fresh.broken[0][0] == name
    assert "safetensors does not load" in fresh.broken[0][1]
    assert [k for k, _ in events] == ["broken", "start", "done"]
    assert "starting fresh" in events[0][1] and "\n" not in events[0][1]

    events = []
    res = run_sweep(pts, tmp / "restored", jobs=1, archive=tmp / "archive",
                    on_event=lambda k, n: events.append((k, n)))
    assert res.done == [name] and res.restored == [name] and not res.broken
    assert [k for k, _ in events] == ["restore", "done"]
    restored = _metrics(tmp / "restored" / name)
    assert len(restored) == EPISODES
    assert restored == _metrics(tmp / "fresh" / name)
    # Finished and archived: the snapshot is gone, the archive holds one finished result.
    assert is_archived(tmp / "archive", name) and not (tmp / "archive" / PARTIAL / name).exists()
    assert find_runs([tmp / "archive"]) == [tmp / "archive" / name]
    (st,) = sweep_status(pts, tmp / "restored", tmp / "archive")
    summary = json.loads((tmp / "archive" / name / "summary.json").read_text())
    assert (st.state, st.episodes, st.final) == ("archived", EPISODES, summary["final_paper_metric_last500"])



def test_sweep_snapshots_runs_in_progress_by_itself(tmp_path):
    """`run_sweep(snapshot_every_s=...)`: while a run trains, valid snapshots appear in the archive
    without anyone calling `--snapshot`; once the run is archived its snapshot is gone."""
    pts = expand(["cn3"], ["il"], [1], [("num_envs", ["4"]), ("rollout_steps", ["25"]), ("checkpoint_every", ["2"])],
                 episodes=EPISODES)
    name, archive = pts[0].name, tmp_path / "archive"
    events, checked = [], []

    def on_event(kind, text):
        events.append(kind)
        if kind == "snap":  # the snapshot is complete when the event fires: it must restore
            check_partial(partial_dir(archive, name), pts[0].expected_config(EPISODES))
            checked.append(int(text.split("update ")[1].split(",")[0]))

    res = run_sweep(pts, tmp_path / "out", jobs=1, archive=archive, on_event=on_event, snapshot_every_s=0.2)
    assert res.done == [name] and events[0] == "start" and events[-1] == "done"
    assert checked and checked == sorted(checked)
    assert is_archived(archive, name) and not partial_dir(archive, name).exists()


def test_sigterm_to_a_sweep_stops_its_runs(tmp_path):
    """A sweep killed with SIGTERM (how a session's end or `kill` stops it) takes its `hammer train`
    children with it instead of leaving them running unowned."""
    import psutil

    out = tmp_path / "out"
    sweep = subprocess.Popen([sys.executable, "-m", "hammer.cli", "sweep", "--out", str(out), "--presets", "cn3",
                              "--variants", "il", "--seeds", "0", "--jobs", "1"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    children = []
    while not children and time.monotonic() < deadline and sweep.poll() is None:
        children = psutil.Process(sweep.pid).children()
        time.sleep(0.05)
    assert children, "the sweep never started its run"
    time.sleep(1.0)  # the child is up (its interpreter running), the sweep is in its wait loop
    sweep.send_signal(signal.SIGTERM)
    sweep.wait(30)
    _gone, alive = psutil.wait_procs(children, timeout=15)
    for p in alive:  # do not leave them running if the test fails
        p.kill()
    assert not alive, f"runs left behind: {[p.pid for p in alive]}"
