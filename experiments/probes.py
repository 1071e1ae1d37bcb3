"""Linear probes with episode-split cross-validation: closed-form ridge in numpy.

What the message analysis (docs/results/plan-messages.md) asks of a probe: a ridge regression from
features X (rows = one agent at one step) to a target Y, its penalty alpha chosen by 5-fold
cross-validation inside each training fold, scored by held-out R² averaged over Y's components.
Rows of one episode are strongly correlated (25 steps of one trajectory), so every split, outer
and inner, is by episode: a row-level split would let a probe memorise an episode from its
neighbouring steps and score well on what it never learned (tests/test_messages.py shows it).

Why not scikit-learn: it is not a dependency, and the whole estimator is a standardisation, one
eigendecomposition of a small Gram matrix per fold (features are ≤ ~30 wide) and a matmul per
alpha. Features are standardised with the training fold's mean and standard deviation, the
intercept is not penalised (centred data), and the penalty is alpha × rows, so the alpha grid
means the same at any data size. R² per component is sklearn's `r2_score`: 1 − SSE / SST with
SST about the held-out fold's own mean.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ALPHAS = (1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)
FOLDS = 5
SEED = 0


def episode_folds(episodes: np.ndarray, k: int = FOLDS, seed: int = SEED) -> list[np.ndarray]:
    """Row indices of the k test folds: the distinct episode ids shuffled (fixed seed) and dealt
    into k groups, so every episode's rows are in exactly one fold."""
    ids = np.unique(episodes)
    if len(ids) < k:
        raise ValueError(f"{len(ids)} episodes cannot be split into {k} folds by episode")
    rng = np.random.default_rng(seed)
    groups = np.array_split(rng.permutation(ids), k)
    return [np.flatnonzero(np.isin(episodes, g)) for g in groups]


def r2(y: np.ndarray, pred: np.ndarray) -> float:
    """R² averaged over the columns of y (n, c); a constant column scores 0 if predicted exactly."""
    sse = np.square(y - pred).sum(axis=0)
    sst = np.square(y - y.mean(axis=0)).sum(axis=0)
    safe = np.where(sst > 0, sst, 1.0)
    return float(np.mean(np.where(sst > 0, 1.0 - sse / safe, np.where(sse > 0, 0.0, 1.0))))


@dataclass
class RidgePath:
    """Ridge solutions of one training set for every alpha at the cost of one eigendecomposition."""

    x_mean: np.ndarray
    x_scale: np.ndarray
    y_mean: np.ndarray
    vecs: np.ndarray
    vals: np.ndarray
    xty: np.ndarray  # V^T X^T Y / n in the eigenbasis

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray) -> RidgePath:
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        mean, scale = x.mean(axis=0), x.std(axis=0)
        scale = np.where(scale > 1e-12, scale, 1.0)
        xs = (x - mean) / scale
        y_mean = y.mean(axis=0)
        n = len(x)
        vals, vecs = np.linalg.eigh(xs.T @ xs / n)
        return cls(mean, scale, y_mean, vecs, np.maximum(vals, 0.0), vecs.T @ (xs.T @ (y - y_mean)) / n)

    def predict(self, x: np.ndarray, alpha: float) -> np.ndarray:
        coef = self.vecs @ (self.xty / (self.vals + alpha)[:, None])
        return ((np.asarray(x, np.float64) - self.x_mean) / self.x_scale) @ coef + self.y_mean


def choose_alpha(x: np.ndarray, y: np.ndarray, episodes: np.ndarray, alphas=ALPHAS, k: int = FOLDS) -> float:
    """The alpha of the best mean held-out R² over k episode-split folds of (x, y)."""
    scores = np.zeros(len(alphas))
    for test in episode_folds(episodes, k, seed=SEED + 1):
        train = np.setdiff1d(np.arange(len(x)), test, assume_unique=True)
        path = RidgePath.fit(x[train], y[train])
        scores += [r2(y[test], path.predict(x[test], a)) for a in alphas]
    return float(alphas[int(np.argmax(scores))])


def cv_r2(x: np.ndarray, y: np.ndarray, episodes: np.ndarray, k: int = FOLDS, alphas=ALPHAS,
          folds: list[np.ndarray] | None = None) -> float:
    """Held-out R² of a ridge probe x -> y, averaged over k outer folds split by episode, alpha chosen
    by k-fold episode-split CV inside each training fold (nested: the test fold never picks alpha).
    `folds` (test row indices) replaces the episode split: tests use it to show what leaks."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if y.ndim == 1:
        y = y[:, None]
    scores = []
    for test in folds if folds is not None else episode_folds(episodes, k):
        train = np.setdiff1d(np.arange(len(x)), test, assume_unique=True)
        alpha = choose_alpha(x[train], y[train], episodes[train], alphas, k)
        scores.append(r2(y[test], RidgePath.fit(x[train], y[train]).predict(x[test], alpha)))
    return float(np.mean(scores))
