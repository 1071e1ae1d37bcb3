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

One option goes beyond mpe2: `observe_others=False` drops the other agents' positions and the
(always zero) communication slots from each local observation, leaving [v_i, p_i, landmarks - p_i].
The world, the rewards and the random streams are unchanged. It exists to test the paper's premise
that the central agent helps when it knows what the local agents do not: the central agent's
input (every local observation) still holds every agent's position, a local agent's no longer does.

`obs_radius=r` grades the same premise: the env still returns the full observations (they build the
central agent's state), and `envs.local_view` masks, in the local agents' copy only, every landmark
and other agent at distance >= r. The env itself only validates the value.
"""

from __future__ import annotations

import numpy as np
from hammer.envs.base import EnvSpec, EpisodeTracker, VecEnv, VecStep

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
    np.array([[0.0, 0.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]], dtype=np.float64) * SENSITIVITY
)


def spread_obs_dim(n_agents: int, observe_others: bool = True) -> int:
    """vel (2) + pos (2) + landmarks (2N) [+ other agents (2(N-1)) + communication (2(N-1))]."""
    own = 4 + 2 * n_agents
    return own + 2 * (n_agents - 1) + DIM_C * (n_agents - 1) if observe_others else own


class VecSimpleSpread(VecEnv):
    """K copies of mpe2 simple_spread_v3 (discrete actions) stepped as numpy arrays.

    Every copy always has all N agents present; episodes last exactly `max_steps` steps and end by
    truncation, after which the copy is reset from its own random stream (auto-reset).

    Internally the copy index K is the *last* axis of every array (positions are (2, N, K)), so
    each numpy operation runs one long contiguous loop over the copies instead of many loops of
    length 2; `pos`, `vel` and `landmarks` expose the state as (K, N, 2) views.
    """

    def __init__(
        self, num_envs: int, n_agents: int = 3, local_ratio: float = 0.5, max_steps: int = 25,
        observe_others: bool = True, obs_radius: float | None = None,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if n_agents < 2:
            raise ValueError(f"n_agents must be >= 2 (agents observe each other), got {n_agents}")
        if not 0.0 <= local_ratio <= 1.0:
            raise ValueError(f"local_ratio is a proportion in [0, 1], got {local_ratio}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        if not isinstance(observe_others, bool):
            raise TypeError(f"observe_others must be true or false, got {observe_others!r}")
        if obs_radius is not None:
            if isinstance(obs_radius, bool) or not isinstance(obs_radius, (int, float)) or not obs_radius >= 0:
                raise ValueError(f"obs_radius must be a distance >= 0 (or unset for the full view), got {obs_radius!r}")
            if not observe_others:
                raise ValueError("obs_radius masks the other agents' slots, which observe_others=false removes: "
                                 "set one of them, not both")
        self.num_envs = num_envs
        self.n_agents = n_agents
        self.local_ratio = float(local_ratio)
        self.max_steps = max_steps
        self.observe_others = observe_others
        # The local agents' view (envs.local_view masks it); this env still returns full observations.
        self.obs_radius = None if obs_radius is None else float(obs_radius)
        self.spec = EnvSpec(
            name="cn",
            n_agents=n_agents,
            obs_dim=spread_obs_dim(n_agents, observe_others),
            discrete=True,
            action_dim=N_ACTIONS,
            max_steps=max_steps,
            agent_ids=tuple(f"agent_{i}" for i in range(n_agents)),
            default_action=0,
        )
        k, n = num_envs, n_agents
        # World state, float64 like mpe2; write it only through set_state, because the pairwise
        # geometry below is cached from it.
        self._p = np.zeros((2, n, k))  # agent positions  [xy, agent, copy]
        self._v = np.zeros((2, n, k))  # agent velocities [xy, agent, copy]
        self._lm = np.zeros((n, 2, k))  # landmark positions [landmark, xy, copy]
        self.t = np.zeros(k, dtype=np.int64)  # world steps taken in the current episode
        # other[i] = indices j != i in increasing order (mpe2's "others" list order); stored
        # transposed so that p[:, other_t] is (2, N-1, N, K).
        self._other_t = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int64).T
        # Geometry of the current positions, shared by the reward/observation of one step and the
        # physics of the next: rel[:, m, i] = p_(m-th other of i) - p_i, dist = |rel| (N-1, N, K).
        self._rel = np.zeros((2, n - 1, n, k))
        self._dist = np.zeros((n - 1, n, k))
        self._action_force = np.ascontiguousarray(_ACTION_FORCE.T)  # (2, 5)
        self._rngs: list[np.random.Generator] | None = None
        self._tracker = EpisodeTracker(k)
        self._all_true = np.ones((k, n), dtype=bool)
        # mpe2 computes dist_min = agent1.size + agent2.size.
        self._dist_min = AGENT_SIZE + AGENT_SIZE

    @property
    def pos(self) -> np.ndarray:
        """Agent positions (K, N, 2), a read-only view."""
        return _readonly(self._p.transpose(2, 1, 0))

    @property
    def vel(self) -> np.ndarray:
        """Agent velocities (K, N, 2), a read-only view."""
        return _readonly(self._v.transpose(2, 1, 0))

    @property
    def landmarks(self) -> np.ndarray:
        """Landmark positions (K, N, 2), a read-only view."""
        return _readonly(self._lm.transpose(2, 0, 1))

    # ------------------------------------------------------------------ reset / state access
    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Seed copy k with `seed + k`, draw every copy's initial state and observe it."""
        self._rngs = [np.random.default_rng(seed + k) for k in range(self.num_envs)]
        self._tracker = EpisodeTracker(self.num_envs)
        return self._reset_copies(np.arange(self.num_envs)), self._all_true.copy()

    def _reset_copies(self, idx: np.ndarray) -> np.ndarray:
        """mpe2 Scenario.reset_world for copies idx: agents' then landmarks' positions ~ U(-1, 1)^2
        from each copy's own stream, velocities 0. Returns those copies' observations (k, N, D)."""
        assert self._rngs is not None
        n, rngs = self.n_agents, self._rngs
        # one draw per resetting copy (resets happen once per episode), then one batched write
        draws = np.stack([rngs[k].uniform(-1.0, 1.0, (2 * n, 2)) for k in idx])  # (k, 2N, 2)
        self._p[:, :, idx] = draws[:, :n].transpose(2, 1, 0)
        self._lm[:, :, idx] = draws[:, n:].transpose(1, 2, 0)
        self._v[:, :, idx] = 0.0
        self.t[idx] = 0
        return self._refresh(idx)

    def _refresh(self, idx: np.ndarray) -> np.ndarray:
        """Recompute the cached geometry of copies idx after their state changed; return obs."""
        p = self._p[:, :, idx]
        rel, dist = self._agent_geometry(p)
        self._rel[..., idx] = rel
        self._dist[..., idx] = dist
        return self._observe(self._v[:, :, idx], p, rel, self._lm[:, :, None, idx] - p[None])

    def get_state(self, k: int) -> dict[str, np.ndarray]:
        """Copies of copy k's world state: agent_pos, agent_vel, landmark_pos (N, 2) and step t."""
        return {
            "agent_pos": self._p[:, :, k].T.copy(),
            "agent_vel": self._v[:, :, k].T.copy(),
            "landmark_pos": self._lm[:, :, k].copy(),
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

        Arrays are (N, 2) as in mpe2's entity states. The step counter `t` is kept unless given,
        so the copy still truncates on schedule.
        """
        shape = (self.n_agents, 2)
        for name, value in (
            ("agent_pos", agent_pos),
            ("agent_vel", agent_vel),
            ("landmark_pos", landmark_pos),
        ):
            if np.shape(value) != shape:
                raise ValueError(f"set_state: {name} must have shape {shape}, got {np.shape(value)}")
        self._p[:, :, k] = np.asarray(agent_pos, dtype=np.float64).T
        self._v[:, :, k] = np.asarray(agent_vel, dtype=np.float64).T
        self._lm[:, :, k] = landmark_pos
        if t is not None:
            self.t[k] = t
        return self._refresh(np.array([k]))[0]

    # ------------------------------------------------------------------ physics / obs / reward
    def _agent_geometry(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rel (2, N-1, N, k): p_j - p_i for the m-th other agent j of i; dist = |rel| (N-1, N, k)."""
        rel = p[:, self._other_t] - p[:, None]
        # mpe2: np.sqrt(np.sum(np.square(d))); with 2 components that is exactly x*x + y*y.
        return rel, np.sqrt(np.square(rel[0]) + np.square(rel[1]))

    def _observe(self, v: np.ndarray, p: np.ndarray, rel: np.ndarray, lm_rel: np.ndarray) -> np.ndarray:
        """Scenario.observation of every agent of k copies, cast to float32: (k, N, D).

        Per agent i: [v_i, p_i, landmark_l - p_i for all l, p_j - p_i for j != i, comm zeros]
        (only the first three with observe_others=False). Built feature-major (D, N, k) with long
        contiguous writes, then transposed once.
        """
        n, kk = self.n_agents, p.shape[-1]
        buf = np.empty((self.spec.obs_dim, n, kk), dtype=np.float32)
        buf[0:2] = v
        buf[2:4] = p
        a = 4 + 2 * n
        buf[4:a].reshape(n, 2, n, kk)[...] = lm_rel  # lm_rel is (L, 2, N, k)
        if self.observe_others:
            b = a + 2 * (n - 1)
            buf[a:b].reshape(n - 1, 2, n, kk)[...] = rel.transpose(1, 0, 2, 3)
            buf[b:] = 0.0  # silent agents: the communication slots are always 0
        return np.ascontiguousarray(buf.transpose(2, 1, 0))

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
            raise ValueError(
                f"actions must be integers in [0, {N_ACTIONS}) (0 no-op, 1 left, 2 right, 3 down, 4 up), "
                f"got dtype {actions.dtype} with values {actions.min()}..{actions.max()}"
            )

        # --- World.apply_action_force + apply_environment_force. mpe2's contact force on i from j
        # is 100 * (p_i - p_j) / d * pen; with rel = p_j - p_i that is exactly -(100 * rel / d * pen).
        # The softplus is only evaluated where it can be non-zero: for exponents below -746,
        # exp underflows to exactly 0 and mpe2's logaddexp(0, z) is exactly 0 too.
        rel, dist = self._rel, self._dist
        z = (self._dist_min - dist) / CONTACT_MARGIN
        pen = np.zeros_like(z)
        np.logaddexp(0.0, z, out=pen, where=z > -746.0)
        pen *= CONTACT_MARGIN
        push = CONTACT_FORCE * rel / dist * pen  # (2, N-1, N, K)
        force = self._action_force[:, actions.T] - push.sum(axis=1)  # (2, N, K)
        # --- World.integrate_state (mass 1, no max speed)
        p, v = self._p, self._v
        p += v * DT
        v *= 1.0 - DAMPING
        v += (force / MASS) * DT

        # --- Scenario.reward / global_reward on the new positions, then the observation
        rel, dist = self._agent_geometry(p)
        self._rel, self._dist = rel, dist
        collisions = (dist < self._dist_min).sum(axis=0)  # (N, K): other agents in contact
        lm_rel = self._lm[:, :, None] - p[None]  # (L, 2, N, K): landmark_l - p_i
        lm_dist = np.sqrt(np.square(lm_rel[:, 0]) + np.square(lm_rel[:, 1]))  # (L, N, K)
        global_rew = -lm_dist.min(axis=1).sum(axis=0)  # (K,): -sum_l min_i |p_i - landmark_l|
        lr = self.local_ratio
        reward = np.ascontiguousarray((global_rew * (1.0 - lr) - collisions * lr).T, dtype=np.float32)
        obs = self._observe(v, p, rel, lm_rel)

        # --- time limit (SimpleEnv.step: truncate when steps >= max_cycles) and auto-reset
        self.t += 1
        done = self.t >= self.max_steps
        truncated = np.repeat(done[:, None], self.n_agents, axis=1)
        final_obs = obs.copy()
        if done.any():
            idx = np.flatnonzero(done)
            obs[idx] = self._reset_copies(idx)
        episodes = self._tracker.record(reward, self._all_true, done)
        return VecStep(
            obs=obs,
            reward=reward,
            terminated=np.zeros((self.num_envs, self.n_agents), dtype=bool),
            truncated=truncated,
            active=self._all_true.copy(),
            next_active=self._all_true.copy(),
            final_obs=final_obs,
            done=done,
            episodes=episodes,
        )


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a
