"""What the env host keeps across a kill: its counters, its episode rows, and the files that hold them.

Resuming (`hammer up --resume`): at every checkpoint point (update % checkpoint_every == 0, where
the env copies are reseeded anyway) the host writes `host_state/ckpt_<update>.json` (its counters,
recent metrics, wall clock) after flushing metrics.csv and the episode rows, so a run killed later
can continue from the latest update that has both this file and the learner's checkpoint.

`episode_links.csv` holds one row per finished episode: its env copy, length, span of global steps
(`start_step..end_step`), and how many agent x copy entries of that copy acted on a fallback
message and used the declared default action (faults/episode_links.py adds the per-link columns).
"""

from __future__ import annotations

import csv
import json
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hammer.learning.rundir import RunDir, fsync_file

HOST_STATE_DIR = "host_state"
EPISODE_LINKS = "episode_links.csv"
EPISODE_ROW_COLUMNS = ("episode", "env_index", "length", "start_step", "end_step", "msg_fallbacks", "default_actions")


def host_state_path(run_dir: Path, update: int) -> Path:
    return Path(run_dir) / HOST_STATE_DIR / f"ckpt_{update:07d}.json"


def host_state_updates(run_dir: Path) -> list[int]:
    """The updates with a saved host state, ascending."""
    d = Path(run_dir) / HOST_STATE_DIR
    return sorted(int(p.stem[5:]) for p in d.glob("ckpt_*.json")) if d.is_dir() else []


def read_host_state(run_dir: Path, update: int) -> dict:
    return json.loads(host_state_path(run_dir, update).read_text())


def write_host_state(run_dir: Path, state: dict, keep: int = 5) -> Path:
    """Atomic (tmp + fsync + rename); keeps the `keep` latest (the learner keeps 3 checkpoints)."""
    path = host_state_path(run_dir, int(state["update"]))
    path.parent.mkdir(exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(state))
    fsync_file(tmp)
    tmp.replace(path)
    for old in host_state_updates(run_dir)[:-keep]:
        host_state_path(run_dir, old).unlink(missing_ok=True)
    return path


@dataclass
class HostState:
    """The env host's counters; all but the latencies survive a resume."""

    update: int = 0
    episodes: int = 0
    env_steps: int = 0
    step: int = 0  # global vector-step counter (message header)
    recent: deque = field(default_factory=lambda: deque(maxlen=500))
    step_latency_ms: deque = field(default_factory=lambda: deque(maxlen=2000))
    steps_at_start: int = 0  # env steps before this session (resume)
    wall_start: float = field(default_factory=time.perf_counter)  # perf_counter at wall_time 0 of the run

    def wall_time(self) -> float:
        return time.perf_counter() - self.wall_start


class EpisodeRows:
    """The finished episodes' rows of episode_links.csv, written to the file as they come.

    A served run finishes thousands of episodes a minute for hours; a row kept in memory for the
    end of the run (~170 B each) made the env host grow without end. Only the rows since the last
    write are held (`pending`, at most `write_every`); the file is the record. A checkpoint
    fsyncs it (`append_new`), and resuming cuts it back to the checkpoint's episodes (`cut`), so
    rows written after the last checkpoint of a killed session never count."""

    write_every = 256

    def __init__(self, run_dir: Path, num_envs: int) -> None:
        self.path = Path(run_dir) / EPISODE_LINKS
        self.pending: list[tuple] = []
        self.total = 0  # rows of the run: on disk + pending
        # Per env copy, since its current episode started: agent-steps on a fallback message / on the
        # default action. Zeroed where an episode starts: after it ends, and at every env reset.
        self.fallback = np.zeros(num_envs, np.int64)
        self.defaulted = np.zeros(num_envs, np.int64)

    def start(self) -> None:
        """A fresh file: the header only (an earlier attempt's rows must not precede ours)."""
        self.path.write_text(",".join(EPISODE_ROW_COLUMNS) + "\n")
        self.pending, self.total = [], 0

    def count(self, fallback: np.ndarray, defaulted: np.ndarray) -> None:
        """One vector step's (K, N) masks of fallback messages and default actions."""
        self.fallback += fallback.sum(axis=1)
        self.defaulted += defaulted.sum(axis=1)

    def reset_counts(self) -> None:
        self.fallback[:] = self.defaulted[:] = 0

    def add(self, episode: int, e, end_step: int) -> None:
        """The row of finished episode number `episode` (an envs.base.EpisodeStats) ending at `end_step`."""
        i = e.env_index
        self.pending.append((episode, i, e.length, end_step - e.length + 1, end_step,
                             int(self.fallback[i]), int(self.defaulted[i])))
        self.total += 1
        if len(self.pending) >= self.write_every:
            self.write_pending()

    def end(self, finished: list) -> None:
        """These copies' episodes ended (counted or beyond the budget): their next ones start at zero."""
        for e in finished:
            self.fallback[e.env_index] = self.defaulted[e.env_index] = 0

    def write_pending(self) -> None:
        """Append the rows not yet on disk (the header first into an empty file)."""
        if self.pending or not self.path.is_file():
            with open(self.path, "a") as f:
                if f.tell() == 0:
                    f.write(",".join(EPISODE_ROW_COLUMNS) + "\n")
                f.writelines(",".join(map(str, row)) + "\n" for row in self.pending)
            self.pending = []

    def append_new(self) -> None:
        """At a checkpoint point: every row on disk, fsynced (the host state vouches for them)."""
        self.write_pending()
        fsync_file(self.path)

    def write_all(self) -> None:
        """At the end of the run: the last rows."""
        self.write_pending()

    def cut(self, n: int) -> None:
        """Keep the first n rows (base columns; a torn last line is never among them) and drop the
        rest, streaming through the file: what a resumed session continues from."""
        tmp = self.path.with_suffix(".csv.tmp")
        kept = 0
        with open(tmp, "w") as out:
            out.write(",".join(EPISODE_ROW_COLUMNS) + "\n")
            if n:
                with open(self.path, newline="") as f:
                    for row in csv.DictReader(f):
                        if kept == n:
                            break
                        vals = tuple(int(row[c]) for c in EPISODE_ROW_COLUMNS)
                        if vals[0] != kept + 1:
                            break
                        out.write(",".join(map(str, vals)) + "\n")
                        kept += 1
        if kept != n:
            tmp.unlink()
            raise ValueError(f"{self.path}: expected episodes 1..{n}, found {kept} in order")
        fsync_file(tmp)
        tmp.replace(self.path)
        self.pending, self.total = [], n


def save(rd: RunDir, state: HostState, episodes: EpisodeRows) -> None:
    """At a checkpoint point: metrics.csv and the episode rows on disk first, then the host
    state that vouches for them (so every count in it is backed by rows on disk)."""
    rd.flush()
    if rd.metrics_path.is_file():
        fsync_file(rd.metrics_path)
    episodes.append_new()
    write_host_state(rd.path, {
        "update": state.update, "episodes": state.episodes, "env_steps": state.env_steps, "step": state.step,
        "wall_time": state.wall_time(), "recent": list(state.recent), "episode_rows": episodes.total})


def restore(rd: RunDir, state: HostState, episodes: EpisodeRows, update: int, step: int) -> int:
    """Continue from host_state/ckpt_<update>.json: counters, recent metrics and wall clock;
    metrics.csv and episode_links.csv cut back to the episodes it counted. Returns the saved step.

    The step counter does not continue from the saved value but from `step`, which the
    launcher puts above every step the killed session may have reached (its latest host
    state + checkpoint_every x rollout_steps): the roles' per-step link logs (RUN/linksteps/)
    of that session stay on disk and are joined to episodes by step number
    (faults.episode_links), so reusing a number would add the lost rollouts' link events to
    the new episodes."""
    path = host_state_path(rd.path, update)
    saved = read_host_state(rd.path, update)
    if int(saved["update"]) != update or int(saved["episode_rows"]) != int(saved["episodes"]):
        raise ValueError(f"{path}: inconsistent host state (update {saved['update']}, "
                         f"{saved['episodes']} episodes, {saved['episode_rows']} episode rows)")
    if step < int(saved["step"]):
        raise ValueError(f"resume_step {step} is below the saved step counter {saved['step']} ({path})")
    state.update, state.episodes, state.env_steps, state.step = update, int(saved["episodes"]), \
        int(saved["env_steps"]), step
    state.recent = deque((float(x) for x in saved["recent"]), maxlen=state.recent.maxlen)
    state.steps_at_start = state.env_steps
    state.wall_start = time.perf_counter() - float(saved["wall_time"])
    rd.truncate_metrics(state.episodes)
    episodes.cut(state.episodes)
    return int(saved["step"])
