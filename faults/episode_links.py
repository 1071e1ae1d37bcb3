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
(the unfinished episodes at the end of the budget) are in `links.json` only.

Torch-free, numpy only.
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np
from hammer.faults.links import LINK_IDS
from hammer.faults.steplog import STEP_LOG_DIR

log = logging.getLogger(__name__)

EPISODE_EVENTS = ("sent", "dropped", "duplicated", "delivered", "late", "duplicate")
BASE_COLUMNS = ("episode", "env_index", "length", "start_step", "end_step", "msg_fallbacks", "default_actions")


def read_step_logs(directory: Path) -> dict[str, np.ndarray]:
    """Counts per column (`<link_id>_<event>`) indexed by global step, summed over every process,
    role and row. A last line without its newline (a process killed while writing) is skipped."""
    acc: dict[str, dict[int, int]] = {}
    for path in sorted(Path(directory).glob("*.csv")):
        lines = path.read_text().split("\n")[:-1]  # the part after the last newline is torn or empty
        header = lines[0].split(",") if lines else []
        if not header or header[0] != "step":
            log.warning("%s: not a step log (header %r); skipped", path, header)
            continue
        cols = header[1:]
        for line in lines[1:]:
            step, *vals = (int(v) for v in line.split(","))
            for c, v in zip(cols, vals, strict=True):
                if v:
                    d = acc.setdefault(c, {})
                    d[step] = d.get(step, 0) + v
    top = max((s for d in acc.values() for s in d), default=-1)
    out: dict[str, np.ndarray] = {}
    for c, d in acc.items():
        a = np.zeros(top + 1, np.int64)
        a[list(d)] = list(d.values())
        out[c] = a
    return out


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


def join(episodes: list[dict], counts: dict[str, np.ndarray], links: list[str]) -> list[dict]:
    """Each episode row (with start_step, end_step) plus the sum of every link column over its
    steps (inclusive); columns no step log has are 0."""
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
        out.append({**e, **{c: int(cum[hi + 1] - cum[lo]) for c, cum in cums.items()}})
    return out


def read_episodes(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: int(v) for k, v in row.items()} for row in csv.DictReader(f)]


def write_episode_links(run_dir: Path, links: list[str]) -> list[dict]:
    """Rewrite RUN/episode_links.csv with the per-episode link columns of `links` added (from
    RUN/linksteps/*.csv); returns the rows. Nothing to do (returns []) without the env host's file."""
    run_dir = Path(run_dir)
    path = run_dir / "episode_links.csv"
    if not path.is_file():
        return []
    episodes = read_episodes(path)
    missing = [c for c in ("start_step", "end_step") if episodes and c not in episodes[0]]
    if missing:
        raise ValueError(f"{path}: no {', '.join(missing)} column (written by an older env host?)")
    rows = join([{c: e[c] for c in BASE_COLUMNS if c in e} for e in episodes],
                read_step_logs(run_dir / STEP_LOG_DIR), links)
    header = [c for c in BASE_COLUMNS if not episodes or c in episodes[0]] + episode_columns(links)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return rows
