"""What the messages say (docs/results/plan-messages.md): a trained team acts with its
frozen weights, every step's messages, local observations and the world state are recorded, and
linear probes ask whether a message tells its receiver what the receiver cannot see.

The team acts in this process with the runtime's own acting code, not a copy of it: the env host's
loop (env reset seed `env_reset_seed(seed, 0)`, `local_view` on the local copy only, previous
actions by `learning.rollout.next_prev_actions`), the central server's numpy forward and sampling
(`NumpyCentralAgent`, `CentralActing.messages`, the randomness contract's streams) and each local
agent's `local_agent.client.LocalAgent` (numpy policy, own stream). Same seed, same episodes: an
uncut evaluation here reproduces `hammer faults sweep` at drop 0 (to 1e-9: only the order of the
final mean's sum differs), and cutting every agent reproduces drop 1.0, a dropped message acted on
the zeros fallback (tests/test_messages.py).

The hidden quantities come from the env's world state (`VecSimpleSpread.pos` / `.landmarks`, read
when the observation is made), which the agents never receive. Per receiving agent i:
  H_agents    p_j − p_i for each other agent j that i cannot see (ownobs: both; obs_radius r: only
              rows where |p_j − p_i| ≥ r; full view: both, visible — the plan's negative reference)
  H_landmark  the landmark nearest to i among those that are no other agent's nearest, minus p_i
              (obs_radius: only rows where it is hidden)
  V           i's nearest landmark minus p_i, a control i sees (obs_radius: only where visible)
  X_actions   exploratory, not in the plan: each other agent's previous action as its force direction
              (x, y in {-1, 0, 1}), which the central agent's state holds and no local agent sees

The warehouse (rware teams; plan-messages.md, addendum of 2026-12-03): the targets come from the
observation's central-only columns (every shelf's cell and requested flag, `envs.rware_vec`), which
the local view zeroes. Per receiving robot i, cells relative to its own (x, y):
  H_agents    each other robot's cell, only where it is outside i's (2·sensor_range+1)² window
  H_shelf     the requested shelf no robot carries that is nearest to i (Euclidean, ties by shelf id),
              only where i carries nothing and that shelf is outside its window ("where to fetch")
  V           the same shelf where it is inside i's window (a control i sees)
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from hammer.experiments.probes import FOLDS, cv_r2

PLAN_TARGETS = ("H_agents", "H_landmark", "H_shelf", "V")  # a team has those of its task (cn or rware)
TARGETS = (*PLAN_TARGETS, "X_actions")
TESTED = ("H_agents", "H_landmark", "H_shelf")  # the plan's tested targets; V is its control; X_actions exploratory
FEATURES = ("u", "o", "ou")  # [u_i], [o_i], [o_i, u_i]
ANALYSIS_VERSION = 2  # bump when a per-team figure would change: cached results are then recomputed


class MessagesError(ValueError):
    """The team cannot be analysed; the message says why and what to do."""


@dataclass
class Recording:
    """One evaluation seed of a team, episode-major: E episodes of T steps, N agents."""

    msgs: np.ndarray  # (E, T, N, M) float32: the message each agent acted on (zeros where cut)
    mean: np.ndarray  # (E, T, N, M) float32: the central policy's mean (rl: before the Gaussian noise)
    local_obs: np.ndarray  # (E, T, N, D) float32: what each local agent saw
    full_obs: np.ndarray  # (E, T, N, D) float32: the env's observation (the central state's part)
    pos: np.ndarray | None  # (E, T, N, 2) float64: cn agent positions when the observation was made
    landmarks: np.ndarray | None  # (E, T, N, 2) float64: cn landmarks; rware: None (targets from full_obs)
    prev: np.ndarray  # (E, T, N, A) float32: the previous actions in the central agent's state
    paper_metric: np.ndarray  # (E,)


@dataclass(frozen=True)
class WarehouseLayout:
    """Where rware's observation row keeps what the targets need (`envs.rware_vec`): the local part's
    length, the shelves and goals of the central-only columns, the robots' sensor range."""

    local_dim: int
    n_shelves: int
    n_goals: int
    sensor_range: int


View = float | None | WarehouseLayout  # cn: the local view's obs_radius (None: none); rware: its layout
ENVS = ("cn", "rware")


class TeamActor:
    """A trained team (a run directory with final/, or a bundle) acting in this process."""

    def __init__(self, run: Path, need_messages: bool = True) -> None:
        """need_messages=False: also a team without messages (IL), for what it sees, not what it is told."""
        from hammer.experiments.fault_sweep import team_source

        self.run = Path(run)
        self.data, self.policy_dir = team_source(self.run)
        cfg = self.config(0, 1)
        if cfg.env not in ENVS:
            raise MessagesError(f"{run}: env {cfg.env!r}; the hidden targets are defined for "
                                f"{' and '.join(ENVS)} only (envs.spread, envs.rware_vec)")
        if need_messages and not cfg.wiring.uses_central:
            raise MessagesError(f"{run}: variant {cfg.variant} sends no messages; fix: pass hammer or random teams")
        self.local_blob = (self.policy_dir / "local.safetensors").read_bytes()
        self.central_blob = ((self.policy_dir / "central.safetensors").read_bytes()
                             if cfg.wiring.has_central_network else None)

    def config(self, seed: int, episodes: int):
        from hammer.experiments.fault_sweep import eval_config

        return eval_config(self.run, episodes, seed)

    def view(self) -> View:
        """What defines the targets of this team's task: cn's obs_radius, or the warehouse's layout."""
        cfg = self.config(0, 1)
        if cfg.env == "cn":
            return (cfg.env_kwargs or {}).get("obs_radius")
        from hammer.envs.registry import make_vec_env

        env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
        try:
            return WarehouseLayout(env.local_dim, env.n_shelves, env.n_goals, env.settings.sensor_range)
        finally:
            env.close()

    def weights_digest(self) -> str:
        h = hashlib.sha256(self.local_blob)
        h.update(self.central_blob or b"")
        return h.hexdigest()

    def rollout(self, seed: int, episodes: int, cut: tuple[int, ...] = (), record: bool = False
                ) -> Recording | np.ndarray:
        """The first `episodes` episodes of evaluation seed `seed` (the runtime's episode order), with the
        messages of the agents in `cut` replaced by zeros; the per-episode paper metric, or everything."""
        from hammer.envs.local_view import local_view_from_config
        from hammer.envs.registry import make_vec_env
        from hammer.learning.central_acting import CentralActing, zero_prev_actions
        from hammer.learning.rollout import next_prev_actions
        from hammer.learning.sampling import ActingStreams, env_reset_seed

        cfg = self.config(seed, episodes)
        env = make_vec_env(cfg.env, cfg.n_agents, cfg.num_envs, env_kwargs=cfg.env_kwargs or None)
        spec, view, agents, net = env.spec, local_view_from_config(cfg, env.spec), *self._networks(cfg, env.spec)
        acting, streams = CentralActing.from_config(cfg), ActingStreams(cfg.seed, cfg.n_agents)
        obs, _ = env.reset(env_reset_seed(cfg.seed, 0))
        prev = zero_prev_actions(spec, cfg.num_envs)
        metrics, steps = [], []
        while len(metrics) < episodes:
            out = acting.messages(acting.global_state(obs, prev), streams, 0.0,
                                  net.message_mean if net is not None else None,
                                  net.values if net is not None and acting.rl else None)
            msgs = out.sent.copy()
            msgs[:, list(cut)] = 0.0
            seen = view(obs)
            if record:
                world = (env.pos.copy(), env.landmarks.copy()) if cfg.env == "cn" else (None, None)
                steps.append((msgs, out.mean, seen, obs, *world, prev))
            actions = np.stack([a.act(seen[:, i], msgs[:, i]) for i, a in enumerate(agents)], axis=1)
            step = env.step(spec.env_action(actions))
            prev = next_prev_actions(spec, actions, step).prev
            obs = step.obs
            metrics += [e.paper_metric for e in step.episodes]
        env.close()
        metric = np.asarray(metrics[:episodes])
        return _episode_major(steps, spec.max_steps, episodes, metric) if record else metric

    def _networks(self, cfg, spec):
        from hammer.learning.numpy_policy import NumpyCentralAgent
        from hammer.local_agent.client import AgentSpec, LocalAgent
        from safetensors.numpy import load as load_safetensors

        agents = [LocalAgent(AgentSpec.from_config(cfg, spec, i)) for i in range(cfg.n_agents)]
        for a in agents:
            a.load_weights(self.local_blob, 0)
        net = NumpyCentralAgent(load_safetensors(self.central_blob)) if self.central_blob is not None else None
        return agents, net


def _episode_major(steps: list[tuple], t: int, episodes: int, metric: np.ndarray) -> Recording:
    """Per-step (K, N, ...) arrays -> (E, T, N, ...): every cn and rware copy's episodes last exactly T
    steps (rware: its time limit, no early end) and all copies reset together, so step s belongs to
    round s // T; episodes are round-major, copy within round (the order the env reports them)."""
    if len(steps) % t:
        raise MessagesError(f"{len(steps)} steps is not a whole number of {t}-step episodes")

    def stack(j: int) -> np.ndarray | None:
        if steps[0][j] is None:
            return None
        a = np.stack([s[j] for s in steps])  # (S, K, N, ...)
        a = a.reshape(len(steps) // t, t, *a.shape[1:])  # (R, T, K, ...)
        a = np.moveaxis(a, 2, 1)  # (R, K, T, ...)
        return a.reshape(a.shape[0] * a.shape[1], *a.shape[2:])[:episodes]  # explicit: IL's messages are empty

    return Recording(*(stack(j) for j in range(7)), paper_metric=metric)


# ----- hidden targets -----------------------------------------------------------------------------
@dataclass
class Target:
    """A target of receiving agents: S 2-D slots per agent and row, each defined only where `mask`."""

    values: np.ndarray  # (R, N, S, 2)
    mask: np.ndarray  # (R, N, S) bool
    names: list[str]  # one per slot


def hidden_targets(pos: np.ndarray, landmarks: np.ndarray, full_obs: np.ndarray, radius: float | None
                   ) -> dict[str, Target]:
    """The plan's targets per row (a step of an episode) and receiving agent, from the world state.
    pos, landmarks (R, N, 2); full_obs (R, N, D) only for which slots a radius hides (the local view's
    own test: squared distance of the float32 relative position, in float64, ≥ r²)."""
    r, n = pos.shape[:2]
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])  # (N, N-1)
    rel_agents = pos[:, others] - pos[:, :, None]  # (R, N, N-1, 2)
    rel_lm = landmarks[:, None] - pos[:, :, None]  # (R, N, L, 2)
    dist_lm = np.linalg.norm(rel_lm, axis=-1)  # (R, N, L)
    nearest = dist_lm.argmin(axis=-1)  # (R, N): each agent's nearest landmark
    claimed = np.zeros(dist_lm.shape, bool)  # (R, N, L): some other agent's nearest
    for i in range(n):
        for j in others[i]:
            claimed[np.arange(r), i, nearest[:, j]] = True
    take = np.where(claimed, np.inf, dist_lm).argmin(axis=-1)  # (R, N): always one left (N-1 claims)
    pick = lambda idx: np.take_along_axis(rel_lm, idx[:, :, None, None], axis=2)
    if radius is None:
        hid_agents = np.ones(rel_agents.shape[:3], bool)
        hid_take = vis_near = np.ones((r, n, 1), bool)
    else:
        d2_lm, d2_ag = _observed_d2(full_obs, n)
        hid_agents = d2_ag >= radius * radius
        hid_take = np.take_along_axis(d2_lm, take[:, :, None], axis=2) >= radius * radius
        vis_near = np.take_along_axis(d2_lm, nearest[:, :, None], axis=2) < radius * radius
    return {"H_agents": Target(rel_agents, hid_agents, [f"other agent {m + 1}" for m in range(n - 1)]),
            "H_landmark": Target(pick(take), hid_take, ["landmark to take"]),
            "V": Target(pick(nearest), vis_near, ["nearest landmark"])}


def _observed_d2(full_obs: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Squared distances (R, N, L) to landmarks and (R, N, N-1) to other agents, as `SpreadRadiusView`
    computes them from the observation's relative-position slots."""
    pairs = n + (n - 1)
    rel = full_obs[..., 4:4 + 2 * pairs].reshape(*full_obs.shape[:-1], pairs, 2)
    d2 = np.square(rel[..., 0], dtype=np.float64) + np.square(rel[..., 1], dtype=np.float64)
    return d2[..., :n], d2[..., n:]


def warehouse_targets(full_obs: np.ndarray, layout: WarehouseLayout) -> dict[str, Target]:
    """The warehouse's targets per row and receiving robot (module docstring), from the observation rows
    (R, N, D): robot i's x, y and load at columns 0-2 of its own row, the shelves' x, y, requested flag
    in the central-only columns (the same in every row)."""
    r, n = full_obs.shape[:2]
    xy, loaded = full_obs[:, :, 0:2].astype(np.float64), full_obs[:, :, 2] > 0.5  # (R, N, 2), (R, N)
    s0 = layout.local_dim
    shelves = full_obs[:, 0, s0:s0 + 3 * layout.n_shelves].reshape(r, layout.n_shelves, 3).astype(np.float64)
    rel = shelves[:, None, :, :2] - xy[:, :, None]  # (R, N, S, 2)
    # A carried shelf sits on its carrier's cell; an empty robot may stand under a shelf it does not carry.
    on_carrier = (np.all(shelves[:, None, :, :2] == xy[:, :, None], axis=-1) & loaded[:, :, None]).any(axis=1)
    free = (shelves[:, :, 2] > 0.5) & ~on_carrier  # (R, S): requested and on the floor
    dist = np.where(free[:, None], np.linalg.norm(rel, axis=-1), np.inf)  # (R, N, S)
    near = dist.argmin(axis=-1)  # first index among ties
    any_free = np.isfinite(np.take_along_axis(dist, near[..., None], axis=2)[..., 0])  # (R, N)
    shelf_rel = np.take_along_axis(rel, near[..., None, None], axis=2)  # (R, N, 1, 2)
    sr = layout.sensor_range
    outside = lambda d: np.abs(d).max(axis=-1) > sr
    seek = (any_free & ~loaded)[..., None]  # (R, N, 1)
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])
    rel_agents = xy[:, others] - xy[:, :, None]  # (R, N, N-1, 2)
    return {"H_agents": Target(rel_agents, outside(rel_agents), [f"other robot {m + 1}" for m in range(n - 1)]),
            "H_shelf": Target(shelf_rel, seek & outside(shelf_rel), ["requested shelf to fetch"]),
            "V": Target(shelf_rel, seek & ~outside(shelf_rel), ["requested shelf in view"])}


def recording_targets(rec: Recording, radius: View) -> dict[str, Target]:
    """`hidden_targets` of every row (episode, step) of a recording, and the exploratory X_actions; for a
    warehouse team (`radius` is its layout) `warehouse_targets`."""
    from hammer.envs.spread import _ACTION_FORCE, SENSITIVITY

    e, t, n = rec.msgs.shape[:3]
    if isinstance(radius, WarehouseLayout):
        return warehouse_targets(rec.full_obs.reshape(e * t, *rec.full_obs.shape[2:]), radius)
    flat = [a.reshape(e * t, *a.shape[2:]) for a in (rec.pos, rec.landmarks, rec.full_obs, rec.prev)]
    out = hidden_targets(*flat[:3], radius)
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])
    direction = flat[3] @ (_ACTION_FORCE / SENSITIVITY)  # (R, N, 2); no previous action: (0, 0)
    out["X_actions"] = Target(direction[:, others], np.ones((e * t, n, n - 1), bool),
                              [f"other agent {m + 1}'s previous action" for m in range(n - 1)])
    return out


# ----- probes -------------------------------------------------------------------------------------
def concat(recs: list[Recording]) -> Recording:
    """The evaluation seeds of one team as one recording (episodes stay whole, ids stay distinct)."""
    cat = lambda f: None if getattr(recs[0], f) is None else np.concatenate([getattr(r, f) for r in recs])
    return Recording(*(cat(f) for f in Recording.__dataclass_fields__))


def features(rec: Recording, agent: int, message: str = "msgs") -> dict[str, np.ndarray]:
    """The probe inputs of one receiving agent, rows = (episode, step): [u_i], [o_i], [o_i, u_i].
    message="mean" probes the central policy's noise-free mean instead of what was sent (exploratory)."""
    e, t = rec.msgs.shape[:2]
    u = getattr(rec, message)[:, :, agent].reshape(e * t, -1)
    o = rec.local_obs[:, :, agent].reshape(e * t, -1)
    return {"u": u, "o": o, "ou": np.concatenate([o, u], axis=1)}


def probe_recording(rec: Recording, radius: View, message: str = "msgs") -> dict:
    """Held-out R² of every feature set and the gain R²([o,u]) − R²([o]), per target: averaged over
    receiving agents and slots (`per_agent` keeps each agent's), each (agent, slot) probe fitted on
    the rows where the slot is defined; NaN where fewer than FOLDS episodes define it."""
    e, t, n = rec.msgs.shape[:3]
    episode = np.repeat(np.arange(e), t)
    targets = recording_targets(rec, radius)
    out = {}
    for name, tgt in targets.items():
        scores = np.full((n, tgt.mask.shape[2], len(FEATURES)), np.nan)
        for i in range(n):
            x = features(rec, i, message)
            for s in range(tgt.mask.shape[2]):
                rows = np.flatnonzero(tgt.mask[:, i, s])
                if len(np.unique(episode[rows])) < FOLDS:
                    continue
                y = tgt.values[rows, i, s]
                scores[i, s] = [cv_r2(x[f][rows], y, episode[rows]) for f in FEATURES]
        per_agent = _nanmean(scores, axis=1)  # (N, F)
        team = _nanmean(per_agent, axis=0)
        out[name] = {**{f: team[k] for k, f in enumerate(FEATURES)}, "gain": team[2] - team[1],
                     "per_agent_gain": [float(v) for v in per_agent[:, 2] - per_agent[:, 1]],
                     "rows": int(tgt.mask.sum())}
    return out


def _nanmean(a: np.ndarray, axis: int) -> np.ndarray:
    """Mean ignoring NaN; NaN (not a warning) where a whole slice is undefined."""
    ok = ~np.isnan(a)
    n = ok.sum(axis=axis)
    return np.where(n > 0, np.where(ok, a, 0.0).sum(axis=axis) / np.maximum(n, 1), np.nan)


# ----- message cut --------------------------------------------------------------------------------
def cut_drops(actor: TeamActor, seeds: list[int], episodes: int, uncut: np.ndarray) -> dict:
    """Per agent i (and, as a check against `hammer faults`, every agent at once): the paper metric of
    the same episodes with i's message zeroed, paired per episode with `uncut` (seeds concatenated):
    drop = mean(uncut − cut) (> 0: the cut costs), its paired standard error over episodes."""
    n = actor.config(0, 1).n_agents
    out = {}
    for name, cut in [*((f"agent {i}", (i,)) for i in range(n)), ("all", tuple(range(n)))]:
        cut_metric = np.concatenate([actor.rollout(s, episodes, cut=cut) for s in seeds])
        d = uncut - cut_metric
        out[name] = {"drop": float(d.mean()), "se": float(d.std(ddof=1) / np.sqrt(len(d)))}
    return out


def initial_central_weights(cfg) -> dict[str, np.ndarray]:
    """The central agent's weights before training: `learning.team.Team` builds the networks right after
    `torch.manual_seed(cfg.seed)`, so building it again gives the run's exact initialisation (its
    checkpoint 0; tests/test_messages.py compares). On the CPU whatever device the run trained on: the
    networks are initialised there in any case, and the analysis machine may have no GPU."""
    from hammer.envs.registry import make_vec_env
    from hammer.learning.team import Team

    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
    try:
        return Team(cfg.model_copy(update={"device": "cpu"}), env.spec).central.export_numpy()
    finally:
        env.close()


def initial_messages(actor: TeamActor, rec: Recording, seed: int = 0) -> np.ndarray:
    """What the team's central agent as initialised before training (`learning.team.Team` seeds torch
    with the run's seed, so these are its exact initial weights) would have sent in the recorded states,
    sampled as it samples (rl: mean + msg_std × N(0, 1) clipped to [-1, 1]). A reference for the probe:
    any function of the global state carries some of what the receiver cannot see, learned or not."""
    from hammer.learning.central_acting import CentralActing
    from hammer.learning.config import build_config
    from hammer.learning.numpy_policy import NumpyCentralAgent

    cfg = build_config(actor.data)
    net = NumpyCentralAgent(initial_central_weights(cfg))
    e, t, n, m = rec.msgs.shape
    state = CentralActing.from_config(cfg).global_state(rec.full_obs.reshape(e * t, n, -1),
                                                        rec.prev.reshape(e * t, n, -1))
    u = net.message_mean(state)
    if cfg.wiring.central_rl:
        u = np.clip(u + cfg.msg_std * np.random.default_rng(seed).standard_normal(u.shape), -1.0, 1.0)
    return u.reshape(e, t, n, m).astype(np.float32)


# ----- one team -----------------------------------------------------------------------------------
def team_key(actor: TeamActor, seeds: list[int], episodes: int) -> str:
    """What a cached result depends on: the weights, the evaluation, the analysis version."""
    blob = json.dumps([actor.weights_digest(), seeds, episodes, ANALYSIS_VERSION])
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def analyse_team(run: Path, seeds: list[int], episodes: int, keep_episode: bool = False) -> dict:
    """Record, probe and cut one team; a JSON-ready dict (with one episode for the figure if asked)."""
    from hammer.experiments.runs import load_run

    actor = TeamActor(run)
    info = load_run(run)
    recs = [actor.rollout(s, episodes, record=True) for s in seeds]
    rec = concat(recs)
    radius = actor.view()
    res = {"run": str(run), "setting": info.setting, "label": info.label, "seed": info.seed,
           "key": team_key(actor, seeds, episodes), "episodes": len(rec.paper_metric), "eval_seeds": seeds,
           "paper_metric": float(rec.paper_metric.mean()),
           "paper_metric_per_seed": [float(r.paper_metric.mean()) for r in recs],
           "probes": probe_recording(rec, radius)}
    if actor.data.get("variant") == "hammer":  # exploratory references, not the plan's tests
        if actor.data.get("central_mode") == "rl":
            res["probes_mean"] = probe_recording(rec, radius, message="mean")  # the noise-free message
        res["probes_initial"] = probe_recording(replace(rec, msgs=initial_messages(actor, rec)), radius)
    res["cut"] = cut_drops(actor, seeds, episodes, rec.paper_metric)
    if keep_episode:
        res["episode"] = episode_trace(recs[0], radius)
    return res


# ----- one episode, for the figure -----------------------------------------------------------------
def hidden_scalars(rec: Recording, radius: View) -> list[tuple[list[str], np.ndarray]]:
    """Every hidden scalar: (its name for each receiving agent, values (R, N) with NaN where the plan
    leaves it undefined), the x and y of the tested targets' slots (H_agents, and H_landmark or H_shelf)."""
    tg = recording_targets(rec, radius)
    n = rec.msgs.shape[2]
    others = [[j for j in range(n) if j != i] for i in range(n)]
    who = "robot" if isinstance(radius, WarehouseLayout) else "agent"
    out = []
    for name in (t for t in TESTED if t in tg):
        for s in range(tg[name].mask.shape[2]):
            for c, axis in enumerate("xy"):
                names = [f"{who} {others[i][s]} {axis} − own {axis} (H_agents)" if name == "H_agents"
                         else f"{tg[name].names[s]} {axis} ({name})" for i in range(n)]
                out.append((names, np.where(tg[name].mask[:, :, s], tg[name].values[:, :, s, c], np.nan)))
    return out


def best_hidden(h_all: list[tuple[list[str], np.ndarray]], u: np.ndarray, i: int, rows: slice) -> dict:
    """The hidden scalar most correlated with one message component u (R,) of agent i over all rows,
    and its values in `rows` rescaled to u's mean and spread (sign of r): what the figure overlays."""
    best = {"name": None, "r": float("nan"), "overlay": [None] * (rows.stop - rows.start)}
    for names, h in h_all:
        ok = np.isfinite(h[:, i])
        if ok.sum() <= 10 or np.std(h[ok, i]) == 0 or np.std(u[ok]) == 0:
            continue
        r = float(np.corrcoef(h[ok, i], u[ok])[0, 1])
        if best["name"] is None or abs(r) > abs(best["r"]):
            z = (h[rows, i] - h[ok, i].mean()) / h[ok, i].std()
            over = u[ok].mean() + np.sign(r) * u[ok].std() * z
            best = {"name": names[i], "r": r, "overlay": [float(v) if np.isfinite(v) else None for v in over]}
    return best


def episode_trace(rec: Recording, radius: View, episode: int = 0) -> dict:
    """One episode's messages and, per agent and component, the hidden scalar that best predicts it
    over the whole recording (largest |correlation|), for messages-episode.png."""
    e, t, n, m = rec.msgs.shape
    h_all = hidden_scalars(rec, radius)
    u = rec.msgs.reshape(e * t, n, m)
    rows = slice(episode * t, (episode + 1) * t)
    best = [[best_hidden(h_all, u[:, i, c], i, rows) for c in range(m)] for i in range(n)]
    return {"msgs": rec.msgs[episode].tolist(), "mean": rec.mean[episode].tolist(), "best": best,
            "paper_metric": float(rec.paper_metric[episode])}
