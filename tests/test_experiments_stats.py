"""experiments.stats against hand-computed values and scipy's own bootstrap."""

import numpy as np
import pytest
from hammer.experiments.report import (
    build_comparisons,
    build_rows,
    comparisons_from_plan,
    parse_comparisons,
    to_markdown,
)
from hammer.experiments.runs import find_runs, load_run
from hammer.experiments.stats import (
    holm,
    iqm,
    iqm_band,
    iqm_ci,
    iqm_difference_ci,
    poi_ci,
    probability_of_improvement,
)
from scipy import stats

from tests.test_experiments_report import runs_dir  # noqa: F401  (the fixture)


def test_iqm_is_the_mean_of_the_middle_half():
    assert iqm(np.array([1.0, 2, 3, 4, 100])) == pytest.approx(3.0)  # 5 runs: the middle 3
    assert iqm(np.arange(1.0, 11)) == pytest.approx(5.5)  # 10 runs: the middle 6 (3..8)
    assert iqm(np.array([10.0, 1, 3, 2])) == pytest.approx(2.5)  # unsorted, 4 runs: the middle 2


def test_probability_of_improvement_counts_ties_half():
    # pairs: 1 beats 0; 2 beats 0 and ties 2, 2; 3 beats all three -> (5 + 2/2) / 9
    assert probability_of_improvement(np.array([1.0, 2, 3]), np.array([2.0, 2, 0])) == pytest.approx(6 / 9)
    # averaged over tasks: 1 (all above) and 0 (all below)
    assert probability_of_improvement([[5.0, 6], [0.0]], [[1.0], [3.0, 4]]) == pytest.approx(0.5)
    p, lo, hi = poi_ci(np.array([5.0, 6, 7]), np.array([1.0, 2]))
    assert p == lo == hi == 1.0  # every resample still has every A above every B


def test_holm_by_hand():
    # sorted .01, .03, .04 times 3, 2, 1 -> .03, .06, .04 -> non-decreasing .03, .06, .06 (input order back)
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert holm([0.5, 0.9]) == pytest.approx([1.0, 1.0])
    assert holm([]) == []


def test_bootstrap_ci_agrees_with_scipy_and_is_reproducible():
    x = np.random.default_rng(3).normal(-19, 0.5, 10)
    q, lo, hi = iqm_ci(x)
    ref = stats.bootstrap((x,), lambda a, axis: stats.trim_mean(a, 0.25, axis=axis), method="percentile",
                          n_resamples=20000, random_state=1).confidence_interval
    assert lo < q < hi
    assert lo == pytest.approx(ref.low, abs=0.05) and hi == pytest.approx(ref.high, abs=0.05)
    assert iqm_ci(x) == (q, lo, hi)  # fixed seed: a regenerated table is identical
    d, dlo, dhi = iqm_difference_ci(x + 1.0, x)
    assert d == pytest.approx(1.0) and dlo < 1.0 < dhi
    band, blo, bhi = iqm_band(np.stack([x, x + 1]).T)  # 10 seeds, 2 points
    assert band == pytest.approx([q, q + 1]) and np.all(blo <= band) and np.all(band <= bhi)


def test_report_lists_declared_comparisons_with_holm(runs_dir, tmp_path):  # noqa: F811
    rows = build_rows([load_run(p) for p in find_runs([runs_dir])], last=500)
    comps = build_comparisons(rows, [("hammer-backprop", "il"), ("il", "hammer-backprop")])
    assert [(c.a, c.b) for c in comps] == [("hammer-backprop-m4", "il"), ("il", "hammer-backprop-m4")]
    assert comps[0].poi == pytest.approx(1 - comps[1].poi)
    assert comps[0].p_holm == pytest.approx(min(1.0, 2 * comps[0].p))  # equal p-values, family of 2
    md = to_markdown(rows, 500, comparisons=comps)
    assert "| cn N=3 | hammer-backprop-m4 | il |" in md and "p (Holm)" in md
    with pytest.raises(ValueError, match="random:il"):
        build_comparisons(rows, [("random", "il")])
    plan = tmp_path / "plan.md"
    plan.write_text("# plan\n\ncomparisons: `hammer-rl:il, random:il`\n")
    assert comparisons_from_plan(plan) == [("hammer-rl", "il"), ("random", "il")]
    with pytest.raises(ValueError, match="A:B"):
        parse_comparisons("hammer-rl il")


def test_iqm_band_plot_centres_on_the_seed_iqm(runs_dir, tmp_path):  # noqa: F811
    from hammer.experiments.plot import plot_runs, seed_band
    from hammer.experiments.runs import rolling_mean

    runs = [load_run(p) for p in find_runs([runs_dir]) if "il-" in p.name]
    _x, centre, lo, hi = seed_band(runs, 100, "iqm")
    curves = np.stack([rolling_mean(r.paper_metric, 100) for r in runs])
    # drawn from the episode where the rolling mean holds a tenth of its window (no spike at episode 0)
    np.testing.assert_allclose(centre, iqm(curves, axis=0)[100 // 10:])
    assert np.all(lo <= centre + 1e-12) and np.all(centre <= hi + 1e-12) and np.any(hi > lo)
    out = plot_runs(runs, tmp_path / "c", window=100, band="iqm")
    assert [p.read_bytes() for p in plot_runs(runs, tmp_path / "d", window=100, band="iqm")] == [
        p.read_bytes() for p in out]
    with pytest.raises(ValueError, match="band"):
        seed_band(runs, 100, "median")


def test_auc_is_the_mean_over_the_first_episodes(runs_dir):  # noqa: F811
    runs = [load_run(p) for p in find_runs([runs_dir])]
    rows = {r.label: r for r in build_rows(runs, auc=200)}
    il = np.array([load_run(runs_dir / f"il-s{s}").paper_metric[:200].mean() for s in range(4)])
    assert rows["il"].mean == pytest.approx(il.mean())
    assert rows["il"].team == pytest.approx(3 * il.mean())
    assert "| AUC 200 (mean ± s.e.) |" in to_markdown(list(rows.values()), 500, auc=200)
    with pytest.raises(ValueError, match="fewer than"):
        build_rows(runs, auc=5000)


def test_report_digits_for_small_metrics():
    """--digits: the warehouse's deliveries per robot (~0.1) need more than two decimals."""
    from hammer.experiments.report import Row, to_markdown

    rows = [Row("rware N=2", "il", 2, 2000, 0.1234, 0.0111, None, [0.1123, 0.1345])]
    assert "| 0.12 ± 0.01 |" in to_markdown(rows, 200)
    assert "| 0.123 ± 0.011 |" in to_markdown(rows, 200, digits=3)
