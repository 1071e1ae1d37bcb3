"""The multi-robot warehouse (`rware`, Papoudakis et al. 2021) behind the `VecEnv` contract.

Why this env: it is the task the HAMMER paper motivates, a central server that knows the whole
warehouse and cheap robots that see a few cells around them. rware is a Gymnasium env with tuple
spaces (one entry per robot), not PettingZoo, so it gets its own small adapter here instead of
going through `envs.pettingzoo_vec`.

What each agent's observation row holds (D = L + 3·S + 2·G):
  [0, L)   rware's own flattened partial observation of robot i (`local_obs_dim` = L): its x, y,
           load, direction (one-hot), on-highway flag, then for each cell of the
           (2·sensor_range+1)² window: agent there, its direction (one-hot), shelf there, requested.
           This is all a local agent may see.
  [L, D)   central-only columns, identical in every row: each shelf's x, y and requested flag in
           rware's shelf-id order (S shelves, a fixed number per layout), then the goal cells' x, y.
The central agent's global state concatenates the rows (as for every env), so it holds every robot's
position, direction and load plus every shelf and goal; `envs.local_view.CentralColumnsView` zeroes
[L, D) in every local-policy input (trainer and env host alike). See docs/architecture.md, "Central
state". Coordinates are rware's raw integers (its default, `normalised_coordinates=False`).

Time: rware ends every robot's episode at `max_steps`; that is a time limit, so it is reported as
`truncated` (bootstrap), never `terminated`. Actions: 5 discrete (0 no-op, 1 forward, 2 left,
3 right, 4 toggle load). Rewards: rware's individual reward (+1 to the robot that delivers a
requested shelf to a goal), so an episode's team return is its number of deliveries.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from hammer.envs.base import EnvSpec, EpisodeTracker, VecEnv, VecStep
from hammer.envs.description import EnvConfigError, EnvDescription

# (shelf_rows, shelf_columns) per size and the request-queue factor per difficulty, as rware/__init__.py
# registers its gym ids (rware-<size>-<N>ag[-easy|-hard]-v2).
SIZES: dict[str, tuple[int, int]] = {"tiny": (1, 3), "small": (2, 3), "medium": (2, 5), "large": (3, 5)}
DIFFICULTY: dict[str, float] = {"easy": 2.0, "normal": 1.0, "hard": 0.5}
REWARD_TYPES = ("individual", "global", "two_stage")
DEFAULTS: dict[str, Any] = {"size": "tiny", "difficulty": "normal", "sensor_range": 1, "max_steps": 500,
                            "column_height": 8, "reward_type": "individual", "request_queue_size": None,
                            "impl": "rware"}
# Two implementations of the same env: rware's own objects (the reference) and the numpy one on all
# copies at once (`envs.rware_numpy`, exact to it step for step, tests/test_rware_exact.py).
IMPLS = ("rware", "numpy")
PRESET_RE = re.compile(r"^rware-(tiny|small|medium|large)-(\d+)ag(?:-(easy|hard))?$")
ABOUT = ("multi-robot warehouse (rware 2.0): partial view per robot, full warehouse for the central agent; "
         "also rware-<size>-<N>ag[-easy|-hard], e.g. rware-tiny-2ag")


def is_rware(name: str) -> bool:
    """Whether `name` is this family: `rware` (layout from env_kwargs) or a preset `rware-tiny-2ag`."""
    return name == "rware" or name.startswith("rware-")


@dataclass(frozen=True)
class RwareSettings:
    """One validated warehouse configuration (what `Warehouse.__init__` is given)."""

    n_agents: int
    shelf_rows: int
    shelf_columns: int
    column_height: int
    sensor_range: int
    request_queue_size: int
    max_steps: int
    reward_type: str
    impl: str = "rware"

    def warehouse(self) -> Any:
        from rware.warehouse import RewardType, Warehouse

        return Warehouse(shelf_columns=self.shelf_columns, column_height=self.column_height,
                         shelf_rows=self.shelf_rows, n_agents=self.n_agents, msg_bits=0,
                         sensor_range=self.sensor_range, request_queue_size=self.request_queue_size,
                         max_inactivity_steps=None, max_steps=self.max_steps,
                         reward_type=RewardType[self.reward_type.upper()])


def _int_field(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise EnvConfigError(f"env 'rware': env_kwargs.{name} must be an int >= {low}, got {value!r}")
    return value


def settings_from(desc: EnvDescription) -> RwareSettings:
    """Validate a `rware`/`rware-<size>-<N>ag` name with its env_kwargs; every mistake names the field."""
    if desc.adapters:
        raise EnvConfigError(f"env_adapters: env {desc.name!r} gives flat float observations and needs none; fix: "
                             "remove env_adapters")
    kwargs = dict(desc.env_kwargs)
    unknown = sorted(set(kwargs) - set(DEFAULTS))
    if unknown:
        raise EnvConfigError(f"env {desc.name!r}: unknown env_kwargs field {unknown[0]!r}; valid fields: "
                             f"{', '.join(sorted(DEFAULTS))} (the robot count is n_agents)")
    if desc.name != "rware":
        m = PRESET_RE.match(desc.name)
        if m is None:
            raise EnvConfigError(f"env: unknown name {desc.name!r}; the warehouse is 'rware' or "
                                 "'rware-<tiny|small|medium|large>-<N>ag[-easy|-hard]', e.g. rware-tiny-2ag")
        for f in ("size", "difficulty"):
            if f in kwargs:
                raise EnvConfigError(f"env {desc.name!r}: env_kwargs.{f} is set by the name; use env 'rware' "
                                     f"with env_kwargs.{f}, or drop env_kwargs.{f}")
        if int(m.group(2)) != desc.n_agents:
            raise EnvConfigError(f"n_agents: env {desc.name!r} has {m.group(2)} robots but n_agents="
                                 f"{desc.n_agents}; set n_agents={m.group(2)}")
        kwargs.update(size=m.group(1), difficulty=m.group(3) or "normal")
    full = {**DEFAULTS, **kwargs}
    if full["size"] not in SIZES:
        raise EnvConfigError(f"env 'rware': env_kwargs.size must be one of {', '.join(SIZES)}, got {full['size']!r}")
    if full["difficulty"] not in DIFFICULTY:
        raise EnvConfigError(f"env 'rware': env_kwargs.difficulty must be one of {', '.join(DIFFICULTY)}, "
                             f"got {full['difficulty']!r}")
    if full["reward_type"] not in REWARD_TYPES:
        raise EnvConfigError(f"env 'rware': env_kwargs.reward_type must be one of {', '.join(REWARD_TYPES)}, "
                             f"got {full['reward_type']!r}")
    if full["impl"] not in IMPLS:
        raise EnvConfigError(f"env 'rware': env_kwargs.impl must be one of {', '.join(IMPLS)}, got {full['impl']!r}")
    queue = full["request_queue_size"]
    if queue is None:  # rware's own rule for its registered ids
        queue = max(1, int(desc.n_agents * DIFFICULTY[full["difficulty"]]))
    rows, cols = SIZES[full["size"]]
    return RwareSettings(n_agents=desc.n_agents, shelf_rows=rows, shelf_columns=cols,
                         column_height=_int_field("column_height", full["column_height"], 1),
                         sensor_range=_int_field("sensor_range", full["sensor_range"], 1),
                         request_queue_size=_int_field("request_queue_size", queue, 1),
                         max_steps=_int_field("max_steps", full["max_steps"], 1), reward_type=full["reward_type"],
                         impl=full["impl"])


def central_columns(wh: Any, out: np.ndarray) -> None:
    """Write the central-only part of one warehouse's state into `out` (3·S + 2·G,): every shelf's
    x, y, requested flag (shelf-id order), then the goals' x, y. Why not rware's global image: the
    shelves are few (32 in tiny) and a list keeps the vector short for an MLP."""
    s = len(wh.shelfs)
    shelves = out[:3 * s].reshape(s, 3)
    requested = {sh.id for sh in wh.request_queue}
    for j, sh in enumerate(wh.shelfs):
        shelves[j, 0], shelves[j, 1], shelves[j, 2] = sh.x, sh.y, sh.id in requested
    out[3 * s:] = np.asarray(wh.goals, dtype=np.float32).reshape(-1)


class RwareVecEnv(VecEnv):
    """K in-process warehouses (rware's `Warehouse`, built directly, not via gym.make) as one batch.

    `index_offset` shifts seeds (copy k is seeded seed + index_offset + k) and episode indices, so a
    worker of `envs.workers.SubprocVecEnv` running a slice behaves like that slice in-process.
    """

    def __init__(self, settings: RwareSettings, num_envs: int, *, name: str = "rware", index_offset: int = 0) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.settings, self.num_envs, self.index_offset = settings, num_envs, index_offset
        self.envs = [settings.warehouse() for _ in range(num_envs)]
        probe = self.envs[0]
        probe.reset(seed=0)  # the shelves exist only after a reset; their number is fixed by the layout
        self.local_dim = int(probe.observation_space[0].shape[0])
        self.n_shelves, self.n_goals = len(probe.shelfs), len(probe.goals)
        n = settings.n_agents
        d = self.local_dim + 3 * self.n_shelves + 2 * self.n_goals
        self.spec = EnvSpec(name=name, n_agents=n, obs_dim=d, discrete=True, action_dim=5,
                            max_steps=settings.max_steps, agent_ids=tuple(f"robot_{i}" for i in range(n)),
                            local_obs_dim=self.local_dim)
        self._obs = np.zeros((num_envs, n, d), dtype=np.float32)
        self._central = np.zeros(d - self.local_dim, dtype=np.float32)
        self.tracker = EpisodeTracker(num_envs)
        self._seeded = False

    def _write(self, k: int, local_obs: tuple[np.ndarray, ...]) -> None:
        row = self._obs[k]
        row[:, :self.local_dim] = np.stack(local_obs)
        central_columns(self.envs[k], self._central)
        row[:, self.local_dim:] = self._central

    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        base = int(seed) + self.index_offset
        for k, env in enumerate(self.envs):
            obs, _ = env.reset(seed=base + k)
            self._write(k, obs)
        self.tracker = EpisodeTracker(self.num_envs)
        self._seeded = True
        return self._obs.copy(), np.ones((self.num_envs, self.spec.n_agents), dtype=bool)

    def step(self, actions: np.ndarray) -> VecStep:
        if not self._seeded:
            raise RuntimeError("call reset(seed) before step(): the copies have not been seeded yet")
        k_, n = self.num_envs, self.spec.n_agents
        acts = np.asarray(actions)
        if acts.shape != (k_, n):
            raise ValueError(f"actions must have shape (K, N) = {(k_, n)} for rware, got {acts.shape}")
        if acts.size and (acts.min() < 0 or acts.max() >= 5):
            raise ValueError(f"rware actions must lie in [0, 5), got {acts.min()}..{acts.max()}")
        acts = acts.astype(np.int64, copy=False).tolist()
        reward = np.zeros((k_, n), dtype=np.float32)
        done = np.zeros(k_, dtype=bool)
        final_obs = np.empty_like(self._obs)
        for k, env in enumerate(self.envs):
            obs, rew, ended, _, _ = env.step(acts[k])
            reward[k] = rew
            self._write(k, obs)
            final_obs[k] = self._obs[k]
            if ended:  # only ever at max_steps (no inactivity limit): a time limit for every robot
                done[k] = True
                obs, _ = env.reset()  # unseeded: this copy's own stream goes on
                self._write(k, obs)
        return warehouse_step(self.tracker, self.index_offset, self._obs, reward, done, final_obs)


def installed_settings(desc: EnvDescription) -> RwareSettings:
    """`desc`'s validated settings, once rware itself is known to import (both implementations
    build rware's layout from it). `envs.catalog.build_local` then builds `RwareVecEnv` (impl
    "rware") or `envs.rware_numpy.NumpyRwareVecEnv` (impl "numpy")."""
    try:
        import rware.warehouse  # noqa: F401
    except ImportError as e:
        raise EnvConfigError(f"env {desc.name!r}: the rware package is not installed ({e}); fix: "
                             "pip install 'hammer-marl[train]' (or pip install rware==2.0.0 --no-deps networkx)") from e
    return settings_from(desc)


def warehouse_step(tracker: EpisodeTracker, index_offset: int, obs: np.ndarray, reward: np.ndarray,
                   done: np.ndarray, final_obs: np.ndarray) -> VecStep:
    """A warehouse step's result, either implementation: every robot always active, an episode's end
    only ever rware's time limit (truncated, never terminated); episode indices shifted by the offset."""
    k_, n = reward.shape
    truncated = np.repeat(done[:, None], n, axis=1)
    active = np.ones((k_, n), dtype=bool)
    episodes = tracker.record(reward, active, done)
    if index_offset:
        episodes = [type(e)(e.env_index + index_offset, e.paper_metric, e.team_return, e.length) for e in episodes]
    return VecStep(obs=obs.copy(), reward=reward, terminated=np.zeros((k_, n), dtype=bool), truncated=truncated,
                   active=active, next_active=active.copy(), final_obs=final_obs, done=done, episodes=episodes)
