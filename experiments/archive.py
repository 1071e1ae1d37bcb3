"""A committable copy of a finished run, so a sweep survives a fresh checkout.

Sessions on this project start from a clean clone: `runs/` (checkpoints, logs, per-episode CSVs)
does not carry over, but git does. When a sweep run finishes, its config, summary and per-episode
curve are copied to an archive directory inside the repository (`docs/results/runs/...`):

    <archive>/<run name>/config.json   the resolved RunConfig
    <archive>/<run name>/summary.json  the run's summary
    <archive>/<run name>/metrics.npz   episode (int32), paper_metric, team_return (float32)
    <archive>/<run name>/train_stats.npz  the learners' per-update statistics, if the run logged
                                       any (`experiments.train_stats`, drawn by `hammer diagnose`)
    <archive>/<run name>/final/*.safetensors  the trained team's exported weights (30-140 KB), so
                                       `hammer faults` can evaluate the team from a clone

about 0.3 MB per 30,000-episode run. The sweep treats an archived run as done, and `hammer plot`
/ `hammer report` read archived runs exactly like run directories. npz is read with
allow_pickle=False: nothing in the archive can execute code.

A run still in progress (multiwalker: 4-5 hours, longer than a session) survives as a partial
snapshot (`hammer sweep ... --snapshot`, `make snapshot` before a session stops):

    <archive>/_partial/<run name>/config.json, config.yaml
    <archive>/_partial/<run name>/checkpoints/ckpt_<U>.json + .safetensors   the latest complete one
    <archive>/_partial/<run name>/metrics.csv.gz   the first `episodes` rows the checkpoint vouches for

A sweep whose run directory holds neither a summary nor a checkpoint restores the snapshot and
resumes it (`hammer train --resume`), so the run ends exactly as it would have uninterrupted. A
snapshot is checked before use (config, checkpoint JSON, safetensors, CSV) and a broken one is
reported and ignored: the run starts fresh. TensorBoard events (tb/) are not kept: a restored
run's curves there start at the snapshot. Partial runs are never results: `hammer plot` /
`hammer report` skip `_partial`, and a run's snapshot is deleted once the run is archived.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.metrics_csv import read_metrics_csv
from hammer.experiments.train_stats import write_train_stats

log = logging.getLogger(__name__)

METRICS_NPZ = "metrics.npz"
PARTIAL = "_partial"  # in-progress snapshots inside an archive: never a finished result


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
    m = read_metrics_csv(run_dir / "metrics.csv")
    tmp = dest / (METRICS_NPZ + ".tmp.npz")
    np.savez_compressed(tmp, episode=m["episode"].astype(np.int32), paper_metric=m["paper_metric"].astype(np.float32),
                        team_return=m["team_return"].astype(np.float32))
    tmp.replace(dest / METRICS_NPZ)
    try:  # optional: runs trained without TensorBoard have none
        write_train_stats(run_dir, dest, m["env_steps"])
    except ValueError as e:  # a `hammer up` run: archive it without them
        log.warning("%s: learner statistics not archived: %s", run_dir.name, e)
    if (run_dir / "final").is_dir():
        (dest / "final").mkdir(exist_ok=True)
        for f in sorted((run_dir / "final").glob("*.safetensors")):
            shutil.copyfile(f, dest / "final" / f.name)
    for f in ("config.json", "summary.json"):  # summary last: its presence marks a complete copy
        shutil.copyfile(run_dir / f, dest / f)
    return dest


def load_metrics_npz(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with np.load(Path(path), allow_pickle=False) as z:
        return (z["episode"].astype(np.float64), z["paper_metric"].astype(np.float64),
                z["team_return"].astype(np.float64))


# ----- partial snapshots of runs in progress ----------------------------------------------------
@dataclass
class Snapshot:
    name: str
    update: int
    episodes: int
    path: Path
    unchanged: bool = False  # the archive already held this very checkpoint


def partial_dir(archive: Path, name: str) -> Path:
    return Path(archive) / PARTIAL / name


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The run's newest complete checkpoint stem: the trainer's own rule (`RunDir.latest_checkpoint`,
    the JSON is written last and marks a complete pair)."""
    from hammer.learning.rundir import RunDir

    return RunDir(run_dir).latest_checkpoint()


def _csv_head(text: str, n_rows: int) -> str:
    """The header and the first n_rows episodes; a run still writing may have more (or a torn last line)."""
    lines = text.splitlines(keepends=True)
    if len(lines) < n_rows + 1 or not all(ln.endswith("\n") for ln in lines[: n_rows + 1]):
        raise ValueError(f"metrics.csv has fewer than the checkpoint's {n_rows} episodes")
    return "".join(lines[: n_rows + 1])


def snapshot_run(run_dir: Path, archive: Path) -> Snapshot | None:
    """Copy an unfinished run's latest complete checkpoint, config and metrics into
    `archive/_partial/<run name>/`; None if it has no checkpoint yet, ValueError (one-line reason)
    if it cannot be snapshotted. Safe while the run is
    writing: a checkpoint counts only once its JSON exists, the safetensors of that same update
    is copied, and a checkpoint pruned under our feet is retried with the next latest one."""
    run_dir = Path(run_dir)
    dest = partial_dir(archive, run_dir.name)
    for _ in range(5):
        stem = latest_checkpoint(run_dir)
        if stem is None:
            return None
        try:
            meta_text = Path(str(stem) + ".json").read_text()
            meta = json.loads(meta_text)
            update, episodes = int(meta["update"]), int(meta["episodes"])
            old = dest / "checkpoints" / (stem.name + ".json")
            if old.is_file() and old.read_text() == meta_text:
                return Snapshot(run_dir.name, update, episodes, dest, unchanged=True)
            tmp = dest.parent / f".tmp-{run_dir.name}-{os.getpid()}"
            shutil.rmtree(tmp, ignore_errors=True)
            (tmp / "checkpoints").mkdir(parents=True)
            shutil.copyfile(str(stem) + ".safetensors", tmp / "checkpoints" / (stem.name + ".safetensors"))
            with open(run_dir / "metrics.csv", newline="") as f:
                metrics = _csv_head(f.read(), episodes)
        except FileNotFoundError as e:
            if not Path(str(stem) + ".json").is_file():  # pruned by the running trainer: take the new latest
                continue
            raise ValueError(f"{Path(e.filename).name} is missing") from None
        # mtime=0: the same checkpoint always gives the same bytes (no noise in git)
        with open(tmp / "metrics.csv.gz", "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
            gz.write(metrics.encode())
        for f in ("config.json", "config.yaml"):
            if (run_dir / f).is_file():
                shutil.copyfile(run_dir / f, tmp / f)
        (tmp / "checkpoints" / (stem.name + ".json")).write_text(meta_text)
        _swap(tmp, dest)
        return Snapshot(run_dir.name, update, episodes, dest)
    raise RuntimeError(f"{run_dir}: checkpoints kept changing while being copied; try again")


def _swap(tmp: Path, dest: Path) -> None:
    """Replace dest by tmp with two renames; the old copy is removed only after the new one is in place."""
    old = dest.parent / f".old-{dest.name}-{os.getpid()}"
    if dest.exists():
        dest.replace(old)
    tmp.replace(dest)
    shutil.rmtree(old, ignore_errors=True)


def drop_partial(archive: Path, name: str) -> None:
    shutil.rmtree(partial_dir(archive, name), ignore_errors=True)


def check_partial(src: Path, expected: dict | None = None) -> tuple[Path, str]:
    """Validate a snapshot before it is used; returns (checkpoint stem, metrics CSV text) or raises
    ValueError with a one-line reason. `expected` is the point's resolved config (model_dump): the
    snapshot must be a run of exactly that point."""
    from hammer.learning.config import ConfigError, build_config, config_changes
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    src = Path(src)
    try:
        cfg = build_config(json.loads((src / "config.json").read_text())).model_dump(mode="json")
    except FileNotFoundError:
        raise ValueError("no config.json") from None
    except (json.JSONDecodeError, ConfigError) as e:
        raise ValueError(f"config.json is not a valid RunConfig ({str(e).splitlines()[0]})") from None
    if expected is not None:
        diff = list(config_changes(cfg, expected, ignore={"out", "torch_threads"}))
        if diff:
            raise ValueError(f"config differs from this sweep point in {', '.join(diff)}")
    stems = sorted((src / "checkpoints").glob("ckpt_*.json")) if (src / "checkpoints").is_dir() else []
    if len(stems) != 1:
        raise ValueError(f"expected one checkpoint JSON, found {len(stems)}")
    stem = stems[0].with_suffix("")
    try:
        meta = json.loads(stems[0].read_text())
        update, episodes = int(meta["update"]), int(meta["episodes"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{stems[0].name} does not parse ({type(e).__name__})") from None
    if stem.name != f"ckpt_{update:07d}":
        raise ValueError(f"{stems[0].name} says update {update}")
    try:
        load_file(str(stem) + ".safetensors")
    except FileNotFoundError:
        raise ValueError(f"{stem.name}.safetensors is missing") from None
    except (SafetensorError, ValueError, TypeError, OSError) as e:
        raise ValueError(f"{stem.name}.safetensors does not load ({str(e).splitlines()[0][:80]})") from None
    try:
        with gzip.open(src / "metrics.csv.gz", "rt", newline="") as f:
            text = f.read()
        rows = list(csv.reader(io.StringIO(text)))
    except (OSError, EOFError, UnicodeDecodeError) as e:
        raise ValueError(f"metrics.csv.gz does not read ({type(e).__name__})") from None
    if len(rows) != episodes + 1:
        raise ValueError(f"metrics.csv.gz has {len(rows) - 1} episodes, the checkpoint {episodes}")
    return stem, text


def restore_partial(src: Path, run_dir: Path, expected: dict | None = None) -> int:
    """Validate the snapshot at `src` and copy it into `run_dir` (which holds no checkpoint);
    returns the restored update. Raises ValueError (one-line reason) and writes nothing if broken."""
    stem, metrics = check_partial(src, expected)
    run_dir = Path(run_dir)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    for f in ("config.json", "config.yaml"):
        if (Path(src) / f).is_file():
            shutil.copyfile(Path(src) / f, run_dir / f)
    with open(run_dir / "metrics.csv", "w", newline="") as f:
        f.write(metrics)
    shutil.copyfile(str(stem) + ".safetensors", run_dir / "checkpoints" / (stem.name + ".safetensors"))
    shutil.copyfile(str(stem) + ".json", run_dir / "checkpoints" / (stem.name + ".json"))  # last: marks it
    return int(stem.name.split("_")[1])
