"""Resumable grids of independent training runs.

A sweep is a directory; every point of the grid (preset × variant × seed × overrides) is one run
directory inside it with a deterministic name. Re-running the same sweep command skips finished
runs (they have summary.json), resumes interrupted ones from their last checkpoint, and starts the
rest, at most `jobs` at a time, each a fresh `hammer train` process with one torch thread.
Several sweep processes may work on one directory at once (say, one per core): a lock file per
run directory (pids of the sweep and its child) keeps them from running the same point twice.
With an archive (`experiments.archive`), finished runs and snapshots of runs in progress are
committed to git, so a sweep continues from a fresh clone: archived runs are skipped, and a
point with no run directory but a partial snapshot is restored from it and resumed.
With `extend_from`, a point with neither continues the same point of a shorter budget found there
(`extend_points`): its run directory is branched from that run's last checkpoint under this point's
name and budget, then resumed like any other, as `hammer train --resume RUN --episodes N` would.
All of that is decided here, for every backend; a launcher (`experiments.launch`) only starts each
command: as a child process (the default) or as a task on a Ray cluster (`experiments.ray_backend`).
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from hammer.experiments.archive import (
    Snapshot,
    archive_run,
    drop_partial,
    is_archived,
    latest_checkpoint,
    partial_dir,
    restore_partial,
    snapshot_run,
)
from hammer.experiments.launch import Job, Launcher, LocalLauncher
from hammer.protocol.ranges import parse_indices
from hammer.runtime.process import take_signals

# Variant spellings accepted by the sweep: `hammer-rl` / `hammer-backprop` pin the central mode.
VARIANTS = ("hammer", "hammer-rl", "hammer-backprop", "il", "random", "centralized")


@dataclass(frozen=True)
class SweepPoint:
    preset: str
    variant: str
    seed: int
    overrides: tuple[tuple[str, str], ...] = ()
    episodes: int | None = None  # a budget other than the preset's: part of the name, so that a
    # shortened run is never mistaken for (or archived as) the full-budget run of the same point

    @property
    def name(self) -> str:
        parts = [self.preset, self.variant]
        parts += [f"{k.replace('.', '_')}={v}" for k, v in self.overrides]
        if self.episodes is not None:
            parts.append(f"ep{self.episodes}")
        parts.append(f"s{self.seed}")
        return "-".join(parts)

    def train_args(self, run_dir: Path, episodes: int | None) -> list[str]:
        variant, _, mode = self.variant.partition("-")
        args = ["train", "--preset", self.preset, "--variant", variant, "--seed", str(self.seed),
                "--run-dir", str(run_dir)]
        if mode:
            args += ["--central-mode", mode]
        for k, v in self.overrides:
            args += ["--set", f"{k}={v}"]
        if episodes is not None:
            args += ["--episodes", str(episodes)]
        return args

    def expected_config(self, episodes: int | None) -> dict:
        """The RunConfig `hammer train` resolves for this point (as `train_args` would pass it)."""
        from hammer.learning.config import merge_config

        variant, _, mode = self.variant.partition("-")
        return merge_config(self.preset, None, [f"{k}={v}" for k, v in self.overrides],
                            {"variant": variant, "central_mode": mode or None, "seed": self.seed,
                             "episodes": episodes}).model_dump(mode="json")


def parse_seeds(text: str) -> list[int]:
    """`0-4` or `0,2,5` -> sorted distinct seeds (protocol.ranges)."""
    return parse_indices(text, "--seeds", what="seed")


def parse_grid_overrides(items: list[str]) -> list[tuple[str, list[str]]]:
    """`msg_dim=1,2,4,8` → [("msg_dim", ["1","2","4","8"])]; each key is one grid axis."""
    axes = []
    for item in items:
        key, eq, values = item.partition("=")
        if not eq or not key or not values:
            raise ValueError(f"--grid {item!r}: expected KEY=V1,V2,... e.g. msg_dim=1,2,4,8")
        axes.append((key.strip(), [v.strip() for v in values.split(",")]))
    return axes


def expand(presets: list[str], variants: list[str], seeds: list[int],
           grid: list[tuple[str, list[str]]] | None = None, episodes: int | None = None) -> list[SweepPoint]:
    for v in variants:
        if v not in VARIANTS:
            raise ValueError(f"variant {v!r} is not one of {', '.join(VARIANTS)}")
    grid = grid or []
    keys = [k for k, _ in grid]
    combos = list(itertools.product(*[vals for _, vals in grid])) or [()]
    # Seed-major order: a sweep cut short still holds every comparison, at fewer seeds.
    return [SweepPoint(p, v, s, tuple(zip(keys, combo, strict=True)), episodes)
            for s in seeds for p in presets for v in variants for combo in combos]


def state_of(run_dir: Path) -> str:
    if (run_dir / "summary.json").is_file():
        return "done"
    if latest_checkpoint(run_dir) is not None:
        return "resume"
    return "new"


@dataclass
class SweepResult:
    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: list[tuple[str, int]] = field(default_factory=list)
    restored: list[str] = field(default_factory=list)  # resumed from a partial snapshot in the archive
    extended: list[str] = field(default_factory=list)  # continued from a shorter run (`extend_points`)
    broken: list[tuple[str, str]] = field(default_factory=list)  # (name, reason): snapshot unusable, ran fresh


SEED_MEMORY = 200 * 2**20  # bytes a seed of a seed batch may take (networks, buffers, env copies, slack)
MAX_SEEDS = 16


# Config fields a variant never reads: its runs at different values are the same run (a sweep that
# crosses them computes duplicates). The fully centralised wiring feeds every local policy the joint
# observation, so the local view's radius never reaches it (docs/results: 50 such runs of the
# dose-response grid are bit for bit its full-view runs).
IGNORED_BY_VARIANT = {"centralized": ("env_kwargs.obs_radius",)}


def duplicate_points(points: list[SweepPoint]) -> list[tuple[SweepPoint, str]]:
    """(point, field) for each point that differs from another point of the grid only in a field its
    variant ignores (`IGNORED_BY_VARIANT`): the sweep would train the same run twice. Not an error (a
    grid may keep them as a check); `hammer sweep` says so before it starts."""
    seen: dict[tuple, SweepPoint] = {}
    out = []
    for p in points:
        ignored = IGNORED_BY_VARIANT.get(p.variant, ())
        kept = tuple((k, v) for k, v in p.overrides if k not in ignored)
        key = (p.preset, p.variant, p.seed, kept, p.episodes)
        if key in seen:
            out.append((p, next(k for k, _ in p.overrides if k in ignored)))
        else:
            seen[key] = p
    return out


def seed_cap() -> int:
    """Most seeds one batched process takes: MAX_SEEDS, fewer if the free memory is short."""
    try:
        with open("/proc/meminfo") as f:
            free = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError):
        return MAX_SEEDS
    return max(1, min(MAX_SEEDS, free // SEED_MEMORY))


def _batch_key(p: SweepPoint, budget: int | None) -> tuple | None:
    """Points with equal keys differ only in seed and train as one seed batch; None: run alone
    (multiwalker steps its walkers in worker processes, which a batch would multiply by S)."""
    if p.preset.startswith("mw"):
        return None
    cfg = p.expected_config(budget)
    if cfg.get("env_workers", 0) or cfg["env"] != "cn":
        return None
    return (p.preset, p.variant, p.overrides, p.episodes, budget)


def run_sweep(points: list[SweepPoint], out: Path, jobs: int | None = None, episodes: int | None = None,
              on_event=None, archive: Path | None = None, snapshot_every_s: float | None = None,
              seed_batch: int | None = None, launcher: Launcher | None = None,
              extend_from: Path | None = None) -> SweepResult:
    """Run every point not yet finished; returns what happened. `on_event(kind, name)` reports progress.

    With `archive`, a point already archived there counts as finished, and every run that finishes
    (or is found finished in `out`) is archived (`experiments.archive`): commit the archive and the
    sweep continues from a fresh clone. A point whose run directory holds neither a summary nor a
    checkpoint is restored from `archive/_partial/<name>` if a valid snapshot is there (event
    "restore"); a broken snapshot is reported (event "broken", name + reason) and the run starts fresh.

    `snapshot_every_s` (with `archive`): every so often, snapshot the runs in progress into
    `archive/_partial/` too (event "snap"), so a session that ends without warning still leaves its
    progress in the working tree, where the next session can find it even if nothing was committed.

    `seed_batch`: most seeds per process (default `seed_cap()`, 1 = every point alone). Fresh cn
    points that differ only in seed start as one seed-batched process (`learning.seed_batch`),
    one ordinary run directory each; points to resume or restore, and mw points, run alone.

    `launcher`: where each command runs (`experiments.launch`): child processes here by default,
    or tasks on a Ray cluster (`experiments.ray_backend`); everything above is the same for both.

    `extend_from`: a folder of runs of these points at a shorter budget (`extend_points`); raises
    ExtendError before anything runs if one of them cannot be continued."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    launcher = launcher or LocalLauncher()
    cap = seed_cap() if seed_batch is None else max(1, seed_batch)
    s = _Scheduler(out, archive, episodes, cap, launcher, on_event)
    if extend_from is not None:
        s.result.extended = extend_points(points, out, extend_from, archive, episodes, on_event)
    s.queue_points(points)
    jobs = jobs or launcher.slots()
    last_snap = time.monotonic()
    # SIGTERM (a session ending, `kill`) must stop the runs too, not orphan them: turn it into an
    # exit through the `finally` below, as Ctrl-C already does.
    _, restore = take_signals((signal.SIGTERM,), _exit_on_sigterm)
    try:
        while s.queue or s.running:
            while s.queue and len(s.running) < jobs:
                s.start_next()
            time.sleep(0.2)
            if archive is not None and snapshot_every_s and time.monotonic() - last_snap >= snapshot_every_s:
                last_snap = time.monotonic()
                _snapshot_running([n for _, names in s.running.values() for n in names], out, archive, on_event)
            s.reap()
    finally:
        s.stop_all()
        restore()
    return s.result


class _Scheduler:
    """The part of a sweep that every backend shares: which points to run, skip, restore, batch and
    archive, and the locks that keep two sweeps off one point. Only `launcher.launch` runs anything."""

    def __init__(self, out: Path, archive: Path | None, episodes: int | None, cap: int,
                 launcher: Launcher, on_event) -> None:
        self.out, self.archive, self.episodes, self.cap = out, archive, episodes, cap
        self.launcher, self.on_event = launcher, on_event
        self.result = SweepResult()
        self.queue: list[tuple[SweepPoint, Path, str]] = []
        self.running: dict[str, tuple[Job, list[str]]] = {}

    def event(self, kind: str, name: str) -> None:
        if self.on_event:
            self.on_event(kind, name)

    def archived(self, name: str) -> bool:
        return self.archive is not None and is_archived(self.archive, name)

    def queue_points(self, points: list[SweepPoint]) -> None:
        """Queue every point not finished here or in the archive (archiving finished ones on the way)."""
        for p in points:
            run_dir = self.out / p.name
            st = state_of(run_dir)
            if st == "done" and self.archive is not None and not self.archived(p.name):
                archive_run(run_dir, self.archive)
            if self.archived(p.name):
                st = "done"
                drop_partial(self.archive, p.name)  # an archived finished run wins over a snapshot of it
            if st == "done":
                self.result.skipped.append(p.name)
                self.event("skip", p.name)
            else:
                self.queue.append((p, run_dir, st))

    def start_next(self) -> None:
        """Lock the next queued point (with the fresh points it batches with) and launch its command."""
        p, run_dir, _ = self.queue.pop(0)
        run_dir.mkdir(parents=True, exist_ok=True)
        if not _lock(run_dir):  # another sweep process is running this point right now
            self.result.skipped.append(p.name)
            self.event("busy", p.name)
            return
        st = state_of(run_dir)  # again: another sweep may have finished it meanwhile
        if st == "done" or self.archived(p.name):
            _unlock(run_dir)
            self.result.skipped.append(p.name)
            self.event("skip", p.name)
            return
        budget = self.episodes if self.episodes is not None else p.episodes
        restored = False
        if st == "new" and self.archive is not None and partial_dir(self.archive, p.name).is_dir():
            try:
                restore_partial(partial_dir(self.archive, p.name), run_dir, p.expected_config(budget))
                st, restored = "resume", True
                self.result.restored.append(p.name)
            except ValueError as e:
                self.result.broken.append((p.name, str(e)))
                self.event("broken", f"{p.name}: snapshot unusable ({e}); starting fresh")
        key = _batch_key(p, budget) if st == "new" and self.cap > 1 else None
        group = [(p, run_dir)]
        if key is not None:
            group += _take_batch(self.queue, key, self.cap - 1, self.out, self.archive, budget,
                                 self.result, self.on_event)
        args = _command(group, st, budget)
        job = self.launcher.launch(args, run_dir / "train.log", [d for _, d in group])
        if job.pid is not None:
            for _, d in group:
                _lock(d, child=job.pid)
        names = [q.name for q, _ in group]
        self.running[p.name] = (job, names)
        for name in names:
            self.event("restore" if restored else "resume" if st == "resume" else "start", name)

    def reap(self) -> None:
        """Unlock, judge and archive every run whose command has ended."""
        for key, (job, names) in list(self.running.items()):
            code = job.poll()
            if code is None:
                continue
            del self.running[key]
            for name in names:
                _unlock(self.out / name)
                # a seed batch can fail after some seeds finished: each seed is judged by its summary
                if code == 0 or (len(names) > 1 and state_of(self.out / name) == "done"):
                    if self.archive is not None:
                        archive_run(self.out / name, self.archive)
                        drop_partial(self.archive, name)
                    self.result.done.append(name)
                    self.event("done", name)
                else:
                    self.result.failed.append((name, code))
                    if job.reason:
                        _note(self.out / name / "train.log", f"hammer sweep: {job.reason}")
                    self.event("fail", f"{name}: {job.reason}" if job.reason else name)

    def stop_all(self) -> None:
        for job, names in self.running.values():
            job.stop()
            for name in names:
                _unlock(self.out / name)
        self.running.clear()


def _command(group: list[tuple[SweepPoint, Path]], st: str, budget: int | None) -> list[str]:
    """The Python arguments that train a group: one point alone (`hammer train`, fresh or --resume),
    or fresh points of one setting as a seed batch (their run directories created here first)."""
    p, run_dir = group[0]
    if len(group) == 1:
        return ["-P", "-m", "hammer.cli", *(["train", "--resume", str(run_dir)] if st == "resume"
                                     else p.train_args(run_dir, budget))]
    from hammer.learning.config import build_config
    from hammer.learning.rundir import RunDir

    for q, d in group:
        RunDir.create(d, build_config(q.expected_config(budget)))
    for _, d in group[1:]:
        _note(d / "train.log", f"seed batch: log in {run_dir / 'train.log'}")
    return ["-P", "-m", "hammer.commands.seeds", *(str(d) for _, d in group)]


def _note(log: Path, line: str) -> None:
    try:
        with open(log, "a") as f:
            f.write(line + "\n")
    except OSError:
        pass  # a note is never worth failing the sweep over


def _take_batch(queue: list[tuple[SweepPoint, Path, str]], key: tuple, n: int, out: Path, archive: Path | None,
                budget: int | None, result: SweepResult, on_event) -> list[tuple[SweepPoint, Path]]:
    """Take up to n more fresh points with this batch key off the queue, locked for this sweep
    (the others stay queued: busy, finished meanwhile, or with a snapshot to restore)."""
    taken: list[tuple[SweepPoint, Path]] = []
    for item in list(queue):
        if len(taken) >= n:
            break
        q, d, _ = item
        if _batch_key(q, budget) != key:
            continue
        if archive is not None and partial_dir(archive, q.name).is_dir():
            continue  # restored and resumed alone
        d.mkdir(parents=True, exist_ok=True)
        if not _lock(d):
            continue
        if state_of(d) != "new" or (archive is not None and is_archived(archive, q.name)):
            _unlock(d)
            continue
        queue.remove(item)
        taken.append((q, d))
    return taken


class ExtendError(ValueError):
    """A run the sweep was asked to continue cannot be: one line, naming the fix."""


def _unbudgeted(name: str) -> str:
    """A point's name without its budget (`-ep10000` before the seed): equal for the same point at any budget."""
    return re.sub(r"-ep\d+(?=-s\d+$)", "", name)


def extension_source(p: SweepPoint, budget: int | None, src_dir: Path) -> Path | None:
    """The run in `src_dir` that point `p` (at `budget` episodes) continues: the same point at another
    budget, found by name (the point's name but for its `epN` part). None if there is none; ExtendError
    if the one there differs from `p` in anything but `episodes`, has no checkpoint, or is not shorter."""
    from hammer.learning.config import ConfigError, build_config, config_changes

    key = _unbudgeted(p.name)
    found = sorted(d for d in Path(src_dir).iterdir() if d.is_dir() and d.name != p.name and _unbudgeted(d.name) == key)
    if not found:
        return None
    fix = f"fix: drop --extend-from for {p.name}, or point it at a folder of runs of this grid at a shorter budget"
    if len(found) > 1:
        raise ExtendError(f"--extend-from {src_dir}: {', '.join(d.name for d in found)} all continue to "
                          f"{p.name}; {fix} (one each)")
    src = found[0]
    expected = p.expected_config(budget)
    try:
        cfg = build_config(json.loads((src / "config.json").read_text())).model_dump(mode="json")
    except (OSError, ValueError, ConfigError) as e:
        raise ExtendError(f"--extend-from: {src} has no readable config.json ({str(e).splitlines()[0][:80]}); {fix}") from None
    diff = list(config_changes(cfg, expected, ignore={"out", "torch_threads", "episodes"}))
    if diff:
        raise ExtendError(f"--extend-from: {src} differs from {p.name} in {', '.join(diff)} (only episodes may); {fix}")
    if cfg["episodes"] >= expected["episodes"]:
        raise ExtendError(f"--extend-from: {src} runs {cfg['episodes']} episodes, not fewer than {p.name}'s "
                          f"{expected['episodes']}; {fix}")
    if latest_checkpoint(src) is None:
        raise ExtendError(f"--extend-from: {src} has no checkpoint (an archive keeps none); fix: point --extend-from "
                          "at the sweep directory that ran it, whose run directories keep their checkpoints/")
    return src


def extend_points(points: list[SweepPoint], out: Path, src_dir: Path, archive: Path | None = None,
                  episodes: int | None = None, on_event=None) -> list[str]:
    """Continue shorter runs to these points' budget: for each point with no run (nothing in `out`,
    not archived, no snapshot in the archive's _partial/) whose same point at a shorter budget is in
    `src_dir` (`extension_source`), branch that run's last checkpoint into `out/<point name>`, with the
    config `hammer train --resume RUN --episodes N` would write (`RunDir.branch`, as `hammer train
    --branch` does): the point is then an interrupted run, which the sweep resumes, `--snapshot`
    snapshots and `--status` shows like any other. `src_dir` is not touched. Every source is checked
    before anything is copied (ExtendError, one line). `src_dir` is read only for points with no run of
    their own, so it may be missing once they all have one. Returns the names extended (event "extend")."""
    from hammer.learning.config import merge_config
    from hammer.learning.rundir import RunDir

    src_dir, out = Path(src_dir), Path(out)
    todo = []
    for p in points:
        budget = episodes if episodes is not None else p.episodes
        if (state_of(out / p.name) != "new" or (archive is not None and (
                is_archived(archive, p.name) or partial_dir(archive, p.name).is_dir()))):
            continue  # its own run (here, archived or snapshotted) goes on instead
        if not src_dir.is_dir():  # asked only for a point with no run of its own: a clone may lack the folder
            raise ExtendError(f"--extend-from {src_dir}: no such directory, and {p.name} has no run of its own; "
                              "fix: pass the sweep directory holding the shorter runs, or drop --extend-from "
                              "to train these points from the start")
        src = extension_source(p, budget, src_dir)
        if src is not None:
            todo.append((p, budget, src))
    done = []
    for p, budget, src in todo:
        run_dir = out / p.name
        run_dir.mkdir(parents=True, exist_ok=True)
        if not _lock(run_dir):
            continue  # another sweep is on it
        try:
            if state_of(run_dir) != "new":
                continue
            src_rd, src_cfg = RunDir.open(src)
            cfg = merge_config(None, None, [], {"episodes": p.expected_config(budget)["episodes"]},
                               base=src_cfg.model_dump(mode="json"))
            RunDir.branch(src_rd, run_dir, cfg)
        finally:
            _unlock(run_dir)
        done.append(p.name)
        if on_event:
            stem = latest_checkpoint(run_dir)
            at = _latest_checkpoint_episodes(run_dir)
            on_event("extend", f"{p.name} from {src} ({stem.name}, {at:,} episodes)")
    return done


def _exit_on_sigterm(signal_name: str) -> None:
    raise SystemExit(128 + signal.Signals[signal_name].value)


def _snapshot_one(run_dir: Path, archive: Path, on_event=None, report_unchanged: bool = True) -> Snapshot | None:
    """Snapshot one run in progress and report it; a failure is reported, never raised, so that one
    bad run costs neither the others their snapshot nor a sweep its runs."""
    try:
        snap = snapshot_run(run_dir, archive)
    except (ValueError, RuntimeError, OSError) as e:
        if on_event:
            on_event("fail", f"{run_dir.name}: not snapshotted ({e})")
        return None
    if snap is not None and on_event and (report_unchanged or not snap.unchanged):
        on_event("same" if snap.unchanged else "snap", f"{run_dir.name}  update {snap.update}, {snap.episodes} episodes")
    return snap


def _snapshot_running(names: list[str], out: Path, archive: Path, on_event=None) -> None:
    """The periodic snapshot of `run_sweep`: runs in progress that have a checkpoint."""
    for name in names:
        if state_of(out / name) == "resume":  # else no checkpoint yet
            _snapshot_one(out / name, archive, on_event, report_unchanged=False)


def snapshot_sweep(points: list[SweepPoint], out: Path, archive: Path, on_event=None) -> list[Snapshot]:
    """Snapshot every unfinished point of `out` that has a checkpoint into `archive/_partial/`
    (and archive finished ones not archived yet), so a session can commit the hours of a run in
    progress before its machine goes. Safe while the sweep is running."""
    out, taken = Path(out), []
    for p in points:
        run_dir = out / p.name
        st = state_of(run_dir)
        if st == "done":
            if not is_archived(archive, p.name):
                archive_run(run_dir, archive)
                if on_event:
                    on_event("archive", p.name)
            drop_partial(archive, p.name)
        elif st == "resume" and not is_archived(archive, p.name):
            snap = _snapshot_one(run_dir, archive, on_event)
            if snap is not None:
                taken.append(snap)
    return taken


@dataclass(frozen=True)
class PointStatus:
    """Where one grid point stands, read from the sweep directory and the archive only."""

    name: str
    state: str  # archived | done | running | resumable | snapshot | started | not started
    episodes: int | None  # episodes recorded so far (finished: all of them)
    budget: int
    final: float | None = None  # mean paper metric of the last 500 episodes, finished runs only
    note: str = ""


def _json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _latest_checkpoint_episodes(run_dir: Path) -> int | None:
    stem = latest_checkpoint(run_dir)
    meta = _json(Path(str(stem) + ".json")) if stem is not None else None
    return int(meta["episodes"]) if meta and "episodes" in meta else None


def _rows(csv_path: Path) -> int | None:
    try:
        with open(csv_path, "rb") as f:
            return max(sum(1 for _ in f) - 1, 0)
    except OSError:
        return None


def sweep_status(points: list[SweepPoint], out: Path, archive: Path | None = None) -> list[PointStatus]:
    """The state of every point, without running or changing anything (safe while sweeps run)."""
    out, rows = Path(out), []
    for p in points:
        run_dir = out / p.name
        budget = p.episodes if p.episodes is not None else int(p.expected_config(None)["episodes"])
        if archive is not None and is_archived(archive, p.name):
            summ = _json(Path(archive) / p.name / "summary.json") or {}
            rows.append(PointStatus(p.name, "archived", summ.get("episodes"), budget,
                                    summ.get("final_paper_metric_last500")))
            continue
        st = state_of(run_dir)
        if st == "done":
            summ = _json(run_dir / "summary.json") or {}
            rows.append(PointStatus(p.name, "done", summ.get("episodes"), budget,
                                    summ.get("final_paper_metric_last500"),
                                    "not archived yet" if archive is not None else ""))
            continue
        ckpt = _latest_checkpoint_episodes(run_dir) if st == "resume" else None
        if _held(run_dir):
            rows.append(PointStatus(p.name, "running", _rows(run_dir / "metrics.csv"), budget,
                                    note=f"checkpoint at {ckpt:,}" if ckpt is not None else ""))
        elif st == "resume":
            rows.append(PointStatus(p.name, "resumable", ckpt, budget, note="resumes from its last checkpoint"))
        elif archive is not None and (partial_dir(archive, p.name) / "checkpoints").is_dir():
            rows.append(PointStatus(p.name, "snapshot", _latest_checkpoint_episodes(partial_dir(archive, p.name)),
                                    budget, note="restored from the archive's _partial/ and resumed"))
        elif run_dir.is_dir():
            rows.append(PointStatus(p.name, "started", _rows(run_dir / "metrics.csv"), budget,
                                    note="no checkpoint yet: starts over"))
        else:
            rows.append(PointStatus(p.name, "not started", None, budget))
    return rows


LOCK = ".sweep.lock"


def _started(pid: int) -> str | None:
    """When process `pid` started (clock ticks since boot, Linux's /proc), or None where unknown."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _holder(pid: int) -> str:
    """A lock's entry for `pid`: "PID@START", so that another process given the same pid later (pids
    are reused, and a lock can outlive its sweep by days) is not taken for the holder."""
    start = _started(pid)
    return f"{pid}@{start}" if start is not None else str(pid)


def _alive(holder: str) -> bool:
    pid_text, _, start = holder.partition("@")
    pid = int(pid_text)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return not start or _started(pid) in (start, None)


def _holders(path: Path) -> list[str]:
    try:
        entries = path.read_text().split()
        for e in entries:
            int(e.partition("@")[0])
        return entries
    except (OSError, ValueError):
        return []


def _held(run_dir: Path) -> bool:
    """Whether a live process (a sweep or its `hammer train` child) holds the run directory's lock."""
    return any(_alive(h) for h in _holders(run_dir / LOCK))


def _create(path: Path, text: str) -> bool:
    """Create `path` holding `text` unless it exists, atomically: the file appears with its content
    (a hard link of a finished temporary file), so no other sweep ever reads it empty."""
    tmp = path.with_name(f"{LOCK}.{os.getpid()}.tmp")
    tmp.write_text(text)
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    finally:
        tmp.unlink(missing_ok=True)


def _lock(run_dir: Path, child: int | None = None) -> bool:
    """Claim a run directory for this sweep process (and, once started, its `hammer train` child),
    so that several sweeps over one directory (e.g. one per core, or a restarted one next to a
    still-running child) never run the same point twice. A lock whose processes are all gone is
    stale and taken over. Returns False if a live process holds it.

    Every step is atomic: the lock appears with its pids in it (`_create`), the child's pid is added
    by replacing the file whole, and a stale lock is moved aside by one rename before it is taken
    over, so of two sweeps that both found it stale only one moves it; the other then finds the
    winner's lock and backs off (a lock it moved by mistake, taken meanwhile, goes back)."""
    path = run_dir / LOCK
    me = " ".join(_holder(pid) for pid in (os.getpid(), child) if pid is not None)
    if child is not None:  # we hold it already: record the child too
        tmp = path.with_name(f"{LOCK}.{os.getpid()}.tmp")
        tmp.write_text(me)
        os.replace(tmp, path)
        return True
    for _ in range(3):
        if _create(path, me):
            return True
        if _held(run_dir):
            return False
        aside = path.with_name(f"{LOCK}.stale-{os.getpid()}")
        try:
            os.rename(path, aside)  # stale: its sweep and child are gone
        except FileNotFoundError:
            continue  # another sweep moved it first
        if any(_alive(h) for h in _holders(aside)):  # a live lock taken between our check and the move
            try:
                os.link(aside, path)
            except FileExistsError:
                pass
            aside.unlink(missing_ok=True)
            return False
        aside.unlink(missing_ok=True)
    return False


def _unlock(run_dir: Path) -> None:
    (run_dir / LOCK).unlink(missing_ok=True)
