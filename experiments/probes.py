"""Linear probes with episode-split cross-validation: closed-form ridge in numpy.

What the message analysis (docs/results/plan-messages.md) asks of a probe: a ridge regression from
features X (rows = one agent at one step) to a target Y, its penalty alpha chosen by 5-fold
cross-validation inside each training fold, scored by held-out R² averaged over Y's components.
Rows of one episode are strongly correlated (25 steps of one trajectory), so every split, outer
and inner, is by episode: a row-level split would let a probe memorise an episode from its
neighbouring steps and score well on what it never learned (tests/test_messages.py shows it).

Why not scikit-learn: it is not a dependency, and the whole estimator is a few sums. Every episode
gets an outer fold (1 of k) and, independently, an inner fold (1 of k); the rows of each of the k²
(outer, inner) cells are reduced once to their moments (count, sum, sum of outer products of
[x, y]). Any training or test set of the nested CV is a union of cells, so its moments are a sum
of cell moments, and the ridge fit (standardised features, unpenalised intercept, penalty alpha ×
rows so the grid means the same at any data size) and the held-out SSE follow from them exactly:
the cost no longer grows with rows × fits, which keeps the dose-response grid's 120 teams cheap.
R² per component is sklearn's `r2_score`: 1 − SSE / SST with SST about the held-out fold's mean.
The inner split of a training fold is its episodes' inner folds (those of the outer test fold left
out), the same as drawing k inner folds of its episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ALPHAS = (1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0)
FOLDS = 5
SEED = 0


def episode_fold_ids(episodes: np.ndarray, k: int = FOLDS, seed: int = SEED) -> np.ndarray:
    """Per row, its episode's fold in 0..k-1: the distinct episode ids shuffled (fixed seed) and dealt
    into k groups, so every episode's rows are in one fold."""
    ids, inverse = np.unique(episodes, return_inverse=True)
    if len(ids) < k:
        raise ValueError(f"{len(ids)} episodes cannot be split into {k} folds by episode")
    fold_of = np.empty(len(ids), np.int64)
    for f, group in enumerate(np.array_split(np.random.default_rng(seed).permutation(len(ids)), k)):
        fold_of[group] = f
    return fold_of[inverse]


def episode_folds(episodes: np.ndarray, k: int = FOLDS, seed: int = SEED) -> list[np.ndarray]:
    """Row indices of the k test folds of `episode_fold_ids`."""
    ids = episode_fold_ids(episodes, k, seed)
    return [np.flatnonzero(ids == f) for f in range(k)]


@dataclass
class Moments:
    """Count, sum and sum of outer products of the rows z = [x, y] of a set."""

    n: float
    s: np.ndarray  # (d,)
    g: np.ndarray  # (d, d)

    @classmethod
    def of(cls, z: np.ndarray) -> Moments:
        return cls(float(len(z)), z.sum(axis=0), z.T @ z)

    def __add__(self, other: Moments) -> Moments:
        return Moments(self.n + other.n, self.s + other.s, self.g + other.g)


def ridge(m: Moments, p: int, alphas) -> list[tuple[np.ndarray, np.ndarray]]:
    """(w (p, q), b (q)) for every alpha, from a training set's moments: features standardised by its
    mean and standard deviation, minimising |y − b − x w|² / n + alpha |w_standardised|²."""
    mean = m.s / m.n
    cov = m.g / m.n - np.outer(mean, mean)
    scale = np.sqrt(np.maximum(np.diag(cov)[:p], 0.0))
    scale = np.where(scale > 1e-12, scale, 1.0)
    cxx = cov[:p, :p] / np.outer(scale, scale)
    cxy = cov[:p, p:] / scale[:, None]
    vals, vecs = np.linalg.eigh(cxx)
    proj = vecs.T @ cxy
    out = []
    for a in alphas:
        w = (vecs @ (proj / (np.maximum(vals, 0.0) + a)[:, None])) / scale[:, None]
        out.append((w, mean[p:] - mean[:p] @ w))
    return out


def r2_of(m: Moments, p: int, w: np.ndarray, b: np.ndarray) -> float:
    """Held-out R² averaged over the q target columns, from the test set's moments: the residual
    r = [−w; I]ᵀ z − b has Σ r rᵀ = Aᵀ G A − Aᵀ s bᵀ − b sᵀ A + n b bᵀ."""
    q = len(b)
    a = np.vstack([-w, np.eye(q)])
    sa = m.s @ a
    sse = np.diag(a.T @ m.g @ a) - 2 * sa * b + m.n * b * b
    sst = np.diag(m.g)[p:] - m.s[p:] ** 2 / m.n
    with np.errstate(divide="ignore", invalid="ignore"):
        score = np.where(sst > 1e-12 * m.n, 1.0 - sse / sst, np.where(sse > 1e-12 * m.n, 0.0, 1.0))
    return float(np.mean(score))


def cv_r2(x: np.ndarray, y: np.ndarray, episodes: np.ndarray, k: int = FOLDS, alphas=ALPHAS,
          outer: np.ndarray | None = None) -> float:
    """Held-out R² of a ridge probe x -> y, averaged over k outer folds split by episode, alpha chosen by
    k-fold episode-split CV inside each training fold (nested: the test fold never picks alpha).
    `outer` (a fold id per row) replaces the outer episode split: tests use it to show what leaks."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    y = np.asarray(y, np.float64).reshape(len(y), -1)
    p = x.shape[1]
    out_id = episode_fold_ids(episodes, k) if outer is None else np.asarray(outer)
    in_id = episode_fold_ids(episodes, k, seed=SEED + 1)
    z = np.concatenate([x, y], axis=1)
    empty = Moments(0.0, np.zeros(z.shape[1]), np.zeros((z.shape[1],) * 2))
    cells = [[Moments.of(z[(out_id == o) & (in_id == i)]) for i in range(k)] for o in range(k)]
    scores = []
    for o in range(k):
        train = [cells[oo][i] for oo in range(k) if oo != o for i in range(k)]
        inner = np.zeros(len(alphas))
        for i in range(k):
            held = sum((cells[oo][i] for oo in range(k) if oo != o), empty)
            if held.n == 0:
                continue
            fit = sum((cells[oo][ii] for oo in range(k) if oo != o for ii in range(k) if ii != i), empty)
            inner += [r2_of(held, p, w, b) for w, b in ridge(fit, p, alphas)]
        best = alphas[int(np.argmax(inner))]
        w, b = ridge(sum(train, empty), p, [best])[0]
        scores.append(r2_of(sum(cells[o], empty), p, w, b))
    return float(np.mean(scores))
