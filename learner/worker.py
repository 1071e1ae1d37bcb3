"""The distributed learner process: experience in, versioned weights out.

`LearnerWorker` reads top to bottom as what it does with each message: a central record
(`on_central_record`) is held until the chunk of its step comes; a rollout chunk (`on_chunk`) is
checked, joined with its records, learned from, and the next version's weights are published.

It receives the env host's rollout (one ExperienceChunk per update, tagged with the policy
version that produced it) and, when the central agent holds information the update needs (rl
mode: Gaussian samples, their log-densities and the central critic's values; message dropout:
which messages were dropped), the central agent's per-step records. It rebuilds exactly the
rollout buffer the in-process trainer would have filled, recomputes the acting-time log-probs and
values with the same networks (it holds the version that acted), runs the shared
`TeamLearner.learn`, and publishes the next version's weights as safetensors blobs.

One learner trains both networks ("team"): in backprop mode the local loss flows into the central
network, so splitting them across processes would need a gradient exchange per minibatch.

Resuming (`hammer up --resume`, `resume_from=U`): the learner loads checkpoints/ckpt_<U> (networks
and optimisers, as `hammer train --resume` does) and serves version U; the env host continues from
its own state of the same update. `learner_summary.json` then says `resumed_from: U`; `updates`
and `policy_version` count the whole run, `samples` only the updates of this session.
"""

from __future__ import annotations

import json
import logging
import time
from typing import Any

import numpy as np
from hammer.envs.base import EnvSpec
from hammer.learner.remote_rollout import BehaviourSnapshots, RemoteRollout
from hammer.learner.tb_curve import TrainCurve
from hammer.learning.config import RunConfig
from hammer.learning.host_info import host_info
from hammer.learning.ppo_update import TeamLearner
from hammer.learning.rundir import RunDir
from hammer.protocol.dims import Dims
from hammer.protocol.rollout_layout import RolloutLayout
from hammer.protocol.schemas import ExperienceChunk, Weights
from hammer.protocol.session import QUEUE_DEPTH, HammerSession
from hammer.runtime.bounds import StepWindow
from hammer.runtime.role import Role
from hammer.runtime.settings import RuntimeSettings
from safetensors.numpy import save as save_safetensors


def weights_blob(params: dict[str, np.ndarray]) -> bytes:
    return save_safetensors({k: np.ascontiguousarray(v) for k, v in params.items()})


class LearnerWorker(Role):
    """Serve updates until told to stop.

    max_policy_lag L > 0 (asynchronous): a chunk acted by version w with update - L <= w <= update
    is used; its acting-time log-probs and values are recomputed with the snapshot of version w
    (the behaviour policy), so PPO's ratio pi_new / pi_w corrects for the lag exactly as it does
    for the epochs of one update. The lag of every update is reported (stats, tensorboard)."""

    republish_s = 1.0  # while no experience comes, late joiners (a restarted agent) get the current policy

    def __init__(self, session: HammerSession, cfg: RunConfig, spec: EnvSpec, rd: RunDir, settings: RuntimeSettings,
                 *, central_wait_s: float = 5.0, start_step: int | None = None) -> None:
        super().__init__(session, "learner", report_faults=False, stall_warn_s=settings.stall_warn_s)
        step_window, max_policy_lag, resume_from = settings.step_window, settings.max_policy_lag, settings.resume_from
        self.stall_what = "experience chunks"
        self.last_step = -1  # the env host's step at the last chunk learned from
        # a chunk comes every rollout_steps steps (records are up to L+1 rollouts ahead of the last chunk)
        width = max(step_window, (max_policy_lag + 2) * cfg.rollout_steps)
        self.window = StepWindow(width, start=start_step)  # runtime.bounds.known_step: no forged first chunk
        self.record_window = StepWindow(width, resync_s=None, start=start_step)
        self.cfg, self.rd = cfg, rd
        self.central_wait_s, self.max_policy_lag, self.resume_from = central_wait_s, max_policy_lag, resume_from
        self.learner = TeamLearner(cfg, spec)
        self.team = self.learner.team
        self.rollout = RemoteRollout(self.learner, spec)
        # Every size of the rollout layout declared: a chunk or record that does not fit this run
        # (array names, dtypes, shapes) is rejected and counted by the subscription, never learned from.
        layout = RolloutLayout.from_config(cfg, spec)
        dims = Dims.from_layout(layout)
        self.chunks = session.subscribe(self.keys.exp("team"), ExperienceChunk, dims,
                                        max_bytes=ExperienceChunk.cap_for(layout))
        # One record per vector step arrives while an update runs: room for every step the env host
        # may run ahead (a rollout per update of policy lag, and one more), never a dropped record.
        self.central_records = (session.subscribe(self.keys.exp("central"), ExperienceChunk, dims,
                                                  maxsize=max(QUEUE_DEPTH, layout.t * (max_policy_lag + 2)))
                                if cfg.wiring.needs_central_record else None)
        if self.central_records is not None:
            self.handle_queued(self.central_records, self.on_central_record)
        self.handle(self.chunks, self.on_chunk)
        self.local_weights_pub = session.publisher(self.keys.weights("local"))
        self.central_weights_pub = (session.publisher(self.keys.weights("central"))
                                    if self.team.central is not None else None)
        self.update = 0 if resume_from is None else load_checkpoint(self.learner, rd, resume_from)
        # TensorBoard on `hammer train`'s tags and env-step axis; a resume drops the points logged after the checkpoint.
        self.curve = TrainCurve(cfg, rd, self.update)
        self.tb = rd.tensorboard(purge_step=self.curve.purge_step(self.update) if resume_from is not None else None)
        self.stats: dict[str, Any] = {
            "updates": self.update, "stale_chunks": 0, "central_steps_missing": 0, "samples": 0,
            "max_policy_lag": max_policy_lag, "lagged_updates": 0, "policy_lag_max": 0,
            # where the learner's time goes (seconds, summed over updates): rebuilding the
            # buffer from a chunk, the PPO epochs, encoding + publishing the new weights
            "time_fill_s": 0.0, "time_learn_s": 0.0, "time_publish_s": 0.0}
        self.held_records: dict[int, dict[str, np.ndarray]] = {}  # step -> the central agent's record
        self.behaviour = BehaviourSnapshots(self.team, max_policy_lag)
        self.last_publish = 0.0

    def counters(self) -> dict[str, Any]:
        return {**self.stats, "bad_chunks": self.bad_chunks}

    def gauges(self) -> dict[str, int]:
        return {"policy_version": self.update}

    @property
    def bad_chunks(self) -> int:
        """Chunks and central records rejected by their subscriptions (malformed, or not this run's layout)."""
        subs = [self.chunks] + ([self.central_records] if self.central_records is not None else [])
        return sum(sub.stats.rejected_total for sub in subs)

    def on_start(self) -> None:
        self.publish_weights()
        self.behaviour.keep(self.update)

    # ----- an update, in the order it flows ------------------------------------------------------
    def on_central_record(self, rec: ExperienceChunk) -> None:
        """Hold a central record of a version the next update can use (others can never be joined);
        one for a step beyond the window would be held for ever: rejected."""
        if self.record_window.ahead(rec.step, self.last_step):
            self.reject("step_ahead", f"central record for step {rec.step} while at {self.last_step}")
            return
        if self.update - self.max_policy_lag <= rec.policy_version <= self.update:
            self.held_records[rec.step] = rec.arrays

    def on_chunk(self, chunk: ExperienceChunk) -> None:
        """One rollout: check it, join it with the central records of its steps, learn, publish."""
        lag = self.update - chunk.policy_version
        if lag < 0:
            self.reject("version_ahead", f"experience of version {chunk.policy_version} while at {self.update}")
            return
        if self.window.ahead(chunk.step, self.last_step):
            self.reject("step_ahead", f"experience up to step {chunk.step} while at {self.last_step}")
            return
        if not 0 <= lag <= self.max_policy_lag:
            self.stats["stale_chunks"] += 1
            self.log.warning("experience of version %d while at %d (max lag %d): discarded",
                             chunk.policy_version, self.update, self.max_policy_lag)
            return
        if self.central_records is not None:
            self.wait_central_records({int(s) for s in chunk.arrays["steps"]})
        self.learn_from(chunk.arrays, chunk.policy_version, lag)
        self.last_step = max(self.last_step, chunk.step)
        self.progressed()

    def wait_central_records(self, steps: set[int]) -> None:
        """The central agent's records of these steps, waiting up to `central_wait_s` for them."""
        deadline = time.monotonic() + self.central_wait_s
        while not steps <= self.held_records.keys() and time.monotonic() < deadline:
            rec = self.central_records.get(timeout=0.05)
            if rec is not None:
                self.on_central_record(rec)

    def learn_from(self, rollout: dict[str, np.ndarray], version: int, lag: int) -> None:
        """Fill the buffer as `version` acted it (the behaviour policy), run PPO, publish the next version."""
        stats = self.stats
        t0 = time.perf_counter()
        with self.behaviour.acting_as(version, self.update):
            stats["central_steps_missing"] += self.rollout.fill(
                rollout, self.held_records if self.central_records is not None else None)
        t1 = time.perf_counter()
        for step in [st for st in self.held_records if st <= int(rollout["steps"][-1])]:
            del self.held_records[step]
        stats["lagged_updates"] += int(lag > 0)
        stats["policy_lag_max"] = max(stats["policy_lag_max"], lag)
        self.curve.add(rollout)
        logs = self.learner.learn(rollout["last_obs"], rollout["last_prev"], self.update, int(rollout["steps"][-1]) + 1)
        t2 = time.perf_counter()
        self.update += 1
        stats["updates"] = self.update
        stats["samples"] += int(rollout["active"].sum())
        self.publish_weights()
        stats["time_fill_s"] += t1 - t0
        stats["time_learn_s"] += t2 - t1
        stats["time_publish_s"] += time.perf_counter() - t2
        self.behaviour.keep(self.update)
        logs["policy_lag"] = lag
        self.curve.log(self.tb, self.update, logs)
        if self.update % self.cfg.checkpoint_every == 0:
            tensors, meta = self.learner.state_tensors()
            meta.update(update=self.update, config=self.cfg.model_dump(mode="json"))
            self.rd.save_checkpoint(self.update, tensors, meta)

    def publish_weights(self) -> None:
        self.local_weights_pub.publish(Weights.from_blob("local", self.update,
                                                         weights_blob(self.team.local.export_numpy())))
        if self.central_weights_pub is not None:
            self.central_weights_pub.publish(Weights.from_blob("central", self.update,
                                                               weights_blob(self.team.central.export_numpy())))
        self.last_publish = time.monotonic()

    def on_idle(self) -> None:
        if time.monotonic() - self.last_publish > self.republish_s:
            self.publish_weights()

    def on_stop(self) -> None:
        """Export the policy of the last version and write learner_summary.json."""
        team = self.team
        self.rd.export_policy(team.local.export_numpy(),
                              team.central.export_numpy() if team.central is not None else None,
                              {"variant": self.cfg.variant, "central_mode": self.cfg.central_mode,
                               "version": str(self.update)})
        (self.rd.path / "learner_summary.json").write_text(json.dumps(
            {**self.counters(), **self.gauges(), **self.rejection_counters(), "resumed_from": self.resume_from, "host": host_info()},
            indent=1))
        self.log.info("stopped: %s", self.counters())


def load_checkpoint(learner: TeamLearner, rd: RunDir, update: int) -> int:
    """Networks and optimisers of checkpoints/ckpt_<update> into `learner`; returns the update."""
    stem = rd.ckpt_dir / f"ckpt_{update:07d}"
    if not stem.with_suffix(".json").is_file():
        raise FileNotFoundError(f"{stem}.json is missing: no learner checkpoint of update {update} to resume from")
    tensors, meta = RunDir.load_checkpoint(stem)
    if int(meta.get("update", -1)) != update:
        raise ValueError(f"{stem}.json: holds update {meta.get('update')}, expected {update}")
    learner.load_state(tensors, meta)
    logging.getLogger("hammer.learner").info("resumed from %s", stem)
    return update
