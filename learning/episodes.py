"""Finished episodes into metrics.csv rows: one bookkeeping for `hammer train` and the env host.

Both runners number episodes on from their count, stop at the budget (episodes finishing in the
same vector step past it are dropped), keep the last 500 paper metrics for the running figures, and
write one row per episode: (episode, env_steps, paper_metric, team_return, length, wall_time).
Written once so that `hammer up` reproduces `hammer train`'s metrics.csv row for row.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import Any


def episode_rows(finished: Sequence[Any], count: int, budget: int, recent: deque, env_steps: int,
                 wall: float) -> list[tuple]:
    """The rows of the episodes in `finished` (objects with paper_metric, team_return, length) that
    fit the budget, numbered from `count` + 1; each one's paper metric is appended to `recent`. The
    caller's count grows by len(rows)."""
    rows = []
    for e in finished:
        if count + len(rows) >= budget:
            break
        recent.append(e.paper_metric)
        rows.append((count + len(rows) + 1, env_steps, repr(e.paper_metric), repr(e.team_return), e.length, wall))
    return rows
