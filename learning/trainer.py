"""The in-process vectorised HAMMER trainer.

One loop, CleanRL style: collect T vector steps from K env copies with the team, compute GAE for
the local agents (and, in rl mode, for the central agent's message streams), then run PPO epochs
over shuffled minibatches of the T*K rows (each row carries all N agents, so the central network
runs once per row).

Reproducibility: acting draws from `learning.sampling` streams, minibatch order from a stream
keyed by the update index, and the env copies are reseeded at every checkpoint point (every
`checkpoint_every` updates, seed `env_reset_seed(seed, update)`), because a VecEnv's internal state
cannot be saved. A checkpoint therefore holds everything needed to continue bit-exactly.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from hammer.envs.base import VecEnv, VecStep
from hammer.learning.central_acting import CentralOut
from hammer.learning.config import RunConfig
from hammer.learning.episodes import episode_rows
from hammer.learning.ppo_update import TeamLearner
from hammer.learning.rollout import RolloutWriter
from hammer.learning.run_env import make_env
from hammer.learning.rundir import RunDir
from hammer.learning.sampling import ActingStreams, env_reset_seed
from hammer.learning.team import torch_device


@dataclass
class Progress:
    """What the trainer reports after every update (for progress bars)."""

    episodes: int
    budget: int
    env_steps: int
    steps_per_s: float
    running_metric: float  # mean paper metric of the last 100 episodes
    update: int


class Trainer:
    def __init__(self, cfg: RunConfig, run_dir: RunDir, env: VecEnv | None = None,
                 on_progress: Callable[[Progress], None] | None = None, tensorboard: bool = True) -> None:
        torch.set_num_threads(cfg.torch_threads)
        self.cfg, self.rd, self.on_progress = cfg, run_dir, on_progress
        torch_device(cfg)  # an unusable device fails before the envs (maybe processes) start
        self.env = env if env is not None else make_env(cfg)
        if self.env.spec.n_agents != cfg.n_agents or self.env.num_envs != cfg.num_envs:
            raise ValueError("env does not match the config's n_agents/num_envs")
        self.learner = TeamLearner(cfg, self.env.spec)
        self.team, self.buf = self.learner.team, self.learner.buf
        self.writer = RolloutWriter(self.buf.arrays, self.env.spec)
        self.streams = ActingStreams(cfg.seed, cfg.n_agents)
        self.update = 0
        self.episodes = 0
        self.env_steps = 0
        self.wall_offset = 0.0
        self._t0 = time.perf_counter()  # run() restarts the clock; set here so _collect works on its own
        self.recent: deque[float] = deque(maxlen=500)
        self.tensorboard = tensorboard

    # ----- checkpoints --------------------------------------------------------------------------
    def checkpoint(self) -> None:
        tensors, meta = self.learner.state_tensors()
        meta.update(update=self.update, episodes=self.episodes, env_steps=self.env_steps,
                    wall_time=self._wall(), streams=self.streams.state(), recent=list(self.recent),
                    config=self.cfg.model_dump(mode="json"))
        self.rd.save_checkpoint(self.update, tensors, meta)

    def restore(self) -> None:
        """Load the run directory's latest checkpoint into this trainer."""
        stem = self.rd.latest_checkpoint()
        if stem is None:
            raise FileNotFoundError(f"{self.rd.path}: no checkpoint to resume from")
        tensors, meta = RunDir.load_checkpoint(stem)
        self.learner.load_state(tensors, meta)
        self.streams.set_state(meta["streams"])
        self.update, self.episodes, self.env_steps = meta["update"], meta["episodes"], meta["env_steps"]
        self.wall_offset = meta["wall_time"]
        self.recent = deque(meta["recent"], maxlen=500)
        self.rd.truncate_metrics(self.episodes)
        self._resumed = True

    def _wall(self) -> float:
        return self.wall_offset + time.perf_counter() - self._t0

    # ----- main loop ----------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        cfg, team, env = self.cfg, self.team, self.env
        resumed = self.start()
        k = cfg.num_envs
        done_training = self.episodes >= cfg.episodes
        obs = prev = None
        while not done_training:
            if self.update % cfg.checkpoint_every == 0:
                if not resumed:
                    self.checkpoint()
                resumed = False
                obs, _ = env.reset(env_reset_seed(cfg.seed, self.update))
                prev = team.zero_prev_actions(k)
            obs, prev, done_training = self._collect(obs, prev)
            if done_training:
                break
            self.log_update(self.learner.learn(obs, prev, self.update, self.vector_step))
        return self.finish()

    def start(self) -> bool:
        """Start the clocks and the TensorBoard log; returns whether this session resumes a run."""
        self._t0 = time.perf_counter()
        resumed = getattr(self, "_resumed", False)
        self._steps_at_start, self._t_start = self.env_steps, time.perf_counter()
        # a resumed run drops what its last life logged after the checkpoint; the update logged at
        # the checkpoint's own env-step count came before it and stays (purge = steps >= this)
        purge = self.env_steps + 1 if resumed else None
        self._tb = self.rd.tensorboard(purge_step=purge) if self.tensorboard else None
        return resumed

    def log_update(self, stats: dict[str, float]) -> None:
        """Count the update just learned and log its statistics."""
        self.update += 1
        sps = (self.env_steps - self._steps_at_start) / max(time.perf_counter() - self._t_start, 1e-9)
        running = float(np.mean(list(self.recent)[-100:])) if self.recent else float("nan")
        tb = self._tb
        if tb is not None:
            for name, val in {**stats, "policy_lag": 0}.items():  # the tags of `hammer up` (synchronous: lag 0)
                tb.add_scalar(f"train/{name}", val, self.env_steps)
            tb.add_scalar("perf/env_steps_per_s", sps, self.env_steps)
            if self.recent:
                tb.add_scalar("episode/paper_metric_100", running, self.env_steps)
        self.rd.flush()
        if self.on_progress:
            self.on_progress(Progress(self.episodes, self.cfg.episodes, self.env_steps, sps, running, self.update))

    def finish(self) -> dict[str, Any]:
        """Export the final policy and write the summary; returns it."""
        cfg, team = self.cfg, self.team
        self.rd.flush()
        elapsed = time.perf_counter() - self._t_start
        summary = self._summary(elapsed, self.env_steps - self._steps_at_start)
        self.rd.export_policy(team.local.export_numpy(),
                              team.central.export_numpy() if team.central is not None else None,
                              {"variant": cfg.variant, "central_mode": cfg.central_mode})
        self.rd.write_summary(summary)
        self.rd.close()
        return summary

    def _summary(self, elapsed: float, steps: int) -> dict[str, Any]:
        import csv

        with open(self.rd.metrics_path, newline="") as f:
            rows = list(csv.DictReader(f))
        paper = np.array([float(r["paper_metric"]) for r in rows[-500:]])
        team = np.array([float(r["team_return"]) for r in rows[-500:]])
        return {
            "episodes": self.episodes,
            "env_steps": self.env_steps,
            "updates": self.update,
            "final_paper_metric_last500": float(paper.mean()) if len(paper) else None,
            "final_team_return_last500": float(team.mean()) if len(team) else None,
            "wall_time": self._wall(),
            "env_steps_per_s_this_session": steps / max(elapsed, 1e-9),
            "n_agents": self.cfg.n_agents,
            "episode_length": int(self.env.spec.max_steps),
            "variant": self.cfg.variant,
            "central_mode": self.cfg.central_mode,
            "env": self.cfg.env,
        }

    @property
    def vector_step(self) -> int:
        """The vector step being acted (1 first), as the env host of `hammer up` numbers it; before
        `_record` counts it."""
        return self.env_steps // self.cfg.num_envs + 1

    def _collect(self, obs: np.ndarray, prev: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """Fill the rollout buffer; returns the next obs/prev actions and whether the budget is spent."""
        cfg, team, streams = self.cfg, self.team, self.streams
        self.writer.begin()
        for t in range(cfg.rollout_steps):
            state = team.global_state(obs, prev, self.vector_step)
            c, action, logp, value = team.act(obs, state, streams, cfg.msg_dropout)
            st = self.env.step(team.env_action(action))
            obs, prev, spent = self._record(t, obs, prev, state, c, action, logp, value, st)
            if spent:
                return obs, prev, True
        return obs, prev, False

    def _record(self, t: int, obs: np.ndarray, prev: np.ndarray, state: np.ndarray, c: CentralOut,
                action: np.ndarray, logp: np.ndarray, value: np.ndarray, st: VecStep
                ) -> tuple[np.ndarray, np.ndarray, bool]:
        """Write vector step t into the buffer, value the copies it reset and log the episodes it
        finished; returns the next obs/prev actions and whether the budget is spent. (The
        seed-batched trainer acts for many seeds at once, then records each seed through this.)"""
        cfg, team, buf = self.cfg, self.team, self.buf
        buf.state[t], buf.msg_raw[t], buf.keep[t], buf.logp[t], buf.values[t] = state, c.raw, c.keep, logp, value
        buf.c_logp[t], buf.c_values[t] = c.logp, c.value
        nxt = self.writer.write(t, obs, prev, c.sent, action, st)
        prev, idx = nxt.prev, nxt.reset_idx
        if idx.size:
            fstate = team.global_state(st.final_obs[idx], nxt.final_prev, self.vector_step, idx)
            buf.final_values[t, idx] = team.local_values(st.final_obs[idx], team.bootstrap_messages(fstate))
            buf.c_final_values[t, idx] = team.central_values(fstate)
        obs = st.obs
        self.env_steps += cfg.num_envs
        if st.episodes:
            rows = episode_rows(st.episodes, self.episodes, cfg.episodes, self.recent, self.env_steps,
                                round(self._wall(), 3))
            self.episodes += len(rows)
            self.rd.append_episodes(rows)
            if self.episodes >= cfg.episodes:
                return obs, prev, True
        return obs, prev, False


def train(cfg: RunConfig, run_dir: RunDir, resume: bool = False, env: VecEnv | None = None,
          on_progress: Callable[[Progress], None] | None = None, tensorboard: bool = True) -> dict[str, Any]:
    """Run (or resume) one training run to its episode budget; returns the summary."""
    trainer = Trainer(cfg, run_dir, env=env, on_progress=on_progress, tensorboard=tensorboard)
    try:
        if resume:
            trainer.restore()
        return trainer.run()
    finally:
        trainer.env.close()
