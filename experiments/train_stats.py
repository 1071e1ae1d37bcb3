"""The learners' per-update statistics (policy entropy, approximate KL, clip fraction, losses),
kept next to an archived run and drawn by `hammer diagnose`.

Why keep them: a final score says *that* a run fell back after it had learned (the multiwalker
runs do), not *why*. The trainer already writes these numbers to TensorBoard (`tb/`, ~2 MB per
multiwalker run and lost with the machine); the archive keeps a compact copy:

    <archive>/<run name>/train_stats.npz
        step     int64    env steps at each logged update
        episode  int32    episodes finished by then (from metrics.csv): the curves' x axis
        <tag>    float32  one value per update; "train/local/entropy" is stored as
                          "train.local.entropy"; NaN where a tag was not logged

Read with allow_pickle=False. TensorBoard's own reader applies the purges a resumed run writes,
so a resumed run's statistics are its uninterrupted ones (the trainer resumes exactly). A run
restored from a `_partial/` snapshot on another machine has statistics only from the restore on:
snapshots do not carry `tb/`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from hammer.experiments.metrics_csv import read_metrics_csv

TRAIN_STATS_NPZ = "train_stats.npz"
PREFIX = "train/"  # only the learners' statistics; speed and running means are elsewhere


def read_tensorboard(run_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{tag: (steps, values)} for every `train/...` scalar in `run_dir/tb`; {} if there is none.
    Only in-process runs (`hammer train`, sweeps): their steps are env steps."""
    tb = Path(run_dir) / "tb"
    if not tb.is_dir() or not any(tb.glob("events.out.tfevents.*")):
        return {}
    if (Path(run_dir) / "learner_summary.json").is_file():
        raise ValueError(f"{run_dir} is a `hammer up` run: its learner logs statistics per update, not per "
                         "env step, so they cannot be placed on the episode axis; fix: diagnose in-process "
                         "runs (`hammer train`, `hammer sweep`), or read tb/ with TensorBoard")
    import logging

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    # it warns for every purge a resumed run wrote; purging is exactly what we want
    logging.getLogger("tensorboard").setLevel(logging.ERROR)
    acc = EventAccumulator(str(tb), size_guidance={"scalars": 0})  # 0 = keep every point
    acc.Reload()
    out = {}
    for tag in acc.Tags()["scalars"]:
        if tag.startswith(PREFIX):
            events = acc.Scalars(tag)
            out[tag] = (np.array([e.step for e in events], np.int64), np.array([e.value for e in events], np.float32))
    return out


def _episodes_at(ends: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Episodes finished by each env-step count, from metrics.csv's cumulative env_steps (`ends`)."""
    return np.searchsorted(ends, steps, side="right").astype(np.int32)


def _episode_ends(run_dir: Path) -> np.ndarray:
    return read_metrics_csv(Path(run_dir) / "metrics.csv")["env_steps"]


def _key(tag: str) -> str:
    if "." in tag:  # "/" maps to "." in the npz keys; a dot would not map back
        raise ValueError(f"statistic tag {tag!r} has a '.'; the trainer's tags never do")
    return tag.replace("/", ".")


def write_train_stats(run_dir: Path, dest_dir: Path, ends: np.ndarray | None = None) -> Path | None:
    """Write `dest_dir/train_stats.npz` from the run's TensorBoard events; None if it has none.
    `ends`: metrics.csv's env_steps column if the caller has read it already."""
    stats = read_tensorboard(run_dir)
    if not stats:
        return None
    # every train/ tag is logged at every update, so one step axis serves all (NaN if one is missing)
    steps = np.unique(np.concatenate([s for s, _ in stats.values()]))
    ends = _episode_ends(run_dir) if ends is None else ends
    arrays = {"step": steps, "episode": _episodes_at(ends, steps)}
    for tag, (s, v) in sorted(stats.items()):
        col = np.full(len(steps), np.nan, np.float32)
        col[np.searchsorted(steps, s)] = v
        arrays[_key(tag)] = col
    dest_dir = Path(dest_dir)
    tmp = dest_dir / (TRAIN_STATS_NPZ + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(dest_dir / TRAIN_STATS_NPZ)
    return dest_dir / TRAIN_STATS_NPZ


def load_train_stats(run_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{tag: (episodes, values)} of a run: its archived train_stats.npz, else its TensorBoard
    events (a run directory); {} if it has neither."""
    run_dir = Path(run_dir)
    npz = run_dir / TRAIN_STATS_NPZ
    if npz.is_file():
        with np.load(npz, allow_pickle=False) as z:
            episode = z["episode"].astype(np.int64)
            out = {}
            for key in z.files:
                if key in ("step", "episode"):
                    continue
                v = z[key].astype(np.float64)
                keep = ~np.isnan(v)
                out[key.replace(".", "/")] = (episode[keep], v[keep])
            return out
    if not (run_dir / "metrics.csv").is_file():
        return {}
    stats = read_tensorboard(run_dir)
    ends = _episode_ends(run_dir) if stats else None
    return {tag: (_episodes_at(ends, steps).astype(np.int64), values.astype(np.float64))
            for tag, (steps, values) in stats.items()}
