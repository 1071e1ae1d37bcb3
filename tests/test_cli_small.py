"""Small things a newcomer sees: --version, the report's wording for one seed and short runs."""

import numpy as np
from hammer.experiments.plot import plot_runs, plotted_curve, seed_curves
from hammer.experiments.report import Row, to_markdown
from hammer.experiments.runs import Run
from typer.testing import CliRunner

from hammer.cli import app


def test_version():
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.startswith("hammer ")


def test_report_one_seed_has_no_plus_minus_and_short_runs_say_so():
    one = Row("cn N=3", "il", 1, 300, -20.0, float("nan"), None, [-20.0])
    two = Row("cn N=3", "hammer-rl-m4", 2, 300, -19.0, 0.5, 0.3, [-18.5, -19.5])
    md = to_markdown([one, two], last=500)
    assert "| -20.00 |" in md and "-19.00 ± 0.50" in md and "± 0.00" not in md
    assert "fewest 300" in md
    assert "fewest" not in to_markdown([Row("cn N=3", "il", 2, 900, -1.0, 0.1, None, [-1, -1])], last=500)


def test_a_single_run_curve_has_no_spike_at_episode_0(tmp_path):
    metric = np.concatenate([[-60.0], np.full(299, -20.0)])  # a wild first episode
    n = len(metric)
    run = Run(tmp_path, {"env": "cn", "n_agents": 3}, np.arange(1, n + 1), metric, metric * 3, True)
    x, mean, se = plotted_curve([run], window=100)
    assert x[0] == 11 and mean.min() > -25.0 and not se.any()
    assert seed_curves([run], 100)[1][0] == -60.0  # what would have been drawn
    written = plot_runs([run], tmp_path / "c", window=100)
    assert all(p.is_file() for p in written)
