"""The batched multi-agent environment contract.

Every environment hammer trains on (the vectorised cooperative navigation, PettingZoo parallel envs
in-process or in subprocess workers) is driven through `VecEnv`: K copies of an N-agent env stepped
as one batch with auto-reset. The in-process trainer and the distributed env host both use it, so
termination/truncation semantics, agent masks and the paper's episode metric are defined once, here.

Array conventions (K = num_envs copies, N = n_agents, D = obs_dim, A = action dim):
  obs          float32 (K, N, D)   zeros for agents not present
  discrete     actions int64   (K, N)     in [0, n_actions)
  continuous   actions float32 (K, N, A)  clipped by the env to [action_low, action_high]
Actions of absent agents are ignored.

Central state hook: an env may append central-only columns to every observation row and declare
where they start (`EnvSpec.local_obs_dim`). The central agent's global state concatenates the full
rows; every local-policy input has those columns zeroed (`envs.local_view`). See
docs/architecture.md, "Central state".
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Self

import numpy as np


@dataclass(frozen=True)
class EnvSpec:
    """Static description of one copy of a multi-agent environment."""

    name: str
    n_agents: int
    obs_dim: int
    discrete: bool
    # Discrete: number of actions. Continuous: length of the action vector.
    action_dim: int
    max_steps: int
    agent_ids: tuple[str, ...]
    action_low: float | None = None
    action_high: float | None = None
    # The action an absent/late agent is given (no-op for discrete, zero torque for continuous).
    default_action: int = 0
    # Central state hook: columns [local_obs_dim, obs_dim) of every observation row are for the central
    # agent only (what the env knows beyond the agents' own views, e.g. the whole warehouse); every
    # local-policy input has them zeroed (`envs.local_view`). None: the whole row is the agent's own.
    local_obs_dim: int | None = None

    @property
    def action_shape(self) -> tuple[int, ...]:
        return () if self.discrete else (self.action_dim,)

    def default_actions(self, num_envs: int) -> np.ndarray:
        """The declared default action for every agent of every copy."""
        if self.discrete:
            return np.full((num_envs, self.n_agents), self.default_action, dtype=np.int64)
        return np.zeros((num_envs, self.n_agents, self.action_dim), dtype=np.float32)

    def env_action(self, action: np.ndarray) -> np.ndarray:
        """What the env is given for a sampled action: discrete as is, continuous clipped to the
        action box (PPO trains the unclipped Gaussian sample; the env only accepts the box)."""
        if self.discrete:
            return action
        return np.clip(action, self.action_low, self.action_high).astype(np.float32)


@dataclass(frozen=True)
class EpisodeStats:
    """One finished episode of one env copy.

    paper_metric is the HAMMER paper's "average reward per local agent": the sum over the episode's
    steps of the mean over the agents present at that step of that step's rewards.
    team_return is the sum over steps and agents.
    """

    env_index: int
    paper_metric: float
    team_return: float
    length: int


@dataclass
class VecStep:
    """What one `VecEnv.step` returns.

    For a copy whose episode ended at this step (done[k]), `obs[k]` and `next_active[k]` already
    belong to the first step of the next episode (auto-reset) while `final_obs[k]` holds the last
    observation of the finished episode, so a learner can bootstrap truncated agents from it.
    """

    obs: np.ndarray  # (K, N, D) float32, observation for the next action
    reward: np.ndarray  # (K, N) float32, 0 for agents that were absent
    terminated: np.ndarray  # (K, N) bool: the task ended this agent's episode (no bootstrap)
    truncated: np.ndarray  # (K, N) bool: the time limit ended it (bootstrap from final_obs)
    active: np.ndarray  # (K, N) bool: the agent was present and acted at this step
    next_active: np.ndarray  # (K, N) bool: the agent is present in `obs`
    final_obs: np.ndarray  # (K, N, D) float32, equal to obs where no reset happened
    done: np.ndarray  # (K,) bool: the copy's episode ended at this step and was reset
    episodes: list[EpisodeStats] = field(default_factory=list)


class VecEnv(abc.ABC):
    """K copies of an N-agent environment with auto-reset.

    Seeding: `reset(seed)` seeds copy k with `seed + k`; each copy's later resets continue that
    copy's own random stream, so a run is reproducible from one seed.
    """

    spec: EnvSpec
    num_envs: int

    @abc.abstractmethod
    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Reset every copy; returns (obs (K,N,D) float32, active (K,N) bool)."""

    @abc.abstractmethod
    def step(self, actions: np.ndarray) -> VecStep:
        """Step every copy with one action per agent; copies whose episode ends are reset."""

    def close(self) -> None:
        """Release workers or simulator resources."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EpisodeTracker:
    """Accumulates per-copy rewards and emits `EpisodeStats` when copies finish.

    Shared by every VecEnv implementation so the paper metric is computed one way only.
    """

    def __init__(self, num_envs: int) -> None:
        self.paper = np.zeros(num_envs, dtype=np.float64)
        self.team_return = np.zeros(num_envs, dtype=np.float64)
        self.length = np.zeros(num_envs, dtype=np.int64)

    def record(self, reward: np.ndarray, active: np.ndarray, done: np.ndarray) -> list[EpisodeStats]:
        """Add one step's rewards (K,N) for the agents active (K,N); close copies with done (K,)."""
        n_active = active.sum(axis=1)
        step_sum = np.where(active, reward, 0.0).sum(axis=1, dtype=np.float64)
        self.paper += np.divide(step_sum, n_active, out=np.zeros_like(step_sum), where=n_active > 0)
        self.team_return += step_sum
        self.length += 1
        out: list[EpisodeStats] = []
        for k in np.flatnonzero(done):
            out.append(EpisodeStats(int(k), float(self.paper[k]), float(self.team_return[k]), int(self.length[k])))
            self.paper[k] = 0.0
            self.team_return[k] = 0.0
            self.length[k] = 0
        return out
