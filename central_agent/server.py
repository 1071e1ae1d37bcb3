"""The central-agent server: one batched forward pass per vector step, one message per local agent.

It runs the same sampling as the in-process trainer (`learning.central_acting.CentralActing`,
same random stream) after a numpy forward of the central network (`learning.numpy_policy`), so
with the same weights and no faults it sends the trainer's messages to float32 tolerance, and the
process never loads torch: it sits on the critical path of every vector step. Weights come from
the learner (`learn/central/weights`, safetensors of `CentralAgent.export_numpy()`); for variant
`random` there are no weights, only the central random stream.

When the learner needs what only the central agent knows (rl mode: the Gaussian sample, its
log-density and the central critic's value; any mode with message dropout: which messages were
dropped), the server publishes a small per-step record to `learn/central/exp`, tagged with the
step, so the learner can join it with the env host's rollout.

When states queue up (the server was paused, or restarted and waited for weights), only the
newest is served: messages for steps the local agents have already acted on would be discarded
as late anyway. Without faults there is never more than one state queued, so this changes nothing.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors.numpy import load as load_safetensors

from envs.base import EnvSpec
from faults.links import flat_fault_counters
from faults.steplog import LoggedPublisher, StepLog, column
from learning.central_acting import CentralActing
from learning.config import RunConfig
from learning.numpy_policy import NumpyCentralAgent
from learning.policy_versions import WeightsInbox
from learning.sampling import ActingStreams
from protocol.schemas import CentralMsg, Control, Dims, ExperienceChunk, GlobalState, Heartbeat, Weights
from protocol.session import HammerSession

log = logging.getLogger("hammer.central")


@dataclass
class CentralCounters:
    steps: int = 0
    states_stale: int = 0  # a state for a step already served (duplicate / reordered)
    states_skipped: int = 0  # an older state still queued when a newer one was there (after a pause)
    weights_loaded: int = 0
    weights_wait_timeouts: int = 0
    states_no_policy: int = 0  # not served: no central weights received yet (local agents fall back)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


def needs_central_record(cfg: RunConfig) -> bool:
    return cfg.wiring.needs_central_record


def run_central(session: HammerSession, cfg: RunConfig, spec: EnvSpec, weights_timeout_s: float,
                idle_exit_s: float | None = None, load_when_idle: bool = False,
                step_log_dir: Path | None = None) -> CentralCounters:
    """Serve messages until a stop command. load_when_idle (evaluation, frozen weights): load the
    policy before the first state arrives so the env host can wait for it (see EnvHost.run_eval);
    training keeps loading weights only when a state asks for them (up == train equivalence).
    step_log_dir: where this process logs its link events per step (faults.steplog; None: nowhere)."""
    keys = session.keys
    acting = CentralActing.from_config(cfg)
    net: NumpyCentralAgent | None = None
    streams = ActingStreams(cfg.seed, cfg.n_agents)
    n = cfg.n_agents
    dims = Dims(num_envs=cfg.num_envs, n_agents=n, obs_dim=spec.obs_dim, action_dim=spec.action_dim,
                discrete=spec.discrete)
    state_sub = session.subscribe(keys.state(), GlobalState, dims)
    w_sub = session.subscribe(keys.weights("central"), Weights) if acting.has_network else None
    ctl_sub = session.subscribe(keys.ctl("all"), Control)
    delivered, late = column("env->central", "delivered"), column("env->central", "late")
    slog = StepLog(step_log_dir, "central", [delivered, late, *(column("central->local", e) for e in
                                                                ("sent", "dropped", "duplicated"))])
    msg_pubs = [LoggedPublisher(session.publisher(keys.msg(i), express=True), session, slog, "central->local")
                for i in range(n)]
    exp_pub = session.publisher(keys.exp("central"))
    hb_pub = session.publisher(keys.heartbeat("central"), reliable=False)
    session.declare_alive("central")
    record = needs_central_record(cfg)

    c = CentralCounters()
    version = -1 if acting.has_network else 0
    last_step = -1
    last_hb = 0.0
    last_state_t = time.monotonic()

    state_dim = n * spec.obs_dim + (n * spec.action_dim if cfg.use_prev_actions else 0)

    def _load(blob: bytes, v: int) -> None:
        nonlocal version, net
        new = NumpyCentralAgent(load_safetensors(blob))
        got = (new.state_dim, new.n_agents, new.msg_dim, new.critic is not None)
        want = (state_dim, n, acting.msg_dim, acting.rl)
        if got != want:  # fail here, not on the first forward (a learner of another run's config)
            raise ValueError(f"central weights v{v} have (state_dim, n_agents, msg_dim, critic) = {got}, "
                             f"this run needs {want}: start the learner from the same config.json")
        net = new
        version = v

    inbox = WeightsInbox(_load, version)

    def take_weights(need: int | None) -> None:
        """Load the policy version the step asks for, never a newer one (see WeightsInbox);
        need=None: load the newest received, without waiting."""
        deadline = time.monotonic() + weights_timeout_s
        while w_sub is not None:
            wait = 0.0 if need is None or version >= need else deadline - time.monotonic()
            w = w_sub.get(timeout=max(wait, 0.0))
            if w is not None:
                inbox.offer(w.version, w.blob)
                if inbox.select(need):
                    c.weights_loaded += 1
                continue
            if need is None:
                return
            if version < need and time.monotonic() < deadline:
                continue
            if version < need:
                c.weights_wait_timeouts += 1
                log.warning("central policy version %d not received in %.0fs; using %d",
                            need, weights_timeout_s, version)
            return

    while True:
        for cmd in ctl_sub.drain():
            if cmd.command in ("stop", "shutdown") and cmd.target in ("*", "central"):
                slog.flush()
                return c
        now = time.monotonic()
        if now - last_hb > 1.0:
            hb_pub.publish(Heartbeat(role="central", pid=os.getpid(), status="running",
                                     counters={**c.as_dict(), **flat_fault_counters(session.fault_report()),
                                               "policy_version": version}))
            slog.flush()  # with the heartbeat: a killed server's step log and last counters agree
            last_hb = now
        s = state_sub.get(timeout=0.2)
        if s is None:
            if load_when_idle:
                take_weights(None)  # never blocks: loads the newest weights already received
            if idle_exit_s is not None and time.monotonic() - last_state_t > idle_exit_s:
                slog.flush()
                return c
            continue
        last_state_t = time.monotonic()
        if s.step <= last_step:
            c.states_stale += 1
            slog.add(s.step, delivered)
            slog.add(s.step, late)
            continue
        take_weights(s.policy_version)
        for newer in state_sub.drain():  # serve the newest queued state only
            old = s if newer.step > s.step else newer
            slog.add(old.step, delivered)
            slog.add(old.step, late)
            if newer.step > s.step:
                c.states_skipped += 1
                s = newer
            else:
                c.states_stale += 1
        if acting.has_network and net is None:
            # Only after a weights timeout: no policy to act with. Sending nothing lets the local
            # agents act on their fallback, as for any missing message; no stream is drawn.
            if c.states_no_policy == 0:
                log.warning("no central weights received yet: step %d not served", s.step)
            c.states_no_policy += 1
            slog.add(s.step, delivered)
            continue
        state = acting.global_state(s.obs, s.prev_actions)
        out = acting.messages(state, streams, cfg.msg_dropout, net.message_mean if net is not None else None,
                              net.values if acting.rl else None)
        for i in range(n):
            msg_pubs[i].publish(CentralMsg(step=s.step, env_idx=s.env_idx, agent=i,
                                           msg=np.ascontiguousarray(out.sent[:, i]), policy_version=max(version, 0)))
        if record:
            exp_pub.publish(ExperienceChunk(
                step=s.step, env_idx=s.env_idx, role="central", policy_version=max(version, 0),
                arrays={"msg_raw": out.raw.astype(np.float32, copy=False), "c_logp": out.logp,
                        "c_values": out.value, "keep": out.keep}))
        last_step = s.step
        c.steps += 1
        slog.add(s.step, delivered)
