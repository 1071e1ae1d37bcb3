"""The env host: steps K env copies and drives the distributed step loop.

Per vector step (3 hops): publish the global state to the central agent and each local agent's
observation; collect every agent's action until all are in or the deadline passes (a missing
action becomes the env's declared default and is counted, env_host/actions.py); step the env.
After T steps it sends the rollout to the learner as one ExperienceChunk tagged with the policy
version that produced it, and waits for the next version's weights before acting again
(on-policy synchronisation).

The loop mirrors `learning.trainer.Trainer._collect` step for step (same env seeds, same reset
points, same episode budget, the same `RolloutWriter`), so without faults a distributed run
reproduces the in-process one.

Evaluation (`run_eval`, RuntimeSettings.mode == "eval"): the same per-step hops with a frozen
policy (version 0 from the policy server), no experience and no waiting for new versions; episodes
until the budget. Both modes write `episode_links.csv` (env_host/checkpoint.py); `hammer up` adds
the per-link columns from the roles' step logs (this process logs the state / observations it
sent and the actions it received, `RUN/linksteps/env-<pid>.csv`; see faults/episode_links.py and
docs/faults.md). `trace.npz` (obs, messages, actions, masks per step) on request.
Resuming (`hammer up --resume`): see env_host/checkpoint.py.

A served run names a version per agent: after `hammer push --canary` (serve/canary.py) the
canary's agents get the new version in their LocalObs while the others and the central agent keep
the base (runtime/pushes.py reads the history; a version is named only once its weights reached
this host). It also writes each agent's health for the rollout's gates (env_host/health.py).
A pushed version is named for the agents it is for only once each of them holds it (their
heartbeats' `policy_held`: the agents pull a push in paced chunks, runtime/weights.py), so no step
waits for weights still crossing a thin link; after `name_timeout_s` (RuntimeSettings
`weights_name_timeout_s`) it is named regardless, counted as `push_named_unheld` and logged.
"""

from __future__ import annotations

import time

import numpy as np
from hammer.env_host import checkpoint
from hammer.env_host.actions import ActionCollector, StepActions
from hammer.env_host.checkpoint import EpisodeRows, HostState
from hammer.env_host.health import AgentHealth
from hammer.env_host.trace import TraceWriter
from hammer.envs.base import VecEnv, VecStep
from hammer.envs.local_view import local_view_from_config
from hammer.faults.steplog import STEP_LOG_DIR, LoggedPublisher, StepLog, column
from hammer.learning.central_acting import zero_prev_actions
from hammer.learning.config import RunConfig
from hammer.learning.episodes import episode_rows
from hammer.learning.rollout import RolloutWriter, next_prev_actions
from hammer.learning.rundir import RunDir
from hammer.learning.sampling import env_reset_seed
from hammer.protocol.access import POLICY
from hammer.protocol.dims import Dims
from hammer.protocol.rollout_layout import RolloutLayout
from hammer.protocol.schemas import (
    Action,
    ExperienceChunk,
    GlobalState,
    Heartbeat,
    LocalObs,
    Weights,
    WeightsAnnounce,
)
from hammer.protocol.session import HammerSession, burst_express
from hammer.runtime.pushes import HistoryError, assignment, read_pushes
from hammer.runtime.role import Role, process_cpu_s
from hammer.runtime.settings import RuntimeSettings

HISTORY_EVERY_S = 0.25  # a served run reads its update history (pushes.json) at most this often


class EnvHost(Role):
    heartbeat_every_s = 0.5

    def __init__(self, session: HammerSession, cfg: RunConfig, env: VecEnv, rd: RunDir,
                 settings: RuntimeSettings) -> None:
        s = settings  # RuntimeSettings checks that resume_from and resume_step go together
        act_deadline_s, weights_timeout_s, trace, echo = s.act_deadline_ms / 1e3, s.weights_timeout_s, s.trace, s.echo
        max_policy_lag, resume_from, resume_step = s.max_policy_lag, s.resume_from, s.resume_step
        self.name_timeout_s = s.weights_name_timeout_s
        # who publishes the weights, as the stall line and the timeout name it
        self.publisher = "the policy server (role policy)" if s.policy_role == POLICY else "the learner"
        self.cfg, self.env, self.rd, self.spec = cfg, env, rd, env.spec
        # Where this session's wall time went (summary `time_s`; `hammer bench scale` reads it).
        self.time_s = {"first_weights": 0.0, "wait_weights": 0.0, "loop": 0.0, "env_step": 0.0}
        self.wiring = cfg.wiring
        self.n, self.k = cfg.n_agents, cfg.num_envs
        self.local_view = local_view_from_config(cfg, self.spec)  # LocalObs only; GlobalState stays full
        self.weights_timeout_s, self.max_policy_lag = weights_timeout_s, max_policy_lag
        self.resume_from, self.resume_step = resume_from, resume_step
        # Link events per step (faults.steplog), joined with the episodes' spans by `hammer up`.
        links = (["env->central"] if self.wiring.uses_central else []) + ["env->local"]
        super().__init__(session, "env", step_log=StepLog(rd.path / STEP_LOG_DIR, "env", [
            *(column(lk, e) for lk in links for e in ("sent", "dropped", "duplicated")),
            *(column("local->env", e) for e in ("delivered", "late", "duplicate", "defaults"))]),
            stall_warn_s=s.stall_warn_s)
        keys, msg_dim = session.keys, self.wiring.msg_dim
        dims = Dims(num_envs=self.k, n_agents=self.n, action_dim=self.spec.action_dim, discrete=self.spec.discrete,
                    msg_dim=msg_dim or None, echo=echo)  # echo: each action carries its message (training, trace)
        self.echo = bool(echo and msg_dim)  # ... which each observation asks for (LocalObs.echo)
        self.collector = ActionCollector(session.subscribe(keys.act("*"), Action, dims), self.spec, self.k,
                                         msg_dim, act_deadline_s, self.step_log, reject=self.reject)
        self.links = self.collector.counters
        self.weights_in = session.subscribe(keys.weights("local"), Weights)
        self.state_out = LoggedPublisher(session.publisher(keys.state(), express=True), session, self.step_log,
                                         "env->central")
        self.obs_out = [LoggedPublisher(session.publisher(keys.obs(i), express=burst_express(i, self.n)), session,
                                        self.step_log, "env->local") for i in range(self.n)]  # a burst: BATCH_MIN
        self.experience_out = session.publisher(keys.exp("team"))
        self.experience_out.max_bytes = ExperienceChunk.cap_for(RolloutLayout.from_config(cfg, self.spec))
        self.state = HostState()
        self.episodes = EpisodeRows(rd.path, self.k)
        self.weights_version = -1
        self.rollout_version = 0  # the policy version the current rollout is acted with
        self.env_idx = np.arange(self.k, dtype=np.int64)
        self.rollout = RolloutLayout.from_config(cfg, self.spec).chunk_steps()
        self.writer = RolloutWriter(self.rollout, self.spec)
        self.trace = TraceWriter(rd.path, int(s.trace_max_mb * 2**20)) if trace else None
        self.agent_versions: np.ndarray | None = None  # eval: each agent's version (a staged rollout)
        self.health: AgentHealth | None = None
        self._history_read, self._history_mtime, self._history_bad, self._named_for = 0.0, None, False, -2
        self.announce_in = None  # eval: the policy server's announcements of pushed versions
        self._pending: tuple[tuple, float] | None = None  # eval: versions to name once held, since when
        self.pushes_named = self.push_named_unheld = 0
        self.push_wait_s = 0.0  # the last push: published (announced) -> named
        self.push_waits_s: list[float] = []  # every push's, in order (the summary)

    def counters(self) -> dict[str, int | float]:
        st = self.state
        return {**self.links.as_dict(), "episodes": st.episodes, "env_steps": st.env_steps, "step": st.step,
                "update": st.update, **({"pushes_named": self.pushes_named, "push_named_unheld": self.push_named_unheld}
                                        if self.announce_in is not None else {})}

    def gauges(self) -> dict[str, int | float]:
        st = self.state
        lat = np.array(st.step_latency_ms) if st.step_latency_ms else np.zeros(1)
        running = float(np.mean(list(st.recent)[-100:])) if st.recent else 0.0
        return {"policy_version": self.weights_version, "paper_metric_100": running,
                "step_p50_ms": float(np.percentile(lat, 50)), "step_p99_ms": float(np.percentile(lat, 99)),
                # eval: the version the steps name (the central one), once the agents hold it; policy_version
                # is the newest published (what a restarted role's bound is measured from)
                **({"push_wait_s": round(self.push_wait_s, 3), "named_version": self.rollout_version}
                   if self.announce_in is not None else {})}

    # ----- training -----------------------------------------------------------------------------
    def run_training(self) -> dict:
        """Drive the training loop to the budget (the env host drives its loop itself instead of
        `Role.run`'s reactive one); returns the summary."""
        cfg, st = self.cfg, self.state
        t_start = st.wall_start = time.perf_counter()
        self.cpu_at_start = process_cpu_s()
        obs = prev = active = None
        if self.resume_from is not None:
            self._restore(self.resume_from, self.resume_step)
        else:  # rows of an earlier attempt in this directory must not precede ours (save appends)
            self.episodes.path.unlink(missing_ok=True)
            self.rd.truncate_metrics(0)  # header only, also in a run dir not made by `hammer up`
        if not self.wait_weights(st.update):
            return self.summary(t_start)
        while self.stop_reason is None:
            if st.update % cfg.checkpoint_every == 0:
                checkpoint.save(self.rd, st, self.episodes)
                obs, active = self._reset_env(st.update)
                prev = zero_prev_actions(self.spec, self.k)
            obs, prev, active, finished = self._rollout(obs, prev, active)
            if finished or self.stop_reason is not None:
                break
            self.experience_out.publish(ExperienceChunk(
                step=st.step, env_idx=self.env_idx, role="team", policy_version=self.rollout_version,
                arrays={**self.rollout, "last_obs": obs, "last_prev": prev}))
            st.update += 1
            # Synchronous (lag 0): wait for the version this rollout trains. With a lag L, go on
            # with the newest version we hold as long as it is at most L updates behind.
            if not self.wait_weights(st.update - self.max_policy_lag):
                break
            self.rollout_version = self.weights_version if self.max_policy_lag else st.update
        self.take_queued_weights()
        self.rd.flush()
        return self.summary(t_start)

    def _rollout(self, obs: np.ndarray, prev: np.ndarray, active: np.ndarray):
        """T vector steps into `self.rollout`; returns the next obs, prev actions, active mask and
        whether the episode budget is spent (a stop leaves `stop_reason` set)."""
        r, st = self.rollout, self.state
        self.writer.begin()
        for t in range(self.cfg.rollout_steps):
            if self.stop_requested():
                break
            self.heartbeat()
            step, got = self._vector_step(obs, prev, active)
            r["defaulted"][t], r["steps"][t] = got.defaulted, st.step
            prev = self.writer.write(t, obs, prev, got.msgs, got.actions, step).prev
            obs, active = step.obs, step.next_active
            st.env_steps += self.k
            if step.episodes and self._record_episodes(step.episodes):
                return obs, prev, active, True
        return obs, prev, active, False

    def wait_weights(self, version: int) -> bool:
        """Block until the learner has published local weights >= version (or stop/timeout). The
        learner cannot be ahead of the chunks it got: a version above version + max_policy_lag is
        forged or a bug, rejected and counted (runtime.bounds)."""
        t0 = time.monotonic()
        deadline = t0 + self.weights_timeout_s
        self.stall_what = f"policy version {version} from {self.publisher}"
        asked = t0
        try:
            while self.weights_version < version:
                if self.stop_requested():
                    return False
                self.heartbeat("ready")
                w = self.weights_in.get(timeout=0.2)
                if w is not None:
                    self.on_weights(w, version)
                elif time.monotonic() - asked >= 1.0:  # a publication missed: ask (a policy server answers)
                    asked = time.monotonic()
                    self.session.fetch(self.keys.weights("local"), self.weights_in)
                elif time.monotonic() > deadline:
                    raise TimeoutError(f"{self.publisher} did not publish policy version {version} within "
                                       f"{self.weights_timeout_s:.0f}s (is `hammer learner` running?)")
            return True
        finally:
            first = self.state.env_steps == self.state.steps_at_start
            self.time_s["first_weights" if first else "wait_weights"] += time.monotonic() - t0

    def on_weights(self, w: Weights, version: int) -> None:
        """A weights announcement while `version` is the newest this host may see (+ the lag)."""
        if w.version > version + self.max_policy_lag:
            self.reject("weights_ahead", f"local weights version {w.version} while waiting for {version}")
        else:
            self.weights_version = max(self.weights_version, w.version)

    def take_queued_weights(self) -> None:
        """At the end of a run: weights that arrived while stepping are checked and counted too."""
        for w in self.weights_in.drain():
            self.on_weights(w, self.state.update)

    # ----- one vector step ----------------------------------------------------------------------
    def _vector_step(self, obs: np.ndarray, prev: np.ndarray, active: np.ndarray) -> tuple[VecStep, StepActions]:
        """State + observations out, actions in (or defaults), env step."""
        st = self.state
        st.step += 1
        t0 = time.perf_counter()
        self._send_observations(obs, prev, active)
        self.stall_what = "actions"
        got = self.collector.collect(st.step, self.rollout_version if self.agent_versions is None
                                     else self.agent_versions)
        if not got.defaulted.all():  # a step of default actions only is no progress of the team
            self.progressed()
        # Control-loop latency: observations out -> every action in (3 hops), env step excluded.
        t1 = time.perf_counter()
        st.step_latency_ms.append((t1 - t0) * 1e3)
        self.episodes.count(got.fallback, got.defaulted)
        if self.health is not None:
            self.health.step(got, got.arrived_ms)
        step = self.env.step(self.spec.env_action(got.actions))
        self.time_s["loop"] += t1 - t0
        self.time_s["env_step"] += time.perf_counter() - t1
        if self.trace is not None:
            self.trace.add(st.step, obs, got.msgs, got.actions, got.fallback, got.defaulted, self.rollout_version)
        return step, got

    def _send_observations(self, obs: np.ndarray, prev: np.ndarray, active: np.ndarray) -> None:
        step, version = self.state.step, self.rollout_version
        if self.wiring.uses_central:
            self.state_out.publish(GlobalState(step=step, env_idx=self.env_idx, obs=obs, prev_actions=prev,
                                               active=active, policy_version=version))
        joint = obs.reshape(self.k, -1) if self.wiring.joint_obs else None
        seen = self.local_view(obs)
        per = self.agent_versions
        for i in range(self.n):
            self.obs_out[i].publish(LocalObs(step=step, env_idx=self.env_idx, agent=i,
                                             obs=joint if joint is not None else np.ascontiguousarray(seen[:, i]),
                                             active=active[:, i], policy_version=version if per is None else int(per[i]),
                                             echo=self.echo))

    # ----- evaluation ---------------------------------------------------------------------------
    def run_eval(self) -> dict:
        """Evaluate the frozen policy (version 0) until the episode budget; no learning."""
        st = self.state
        t_start = st.wall_start = time.perf_counter()
        self.cpu_at_start = process_cpu_s()
        self.rd.truncate_metrics(0)
        self.episodes.start()
        if not self.wait_weights(0) or not self._wait_actors_ready():
            return self.summary(t_start)
        obs, active = self._reset_env(0)
        prev = zero_prev_actions(self.spec, self.k)
        self.agent_versions = np.zeros(self.n, np.int64)
        self.health = AgentHealth(self.session, self.rd.path, self.n)
        self.announce_in = self.session.subscribe(self.keys.weights_announce("local"), WeightsAnnounce)
        try:
            while not self.stop_requested():
                self.heartbeat()
                self._take_pushed_version()
                step, got = self._vector_step(obs, prev, active)
                prev = next_prev_actions(self.spec, got.actions, step).prev
                obs, active = step.obs, step.next_active
                st.env_steps += self.k
                for e in step.episodes:
                    self.health.episode(e.paper_metric, e.team_return)
                if step.episodes and self._record_episodes(step.episodes):
                    break
                self.health.poll(st.step, self.agent_versions.tolist(), self.rollout_version)
            self.health.write(st.step, self.agent_versions.tolist(), self.rollout_version)
        finally:
            self.health.close()
        self.rd.flush()
        return self.summary(t_start)

    def _take_pushed_version(self) -> None:
        """Eval: a newer policy version published (`hammer push` / `hammer rollback` / a staged
        rollout) is named from the next step on, by the observations of the agents it is for (every
        agent, or the canary's) and, once every agent is on it, by the global state (actors hold it
        until then). Which agents: the run's history (runtime/pushes.py), re-read when it changed;
        without a readable history every agent takes the newest version (a plain push)."""
        for w in [*self.weights_in.drain(), *self.announce_in.drain()]:
            self.weights_version = max(self.weights_version, w.version)
        now = time.monotonic()
        if now - self._history_read < HISTORY_EVERY_S:
            return
        self._history_read = now
        try:
            mtime = (self.rd.path / "pushes.json").stat().st_mtime_ns
        except FileNotFoundError:
            mtime = None
        if mtime == self._history_mtime and self.weights_version == self._named_for and self._pending is None:
            return
        self._history_mtime, self._named_for = mtime, self.weights_version
        try:
            entries = read_pushes(self.rd.path)
        except HistoryError as e:
            if not self._history_bad:
                self.log.error("%s (every agent takes the newest version)", e)
            self._history_bad, entries = True, []
        a = assignment(entries, self.weights_version)
        if not entries:  # no history to follow: the newest published version, for everyone
            a.base = max(self.weights_version, self.rollout_version)
        versions = np.array([max(v, int(old)) for v, old in zip(a.agent_versions(self.n), self.agent_versions)])
        base = max(a.base, self.rollout_version)  # never back: a version once named stays named
        if base == self.rollout_version and np.array_equal(versions, self.agent_versions):
            self._pending = None
            return
        if not self._all_hold(base, versions, now):
            return
        self.log.info("from step %d: central version %d, agents %s", self.state.step + 1, base, versions.tolist())
        self.rollout_version, self.agent_versions = base, versions

    def _all_hold(self, base: int, versions: np.ndarray, now: float) -> bool:
        """Whether to name `versions` now: every agent whose version changes holds its new one (its
        heartbeat says so), or `name_timeout_s` passed since these versions were first due (then
        counted as push_named_unheld and logged: those agents wait for the weights at that step)."""
        due = (base, tuple(versions.tolist()))
        if self._pending is None or self._pending[0] != due:
            self._pending = (due, now)
        self.health.beats(now)
        lacking = [i for i in range(self.n) if versions[i] != self.agent_versions[i] and self.health.held[i] < versions[i]]
        waited = now - self._pending[1]
        if lacking and waited < self.name_timeout_s:
            return False
        if lacking:
            self.push_named_unheld += 1
            self.log.warning("naming versions %s although agents %s do not hold theirs after %.1f s (held: %s)",
                             versions.tolist(), lacking, waited, self.health.held.tolist())
        self.pushes_named += 1
        self.push_wait_s, self._pending = waited, None
        self.push_waits_s.append(round(waited, 3))
        self.heartbeat_soon()
        return True

    def _wait_actors_ready(self) -> bool:
        """Eval: start stepping only once the central agent and every local agent hold the policy
        (their heartbeats say so), so that a fault-free evaluation has no message missing at
        start-up and no first step slowed by an agent still loading its weights."""
        roles = [f"local-{i}" for i in range(self.n)]
        if self.wiring.uses_central and self.wiring.has_central_network:
            roles.insert(0, "central")
        subs = {r: self.session.subscribe(self.keys.heartbeat(r), Heartbeat) for r in roles}
        deadline = time.monotonic() + self.weights_timeout_s
        try:
            while subs and time.monotonic() < deadline:
                if self.stop_requested():
                    return False
                for r, sub in list(subs.items()):
                    if any(hb.gauges.get("policy_version", -1) >= 0 for hb in sub.drain()):
                        del subs[r]
                if subs:
                    time.sleep(0.005)
        finally:
            for sub in subs.values():
                sub.close()
        if subs:
            raise TimeoutError(f"{', '.join(subs)} did not load the policy within {self.weights_timeout_s:.0f}s "
                               "(are `hammer central` / `hammer local` running?)")
        return True

    # ----- episodes and resume ------------------------------------------------------------------
    def _reset_env(self, update: int) -> tuple[np.ndarray, np.ndarray]:
        """Reseed every env copy (the points shared with `hammer train`); running episodes are
        dropped unrecorded, so their fallback/default counts go with them."""
        self.episodes.reset_counts()
        return self.env.reset(env_reset_seed(self.cfg.seed, update))

    def _record_episodes(self, finished: list) -> bool:
        """Append finished episodes to metrics.csv; True once the budget is spent."""
        st, budget = self.state, self.cfg.episodes
        rows = episode_rows(finished, st.episodes, budget, st.recent, st.env_steps, round(st.wall_time(), 3))
        for row, e in zip(rows, finished):  # the episodes that fit the budget: their link columns
            self.episodes.add(row[0], e, st.step)
        st.episodes += len(rows)
        self.episodes.end(finished)
        self.rd.append_episodes(rows)
        return st.episodes >= budget

    def _restore(self, update: int, step: int) -> None:
        saved_step = checkpoint.restore(self.rd, self.state, self.episodes, update, step)
        self.rollout_version = update
        self.log.info("resumed at update %d: %d episodes, %d env steps, step counter %d (saved %d)",
                      update, self.state.episodes, self.state.env_steps, step, saved_step)

    def write_episode_links(self) -> None:
        """episode_links.csv (`hammer up` then adds the per-link columns, faults.episode_links);
        also flushes this process's step log and writes the trace."""
        self.step_log.flush()
        self.episodes.write_all()
        if self.trace is not None:
            self.trace.close()

    def summary(self, t_start: float) -> dict:
        """`wall_time` covers the whole run (it continues across resumes, like metrics.csv's
        wall_time column); `env_steps_per_s` is this session's rate."""
        st, cfg = self.state, self.cfg
        elapsed = time.perf_counter() - t_start
        lat = np.array(st.step_latency_ms) if st.step_latency_ms else np.zeros(1)
        recent = list(st.recent)
        return {
            "episodes": st.episodes, "env_steps": st.env_steps, "updates": st.update,
            "final_paper_metric_last500": float(np.mean(recent)) if recent else None,
            "env_steps_per_s": (st.env_steps - st.steps_at_start) / max(elapsed, 1e-9),
            # the same without the wait for the learner's first weights (its start-up: torch import,
            # networks), as `hammer train` times itself after its set-up (`hammer bench scale`)
            "env_steps_per_s_after_start": (st.env_steps - st.steps_at_start)
            / max(elapsed - self.time_s["first_weights"], 1e-9),
            "step_latency_ms_p50": float(np.percentile(lat, 50)),
            "step_latency_ms_p99": float(np.percentile(lat, 99)),
            "wall_time": st.wall_time(), "session_wall_time": elapsed,
            "resumed_from": self.resume_from, "n_agents": cfg.n_agents, "episode_length": int(self.spec.max_steps),
            "variant": cfg.variant, "central_mode": cfg.central_mode, "env": cfg.env,
            "links": self.links.as_dict(), "step": st.step, "completed": st.episodes >= cfg.episodes,
            "time_s": {**{k: round(v, 3) for k, v in self.time_s.items()},
                       "rest": round(elapsed - sum(self.time_s.values()), 3)},
            **({"pushes": {"named": self.pushes_named, "named_unheld": self.push_named_unheld,
                           "last_wait_s": round(self.push_wait_s, 3), "waits_s": self.push_waits_s[-32:]}} if self.announce_in is not None else {}),
        }
