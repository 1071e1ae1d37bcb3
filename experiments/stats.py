"""Statistics a reviewer trusts with few seeds: interquartile mean (IQM) with stratified bootstrap
confidence intervals, probability of improvement, and Holm's correction across a study's
comparisons, as recommended by Agarwal et al., "Deep RL at the edge of the statistical precipice"
(NeurIPS 2021, the `rliable` package).

Written here instead of depending on `rliable`: that package pulls in arch, statsmodels, pandas and
seaborn for a few lines of numpy. The estimators follow rliable's definitions:

* IQM = mean of the middle 50 % of the runs (`scipy.stats.trim_mean(x, 0.25)`: with 5 runs the
  middle 3, with 10 the middle 6). Less sensitive to one outlying seed than the mean, more
  efficient than the median.
* Stratified bootstrap: each task's (here: each group's) runs are resampled with replacement
  independently, the statistic is recomputed on every resample, and the 95 % interval is the
  2.5th and 97.5th percentile of those values (percentile bootstrap). With one task it is the
  ordinary bootstrap over seeds.
* Probability of improvement P(X > Y) = the chance that a random run of X ends above a random run
  of Y, ties counting half (the Mann-Whitney U statistic / (n m)); averaged over tasks when there
  are several. Its CI resamples X's and Y's runs independently.
* Holm's step-down correction: sort the m p-values, multiply the i-th smallest by m - i + 1, make
  the sequence non-decreasing, cap at 1. Controls the family-wise error rate at any dependence.

Every bootstrap draws from a fixed seed, so a table regenerated from the same runs is identical.

With 3-10 seeds a percentile bootstrap is too narrow (resampling 5 values never produces a value
outside them), and when every run of A beats every run of B, P(A > B)'s interval is [1, 1]. The
intervals describe these seeds; the decisions use the Holm-corrected tests the plans declare.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import stats

REPS = 5000  # bootstrap resamples: Monte-Carlo error of a 95 % bound well below the digits printed
SEED = 0


def iqm(x: np.ndarray, axis: int = 0) -> np.ndarray | float:
    """Interquartile mean along `axis` (rliable's `aggregate_iqm` on one task)."""
    return stats.trim_mean(np.asarray(x, dtype=np.float64), 0.25, axis=axis)


def _resample_indices(rng: np.random.Generator, n: int, reps: int) -> np.ndarray:
    return rng.integers(0, n, size=(reps, n))


def stratified_bootstrap_ci(statistic: Callable[..., np.ndarray], *groups: Sequence[np.ndarray],
                            reps: int = REPS, alpha: float = 0.05, seed: int = SEED) -> tuple[float, float]:
    """Percentile CI of `statistic(*groups)`. Each argument is a list of per-task arrays of run
    scores; every task's runs are resampled on their own. `statistic` receives, per argument, the
    list of resampled arrays stacked as (reps, n_task_runs) and must return (reps,) values."""
    rng = np.random.default_rng(seed)
    resampled = []
    for tasks in groups:
        per_task = []
        for x in tasks:
            x = np.asarray(x, dtype=np.float64)
            per_task.append(x[_resample_indices(rng, len(x), reps)])
        resampled.append(per_task)
    values = np.asarray(statistic(*resampled), dtype=np.float64)
    lo, hi = np.percentile(values, [100 * alpha / 2, 100 * (1 - alpha / 2)])
    return float(lo), float(hi)


def iqm_ci(x: np.ndarray, reps: int = REPS, seed: int = SEED) -> tuple[float, float, float]:
    """(IQM, CI low, CI high) of one group's run scores."""
    x = np.asarray(x, dtype=np.float64)
    lo, hi = stratified_bootstrap_ci(lambda t: iqm(t[0], axis=1), [x], reps=reps, seed=seed)
    return float(iqm(x)), lo, hi


def iqm_difference_ci(x: np.ndarray, y: np.ndarray, reps: int = REPS, seed: int = SEED
                      ) -> tuple[float, float, float]:
    """(IQM(x) - IQM(y), CI low, CI high), x's and y's runs resampled independently: the
    dose-response measure HAMMER - IL."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    lo, hi = stratified_bootstrap_ci(lambda a, b: iqm(a[0], axis=1) - iqm(b[0], axis=1), [x], [y],
                                     reps=reps, seed=seed)
    return float(iqm(x) - iqm(y)), lo, hi


def _poi(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y) / 2 along the last axis; x (..., n), y (..., m)."""
    gt = (x[..., :, None] > y[..., None, :]).mean(axis=(-2, -1))
    eq = (x[..., :, None] == y[..., None, :]).mean(axis=(-2, -1))
    return gt + 0.5 * eq


def probability_of_improvement(x: Sequence[np.ndarray] | np.ndarray, y: Sequence[np.ndarray] | np.ndarray
                               ) -> float:
    """P(a run of X ends above a run of Y), averaged over tasks; x and y are one array of run
    scores each, or lists of them (one per task, paired by position)."""
    xs, ys = _tasks(x), _tasks(y)
    return float(np.mean([_poi(a, b) for a, b in zip(xs, ys, strict=True)]))


def poi_ci(x: Sequence[np.ndarray] | np.ndarray, y: Sequence[np.ndarray] | np.ndarray, reps: int = REPS,
           seed: int = SEED) -> tuple[float, float, float]:
    """(P(X > Y), CI low, CI high) with X's and Y's runs of every task resampled independently."""
    xs, ys = _tasks(x), _tasks(y)
    lo, hi = stratified_bootstrap_ci(
        lambda a, b: np.mean([_poi(ra, rb) for ra, rb in zip(a, b, strict=True)], axis=0), xs, ys,
        reps=reps, seed=seed)
    return probability_of_improvement(xs, ys), lo, hi


def _tasks(x) -> list[np.ndarray]:
    if isinstance(x, np.ndarray) and x.ndim == 1:
        return [x.astype(np.float64)]
    return [np.asarray(t, dtype=np.float64) for t in x]


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm-adjusted p-values, in the input order."""
    p = np.asarray(pvalues, dtype=np.float64)
    m = len(p)
    if m == 0:
        return []
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, np.maximum.accumulate(p[order] * (m - np.arange(m))))
    out = np.empty(m)
    out[order] = adj
    return [float(v) for v in out]


def welch_p(x: np.ndarray, y: np.ndarray) -> float | None:
    """Two-sided Welch t-test p-value, None with fewer than 2 runs on either side."""
    if len(x) < 2 or len(y) < 2:
        return None
    return float(stats.ttest_ind(x, y, equal_var=False).pvalue)


def iqm_band(curves: np.ndarray, reps: int = 1000, seed: int = SEED, chunk: int = 100
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(IQM, CI low, CI high) at every point of (S, P) per-seed curves: the seeds are resampled
    together for the whole curve (one resample = one set of seeds), in chunks to bound memory."""
    curves = np.asarray(curves, dtype=np.float64)
    s = curves.shape[0]
    rng = np.random.default_rng(seed)
    idx = _resample_indices(rng, s, reps)
    vals = np.concatenate([iqm(curves[idx[i:i + chunk]], axis=1) for i in range(0, reps, chunk)])
    lo, hi = np.percentile(vals, [2.5, 97.5], axis=0)
    return iqm(curves, axis=0), lo, hi
