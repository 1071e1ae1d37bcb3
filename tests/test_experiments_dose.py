"""`hammer dose`: Δ per hidden-information level and its slope, on runs in the on-disk format."""

from pathlib import Path

import numpy as np
import pytest
from hammer.experiments.dose import cells, dose_levels, dose_slope, plot_dose, to_markdown
from hammer.experiments.runs import find_runs, load_run
from hammer.experiments.stats import iqm

from tests.runtime_helpers import hammer
from tests.test_experiments_report import write_run


@pytest.fixture
def dose_dir(tmp_path):
    """il ends at -20 at every level; hammer-rl gains 0, 0.6 and 1.2 as r shrinks from full to 0."""
    rng = np.random.default_rng(0)
    for radius, gain in ((None, 0.0), (1.0, 0.6), (0.0, 1.2)):
        kw = {} if radius is None else {"env_kwargs": {"obs_radius": radius}}
        for seed in range(6):
            base = {"env": "cn", "n_agents": 3, "seed": seed, "msg_dim": 4, **kw}
            write_run(tmp_path, f"il-{radius}-s{seed}", {**base, "variant": "il"}, rng.normal(-20, 0.3, 600))
            write_run(tmp_path, f"hm-{radius}-s{seed}", {**base, "variant": "hammer", "central_mode": "rl"},
                      rng.normal(-20 + gain, 0.3, 600))
    return tmp_path


def test_dose_levels_and_slope(dose_dir, tmp_path):
    values = cells([load_run(p) for p in find_runs([dose_dir])])
    levels = dose_levels(values, "hammer-rl")
    assert [lv.radius for lv in levels] == [None, 1.0, 0.0]  # from everything visible to nothing
    assert levels[0].hidden == 0.0 and levels[-1].hidden == 1.0
    hm = values[(1.0, "hammer-rl-m4")]
    il = values[(1.0, "il")]
    assert levels[1].delta == pytest.approx(iqm(hm) - iqm(il))
    assert all(lv.lo <= lv.delta <= lv.hi for lv in levels)
    assert levels[-1].lo > 0.8 and abs(levels[0].delta) < 0.2
    s = dose_slope(values, "hammer-rl")
    assert 0.9 < s.slope < 1.5 and s.lo5 > 0  # the gain grows with what is hidden: H2's rule holds
    flat = dose_slope(values, "il")  # il against itself: Δ = 0 everywhere
    assert flat.slope == pytest.approx(0.0) and flat.lo <= 0 <= flat.hi
    md = to_markdown(levels, [s], "final")
    assert "| hammer-rl | full | 0.000 | 6 / 6 |" in md
    assert [p.suffix for p in plot_dose(levels, tmp_path / "dose")] == [".png", ".svg"]


def test_dose_cli(dose_dir, tmp_path):
    res = hammer("dose", str(dose_dir), "--variants", "hammer-rl", "--out", str(tmp_path / "d"))
    assert res.returncode == 0, res.stderr[-2000:]
    assert (tmp_path / "d.md").read_text().count("| hammer-rl |") == 4  # 3 levels + the slope row
    res = hammer("dose", str(dose_dir), "--variants", "random")
    assert res.returncode != 0 and "error: no level has runs of both il and one of random" in res.stderr


def test_trained_teams_hide_less_than_random_play_and_the_ends_are_exact():
    """The exploratory h under a trained team (its archived final/ weights, the runtime's acting): 1
    when nothing is visible, and below the random-play h at r = 0.6 (trained agents sit nearer their
    landmarks and each other), above 0."""
    from hammer.envs.local_view import spread_hidden_fraction
    from hammer.experiments.dose import learned_hidden
    from hammer.experiments.runs import load_run

    archive = Path(__file__).resolve().parents[1] / "docs/results/runs/cn3-dose"
    blind = load_run(archive / "cn3-il-compile=true-env_kwargs_obs_radius=0.0-s0")
    assert learned_hidden(blind, episodes=20) == 1.0
    mid = load_run(archive / "cn3-hammer-rl-compile=true-env_kwargs_obs_radius=0.6-s0")
    h = learned_hidden(mid, episodes=20)
    assert 0.5 < h < spread_hidden_fraction(0.6) - 0.05
