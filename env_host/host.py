"""The env host: steps K env copies and drives the distributed step loop.

Per vector step (3 hops): publish the global state to the central agent and each local agent's
observation; collect every agent's action until all are in or the deadline passes (a missing
action becomes the env's declared default and is counted); step the env. After T steps it sends
the rollout to the learner as one ExperienceChunk tagged with the policy version that produced it,
and waits for the next version's weights before acting again (on-policy synchronisation).

The loop mirrors `learning.trainer.Trainer._collect` step for step (same env seeds, same reset
points, same episode budget), so without faults a distributed run reproduces the in-process one.

Evaluation (`run_eval`, RuntimeSettings.mode == "eval"): the same per-step hops with a frozen
policy (version 0 from the policy server), no experience and no waiting for new versions; episodes
until the budget. Both modes write `episode_links.csv`: per finished episode, its env copy, length
and span of global steps (`start_step..end_step`), and how many agent x copy entries of that copy
acted on a fallback message and used the declared default action; `hammer up` adds the per-link
columns from the roles' step logs (this process logs the state / observations it sent and the
actions it received, `RUN/linksteps/env-<pid>.csv`; see faults/episode_links.py and
docs/faults.md). `trace.npz` (obs, messages, actions, masks per step) on request.

Resuming (`hammer up --resume`): at every checkpoint point (update % checkpoint_every == 0, where
the env copies are reseeded anyway) the host writes `host_state/ckpt_<update>.json` (its counters,
recent metrics, wall clock) after flushing metrics.csv and the episode rows, so a run killed later
can continue from the latest update that has both this file and the learner's checkpoint.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from envs.base import VecEnv
from faults.steplog import STEP_LOG_DIR, LoggedPublisher, StepLog, column
from learning.central_acting import encode_actions, zero_prev_actions
from learning.config import RunConfig
from learning.rundir import RunDir, fsync_file
from learning.sampling import env_reset_seed
from protocol.schemas import (
    Action,
    Control,
    Dims,
    EpisodeInfo,
    ExperienceChunk,
    GlobalState,
    Heartbeat,
    LocalObs,
    StepResult,
    Weights,
)
from protocol.session import HammerSession

log = logging.getLogger("hammer.env_host")


@dataclass
class LinkCounters:
    """Counts for the local→env action link (per run)."""

    actions_on_time: int = 0
    actions_late: int = 0  # arrived after the deadline of their step (discarded)
    actions_duplicate: int = 0
    default_actions: int = 0  # agent×copy entries that used the declared default
    msg_fallback_copies: int = 0  # agent×copy entries whose agent acted on a fallback message
    off_policy_actions: int = 0  # actions produced by another policy version than the rollout's

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


HOST_STATE_DIR = "host_state"
EPISODE_ROW_COLUMNS = ("episode", "env_index", "length", "start_step", "end_step", "msg_fallbacks", "default_actions")


def host_state_path(run_dir: Path, update: int) -> Path:
    return Path(run_dir) / HOST_STATE_DIR / f"ckpt_{update:07d}.json"


def host_state_updates(run_dir: Path) -> list[int]:
    """The updates with a saved host state, ascending."""
    d = Path(run_dir) / HOST_STATE_DIR
    return sorted(int(p.stem[5:]) for p in d.glob("ckpt_*.json")) if d.is_dir() else []


def read_host_state(run_dir: Path, update: int) -> dict:
    return json.loads(host_state_path(run_dir, update).read_text())


def write_host_state(run_dir: Path, state: dict, keep: int = 5) -> Path:
    """Atomic (tmp + fsync + rename); keeps the `keep` latest (the learner keeps 3 checkpoints)."""
    path = host_state_path(run_dir, int(state["update"]))
    path.parent.mkdir(exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(state))
    fsync_file(tmp)
    tmp.replace(path)
    for old in host_state_updates(run_dir)[:-keep]:
        host_state_path(run_dir, old).unlink(missing_ok=True)
    return path


@dataclass
class HostState:
    update: int = 0
    episodes: int = 0
    env_steps: int = 0
    step: int = 0  # global vector-step counter (message header)
    recent: deque = field(default_factory=lambda: deque(maxlen=500))
    step_latency_ms: deque = field(default_factory=lambda: deque(maxlen=2000))


class _Wiring:
    """What the env host needs of the team's wiring: action encodings for the global state, the
    message width, whether a central network exists. Torch-free (`learning.central_acting`), so
    the env host process does not load torch."""

    def __init__(self, cfg: RunConfig, spec) -> None:
        self.spec = spec
        self.act_dim, self.msg_dim = spec.action_dim, cfg.effective_msg_dim
        self.has_central_network = cfg.wiring.has_central_network

    def encode_actions(self, actions: np.ndarray, active: np.ndarray) -> np.ndarray:
        return encode_actions(self.spec, actions, active)

    def zero_prev_actions(self, k: int) -> np.ndarray:
        return zero_prev_actions(self.spec, k)

    def env_action(self, action: np.ndarray) -> np.ndarray:
        return self.spec.env_action(action)


class EnvHost:
    def __init__(self, session: HammerSession, cfg: RunConfig, env: VecEnv, rd: RunDir,
                 act_deadline_s: float, weights_timeout_s: float, trace: bool = False,
                 max_policy_lag: int = 0, resume_from: int | None = None, resume_step: int | None = None) -> None:
        self.s, self.cfg, self.env, self.rd = session, cfg, env, rd
        self.spec = env.spec
        self.team = _Wiring(cfg, env.spec)
        self.n, self.k = cfg.n_agents, cfg.num_envs
        self.act_deadline_s, self.weights_timeout_s = act_deadline_s, weights_timeout_s
        self.uses_central = cfg.wiring.uses_central
        keys = session.keys
        dims = Dims(num_envs=self.k, n_agents=self.n, action_dim=self.spec.action_dim, discrete=self.spec.discrete,
                    msg_dim=self.team.msg_dim or None)
        self.act_sub = session.subscribe(keys.act("*"), Action, dims)
        self.w_sub = session.subscribe(keys.weights("local"), Weights)
        self.ctl_sub = session.subscribe(keys.ctl("all"), Control)
        self.obs_pubs = [session.publisher(keys.obs(i), express=True) for i in range(self.n)]
        self.state_pub = session.publisher(keys.state(), express=True)
        self.result_pub = session.publisher(keys.result(), reliable=False)
        self.exp_pub = session.publisher(keys.exp("team"))
        self.hb_pub = session.publisher(keys.heartbeat("env"), reliable=False)
        self.c = LinkCounters()
        self.h = HostState()
        self.weights_version = -1
        self.max_policy_lag = max_policy_lag
        if (resume_from is None) != (resume_step is None):
            raise ValueError("resume_from and resume_step go together")
        self.resume_from, self.resume_step = resume_from, resume_step
        self.rollout_version = 0  # the policy version the current rollout is acted with
        self.env_idx = np.arange(self.k, dtype=np.int64)
        self._last_hb = 0.0
        self._stop = False
        # Per env copy, since its current episode started: agent-steps on a fallback message / on the
        # default action. Zeroed where an episode starts: after it ends, and at every env reset.
        self.ep_fallback = np.zeros(self.k, np.int64)
        self.ep_default = np.zeros(self.k, np.int64)
        self._ep_rows: list[tuple] = []
        self._ep_rows_saved = 0  # rows already in episode_links.csv (written at checkpoint points)
        self._steps0 = 0  # env steps before this session (resume)
        # Link events per step (faults.steplog), joined with the episodes' spans by `hammer up`.
        links = (["env->central"] if self.uses_central else []) + ["env->local"]
        self.step_log = StepLog(rd.path / STEP_LOG_DIR, "env", [
            *(column(lk, e) for lk in links for e in ("sent", "dropped", "duplicated")),
            *(column("local->env", e) for e in ("delivered", "late", "duplicate", "defaults"))])
        self.state_pub = LoggedPublisher(self.state_pub, session, self.step_log, "env->central")
        self.obs_pubs = [LoggedPublisher(p, session, self.step_log, "env->local") for p in self.obs_pubs]
        self._act_cols = {e: column("local->env", e) for e in ("delivered", "late", "duplicate", "defaults")}
        self._recent_got: dict[int, np.ndarray] = {}  # step -> agents whose action arrived (duplicate detection)
        self.trace: dict[str, list] | None = {"steps": [], "obs": [], "msgs": [], "actions": [], "fallback": [],
                                               "defaulted": []} if trace else None
        sh = self.spec
        t = cfg.rollout_steps
        a_shape = sh.action_shape
        self.rollout = {
            "obs": np.zeros((t, self.k, self.n, sh.obs_dim), np.float32),
            "prev": np.zeros((t, self.k, self.n, self.team.act_dim), np.float32),
            "msg": np.zeros((t, self.k, self.n, self.team.msg_dim), np.float32),
            "actions": np.zeros((t, self.k, self.n, *a_shape), np.int64 if sh.discrete else np.float32),
            "rewards": np.zeros((t, self.k, self.n), np.float32),
            "terminated": np.zeros((t, self.k, self.n), bool),
            "truncated": np.zeros((t, self.k, self.n), bool),
            "active": np.zeros((t, self.k, self.n), bool),
            "reset": np.zeros((t, self.k, self.n), bool),
            "final_obs": np.zeros((t, self.k, self.n, sh.obs_dim), np.float32),
            "final_prev": np.zeros((t, self.k, self.n, self.team.act_dim), np.float32),
            "defaulted": np.zeros((t, self.k, self.n), bool),
            "steps": np.zeros(t, np.int64),
        }

    # ----- weights / control --------------------------------------------------------------------
    def _poll_control(self) -> None:
        for cmd in self.ctl_sub.drain():
            if cmd.command in ("stop", "shutdown") and cmd.target in ("*", "env"):
                self._stop = True

    def wait_weights(self, version: int) -> bool:
        """Block until the learner has published local weights >= version (or stop/timeout)."""
        deadline = time.monotonic() + self.weights_timeout_s
        while self.weights_version < version:
            self._poll_control()
            self._heartbeat("ready")
            if self._stop:
                return False
            w = self.w_sub.get(timeout=0.2)
            if w is not None:
                self.weights_version = max(self.weights_version, w.version)
            elif time.monotonic() > deadline:
                raise TimeoutError(f"learner did not publish policy version {version} within "
                                   f"{self.weights_timeout_s:.0f}s (is `hammer learner` running?)")
        return True

    def _heartbeat(self, status: str = "running") -> None:
        now = time.monotonic()
        if now - self._last_hb < 0.5:
            return
        self._last_hb = now
        lat = np.array(self.h.step_latency_ms) if self.h.step_latency_ms else np.zeros(1)
        running = float(np.mean(list(self.h.recent)[-100:])) if self.h.recent else 0.0
        self.hb_pub.publish(Heartbeat(role="env", pid=os.getpid(), status=status, counters={
            **self.c.as_dict(), **self.s_fault_counters(), "episodes": self.h.episodes,
            "env_steps": self.h.env_steps, "step": self.h.step,
            "update": self.h.update, "policy_version": self.weights_version, "paper_metric_100": running,
            "step_p50_ms": float(np.percentile(lat, 50)), "step_p99_ms": float(np.percentile(lat, 99))}))

    def s_fault_counters(self) -> dict[str, int]:
        from faults.links import flat_fault_counters

        return flat_fault_counters(self.s.fault_report())

    # ----- one vector step ----------------------------------------------------------------------
    def _collect_actions(self, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All agents' actions for `step` (defaults where missing), messages used, defaulted mask."""
        n, k = self.n, self.k
        actions = self.spec.default_actions(k)
        msgs = np.zeros((k, n, self.team.msg_dim), np.float32)
        fallback = np.zeros((k, n), dtype=bool)
        got = np.zeros(n, dtype=bool)
        cols = self._act_cols
        deadline = time.monotonic() + self.act_deadline_s
        while not got.all():
            a = self.act_sub.get(timeout=max(0.0, deadline - time.monotonic()))
            if a is None:
                break
            if a.step > step:  # cannot happen without a bug upstream: we have not published it yet
                log.warning("action for future step %d (now %d) from agent %d ignored", a.step, step, a.agent)
                continue
            self.step_log.add(a.step, cols["delivered"])
            if a.step < step:
                prev_got = self._recent_got.get(a.step)
                if prev_got is not None and prev_got[a.agent]:
                    self.c.actions_duplicate += 1  # a second copy of an action already applied
                    self.step_log.add(a.step, cols["duplicate"])
                else:
                    self.c.actions_late += 1
                    self.step_log.add(a.step, cols["late"])
                continue
            if got[a.agent]:
                self.c.actions_duplicate += 1
                self.step_log.add(step, cols["duplicate"])
                continue
            if a.policy_version != self.rollout_version:
                self.c.off_policy_actions += 1
            rows = a.env_idx
            actions[rows, a.agent] = a.action
            if a.msg is not None and self.team.msg_dim:
                msgs[rows, a.agent] = a.msg
            self.c.msg_fallback_copies += int(a.fallback.sum())
            fallback[rows, a.agent] = a.fallback
            got[a.agent] = True
            self.c.actions_on_time += 1
        defaulted = np.zeros((k, n), dtype=bool)
        defaulted[:, ~got] = True
        self.c.default_actions += int(defaulted.sum())
        self.step_log.add(step, cols["defaults"], int(defaulted.sum()))
        self.step_log.maybe_flush()
        self._recent_got[step] = got
        self._recent_got.pop(step - 16, None)
        self.ep_fallback += fallback.sum(axis=1)
        self.ep_default += defaulted.sum(axis=1)
        self._fallback = fallback
        return actions, msgs, defaulted

    def _vector_step(self, obs: np.ndarray, prev: np.ndarray, active: np.ndarray):
        """One step of the loop: state + observations out, actions in (or defaults), env step,
        result out. Returns (VecStep, actions, messages used, defaulted mask)."""
        h, cfg = self.h, self.cfg
        h.step += 1
        t0 = time.perf_counter()
        if self.uses_central:
            self.state_pub.publish(GlobalState(step=h.step, env_idx=self.env_idx, obs=obs,
                                               prev_actions=prev, active=active, policy_version=self.rollout_version))
        joint = obs.reshape(self.k, -1) if cfg.wiring.joint_obs else None
        for i in range(self.n):
            self.obs_pubs[i].publish(LocalObs(step=h.step, env_idx=self.env_idx, agent=i,
                                              obs=joint if joint is not None else np.ascontiguousarray(obs[:, i]),
                                              active=active[:, i], policy_version=self.rollout_version))
        action, msgs, defaulted = self._collect_actions(h.step)
        # Control-loop latency: observations out -> every action in (3 hops), env step excluded.
        h.step_latency_ms.append((time.perf_counter() - t0) * 1e3)
        st = self.env.step(self.team.env_action(action))
        if self.trace is not None:
            for name, v in (("steps", h.step), ("obs", obs), ("msgs", msgs), ("actions", action),
                            ("fallback", self._fallback), ("defaulted", defaulted)):
                self.trace[name].append(np.copy(v))
        self.result_pub.publish(StepResult(
            step=h.step, env_idx=self.env_idx, rewards=st.reward, terminated=st.terminated,
            truncated=st.truncated, done=st.done, defaulted=defaulted,
            episodes=[EpisodeInfo.from_stats(e) for e in st.episodes]))
        return st, action, msgs, defaulted

    def run_eval(self) -> dict:
        """Evaluate the frozen policy (version 0) until the episode budget; no learning."""
        team, h = self.team, self.h
        t_start = self._t_wall0 = time.perf_counter()
        if not self.wait_weights(0) or not self._wait_actors_ready():
            return self.summary(t_start)
        obs, active = self._reset_env(0)
        prev = team.zero_prev_actions(self.k)
        while not self._stop:
            self._poll_control()
            if self._stop:
                break
            self._heartbeat()
            st, action, _, _ = self._vector_step(obs, prev, active)
            prev = team.encode_actions(action, st.active)
            if st.done.any():
                prev[np.flatnonzero(st.done)] = 0.0
            obs, active = st.obs, st.next_active
            h.env_steps += self.k
            if st.episodes and self._record_episodes(st.episodes):
                break
        self.rd.flush()
        return self.summary(t_start)

    def _wait_actors_ready(self) -> bool:
        """Eval: start stepping only once the central agent and every local agent hold the policy
        (their heartbeats say so), so that a fault-free evaluation has no message missing at
        start-up and no first step slowed by an agent still loading its weights."""
        roles = [f"local-{i}" for i in range(self.n)]
        if self.uses_central and self.team.has_central_network:
            roles.insert(0, "central")
        subs = {r: self.s.subscribe(self.s.keys.heartbeat(r), Heartbeat) for r in roles}
        deadline = time.monotonic() + self.weights_timeout_s
        try:
            while subs and time.monotonic() < deadline:
                self._poll_control()
                if self._stop:
                    return False
                for r, sub in list(subs.items()):
                    for hb in sub.drain():
                        if hb.counters.get("policy_version", -1) >= 0:
                            del subs[r]
                            break
                if subs:
                    time.sleep(0.005)
        finally:
            for sub in subs.values():
                sub.close()
        if subs:
            raise TimeoutError(f"{', '.join(subs)} did not load the policy within {self.weights_timeout_s:.0f}s "
                               "(are `hammer central` / `hammer local` running?)")
        return True

    def run(self) -> dict:
        cfg, team, h, r = self.cfg, self.team, self.h, self.rollout
        t_start = self._t_wall0 = time.perf_counter()
        obs = prev = active = None
        if self.resume_from is not None:
            self._restore(self.resume_from, self.resume_step)
        else:  # rows of an earlier attempt in this directory must not precede ours (_save_state appends)
            (self.rd.path / "episode_links.csv").unlink(missing_ok=True)
        if not self.wait_weights(h.update):
            return self.summary(t_start)
        while not self._stop:
            if h.update % cfg.checkpoint_every == 0:
                self._save_state()
                obs, active = self._reset_env(h.update)
                prev = team.zero_prev_actions(self.k)
            r["reset"][:] = False
            finished = False
            for t in range(cfg.rollout_steps):
                self._poll_control()
                if self._stop:
                    break
                self._heartbeat()
                st, action, msgs, defaulted = self._vector_step(obs, prev, active)
                r["obs"][t], r["prev"][t], r["msg"][t], r["actions"][t] = obs, prev, msgs, action
                r["rewards"][t], r["terminated"][t], r["truncated"][t] = st.reward, st.terminated, st.truncated
                r["active"][t], r["defaulted"][t], r["steps"][t] = st.active, defaulted, h.step
                prev = team.encode_actions(action, st.active)
                if st.done.any():
                    idx = np.flatnonzero(st.done)
                    r["reset"][t, idx] = True
                    r["final_obs"][t, idx] = st.final_obs[idx]
                    r["final_prev"][t, idx] = prev[idx]
                    prev[idx] = 0.0
                obs, active = st.obs, st.next_active
                h.env_steps += self.k
                if st.episodes and self._record_episodes(st.episodes):
                    finished = True
                    break
            if finished or self._stop:
                break
            self.exp_pub.publish(ExperienceChunk(
                step=h.step, env_idx=self.env_idx, role="team", policy_version=self.rollout_version,
                arrays={**r, "last_obs": obs, "last_prev": prev}))
            h.update += 1
            # Synchronous (lag 0): wait for the version this rollout trains. With a lag L, go on
            # with the newest version we hold as long as it is at most L updates behind.
            if not self.wait_weights(h.update - self.max_policy_lag):
                break
            self.rollout_version = self.weights_version if self.max_policy_lag else h.update
        self.rd.flush()
        return self.summary(t_start)

    # ----- resume -------------------------------------------------------------------------------
    def _save_state(self) -> None:
        """At a checkpoint point: metrics.csv and the episode rows on disk first, then the host
        state that vouches for them (so every count in it is backed by rows on disk)."""
        self.rd.flush()
        if self.rd.metrics_path.is_file():
            fsync_file(self.rd.metrics_path)
        path = self.rd.path / "episode_links.csv"
        new = self._ep_rows[self._ep_rows_saved:]
        if new or not path.is_file():
            with open(path, "a") as f:
                if f.tell() == 0:
                    f.write(",".join(EPISODE_ROW_COLUMNS) + "\n")
                f.writelines(",".join(map(str, row)) + "\n" for row in new)
            fsync_file(path)
            self._ep_rows_saved = len(self._ep_rows)
        h = self.h
        write_host_state(self.rd.path, {
            "update": h.update, "episodes": h.episodes, "env_steps": h.env_steps, "step": h.step,
            "wall_time": time.perf_counter() - self._t_wall0, "recent": list(h.recent),
            "episode_rows": len(self._ep_rows)})

    def _restore(self, update: int, step: int) -> None:
        """Continue from host_state/ckpt_<update>.json: counters, recent metrics and wall clock;
        metrics.csv and episode_links.csv cut back to the episodes it counted.

        The step counter does not continue from the saved value but from `step`, which the
        launcher puts above every step the killed session may have reached (its latest host
        state + checkpoint_every x rollout_steps): the roles' per-step link logs (RUN/linksteps/)
        of that session stay on disk and are joined to episodes by step number
        (faults.episode_links), so reusing a number would add the lost rollouts' link events to
        the new episodes."""
        h = self.h
        path = host_state_path(self.rd.path, update)
        st = read_host_state(self.rd.path, update)
        if int(st["update"]) != update or int(st["episode_rows"]) != int(st["episodes"]):
            raise ValueError(f"{path}: inconsistent host state (update {st['update']}, "
                             f"{st['episodes']} episodes, {st['episode_rows']} episode rows)")
        if step < int(st["step"]):
            raise ValueError(f"resume_step {step} is below the saved step counter {st['step']} ({path})")
        h.update, h.episodes, h.env_steps, h.step = update, int(st["episodes"]), int(st["env_steps"]), step
        h.recent = deque((float(x) for x in st["recent"]), maxlen=h.recent.maxlen)
        self._steps0 = h.env_steps
        self._t_wall0 = time.perf_counter() - float(st["wall_time"])
        self.rollout_version = update
        self.rd.truncate_metrics(h.episodes)
        self._ep_rows = self._read_episode_rows(h.episodes)
        self._ep_rows_saved = 0  # _save_state rewrites the file with exactly these rows
        (self.rd.path / "episode_links.csv").unlink(missing_ok=True)
        log.info("resumed at update %d: %d episodes, %d env steps, step counter %d (saved %d)",
                 update, h.episodes, h.env_steps, step, st["step"])

    def _read_episode_rows(self, n: int) -> list[tuple]:
        """The first n rows of episode_links.csv (base columns; a torn last line is never among them)."""
        path = self.rd.path / "episode_links.csv"
        rows: list[tuple] = []
        if n:
            with open(path, newline="") as f:
                for row in csv.DictReader(f):
                    if len(rows) == n:
                        break
                    rows.append(tuple(int(row[c]) for c in EPISODE_ROW_COLUMNS))
        if len(rows) != n or [r[0] for r in rows] != list(range(1, n + 1)):
            raise ValueError(f"{path}: expected episodes 1..{n}, found {len(rows)} rows")
        return rows

    def _reset_env(self, update: int) -> tuple[np.ndarray, np.ndarray]:
        """Reseed every env copy (the points shared with `hammer train`); running episodes are
        dropped unrecorded, so their fallback/default counts go with them."""
        self.ep_fallback[:] = self.ep_default[:] = 0
        return self.env.reset(env_reset_seed(self.cfg.seed, update))

    def _record_episodes(self, episodes: list) -> bool:
        """Append finished episodes to metrics.csv; True once the budget is spent."""
        h, cfg = self.h, self.cfg
        wall = round(time.perf_counter() - self._t_wall0, 3)
        rows = []
        for e in episodes:
            if h.episodes >= cfg.episodes:
                break
            h.episodes += 1
            h.recent.append(e.paper_metric)
            rows.append((h.episodes, h.env_steps, repr(e.paper_metric), repr(e.team_return), e.length, wall))
            i = e.env_index
            self._ep_rows.append((h.episodes, i, e.length, h.step - e.length + 1, h.step,
                                  int(self.ep_fallback[i]), int(self.ep_default[i])))
        for e in episodes:
            self.ep_fallback[e.env_index] = self.ep_default[e.env_index] = 0
        self.rd.append_episodes(rows)
        return h.episodes >= cfg.episodes

    def write_episode_links(self) -> None:
        """episode_links.csv: per finished episode, its span of global steps and the agent x copy
        entries that acted on a fallback message / used the default action (`hammer up` then adds
        the per-link columns, faults.episode_links); also flushes this process's step log."""
        self.step_log.flush()
        with open(self.rd.path / "episode_links.csv", "w") as f:
            f.write(",".join(EPISODE_ROW_COLUMNS) + "\n")
            f.writelines(",".join(map(str, row)) + "\n" for row in self._ep_rows)
        if self.trace is not None and self.trace["steps"]:
            np.savez(self.rd.path / "trace.npz", **{k: np.stack(v) for k, v in self.trace.items()})

    def summary(self, t_start: float) -> dict:
        """`wall_time` covers the whole run (it continues across resumes, like metrics.csv's
        wall_time column); `env_steps_per_s` is this session's rate."""
        elapsed = time.perf_counter() - t_start
        lat = np.array(self.h.step_latency_ms) if self.h.step_latency_ms else np.zeros(1)
        recent = list(self.h.recent)
        return {
            "episodes": self.h.episodes, "env_steps": self.h.env_steps, "updates": self.h.update,
            "final_paper_metric_last500": float(np.mean(recent)) if recent else None,
            "env_steps_per_s": (self.h.env_steps - self._steps0) / max(elapsed, 1e-9),
            "step_latency_ms_p50": float(np.percentile(lat, 50)),
            "step_latency_ms_p99": float(np.percentile(lat, 99)),
            "wall_time": time.perf_counter() - getattr(self, "_t_wall0", t_start), "session_wall_time": elapsed,
            "resumed_from": self.resume_from, "n_agents": self.cfg.n_agents, "episode_length": int(self.spec.max_steps),
            "variant": self.cfg.variant, "central_mode": self.cfg.central_mode, "env": self.cfg.env,
            "links": self.c.as_dict(), "step": self.h.step, "completed": self.h.episodes >= self.cfg.episodes,
        }
