"""The learner's TensorBoard points on `hammer train`'s axis and tags.

`hammer train` logs every update at its env-step count (K copies x T steps per rollout) with the
running paper metric of the last 100 finished episodes and the env-step rate. The learner of a
`hammer up` run sees the same rollouts, so it recovers the same points from the chunks: env steps
are update x K x T (every chunk is a full rollout), finished episodes come out of the chunk's
rewards, active masks and resets through the env's own `EpisodeTracker` (the same sums the env
host writes into metrics.csv). After a resume the last episodes before the checkpoint are read
back from metrics.csv, as the trainer keeps them in its checkpoint.
"""

from __future__ import annotations

import csv
import time
from collections import deque

import numpy as np
from hammer.envs.base import EpisodeTracker
from hammer.learning.config import RunConfig
from hammer.learning.rundir import RunDir


class TrainCurve:
    def __init__(self, cfg: RunConfig, rd: RunDir, update: int) -> None:
        self.steps_per_update = cfg.num_envs * cfg.rollout_steps
        self.tracker = EpisodeTracker(cfg.num_envs)
        self.recent: deque[float] = deque(maxlen=100)
        self.start_steps, self.t0 = self.env_steps(update), None
        if update and rd.metrics_path.is_file():
            with open(rd.metrics_path, newline="") as f:
                self.recent.extend(float(r["paper_metric"]) for r in csv.DictReader(f)
                                   if int(r["env_steps"]) <= self.start_steps)

    def env_steps(self, update: int) -> int:
        return update * self.steps_per_update

    def purge_step(self, update: int) -> int:
        """A resumed run drops the points an earlier session logged after its checkpoint."""
        return self.env_steps(update) + 1

    def add(self, rollout: dict[str, np.ndarray]) -> None:
        if self.t0 is None:
            self.t0 = time.perf_counter()
        for t in range(rollout["rewards"].shape[0]):
            done = rollout["reset"][t].any(axis=1)
            self.recent.extend(e.paper_metric for e in self.tracker.record(rollout["rewards"][t],
                                                                          rollout["active"][t], done))

    def log(self, tb, update: int, stats: dict) -> None:
        """The points of update `update` (counted after it), as `hammer train` writes them."""
        x = self.env_steps(update)
        for name, v in stats.items():
            tb.add_scalar(f"train/{name}", v, x)
        rate = (x - self.start_steps) / max(time.perf_counter() - (self.t0 or time.perf_counter()), 1e-9)
        tb.add_scalar("perf/env_steps_per_s", rate, x)
        if self.recent:
            tb.add_scalar("episode/paper_metric_100", float(np.mean(self.recent)), x)
