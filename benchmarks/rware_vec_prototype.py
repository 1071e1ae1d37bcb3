"""What a vectorised warehouse would cost per step: a numpy prototype of rware's step on K copies.

Not an env and not used by training: a speed figure for docs/results/warehouse.md, measured before
deciding to build a vectorised rware (as `docs/fast-envs.md` did for cn). It does the work of
rware's step for all K copies at once with arrays (copy index first): forward targets clipped to
the grid, the loaded-robot-into-shelf cancel, conflict resolution, moves, turns, load toggles, grid
rebuild, deliveries with new requests, the (2r+1)² observation windows and the central columns. Its
one simplification is the conflict rule: rware resolves moves through networkx (cycles of 3+ move,
swaps fail, otherwise the longest path of a chain moves); here a fixed point over N rounds lets a
robot move when its target is free or being vacated, the lowest index winning a contested cell, and
rotations of 3+ robots do not move. An exact version needs the same array work plus tie-breaking as
networkx breaks ties, so its cost is of the same order.

    PYTHONPATH=. .venv/bin/python -m hammer.benchmarks.rware_vec_prototype [--n 2 4] [--k 16 64 256]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

DIRS = np.array([[0, -1], [0, 1], [-1, 0], [1, 0]])  # UP, DOWN, LEFT, RIGHT as (dx, dy), rware's order
RIGHT_OF = np.array([3, 2, 0, 1])  # turning right from UP, DOWN, LEFT, RIGHT
LEFT_OF = np.array([2, 3, 1, 0])


class VecWarehouse:
    """K tiny warehouses (11 x 10, 32 shelves, goals at the bottom middle) as arrays."""

    def __init__(self, k: int, n: int, seed: int = 0, sensor_range: int = 1) -> None:
        from hammer.envs.rware_vec import RwareSettings

        wh = RwareSettings(n, 1, 3, 8, sensor_range, n, 500, "individual").warehouse()
        wh.reset(seed=seed)
        self.k, self.n, self.r = k, n, sensor_range
        self.h, self.w = wh.grid_size
        self.highway = np.asarray(wh.highways, dtype=bool)
        self.goals = np.asarray(wh.goals)  # (G, 2) x, y
        self.rng = np.random.default_rng(seed)
        shelf_xy = np.array([(s.x, s.y) for s in wh.shelfs])
        self.s = len(shelf_xy)
        self.shelf = np.broadcast_to(shelf_xy, (k, self.s, 2)).copy()
        free = np.flatnonzero(np.ones(self.h * self.w))
        cells = np.stack([self.rng.choice(free, n, replace=False) for _ in range(k)])
        self.pos = np.stack([cells % self.w, cells // self.w], axis=-1)  # (K, N, 2)
        self.dir = self.rng.integers(0, 4, (k, n))
        self.load = np.full((k, n), -1)  # carried shelf index or -1
        self.req = np.stack([self.rng.choice(self.s, n, replace=False) for _ in range(k)])  # (K, R)
        self.kk = np.arange(k)[:, None]
        self._grids()

    def _grids(self) -> None:
        """Shelf and robot grids (K, H, W) holding index + 1 (0 empty)."""
        self.sg = np.zeros((self.k, self.h, self.w), dtype=np.int64)
        self.sg[self.kk, self.shelf[..., 1], self.shelf[..., 0]] = np.arange(1, self.s + 1)
        self.ag = np.zeros((self.k, self.h, self.w), dtype=np.int64)
        self.ag[self.kk, self.pos[..., 1], self.pos[..., 0]] = np.arange(1, self.n + 1)

    def _resolve(self, fwd: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Which forward robots move: fixed point over N rounds (see the module docstring)."""
        moves = fwd.copy()
        for _ in range(self.n):
            occ = self.ag[self.kk, target[..., 1], target[..., 0]] - 1  # robot now at my target, or -1
            vacated = np.where(occ >= 0, np.take_along_axis(moves, np.maximum(occ, 0), axis=1), True)
            same = (target[:, :, None, :] == target[:, None, :, :]).all(-1) & moves[:, None, :]
            earlier = np.tril(np.ones((self.n, self.n), dtype=bool), -1)
            beaten = (same & earlier).any(-1)
            swap = (occ >= 0) & (np.take_along_axis(target, np.maximum(occ, 0)[..., None], axis=1)
                                 == self.pos).all(-1)
            new = fwd & vacated & ~beaten & ~swap
            if np.array_equal(new, moves):
                break
            moves = new
        return moves

    def step(self, act: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fwd = act == 1
        target = np.clip(self.pos + DIRS[self.dir] * fwd[..., None], 0, [self.w - 1, self.h - 1])
        carrying = self.load >= 0
        into_shelf = self.sg[self.kk, target[..., 1], target[..., 0]] > 0
        fwd &= ~(carrying & into_shelf)
        moves = self._resolve(fwd, target)
        self.pos = np.where(moves[..., None], target, self.pos)
        self.dir = np.where(act == 2, LEFT_OF[self.dir], np.where(act == 3, RIGHT_OF[self.dir], self.dir))
        held = np.maximum(self.load, 0)
        self.shelf[self.kk, held] = np.where(carrying[..., None], self.pos, self.shelf[self.kk, held])
        under = self.sg[self.kk, self.pos[..., 1], self.pos[..., 0]] - 1
        on_highway = self.highway[self.pos[..., 1], self.pos[..., 0]]
        toggle = act == 4
        self.load = np.where(toggle & ~carrying & (under >= 0), under,
                             np.where(toggle & carrying & ~on_highway, -1, self.load))
        self._grids()
        return self._deliver(), self._observe()

    def _deliver(self) -> np.ndarray:
        reward = np.zeros((self.k, self.n), dtype=np.float32)
        for gx, gy in self.goals:
            sh = self.sg[:, gy, gx] - 1
            hit = (sh[:, None] == self.req) & (sh[:, None] >= 0)
            for k, slot in zip(*np.nonzero(hit)):
                reward[k, self.ag[k, gy, gx] - 1] += 1.0
                free = np.setdiff1d(np.arange(self.s), self.req[k])
                self.req[k, slot] = self.rng.choice(free)
        return reward

    def _observe(self) -> np.ndarray:
        r, k, n = self.r, self.k, self.n
        pa = np.pad(self.ag, ((0, 0), (r, r), (r, r)))
        ps = np.pad(self.sg, ((0, 0), (r, r), (r, r)))
        off = np.arange(-r, r + 1)
        ys = self.pos[..., 1, None, None] + r + off[:, None]
        xs = self.pos[..., 0, None, None] + r + off[None, :]
        kk = self.kk[..., None, None]
        wa = pa[kk, ys, xs].reshape(k, n, -1)  # (K, N, cells) robot index + 1
        ws = ps[kk, ys, xs].reshape(k, n, -1)
        requested = np.zeros((k, self.s + 1), dtype=bool)
        requested[self.kk, self.req + 1] = True
        cells = wa.shape[-1]
        win = np.zeros((k, n, cells, 7), dtype=np.float32)
        win[..., 0] = wa > 0
        win[..., 1:5] = np.eye(4, dtype=np.float32)[np.take_along_axis(
            self.dir, np.maximum(wa - 1, 0).reshape(k, -1), axis=1).reshape(k, n, cells)]
        win[..., 1] = np.where(wa > 0, win[..., 1], 1.0)
        win[..., 5] = ws > 0
        win[..., 6] = np.take_along_axis(requested, ws.reshape(k, -1), axis=1).reshape(k, n, cells)
        own = np.concatenate([self.pos, (self.load >= 0)[..., None], np.eye(4)[self.dir],
                              self.highway[self.pos[..., 1], self.pos[..., 0]][..., None]], axis=-1)
        central = np.concatenate([self.shelf, requested[:, 1:, None]], axis=-1).reshape(k, -1)
        central = np.concatenate([central, np.broadcast_to(self.goals.reshape(-1), (k, self.goals.size))], axis=1)
        return np.concatenate([own.astype(np.float32), win.reshape(k, n, -1),
                               np.broadcast_to(central[:, None], (k, n, central.shape[1]))], axis=-1)


def measure(k: int, n: int, seconds: float = 3.0) -> tuple[float, float]:
    """(copy-steps/s, copy-steps per CPU-second) of the prototype with uniform-random actions; the
    second is what to compare on a shared machine."""
    env = VecWarehouse(k, n)
    rng = np.random.default_rng(0)
    acts = rng.integers(0, 5, (64, k, n))
    steps, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds:
        env.step(acts[steps % 64])
        steps += 1
    return steps * k / (time.perf_counter() - t0), steps * k / max(time.process_time() - c0, 1e-9)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--k", type=int, nargs="+", default=[16, 64, 256])
    ap.add_argument("--seconds", type=float, default=3.0)
    a = ap.parse_args()
    for n in a.n:
        for k in a.k:
            wall, cpu = measure(k, n, a.seconds)
            print(f"prototype N={n} K={k}: {wall:9.0f} copy-steps/s, {cpu:9.0f} per CPU-s", flush=True)


if __name__ == "__main__":
    main()
