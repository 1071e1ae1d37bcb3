"""The one reader of a run directory's `metrics.csv` (one row per finished episode, written by
`hammer train` and `hammer up`), for reports, the archive and the learner statistics."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

COLUMNS = ("episode", "env_steps", "paper_metric", "team_return")


def read_metrics_csv(path: Path) -> dict[str, np.ndarray]:
    """{column: float64 array} for COLUMNS (env_steps: cumulative env steps at each episode's end)."""
    cols: dict[str, list[float]] = {c: [] for c in COLUMNS}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            for c in COLUMNS:
                cols[c].append(float(row[c]))
    return {c: np.asarray(v, np.float64) for c, v in cols.items()}
