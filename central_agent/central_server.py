"""The central-agent server: one batched forward pass per vector step, one message per local agent.

It runs the same sampling as the in-process trainer (`learning.central_acting.CentralActing`,
same random stream) after a numpy forward of the central network (`learning.numpy_policy`), so
with the same weights and no faults it sends the trainer's messages to float32 tolerance, and the
process never loads torch: it sits on the critical path of every vector step. Weights come from
the learner (`learn/central/weights`, safetensors of `CentralAgent.export_numpy()`, or of
`SetCentralAgent`'s with `central_net=set`); for variant `random` there are no weights, only the
central random stream.

When the learner needs what only the central agent knows (rl mode: the Gaussian sample, its
log-density and the central critic's value; any mode with message dropout: which messages were
dropped), the server publishes a small per-step record to `learn/central/exp`, tagged with the
step, so the learner can join it with the env host's rollout.

`CentralServer` reads top to bottom as what it does with each global state (`on_state`): load
the policy version the state names, serve the newest state queued, sample and publish the
messages, publish the learner's record.

When states queue up (the server was paused, or restarted and waited for weights), only the
newest is served: messages for steps the local agents have already acted on would be discarded
as late anyway. Without faults there is never more than one state queued, so this changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.envs.base import EnvSpec
from hammer.faults.steplog import LoggedPublisher, StepLog, column
from hammer.learning.central_acting import CentralActing, CentralOut
from hammer.learning.config import RunConfig
from hammer.learning.numpy_policy import (
    NumpyCentralAgent,
    NumpySetCentralAgent,
    numpy_central,
    params_from_blob,
)
from hammer.learning.sampling import ActingStreams
from hammer.protocol.dims import Dims
from hammer.protocol.schemas import CentralMsg, ExperienceChunk, GlobalState
from hammer.protocol.session import HammerSession, burst_express
from hammer.runtime.bounds import StepWindow
from hammer.runtime.role import Role
from hammer.runtime.settings import RuntimeSettings
from hammer.runtime.weights import WeightsIntake

DELIVERED, LATE = column("env->central", "delivered"), column("env->central", "late")


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


class CentralServer(Role):
    """Global state in, one message per local agent out (and the learner's record, when it needs one).

    load_when_idle (evaluation, frozen weights): load the policy before the first state arrives so
    the env host can wait for it (see EnvHost.run_eval); training loads weights only when a state
    asks for them (up == train equivalence). step_log_dir: where this process logs its link events
    per step (faults.steplog; None: nowhere)."""

    def __init__(self, session: HammerSession, cfg: RunConfig, spec: EnvSpec, settings: RuntimeSettings, *,
                 idle_exit_s: float | None = None, step_log_dir: Path | None = None, start_step: int | None = None,
                 start_version: int | None = None) -> None:
        # a served run (eval) loads the policy as soon as it is there, before the first state
        training, load_when_idle = settings.mode == "train", settings.mode == "eval"
        step_window, max_policy_lag = settings.step_window, settings.max_policy_lag
        step_log = StepLog(step_log_dir, "central", [DELIVERED, LATE, *(column("central->local", e) for e in
                                                                       ("sent", "dropped", "duplicated"))])
        super().__init__(session, "central", step_log=step_log, idle_exit_s=idle_exit_s,
                         stall_warn_s=settings.stall_warn_s)
        self.cfg, self.n_agents = cfg, cfg.n_agents
        self.acting = CentralActing.from_config(cfg)
        # a training run: the absences missing_prob simulates apply (as in the trainer), and the learner gets
        # a record of each step; a served run has no learner, so no record goes out
        self.training = training
        self.streams = ActingStreams(cfg.seed, cfg.n_agents)
        self.local_obs_dim = spec.local_obs_dim  # the site feed's columns from here on (site_missing_prob)
        self.state_dim = cfg.n_agents * (spec.obs_dim + (spec.action_dim if cfg.use_prev_actions else 0))
        self.load_when_idle = load_when_idle
        self.counts = CentralCounters()
        self.net: NumpyCentralAgent | NumpySetCentralAgent | None = None
        self.last_step = -1
        self.window = StepWindow(step_window, start=start_step)  # runtime.bounds.known_step: no forged first step
        self.stall_what = "global states"
        dims = Dims(num_envs=cfg.num_envs, n_agents=cfg.n_agents, obs_dim=spec.obs_dim,
                    action_dim=spec.action_dim, discrete=spec.discrete)
        self.states = session.subscribe(self.keys.state(), GlobalState, dims)
        self.handle(self.states, self.on_state)
        self.weights = (WeightsIntake(session, "central", self.load_weights, settings.weights_timeout_s, reject=self.reject,
                                      max_policy_lag=max_policy_lag, start_version=start_version)
                        if self.acting.has_network else None)
        n = cfg.n_agents  # N messages a step: a burst (protocol.session.BATCH_MIN)
        self.msg_pubs = [LoggedPublisher(session.publisher(self.keys.msg(i), express=burst_express(i, n)), session,
                                         step_log, "central->local") for i in range(n)]
        self.record_pub = (session.publisher(self.keys.exp("central")) if training and cfg.wiring.needs_central_record
                           else None)

    @property
    def version(self) -> int:
        """The policy version acting (variant `random`, no network: always 0)."""
        return self.weights.version if self.weights is not None else 0

    def counters(self) -> dict[str, int]:
        return self.counts.as_dict()

    def gauges(self) -> dict[str, int]:
        return {"policy_version": self.version}

    # ----- a step, in the order it flows ---------------------------------------------------------
    def on_state(self, state: GlobalState) -> None:
        """Serve one vector step: load the version it names, then send the messages of the newest state queued."""
        if state.step <= self.last_step and self.window.stale(state.step, self.last_step):
            self.counts.states_stale += 1
            self.log_late(state.step)
            return
        if state.step <= self.last_step:  # the real stream is below an anchor it never followed
            self.reject("step_resync", f"global states up to step {state.step} came steadily below "
                                       f"{self.last_step}: following them")
        if self.window.ahead(state.step, self.last_step):
            self.reject("step_ahead", f"global state for step {state.step} while at {self.last_step}")
            return
        if self.weights is not None and self.weights.ahead(state.policy_version):
            self.reject("version_ahead", f"global state names policy version {state.policy_version}")
            return
        self.take_weights(state.policy_version)
        state = self.newest_queued(state)
        if self.acting.has_network and self.net is None:
            self.skip_without_policy(state.step)
            return
        net = self.net
        gstate = (self.acting.training_state(state.obs, state.prev_actions, state.step, state.env_idx,
                                             self.local_obs_dim) if self.training
                  else self.acting.global_state(state.obs, state.prev_actions))
        out = self.acting.messages(gstate, self.streams,
                                   self.cfg.msg_dropout, net.message_mean if net is not None else None,
                                   net.values if self.acting.rl else None)
        self.publish_messages(state, out)
        if self.record_pub is not None:
            self.publish_record(state, out)
        self.last_step = state.step
        self.counts.steps += 1
        self.step_log.add(state.step, DELIVERED)
        self.progressed()

    def take_weights(self, need: int | None) -> None:
        if self.weights is None:
            return
        self.weights.take(need)
        self.counts.weights_loaded, self.counts.weights_wait_timeouts = self.weights.loaded, self.weights.wait_timeouts

    def load_weights(self, blob: bytes, version: int) -> None:
        """WeightsIntake's loader: fail on weights of another run's config here, not on the first forward."""
        net = numpy_central(params_from_blob(blob))
        got = (net.kind, net.state_dim, net.n_agents, net.msg_dim, net.critic is not None)
        want = (self.cfg.central_net, self.state_dim, self.n_agents, self.acting.msg_dim, self.acting.rl)
        if got != want:
            raise ValueError(f"central weights v{version} have (central_net, state_dim, n_agents, msg_dim, critic) = "
                             f"{got}, this run needs {want}: start the learner from the same config.json")
        self.net = net

    def newest_queued(self, state: GlobalState) -> GlobalState:
        """Serve the newest queued state only: the others are for steps the local agents have acted on."""
        for newer in self.states.drain():
            if newer.step > state.step and self.window.ahead(newer.step, state.step):
                self.reject("step_ahead", f"global state for step {newer.step} while at {state.step}")
                continue
            self.log_late(min(newer.step, state.step))  # the older of the two is not served
            if newer.step > state.step:
                self.counts.states_skipped += 1
                state = newer
            else:
                self.counts.states_stale += 1
        return state

    def skip_without_policy(self, step: int) -> None:
        """Only after a weights timeout: no policy to act with. Sending nothing lets the local agents
        act on their fallback, as for any missing message; no stream is drawn."""
        if self.counts.states_no_policy == 0:
            self.log.warning("no central weights received yet: step %d not served", step)
        self.counts.states_no_policy += 1
        self.step_log.add(step, DELIVERED)

    def publish_messages(self, state: GlobalState, out: CentralOut) -> None:
        for i, pub in enumerate(self.msg_pubs):
            pub.publish(CentralMsg(step=state.step, env_idx=state.env_idx, agent=i,
                                   msg=np.ascontiguousarray(out.sent[:, i]), policy_version=max(self.version, 0)))

    def publish_record(self, state: GlobalState, out: CentralOut) -> None:
        """What only the central agent knows of this step, for the learner (joined by step)."""
        self.record_pub.publish(ExperienceChunk(
            step=state.step, env_idx=state.env_idx, role="central", policy_version=max(self.version, 0),
            arrays={"msg_raw": out.raw.astype(np.float32, copy=False), "c_logp": out.logp,
                    "c_values": out.value, "keep": out.keep}))

    def log_late(self, step: int) -> None:
        """A state for `step` arrived and was not served."""
        self.step_log.add(step, DELIVERED)
        self.step_log.add(step, LATE)

    def on_idle(self) -> None:
        if self.load_when_idle:
            self.take_weights(None)  # never blocks: loads the newest weights already received
