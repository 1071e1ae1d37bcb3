"""A committable copy of a finished run, so a sweep survives a fresh checkout.

Sessions on this project start from a clean clone: `runs/` (checkpoints, logs, per-episode CSVs)
does not carry over, but git does. When a sweep run finishes, its config, summary and per-episode
curve are copied to an archive directory inside the repository (`docs/results/runs/...`):

    <archive>/<run name>/config.json   the resolved RunConfig
    <archive>/<run name>/summary.json  the run's summary
    <archive>/<run name>/metrics.npz   episode (int32), paper_metric, team_return (float32)

about 0.2 MB per 30,000-episode run. The sweep treats an archived run as done, and `hammer plot`
/ `hammer report` read archived runs exactly like run directories. npz is read with
allow_pickle=False: nothing in the archive can execute code.
"""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np

METRICS_NPZ = "metrics.npz"


def is_archived(archive: Path, name: str) -> bool:
    d = Path(archive) / name
    return all((d / f).is_file() for f in ("config.json", "summary.json", METRICS_NPZ))


def archive_run(run_dir: Path, archive: Path) -> Path:
    """Copy a finished run directory's record into `archive/<run name>/`; returns that directory."""
    run_dir = Path(run_dir)
    if not (run_dir / "summary.json").is_file():
        raise FileNotFoundError(f"{run_dir} has no summary.json: only finished runs are archived")
    dest = Path(archive) / run_dir.name
    dest.mkdir(parents=True, exist_ok=True)
    eps, metric, team = [], [], []
    with open(run_dir / "metrics.csv", newline="") as f:
        for row in csv.DictReader(f):
            eps.append(int(float(row["episode"])))
            metric.append(float(row["paper_metric"]))
            team.append(float(row["team_return"]))
    tmp = dest / (METRICS_NPZ + ".tmp.npz")
    np.savez_compressed(tmp, episode=np.asarray(eps, np.int32), paper_metric=np.asarray(metric, np.float32),
                        team_return=np.asarray(team, np.float32))
    tmp.replace(dest / METRICS_NPZ)
    for f in ("config.json", "summary.json"):  # summary last: its presence marks a complete copy
        shutil.copyfile(run_dir / f, dest / f)
    return dest


def load_metrics_npz(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with np.load(Path(path), allow_pickle=False) as z:
        return (z["episode"].astype(np.float64), z["paper_metric"].astype(np.float64),
                z["team_return"].astype(np.float64))
