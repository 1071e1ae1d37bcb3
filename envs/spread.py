"""Cooperative navigation (MPE simple_spread) for K copies at once, numerically equal to mpe2.

`mpe2.simple_spread_v3` steps one copy through Python objects, per-agent loops and a PettingZoo
AEC -> parallel wrapper; that costs about a millisecond per copy step, far too slow for the
in-process trainer (750k env steps in ~2 minutes). This module re-implements the same environment
with every copy as a row of numpy arrays, so one `step` costs a handful of array operations
regardless of K.

What is reproduced from mpe2 (mpe2/simple_spread/simple_spread.py, _mpe_utils/core.py,
_mpe_utils/simple_env.py), with discrete actions and the defaults `N`, `local_ratio=0.5`,
`max_cycles=25`:

* world: N agents (size 0.15, mass 1, movable, colliding, silent) and N landmarks (not movable,
  not colliding); dt 0.1, damping 0.25, contact force 100, contact margin 1e-3, no max speed,
  no action noise.
* reset: each agent's position, then each landmark's, drawn uniform(-1, 1) in that order from the
  copy's own Generator; velocities and communication zero. Copy k is seeded with `seed + k`
  through the same `np.random.default_rng` construction gymnasium's `seeding.np_random` uses, so
  copy k draws exactly the states `mpe2 ... .reset(seed=seed + k)` draws, and later resets
  continue the stream exactly like mpe2's unseeded `reset()`.
* action a in {0: no-op, 1: left, 2: right, 3: down, 4: up} -> force 5 * unit vector.
* collisions: every agent pair gets force 100 * (p_i - p_j) / |p_i - p_j| * softplus-penetration
  with penetration = 1e-3 * logaddexp(0, -(|p_i - p_j| - 0.3) / 1e-3) (always applied, smooth).
* integration (semi-implicit as mpe2): p += v * dt; v *= 0.75; v += F * dt.
* reward, after the physics step: global = -sum over landmarks of the min agent distance;
  local_i = -(number of other agents within distance 0.3); r_i = global * (1 - lr) + local_i * lr.
* observation (float32 cast of float64): [v_i, p_i, landmark_l - p_i for all l,
  p_j - p_i for j != i in index order, 2 * (N - 1) zeros of communication].
* time: the t-th world step (t = 1..max_steps) truncates every agent when t >= max_steps;
  nothing ever terminates (terminate_on_success is off in the paper's setting).

The floating-point operations are the same as mpe2's except the order in which an agent's
contact forces are summed, so trajectories agree to ~1e-15 (see tests/test_spread_exact.py).
"""

from __future__ import annotations

import numpy as np

from envs.base import EnvSpec, EpisodeTracker, VecEnv, VecStep

# Physical constants of mpe2's World / simple_spread Scenario.
DT = 0.1
DAMPING = 0.25
CONTACT_FORCE = 1e2
CONTACT_MARGIN = 1e-3
AGENT_SIZE = 0.15
MASS = 1.0
SENSITIVITY = 5.0  # simple_env._set_action: agent.accel is None -> 5.0
N_ACTIONS = 5
DIM_C = 2  # communication channel width; agents are silent so these observation slots are 0

# Discrete action -> applied force (mpe2 sets u[axis] = +-1.0, then multiplies by sensitivity).
_ACTION_FORCE = (
    np.array([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]], dtype=np.float64)
    * SENSITIVITY
)


def spread_obs_dim(n_agents: int) -> int:
    """vel (2) + pos (2) + landmarks (2N) + other agents (2(N-1)) + communication (2(N-1))."""
    return 4 + 2 * n_agents + 2 * (n_agents - 1) + DIM_C * (n_agents - 1)


class VecSimpleSpread(VecEnv):
    """K copies of mpe2 simple_spread_v3 (discrete actions) stepped as numpy arrays.

    State arrays (float64, like mpe2): `pos`, `vel` (K, N, 2) for agents and `landmarks` (K, N, 2).
    Every copy always has all N agents present; episodes last exactly `max_steps` steps and end by
    truncation, after which the copy is reset from its own random stream (auto-reset).
    """

    def __init__(
        self, num_envs: int, n_agents: int = 3, local_ratio: float = 0.5, max_steps: int = 25
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if n_agents < 2:
            raise ValueError(f"n_agents must be >= 2 (agents observe each other), got {n_agents}")
        if not 0.0 <= local_ratio <= 1.0:
            raise ValueError(f"local_ratio is a proportion in [0, 1], got {local_ratio}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.num_envs = num_envs
        self.n_agents = n_agents
        self.local_ratio = float(local_ratio)
        self.max_steps = max_steps
        self.spec = EnvSpec(
            name="cn",
            n_agents=n_agents,
            obs_dim=spread_obs_dim(n_agents),
            discrete=True,
            action_dim=N_ACTIONS,
            max_steps=max_steps,
            agent_ids=tuple(f"agent_{i}" for i in range(n_agents)),
            default_action=0,
        )
        k, n = num_envs, n_agents
        self.pos = np.zeros((k, n, 2))
        self.vel = np.zeros((k, n, 2))
        self.landmarks = np.zeros((k, n, 2))
        self.t = np.zeros(k, dtype=np.int64)  # world steps taken in the current episode
        self._rngs: list[np.random.Generator] | None = None
        self._tracker = EpisodeTracker(k)
        # other[i] = indices j != i in increasing order (mpe2's "others" list order).
        self._other = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int64)
        self._rows = np.arange(n)[:, None]
        self._eye = np.eye(n, dtype=bool)
        self._all_true = np.ones((k, n), dtype=bool)
        self._no_term = np.zeros((k, n), dtype=bool)
        # mpe2 computes dist_min = agent1.size + agent2.size.
        self._dist_min = AGENT_SIZE + AGENT_SIZE

    # ------------------------------------------------------------------ reset / state access
    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Seed copy k with `seed + k`, draw every copy's initial state and observe it."""
        self._rngs = [np.random.default_rng(seed + k) for k in range(self.num_envs)]
        self._reset_copies(np.arange(self.num_envs))
        self._tracker = EpisodeTracker(self.num_envs)
        return self._observe_all(), self._all_true.copy()

    def _reset_copies(self, idx: np.ndarray) -> None:
        """mpe2 Scenario.reset_world: agents' then landmarks' positions ~ U(-1, 1)^2, all else 0."""
        assert self._rngs is not None
        n = self.n_agents
        for k in idx:
            draw = self._rngs[k].uniform(-1.0, 1.0, (2 * n, 2))
            self.pos[k] = draw[:n]
            self.landmarks[k] = draw[n:]
        self.vel[idx] = 0.0
        self.t[idx] = 0

    def get_state(self, k: int) -> dict[str, np.ndarray]:
        """Copies of copy k's world state: agent_pos, agent_vel, landmark_pos (N, 2) and step t."""
        return {
            "agent_pos": self.pos[k].copy(),
            "agent_vel": self.vel[k].copy(),
            "landmark_pos": self.landmarks[k].copy(),
            "t": np.int64(self.t[k]),
        }

    def set_state(
        self,
        k: int,
        agent_pos: np.ndarray,
        agent_vel: np.ndarray,
        landmark_pos: np.ndarray,
        t: int | None = None,
    ) -> np.ndarray:
        """Overwrite copy k's world state (e.g. from an mpe2 world) and return its obs (N, D).

        The step counter `t` is kept unless given, so the copy still truncates on schedule.
        """
        shape = (self.n_agents, 2)
        for name, value in (("agent_pos", agent_pos), ("agent_vel", agent_vel), ("landmark_pos", landmark_pos)):
            if np.shape(value) != shape:
                raise ValueError(f"set_state: {name} must have shape {shape}, got {np.shape(value)}")
        self.pos[k] = agent_pos
        self.vel[k] = agent_vel
        self.landmarks[k] = landmark_pos
        if t is not None:
            self.t[k] = t
        return self._observe(self.pos[k : k + 1], self.vel[k : k + 1], self.landmarks[k : k + 1])[0]

    # ------------------------------------------------------------------ physics / obs / reward
    def _observe(self, pos: np.ndarray, vel: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
        """Scenario.observation for every agent of the given copies: (k, N, D) float32."""
        kk, n = pos.shape[0], self.n_agents
        obs = np.zeros((kk, n, self.spec.obs_dim), dtype=np.float32)
        obs[:, :, 0:2] = vel
        obs[:, :, 2:4] = pos
        end = 4 + 2 * n
        obs[:, :, 4:end] = (landmarks[:, None, :, :] - pos[:, :, None, :]).reshape(kk, n, 2 * n)
        other = pos[:, self._other, :] - pos[:, :, None, :]  # (k, N, N-1, 2): p_j - p_i
        obs[:, :, end : end + 2 * (n - 1)] = other.reshape(kk, n, 2 * (n - 1))
        # the remaining DIM_C * (N - 1) communication slots stay 0 (agents are silent)
        return obs

    def _observe_all(self) -> np.ndarray:
        return self._observe(self.pos, self.vel, self.landmarks)

    def _pairwise(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """delta[k, i, j] = p_i - p_j and its length, with self-distances set to +inf."""
        delta = pos[:, :, None, :] - pos[:, None, :, :]
        # np.sqrt(np.sum(np.square(d))) in mpe2; for 2 components that is x*x + y*y exactly.
        dist = np.sqrt(np.square(delta[..., 0]) + np.square(delta[..., 1]))
        dist[:, self._eye] = np.inf  # no self-collision: force and penetration become exactly 0
        return delta, dist

    def step(self, actions: np.ndarray) -> VecStep:
        """One world step of every copy (mpe2 SimpleEnv._execute_world_step), then auto-reset."""
        if self._rngs is None:
            raise RuntimeError("VecSimpleSpread.step called before reset(seed); call reset first")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs, self.n_agents):
            raise ValueError(
                f"actions must have shape (num_envs, n_agents) = {(self.num_envs, self.n_agents)}, "
                f"got {actions.shape}"
            )
        if actions.dtype.kind not in "iu" or actions.min() < 0 or actions.max() >= N_ACTIONS:
            raise ValueError(f"actions must be integers in [0, {N_ACTIONS}), got {actions.dtype} {actions.min()}..{actions.max()}")

        # --- forces: action force + pairwise soft contact forces (World.apply_*_force)
        force = _ACTION_FORCE[actions]  # fresh (K, N, 2) array
        delta, dist = self._pairwise(self.pos)
        pen = np.logaddexp(0.0, -(dist - self._dist_min) / CONTACT_MARGIN) * CONTACT_MARGIN
        contact = CONTACT_FORCE * delta / dist[..., None] * pen[..., None]
        force += contact.sum(axis=2)
        # --- World.integrate_state
        self.pos += self.vel * DT
        self.vel *= 1.0 - DAMPING
        self.vel += (force / MASS) * DT

        # --- rewards on the new positions (Scenario.reward / global_reward)
        _, dist = self._pairwise(self.pos)
        collisions = (dist < self._dist_min).sum(axis=2)  # self-distance is inf: never counted
        lm_delta = self.landmarks[:, :, None, :] - self.pos[:, None, :, :]  # (K, L, N, 2)
        lm_dist = np.sqrt(np.square(lm_delta[..., 0]) + np.square(lm_delta[..., 1]))
        global_rew = -lm_dist.min(axis=2).sum(axis=1)  # (K,)
        reward = (
            global_rew[:, None] * (1.0 - self.local_ratio) - collisions * self.local_ratio
        ).astype(np.float32)

        obs = self._observe_all()
        self.t += 1
        done = self.t >= self.max_steps
        truncated = np.repeat(done[:, None], self.n_agents, axis=1)
        final_obs = obs.copy()
        if done.any():
            idx = np.flatnonzero(done)
            self._reset_copies(idx)
            obs[idx] = self._observe(self.pos[idx], self.vel[idx], self.landmarks[idx])
        episodes = self._tracker.record(reward, self._all_true, done)
        return VecStep(
            obs=obs,
            reward=reward,
            terminated=self._no_term.copy(),
            truncated=truncated,
            active=self._all_true.copy(),
            next_active=self._all_true.copy(),
            final_obs=final_obs,
            done=done,
            episodes=episodes,
        )
