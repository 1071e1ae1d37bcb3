"""The distributed learner process: experience in, versioned weights out.

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
import os
import time
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from safetensors.numpy import save as save_safetensors

from envs.base import EnvSpec
from learning.config import RunConfig
from learning.learner import TeamLearner
from learning.rundir import RunDir
from learning.team import Team
from protocol.schemas import Control, ExperienceChunk, Heartbeat, Weights
from protocol.session import HammerSession

log = logging.getLogger("hammer.learner")


class ChunkError(ValueError):
    """An experience chunk whose arrays do not fit this run (named array and what is wrong)."""


def expected_arrays(cfg: RunConfig, spec: EnvSpec, act_dim: int, msg_dim: int) -> dict[str, tuple[tuple, str]]:
    """Name -> (shape, dtype) of the env host's rollout chunk."""
    t, k, n, d = cfg.rollout_steps, cfg.num_envs, cfg.n_agents, spec.obs_dim
    a_shape = spec.action_shape
    return {
        "obs": ((t, k, n, d), "float32"), "prev": ((t, k, n, act_dim), "float32"),
        "msg": ((t, k, n, msg_dim), "float32"),
        "actions": ((t, k, n, *a_shape), "int64" if spec.discrete else "float32"),
        "rewards": ((t, k, n), "float32"), "terminated": ((t, k, n), "bool"), "truncated": ((t, k, n), "bool"),
        "active": ((t, k, n), "bool"), "reset": ((t, k, n), "bool"),
        "final_obs": ((t, k, n, d), "float32"), "final_prev": ((t, k, n, act_dim), "float32"),
        "defaulted": ((t, k, n), "bool"), "steps": ((t,), "int64"),
        "last_obs": ((k, n, d), "float32"), "last_prev": ((k, n, act_dim), "float32"),
    }


def check_chunk(arrays: dict[str, np.ndarray], expected: dict[str, tuple[tuple, str]]) -> None:
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise ChunkError(f"experience chunk lacks arrays {missing}")
    for name, (shape, dtype) in expected.items():
        a = arrays[name]
        if a.shape != shape or a.dtype != np.dtype(dtype):
            raise ChunkError(f"array {name}: got {a.dtype}{a.shape}, expected {dtype}{shape}")


def weights_blob(params: dict[str, np.ndarray]) -> bytes:
    return save_safetensors({k: np.ascontiguousarray(v) for k, v in params.items()})


class RemoteRollout:
    """Fills a TeamLearner's buffer from a rollout chunk (+ central records) as the trainer would."""

    def __init__(self, learner: TeamLearner, spec: EnvSpec) -> None:
        self.learner, self.spec = learner, spec
        self.team = learner.team

    @torch.no_grad()
    def fill(self, r: dict[str, np.ndarray], central: dict[int, dict[str, np.ndarray]] | None) -> int:
        """Returns how many steps lacked a central record (their messages count as not kept)."""
        team, buf = self.team, self.learner.buf
        missing = 0
        buf.reset[:] = r["reset"]
        buf.actions[:] = r["actions"]
        buf.rewards[:], buf.terminated[:], buf.truncated[:] = r["rewards"], r["terminated"], r["truncated"]
        buf.active[:] = r["active"]
        buf.final_values[:] = 0.0
        buf.c_final_values[:] = 0.0
        for t in range(buf.t):
            obs, msg = r["obs"][t], r["msg"][t]
            buf.obs[t], buf.msg[t] = obs, msg
            buf.state[t] = team.global_state(obs, r["prev"][t])
            if central is not None:
                rec = central.get(int(r["steps"][t]))
                if rec is None:  # the central agent never saw this step: agents acted on fallbacks
                    missing += 1
                    buf.msg_raw[t], buf.c_logp[t], buf.c_values[t], buf.keep[t] = msg, 0.0, 0.0, 0.0
                else:
                    buf.msg_raw[t], buf.c_logp[t], buf.c_values[t] = rec["msg_raw"], rec["c_logp"], rec["c_values"]
                    buf.keep[t] = rec["keep"]
            else:
                buf.msg_raw[t], buf.keep[t] = msg, 1.0
                buf.c_logp[t], buf.c_values[t] = 0.0, 0.0
            buf.logp[t], buf.values[t] = team.local_evaluate(obs, msg, r["actions"][t])
            if r["reset"][t].any():
                idx = np.flatnonzero(r["reset"][t].any(axis=1))
                fobs = r["final_obs"][t][idx]
                fstate = team.global_state(fobs, r["final_prev"][t][idx])
                buf.final_values[t, idx] = team.local_values(fobs, team.bootstrap_messages(fstate))
                buf.c_final_values[t, idx] = team.central_values(fstate)
        return missing


class BehaviourSnapshots:
    """The network states of the last `max_lag` + 1 policy versions, so experience acted by an
    older version can be evaluated with exactly that version (its log-probs and values)."""

    def __init__(self, team: Team, max_lag: int) -> None:
        self.max_lag = max_lag
        self.nets = [team.local] + ([team.central] if team.central is not None else [])
        self.states: dict[int, list[dict[str, torch.Tensor]]] = {}

    def _state(self) -> list[dict[str, torch.Tensor]]:
        return [{k: v.detach().clone() for k, v in net.state_dict().items()} for net in self.nets]

    def _load(self, states: list[dict[str, torch.Tensor]]) -> None:
        for net, st in zip(self.nets, states, strict=True):
            net.load_state_dict(st)

    def keep(self, version: int) -> None:
        """Remember the current weights as `version` (a no-op when synchronous)."""
        if not self.max_lag:
            return
        self.states[version] = self._state()
        for v in [v for v in self.states if v < version - self.max_lag]:
            del self.states[v]

    @contextmanager
    def acting_as(self, version: int, current: int):
        """Within the block the networks hold `version`; the current weights come back after."""
        if version == current:
            yield
            return
        if version not in self.states:
            raise KeyError(f"no snapshot of policy version {version} (kept: {sorted(self.states)})")
        now = self.states.get(current) or self._state()  # keep(current) ran after its publish
        self._load(self.states[version])
        try:
            yield
        finally:
            self._load(now)


def load_checkpoint(learner: TeamLearner, rd: RunDir, update: int) -> int:
    """Networks and optimisers of checkpoints/ckpt_<update> into `learner`; returns the update."""
    stem = rd.ckpt_dir / f"ckpt_{update:07d}"
    if not stem.with_suffix(".json").is_file():
        raise FileNotFoundError(f"{stem}.json is missing: no learner checkpoint of update {update} to resume from")
    tensors, meta = RunDir.load_checkpoint(stem)
    if int(meta.get("update", -1)) != update:
        raise ValueError(f"{stem}.json: holds update {meta.get('update')}, expected {update}")
    learner.load_state(tensors, meta)
    log.info("resumed from %s", stem)
    return update


def run_learner(session: HammerSession, cfg: RunConfig, spec: EnvSpec, rd: RunDir,
                central_wait_s: float = 5.0, max_policy_lag: int = 0,
                resume_from: int | None = None) -> dict[str, Any]:
    """Serve updates until told to stop.

    max_policy_lag L > 0 (asynchronous): a chunk acted by version w with update - L <= w <= update
    is used; its acting-time log-probs and values are recomputed with the snapshot of version w
    (the behaviour policy), so PPO's ratio pi_new / pi_w corrects for the lag exactly as it does
    for the epochs of one update. The lag of every update is reported (stats, tensorboard)."""
    from central_agent.server import needs_central_record

    keys = session.keys
    learner = TeamLearner(cfg, spec)
    team = learner.team
    rollout = RemoteRollout(learner, spec)
    expected = expected_arrays(cfg, spec, team.act_dim, team.msg_dim)
    exp_sub = session.subscribe(keys.exp("team"), ExperienceChunk)
    records = needs_central_record(cfg)
    c_sub = session.subscribe(keys.exp("central"), ExperienceChunk) if records else None
    ctl_sub = session.subscribe(keys.ctl("all"), Control)
    w_local = session.publisher(keys.weights("local"))
    w_central = session.publisher(keys.weights("central")) if team.central is not None else None
    hb = session.publisher(keys.heartbeat("learner"), reliable=False)
    update = 0
    if resume_from is not None:
        update = load_checkpoint(learner, rd, resume_from)
    # A resumed run drops the killed session's TensorBoard points after the checkpoint.
    tb = rd.tensorboard(purge_step=update + 1 if resume_from is not None else None)
    session.declare_alive("learner")

    stats = {"updates": update, "stale_chunks": 0, "bad_chunks": 0, "central_steps_missing": 0, "samples": 0,
             "max_policy_lag": max_policy_lag, "lagged_updates": 0, "policy_lag_max": 0,
             # where the learner's time goes (seconds, summed over updates): rebuilding the
             # buffer from a chunk, the PPO epochs, encoding + publishing the new weights
             "time_fill_s": 0.0, "time_learn_s": 0.0, "time_publish_s": 0.0}
    central_recs: dict[int, dict[str, np.ndarray]] = {}
    behaviour = BehaviourSnapshots(team, max_policy_lag)

    def publish_weights() -> None:
        w_local.publish(Weights.from_blob("local", update, weights_blob(team.local.export_numpy())))
        if w_central is not None:
            w_central.publish(Weights.from_blob("central", update, weights_blob(team.central.export_numpy())))

    def snapshot() -> None:
        behaviour.keep(update)

    def fill_as(version: int, r: dict[str, np.ndarray]) -> int:
        """Fill the buffer with the acting-time quantities of `version` (the behaviour policy)."""
        with behaviour.acting_as(version, update):
            return rollout.fill(r, central_recs if c_sub is not None else None)

    def take_central() -> None:
        for rec in c_sub.drain():
            if update - max_policy_lag <= rec.policy_version <= update:
                central_recs[rec.step] = rec.arrays

    publish_weights()
    snapshot()
    last_pub = last_hb = time.monotonic()
    while True:
        if any(c.command in ("stop", "shutdown") and c.target in ("*", "learner") for c in ctl_sub.drain()):
            break
        now = time.monotonic()
        if now - last_hb > 1.0:
            hb.publish(Heartbeat(role="learner", pid=os.getpid(), status="running",
                                 counters={**stats, "policy_version": update}))
            last_hb = now
        if c_sub is not None:
            take_central()
        chunk = exp_sub.get(timeout=0.2)
        if chunk is None:
            if time.monotonic() - last_pub > 1.0:  # late joiners (a restarted agent) get the current policy
                publish_weights()
                last_pub = time.monotonic()
            continue
        lag = update - chunk.policy_version
        if not 0 <= lag <= max_policy_lag:
            stats["stale_chunks"] += 1
            log.warning("experience of version %d while at %d (max lag %d): discarded",
                        chunk.policy_version, update, max_policy_lag)
            continue
        try:
            check_chunk(chunk.arrays, expected)
        except ChunkError as e:
            stats["bad_chunks"] += 1
            log.error("bad experience chunk: %s", e)
            continue
        r = chunk.arrays
        if c_sub is not None:
            need = {int(s) for s in r["steps"]}
            deadline = time.monotonic() + central_wait_s
            while not need <= central_recs.keys() and time.monotonic() < deadline:
                rec = c_sub.get(timeout=0.05)
                if rec is not None and update - max_policy_lag <= rec.policy_version <= update:
                    central_recs[rec.step] = rec.arrays
        t0 = time.perf_counter()
        missing = fill_as(chunk.policy_version, r)
        t1 = time.perf_counter()
        stats["central_steps_missing"] += missing
        for step in [st for st in central_recs if st <= int(r["steps"][-1])]:
            del central_recs[step]
        stats["lagged_updates"] += int(lag > 0)
        stats["policy_lag_max"] = max(stats["policy_lag_max"], lag)
        logs = learner.learn(r["last_obs"], r["last_prev"], update)
        t2 = time.perf_counter()
        update += 1
        stats["updates"] = update
        stats["samples"] += int(r["active"].sum())
        publish_weights()
        stats["time_fill_s"] += t1 - t0
        stats["time_learn_s"] += t2 - t1
        stats["time_publish_s"] += time.perf_counter() - t2
        snapshot()
        last_pub = time.monotonic()
        logs["policy_lag"] = lag
        for name, v in logs.items():
            tb.add_scalar(f"train/{name}", v, update)
        if update % cfg.checkpoint_every == 0:
            tensors, meta = learner.state_tensors()
            meta.update(update=update, config=cfg.model_dump(mode="json"))
            rd.save_checkpoint(update, tensors, meta)
    rd.export_policy(team.local.export_numpy(), team.central.export_numpy() if team.central is not None else None,
                     {"variant": cfg.variant, "central_mode": cfg.central_mode, "version": str(update)})
    (rd.path / "learner_summary.json").write_text(json.dumps({**stats, "policy_version": update,
                                                                      "resumed_from": resume_from}, indent=1))
    log.info("stopped: %s", stats)
    return stats
