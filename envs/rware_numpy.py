"""The multi-robot warehouse on K copies at once in numpy, step for step the same as rware 2.0.0.

Why: the plain adapter (`envs.rware_vec.RwareVecEnv`) steps one rware `Warehouse` per copy through
Python objects and a networkx graph per step, a few thousand env steps per CPU-second, which caps
the warehouse study's budget. This is the same environment as that adapter (same `EnvSpec`, same
observation row, same seeds and streams), selected with env_kwargs `impl="numpy"`; the plain one
(`impl="rware"`, the default) stays the reference that `tests/test_rware_exact.py` holds it to.

What is reproduced from rware/warehouse.py (read against the installed 2.0.0):
  * Layout, highways, goals and the shelves' initial cells come from a rware `Warehouse` built once
    (one source of truth for the geometry); shelf and robot ids are rware's (row-major shelves,
    robots in spawn order).
  * Reset: copy k's `numpy.random.Generator` is gymnasium's `np_random(seed)`; the draws are
    rware's, in its order: robot cells `choice(H*W, N, replace=False)`, directions `choice(4, N)`,
    requests `choice(S, Q, replace=False)`. Later resets continue the copy's stream.
  * Moves: targets clipped to the grid; a loaded robot heading into a cell with a shelf is cancelled
    unless a loaded robot stands there. rware then builds a graph with one edge start -> target per
    robot (a self-loop for robots that stay) and, per weakly connected component: a cycle of 3+
    moves, a swap (2-cycle) or a component ending in a robot that stays moves nobody, and a
    component ending in a free cell moves the robots on networkx's `dag_longest_path`. Each cell
    has at most one robot, so every component has at most one cycle; here that is pointer chasing
    over the robots (K x N arrays, N rounds): cycle lengths, each robot's height (the longest chain
    behind it), and the chain from the free cell that always takes the unique highest robot.
    Where two robots tie for highest at a cell on that chain, networkx's choice depends on the
    iteration order of its subgraph copies (for small components, a Python set's), so those copies
    alone (`_networkx_commit`) run rware's own graph code on their robots; everything else is
    arrays.
  * Turns, then load toggles against the shelf grid as it was before the move (a toggling robot
    stands still, so that is its cell), dropping only off highways (two_stage: +0.5 after a
    delivery).
  * Deliveries: for each goal in rware's order, a requested shelf there is replaced in its queue
    slot by `choice` over the unrequested shelves (shelf-id order) from the copy's generator, and
    rewarded (individual: the robot at the goal, global: every robot, two_stage: +0.5). Copies with
    a requested shelf on a goal are handled one by one in Python (a few per episode), in rware's
    order, since a new request can make the other goal's shelf a delivery in the same step.
  * Observation: rware's flattened view (x, y, loaded, direction one-hot, on-highway, then per cell
    of the (2r+1)^2 window, row-major: robot there, its direction one-hot ([1,0,0,0] for none),
    shelf there, requested; outside the map reads as empty), then `envs.rware_vec`'s central
    columns (each shelf's x, y, requested; the goals' x, y).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from hammer.envs.base import EnvSpec, EpisodeTracker, VecEnv, VecStep
from hammer.envs.rware_vec import RwareSettings, warehouse_step

# rware's Direction order: UP, DOWN, LEFT, RIGHT
DX = np.array([0, 0, -1, 1], dtype=np.int64)
DY = np.array([-1, 1, 0, 0], dtype=np.int64)
LEFT_OF = np.array([2, 3, 1, 0], dtype=np.int64)  # wraplist UP, RIGHT, DOWN, LEFT, one step back
RIGHT_OF = np.array([3, 2, 0, 1], dtype=np.int64)
EYE4 = np.eye(4, dtype=np.float32)


def _cell_table() -> np.ndarray:
    """The 7 observation values of a window cell from code = robot * 3 + shelf, where robot is 0 (none)
    or 1 + its direction and shelf is 0 (none), 1 (not requested) or 2 (requested)."""
    table = np.zeros((15, 7), dtype=np.float32)
    for robot in range(5):
        for shelf in range(3):
            row = table[robot * 3 + shelf]
            row[0] = robot > 0
            row[1 + (robot - 1 if robot else 0)] = 1.0  # rware writes UP for an empty cell
            row[5], row[6] = shelf > 0, shelf == 2
    return table


CELL_TABLE = _cell_table()


def _np_random(seed: int) -> np.random.Generator:
    """gymnasium.utils.seeding.np_random(seed)'s generator (what `Warehouse.reset(seed=...)` installs)."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed)))


class NumpyRwareVecEnv(VecEnv):
    """K warehouses as arrays (copy index first). Same contract and results as `RwareVecEnv`."""

    def __init__(self, settings: RwareSettings, num_envs: int, *, name: str = "rware", index_offset: int = 0) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.settings, self.num_envs, self.index_offset = settings, num_envs, index_offset
        probe = settings.warehouse()
        probe.reset(seed=0)  # the layout (shelves, goals, highways) is rware's own
        self.h, self.w = (int(v) for v in probe.grid_size)
        self.r = r = settings.sensor_range
        self.wp = self.w + 2 * r  # grids are kept padded by r so every window is a plain gather
        self.highway = np.asarray(probe.highways, dtype=bool)
        self.goals = np.asarray(probe.goals, dtype=np.int64).reshape(-1, 2)  # (G, 2) x, y, rware's order
        self.goal_cells = (self.goals[:, 1] + r) * self.wp + self.goals[:, 0] + r
        self.shelf_home = np.array([(s.x, s.y) for s in probe.shelfs], dtype=np.int64)  # (S, 2)
        self.n_shelves, self.n_goals = len(self.shelf_home), len(self.goals)
        self.local_dim = int(probe.observation_space[0].shape[0])
        n, k = settings.n_agents, num_envs
        self.n, self.q = n, settings.request_queue_size
        self.cells = (2 * r + 1) ** 2
        if self.local_dim != 8 + 7 * self.cells:
            raise RuntimeError(f"rware's flattened observation has {self.local_dim} values, expected "
                               f"{8 + 7 * self.cells}; this numpy warehouse follows rware 2.0.0")
        d = self.local_dim + 3 * self.n_shelves + 2 * self.n_goals
        self.spec = EnvSpec(name=name, n_agents=n, obs_dim=d, discrete=True, action_dim=5,
                            max_steps=settings.max_steps, agent_ids=tuple(f"robot_{i}" for i in range(n)),
                            local_obs_dim=self.local_dim)
        off = np.arange(-r, r + 1)
        self.window = (off[:, None] * self.wp + off[None, :]).reshape(-1)  # row-major (y, then x)
        self.kk = np.arange(k)[:, None]
        self.idx = np.arange(n)
        self.x = np.zeros((k, n), dtype=np.int64)
        self.y = np.zeros((k, n), dtype=np.int64)
        self.dir = np.zeros((k, n), dtype=np.int64)
        self.carry = np.full((k, n), -1, dtype=np.int64)  # shelf index carried, or -1
        self.delivered = np.zeros((k, n), dtype=bool)  # rware's has_delivered (two_stage rewards)
        self.sx = np.zeros((k, self.n_shelves), dtype=np.int64)
        self.sy = np.zeros((k, self.n_shelves), dtype=np.int64)
        self.req = np.zeros((k, self.q), dtype=np.int64)  # the request queue, shelf indices in slot order
        self.t = np.zeros(k, dtype=np.int64)
        cells = (self.h + 2 * r) * self.wp
        self.ag = np.zeros((k, cells), dtype=np.int64)  # robot index + 1 per padded cell, 0 empty
        self.sg = np.zeros((k, cells), dtype=np.int64)  # shelf index + 1 per padded cell, 0 empty
        self.rngs: list[np.random.Generator] = [_np_random(0) for _ in range(k)]
        self._obs = np.zeros((k, n, d), dtype=np.float32)
        self._obs[:, :, d - 2 * self.n_goals:] = self.goals.reshape(-1)
        self.tracker = EpisodeTracker(k)
        self._seeded = False
        self.fallback_copies = 0  # copy-steps resolved by rware's graph code (ties), for the bench

    # ---- state --------------------------------------------------------------------------------
    def _pcell(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return (y + self.r) * self.wp + x + self.r

    def _grids(self) -> None:
        """rware's _recalc_grid for every copy: shelves in id order, then robots."""
        self.sg.fill(0)
        self.sg[self.kk, self._pcell(self.sx, self.sy)] = np.arange(1, self.n_shelves + 1)
        self.ag.fill(0)
        self.ag[self.kk, self._pcell(self.x, self.y)] = self.idx + 1

    def _reset_copy(self, k: int, seed: int | None) -> None:
        if seed is not None:
            self.rngs[k] = _np_random(seed)
        rng = self.rngs[k]
        locs = rng.choice(self.h * self.w, size=self.n, replace=False)
        self.y[k], self.x[k] = np.divmod(locs, self.w)
        self.dir[k] = rng.choice(4, size=self.n)
        self.req[k] = rng.choice(self.n_shelves, size=self.q, replace=False)
        self.carry[k], self.delivered[k], self.t[k] = -1, False, 0
        self.sx[k], self.sy[k] = self.shelf_home[:, 0], self.shelf_home[:, 1]

    def get_state(self, k: int) -> dict[str, Any]:
        """Copy k's state in rware's terms (robots and shelves in id order, 0-based ids)."""
        return {"x": self.x[k].copy(), "y": self.y[k].copy(), "dir": self.dir[k].copy(),
                "carry": self.carry[k].copy(), "delivered": self.delivered[k].copy(),
                "shelf_x": self.sx[k].copy(), "shelf_y": self.sy[k].copy(), "requests": self.req[k].copy(),
                "t": int(self.t[k])}

    def set_state(self, k: int, **state: Any) -> np.ndarray:
        """Overwrite parts of copy k's state (keys of `get_state`) and return its new observation rows.
        For tests: staged crowds, swaps and rotations. The caller keeps it a legal warehouse (one
        robot per cell, carried shelves under their robots)."""
        fields = {"x": self.x, "y": self.y, "dir": self.dir, "carry": self.carry, "delivered": self.delivered,
                  "shelf_x": self.sx, "shelf_y": self.sy, "requests": self.req}
        for key, value in state.items():
            if key == "t":
                self.t[k] = int(value)
            elif key in fields:
                fields[key][k] = np.asarray(value)
            else:
                raise ValueError(f"set_state: unknown field {key!r}; valid: {', '.join([*fields, 't'])}")
        self._grids()
        self._observe(self._obs)
        return self._obs[k].copy()

    # ---- VecEnv -------------------------------------------------------------------------------
    def reset(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        base = int(seed) + self.index_offset
        for k in range(self.num_envs):
            self._reset_copy(k, base + k)
        self._grids()
        self._observe(self._obs)
        self.tracker = EpisodeTracker(self.num_envs)
        self._seeded = True
        return self._obs.copy(), np.ones((self.num_envs, self.n), dtype=bool)

    def step(self, actions: np.ndarray) -> VecStep:
        if not self._seeded:
            raise RuntimeError("call reset(seed) before step(): the copies have not been seeded yet")
        k_, n = self.num_envs, self.n
        acts = np.asarray(actions)
        if acts.shape != (k_, n):
            raise ValueError(f"actions must have shape (K, N) = {(k_, n)} for rware, got {acts.shape}")
        if acts.size and (acts.min() < 0 or acts.max() >= 5):
            raise ValueError(f"rware actions must lie in [0, 5), got {acts.min()}..{acts.max()}")
        acts = acts.astype(np.int64, copy=False)
        reward = self._advance(acts)
        done = self.t >= self.settings.max_steps
        self._observe(self._obs)
        final_obs = self._obs.copy()
        if done.any():  # only ever at max_steps: a time limit for every robot
            for k in np.flatnonzero(done):
                self._reset_copy(int(k), None)  # unseeded: this copy's own stream goes on
            self._grids()
            self._observe(self._obs)
        return warehouse_step(self.tracker, self.index_offset, self._obs, reward, done, final_obs)

    # ---- one step of rware on every copy ------------------------------------------------------
    def _advance(self, acts: np.ndarray) -> np.ndarray:
        x, y, d = self.x, self.y, self.dir
        fwd = acts == 1
        tx = np.where(fwd, np.clip(x + DX[d], 0, self.w - 1), x)
        ty = np.where(fwd, np.clip(y + DY[d], 0, self.h - 1), y)
        sc, tc = self._pcell(x, y), self._pcell(tx, ty)
        carrying = self.carry >= 0
        moving = tc != sc
        occ = np.take_along_axis(self.ag, tc, 1) - 1  # robot standing on my target, or -1
        occ_loaded = (occ >= 0) & np.take_along_axis(carrying, np.maximum(occ, 0), 1)
        cancel = carrying & moving & (np.take_along_axis(self.sg, tc, 1) > 0) & ~occ_loaded
        moving &= ~cancel
        move = self._resolve(moving, occ, tc, cancel, tx, ty) if moving.any() else moving
        reward = np.zeros((self.num_envs, self.n), dtype=np.float32)
        under = np.take_along_axis(self.sg, sc, 1) - 1  # shelf grid before the move (togglers stand still)
        on_highway = self.highway[y, x]
        self.x = np.where(move, tx, x)
        self.y = np.where(move, ty, y)
        self.dir = np.where(acts == 2, LEFT_OF[d], np.where(acts == 3, RIGHT_OF[d], d))
        kc, ic = np.nonzero(carrying)
        if kc.size:  # carried shelves go with their robots
            held = self.carry[kc, ic]
            self.sx[kc, held], self.sy[kc, held] = self.x[kc, ic], self.y[kc, ic]
        toggle = acts == 4
        pick = toggle & ~carrying & (under >= 0)
        drop = toggle & carrying & ~on_highway
        if self.settings.reward_type == "two_stage":
            reward += np.where(drop & self.delivered, np.float32(0.5), np.float32(0.0))
        self.delivered &= ~drop
        self.carry = np.where(pick, under, np.where(drop, -1, self.carry))
        self._grids()
        at_goal = self.sg[:, self.goal_cells] - 1  # (K, G)
        hit = (at_goal[:, :, None] == self.req[:, None, :]).any(axis=(1, 2))
        for k in np.flatnonzero(hit):
            self._deliver(int(k), reward)
        self.t += 1
        return reward

    def _resolve(self, moving: np.ndarray, occ: np.ndarray, tc: np.ndarray, cancel: np.ndarray,
                 tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
        """Which robots move (see the module docstring); `moving` = wants a different cell."""
        k_, n = moving.shape
        idx = self.idx
        free = n  # index of "a free cell" in the pointer arrays
        nxt = np.where(moving, np.where(occ >= 0, occ, free), idx)  # the robot at my target (me if I stay)
        nxt_ext = np.concatenate([nxt, np.full((k_, 1), free)], axis=1)
        p, cycle_len = nxt, np.zeros((k_, n), dtype=np.int64)
        for step in range(1, n + 1):  # p = nxt applied `step` times
            cycle_len = np.where((p == idx) & (cycle_len == 0), step, cycle_len)
            p = np.take_along_axis(nxt_ext, p, 1)
        tree = p == free  # my chain ends in a free cell
        move = cycle_len >= 3
        if tree.any():
            behind = (nxt[:, :, None] == idx) & tree[:, :, None]  # [k, j, i]: robot j targets robot i's cell
            h = np.zeros((k_, n), dtype=np.int64)  # the longest chain of robots behind me
            if behind.any():
                for _ in range(n - 1):
                    h = np.where(behind, h[:, :, None] + 1, 0).max(axis=1)
            hm = np.where(tree, h, -1)
            same = (tc[:, :, None] == tc[:, None, :]) & tree[:, :, None] & tree[:, None, :]
            best = np.where(same, hm[:, None, :], -1).max(axis=2)
            top = tree & (h == best)
            n_top = (same & (hm[:, None, :] == best[:, :, None])).sum(axis=2)
            win = top & (n_top == 1)
            root = nxt == free
            chain = win & root
            c_ext = np.zeros((k_, n + 1), dtype=bool)
            for _ in range(n - 1):
                c_ext[:, :n] = chain
                chain = win & (root | np.take_along_axis(c_ext, nxt, 1))
            c_ext[:, :n] = chain
            tied = top & (n_top >= 2) & (root | np.take_along_axis(c_ext, nxt, 1))
            move = move | chain
            for k in np.flatnonzero(tied.any(axis=1)):
                move[k] = self._networkx_commit(int(k), cancel[k], tx[k], ty[k]) & moving[k]
                self.fallback_copies += 1
        return move & moving

    def _networkx_commit(self, k: int, cancel: np.ndarray, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
        """rware's own conflict code (Warehouse.step) on copy k: which robots it commits."""
        import networkx as nx

        xs, ys = self.x[k].tolist(), self.y[k].tolist()
        at = {(xs[i], ys[i]): i + 1 for i in range(self.n)}  # the agent grid: cell -> robot id
        g = nx.DiGraph()
        for i in range(self.n):
            start = xs[i], ys[i]
            g.add_edge(start, start if cancel[i] else (int(tx[i]), int(ty[i])))
        committed: set[int] = set()
        for comp in [g.subgraph(c).copy() for c in nx.weakly_connected_components(g)]:
            try:
                cycle = nx.algorithms.find_cycle(comp)
                if len(cycle) == 2:
                    continue
                committed.update(at[e[0]] for e in cycle if e[0] in at)
            except nx.NetworkXNoCycle:
                committed.update(at[v] for v in nx.algorithms.dag_longest_path(comp) if v in at)
        out = np.zeros(self.n, dtype=bool)
        out[[i - 1 for i in committed]] = True
        return out

    def _deliver(self, k: int, reward: np.ndarray) -> None:
        """rware's delivery loop on copy k (goals in order; a refill can make the next goal's shelf due)."""
        queue = self.req[k].tolist()
        for cell in self.goal_cells:
            shelf = int(self.sg[k, cell]) - 1
            if shelf < 0 or shelf not in queue:
                continue
            candidates = [s for s in range(self.n_shelves) if s not in queue]
            queue[queue.index(shelf)] = candidates[int(self.rngs[k].choice(len(candidates)))]
            robot = int(self.ag[k, cell]) - 1  # -1 would be rware's rewards[-1] too
            kind = self.settings.reward_type
            if kind == "global":
                reward[k] += 1.0
            elif kind == "individual":
                reward[k, robot] += 1.0
            else:
                self.delivered[k, robot] = True
                reward[k, robot] += 0.5
        self.req[k] = queue

    def _observe(self, out: np.ndarray) -> None:
        k_, n = self.num_envs, self.n
        out[..., 0], out[..., 1] = self.x, self.y
        out[..., 2] = self.carry >= 0
        out[..., 3:7] = EYE4[self.dir]
        out[..., 7] = self.highway[self.y, self.x]
        requested = np.zeros((k_, self.n_shelves + 1), dtype=bool)
        requested[self.kk, self.req + 1] = True
        shelf_code = np.ones((k_, self.n_shelves + 1), dtype=np.int64) + requested
        shelf_code[:, 0] = 0
        robot_code = np.concatenate([np.zeros((k_, 1), dtype=np.int64), 1 + self.dir], axis=1)
        win = (self._pcell(self.x, self.y)[..., None] + self.window).reshape(k_, -1)
        code = (np.take_along_axis(robot_code, np.take_along_axis(self.ag, win, 1), 1) * 3
                + np.take_along_axis(shelf_code, np.take_along_axis(self.sg, win, 1), 1))
        out[..., 8:self.local_dim] = CELL_TABLE[code].reshape(k_, n, -1)
        s = self.n_shelves
        central = out[..., self.local_dim:self.local_dim + 3 * s].reshape(k_, n, s, 3)
        central[..., 0] = self.sx[:, None, :]
        central[..., 1] = self.sy[:, None, :]
        central[..., 2] = requested[:, None, 1:]
