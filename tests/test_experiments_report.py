"""Report and plot from run directories written in the on-disk format of `hammer train`."""

import csv
import json

import numpy as np
import pytest
from hammer.experiments.plot import plot_runs
from hammer.experiments.report import build_rows, to_markdown
from hammer.experiments.runs import find_runs, load_run, rolling_mean
from scipy import stats


def write_run(root, name, cfg, metric):
    d = root / name
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps(cfg))
    with open(d / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "env_steps", "paper_metric", "team_return", "length", "wall_time"])
        for i, m in enumerate(metric):
            w.writerow([i + 1, 25 * (i + 1), m, 3 * m, 25, 0.01 * i])
    (d / "summary.json").write_text("{}")
    return d


@pytest.fixture
def runs_dir(tmp_path):
    rng = np.random.default_rng(0)
    for seed in range(4):
        base = {"env": "cn", "n_agents": 3, "seed": seed, "msg_dim": 4}
        write_run(tmp_path, f"il-s{seed}", {**base, "variant": "il"}, rng.normal(-20, 1, 800))
        write_run(tmp_path, f"hm-s{seed}", {**base, "variant": "hammer", "central_mode": "backprop"},
                  rng.normal(-18, 1, 800) - np.linspace(2, 0, 800))
    return tmp_path


def test_rolling_mean_matches_naive():
    x = np.random.default_rng(1).normal(size=57)
    w = 10
    naive = [x[max(0, i - w + 1): i + 1].mean() for i in range(len(x))]
    np.testing.assert_allclose(rolling_mean(x, w), naive)


def test_report_means_sem_and_welch(runs_dir):
    runs = [load_run(p) for p in find_runs([runs_dir])]
    assert len(runs) == 8
    rows = {r.label: r for r in build_rows(runs, last=500)}
    il = np.array([load_run(runs_dir / f"il-s{s}").paper_metric[-500:].mean() for s in range(4)])
    hm = np.array([load_run(runs_dir / f"hm-s{s}").paper_metric[-500:].mean() for s in range(4)])
    assert rows["il"].mean == pytest.approx(il.mean())
    assert rows["il"].sem == pytest.approx(il.std(ddof=1) / 2)
    assert rows["hammer-backprop-m4"].p_vs_il == pytest.approx(stats.ttest_ind(hm, il, equal_var=False).pvalue)
    assert rows["il"].p_vs_il is None
    md = to_markdown(list(rows.values()), 500)
    assert "| cn N=3 | hammer-backprop-m4 | 4 | 800 |" in md


def test_runs_with_changed_settings_are_never_pooled(runs_dir):
    """A run that changed a learning field (or an env kwarg) from its preset is its own setting,
    named by the change; fields equal to the preset's, and speed/bookkeeping fields, change nothing."""
    rng = np.random.default_rng(2)
    base = {"env": "cn", "n_agents": 3, "msg_dim": 4, "variant": "il", "gamma": 0.95, "env_workers": 2}
    for seed in range(2):
        write_run(runs_dir, f"il-lr-s{seed}", {**base, "seed": seed, "lr_local": 1e-4}, rng.normal(-25, 1, 800))
        write_run(runs_dir, f"il-own-s{seed}", {**base, "seed": seed, "env_kwargs": {"observe_others": False}},
                  rng.normal(-25, 1, 800))
    write_run(runs_dir, "il-same-s9", {**base, "seed": 9}, rng.normal(-20, 1, 800))
    rows = {(r.setting, r.label): r for r in build_rows([load_run(p) for p in find_runs([runs_dir])], last=500)}
    assert set(rows) == {("cn N=3", "il"), ("cn N=3", "hammer-backprop-m4"), ("cn N=3 (lr_local=0.0001)", "il"),
                         ("cn N=3 (env_kwargs.observe_others=false)", "il")}
    assert rows[("cn N=3", "il")].n_seeds == 5  # the four fixture seeds and il-same-s9
    assert rows[("cn N=3 (lr_local=0.0001)", "il")].n_seeds == 2


def test_report_by_best_rolling_mean(runs_dir):
    runs = [load_run(p) for p in find_runs([runs_dir])]
    # one IL seed peaks early and falls back: by final mean it is low, by best rolling mean high
    il0 = next(r for r in runs if r.path.name == "il-s0")
    il0.paper_metric = np.concatenate([np.full(300, 5.0), np.full(500, -40.0)])
    best = {
        label: np.array([max(r.paper_metric[i - 100:i].mean() for i in range(100, len(r.paper_metric) + 1))
                         for r in runs if r.label == label])
        for label in ("il", "hammer-backprop-m4")
    }
    rows = {r.label: r for r in build_rows(runs, last=500, best_window=100)}
    assert rows["il"].finals[[r for r in runs if r.label == "il"].index(il0)] == pytest.approx(5.0)
    assert rows["il"].mean == pytest.approx(best["il"].mean())
    assert rows["hammer-backprop-m4"].p_vs_il == pytest.approx(
        stats.ttest_ind(best["hammer-backprop-m4"], best["il"], equal_var=False).pvalue)
    assert "| best (mean ± s.e.) |" in to_markdown(list(rows.values()), 500, best_window=100)


def test_plot_writes_png_and_svg(runs_dir, tmp_path):
    runs = [load_run(p) for p in find_runs([runs_dir])]
    out = plot_runs(runs, tmp_path / "figs" / "curves", window=100)
    assert [p.suffix for p in out] == [".png", ".svg"]
    assert all(p.stat().st_size > 1000 for p in out)
    # Redrawing the same runs gives the same bytes: regenerated figures only show in git when their data changed.
    again = plot_runs(runs, tmp_path / "figs2" / "curves", window=100)
    assert [p.read_bytes() for p in again] == [p.read_bytes() for p in out]


def test_missing_run_path_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        find_runs([tmp_path / "nope"])


def test_archived_runs_read_like_run_directories(runs_dir, tmp_path):
    from hammer.experiments.archive import archive_run, is_archived

    archive = tmp_path / "archive"
    for p in find_runs([runs_dir]):
        archive_run(p, archive)
    assert is_archived(archive, "il-s0") and not (archive / "il-s0" / "metrics.csv").exists()
    original = {r.path.name: r for r in (load_run(p) for p in find_runs([runs_dir]))}
    archived = [load_run(p) for p in find_runs([archive])]
    assert sorted(r.path.name for r in archived) == sorted(original)
    for r in archived:
        o = original[r.path.name]
        assert r.label == o.label and r.finished
        np.testing.assert_allclose(r.paper_metric, o.paper_metric, rtol=1e-6)  # float32 on disk
        np.testing.assert_array_equal(r.episodes, o.episodes)
    a_rows = {r.label: r.mean for r in build_rows(archived, last=500)}
    o_rows = {r.label: r.mean for r in build_rows(list(original.values()), last=500)}
    assert a_rows == pytest.approx(o_rows, abs=1e-5)


def test_only_finished_runs_are_archived(runs_dir, tmp_path):
    from hammer.experiments.archive import archive_run

    (runs_dir / "il-s0" / "summary.json").unlink()
    with pytest.raises(FileNotFoundError, match="only finished runs"):
        archive_run(runs_dir / "il-s0", tmp_path / "archive")
