"""Per-episode link counters: the roles' step logs summed over each episode's steps.

The env host writes `RUN/episode_links.csv` with one row per recorded episode: the env copy, its
length and its span of global vector steps `start_step..end_step` (an episode of length L that
finished at step s spans s-L+1..s), plus the fallback / default-action entries it counted itself.
At the end of `hammer up` this module adds, for every link of the run's variant and every event of
`EPISODE_EVENTS`, the sum over the episode's steps of the roles' step logs (`faults.steplog`).

What a count means: step-loop messages are per (step, agent) and cover every env copy at once, so
`central_local_dropped = 4` says that 4 of the (step, agent) messages for this episode's steps
were dropped; the same message counts in every episode running at that step (16 env copies in
step: once in each of the 16 episodes). Summed over all episodes, a step's events therefore count
once per recorded episode covering that step, and events at steps outside every recorded episode
(the unfinished episodes at the end of the budget) are in `links.json` only. Where a process's
step log was rotated and its oldest rows deleted (`step_log_max_mb`, faults.steplog), the
episodes that began at or before the last deleted step get empty link columns: unknown, not zero.

Torch-free, numpy only.
"""

from __future__ import annotations

import csv
import itertools
import logging
from pathlib import Path

import numpy as np
from hammer.faults.links import LINK_IDS
from hammer.faults.steplog import STEP_LOG_DIR, read_cut

log = logging.getLogger(__name__)

EPISODE_EVENTS = ("sent", "dropped", "duplicated", "delivered", "late", "duplicate")
BASE_COLUMNS = ("episode", "env_index", "length", "start_step", "end_step", "msg_fallbacks", "default_actions")


def read_step_logs(directory: Path, chunk_lines: int = 65_536) -> dict[str, np.ndarray]:
    """Counts per column (`<link_id>_<event>`) indexed by global step, summed over every process,
    role and row. A last line without its newline (a process killed while writing) is skipped.
    Read in chunks into numpy arrays: the logs of a run of hours hold millions of rows, which a
    Python object per (step, column) would turn into gigabytes in the launcher at the run's end."""
    acc: dict[str, np.ndarray] = {}
    top = -1
    for path in sorted(Path(directory).glob("*.csv")):
        with open(path) as f:
            first = f.readline()
            header = first.rstrip("\n").split(",") if first.endswith("\n") else []
            if not header or header[0] != "step":
                log.warning("%s: not a step log (header %r); skipped", path, header)
                continue
            cols = header[1:]
            while lines := list(itertools.islice(f, chunk_lines)):
                if not lines[-1].endswith("\n"):  # torn: only ever the file's last line
                    lines.pop()
                if not lines:
                    break
                rows = np.loadtxt(lines, delimiter=",", dtype=np.int64, ndmin=2)
                if rows.shape[1] != len(header):
                    raise ValueError(f"{path}: rows of {rows.shape[1]} values under a header of {len(header)}")
                steps = rows[:, 0]
                for j, c in enumerate(cols, start=1):
                    hit = rows[:, j] != 0
                    if not hit.any():
                        continue
                    need = int(steps[hit].max()) + 1
                    top = max(top, need - 1)
                    a = acc.get(c)
                    if a is None or len(a) < need:
                        grown = np.zeros(max(need, 2 * len(a) if a is not None else need), np.int64)
                        if a is not None:
                            grown[:len(a)] = a
                        acc[c] = a = grown
                    np.add.at(a, steps[hit], rows[hit, j])
    return {c: a[:top + 1] if len(a) > top else np.concatenate([a, np.zeros(top + 1 - len(a), np.int64)])
            for c, a in acc.items()}


def step_totals(counts: dict[str, np.ndarray]) -> dict[str, dict[str, int]]:
    """Run totals per link and event (compare with `links.json`)."""
    out: dict[str, dict[str, int]] = {}
    for link, lid in LINK_IDS.items():
        for c, a in counts.items():
            if c.startswith(lid + "_"):
                out.setdefault(link, {})[c[len(lid) + 1:]] = int(a.sum())
    return out


def episode_columns(links: list[str]) -> list[str]:
    return [f"{LINK_IDS[link]}_{e}" for link in links for e in EPISODE_EVENTS]


def join(episodes: list[dict], counts: dict[str, np.ndarray], links: list[str], cut: int = -1) -> list[dict]:
    """Each episode row (with start_step, end_step) plus the sum of every link column over its
    steps (inclusive); columns no step log has are 0; an episode beginning at or before `cut` (the
    last step whose step-log rows were deleted) gets "" in every link column."""
    top = max([len(a) for a in counts.values()] + [int(e["end_step"]) + 1 for e in episodes] + [1])
    cums = {}
    for c in episode_columns(links):
        a = np.zeros(top, np.int64)
        if c in counts:
            a[:len(counts[c])] = counts[c]
        cums[c] = np.concatenate([[0], np.cumsum(a)])
    out = []
    for e in episodes:
        lo, hi = int(e["start_step"]), int(e["end_step"])
        if lo <= cut:
            out.append({**e, **dict.fromkeys(cums, "")})
            continue
        out.append({**e, **{c: int(cum[hi + 1] - cum[lo]) for c, cum in cums.items()}})
    return out


def read_episodes(path: Path) -> list[dict]:
    """Every row as ints ("" where a link column is unknown, after a step log was rotated: None)."""
    with open(path, newline="") as f:
        return [{k: int(v) if v != "" else None for k, v in row.items()} for row in csv.DictReader(f)]


def write_episode_links(run_dir: Path, links: list[str], return_rows: bool = True) -> list[dict]:
    """Rewrite RUN/episode_links.csv with the per-episode link columns of `links` added (from
    RUN/linksteps/*.csv); returns the rows (`return_rows=False`: [], and the episodes stream from
    the file to the new one, so a run of millions of episodes is never held in memory). Nothing to
    do (returns []) without the env host's file."""
    run_dir = Path(run_dir)
    path = run_dir / "episode_links.csv"
    if not path.is_file():
        return []
    counts = read_step_logs(run_dir / STEP_LOG_DIR)
    cut = read_cut(run_dir / STEP_LOG_DIR)
    columns = episode_columns(links)
    cums = {c: np.concatenate([[0], np.cumsum(counts.pop(c))]) if c in counts else None for c in columns}
    kept: list[dict] = []
    tmp = path.with_suffix(".csv.tmp")
    with open(path, newline="") as src, open(tmp, "w", newline="") as out:
        reader = csv.DictReader(src)
        base = [c for c in BASE_COLUMNS if c in (reader.fieldnames or BASE_COLUMNS)]
        missing = [c for c in ("start_step", "end_step") if reader.fieldnames and c not in reader.fieldnames]
        if missing:
            raise ValueError(f"{path}: no {', '.join(missing)} column (written by an older env host?)")
        w = csv.DictWriter(out, fieldnames=base + columns, lineterminator="\n")
        w.writeheader()
        for e in reader:
            row: dict = {c: int(e[c]) for c in base}
            lo, hi = row["start_step"], row["end_step"]
            for c, cum in cums.items():
                if lo <= cut:
                    row[c] = ""
                elif cum is None:
                    row[c] = 0
                else:
                    row[c] = int(cum[min(hi + 1, len(cum) - 1)] - cum[min(lo, len(cum) - 1)])
            w.writerow(row)
            if return_rows:
                kept.append(row)
    tmp.replace(path)
    return kept
