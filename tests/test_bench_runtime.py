"""How `hammer bench` decides that `hammer up` reproduced `hammer train`."""

from __future__ import annotations

from pathlib import Path

from hammer.benchmarks.runtime import _same_metrics, same_label


def _metrics(d: Path, values: list[float]) -> Path:
    d.mkdir()
    rows = "".join(f"{i + 1},{25 * (i + 1)},{v!r},{3 * v!r},25,0.1\n" for i, v in enumerate(values))
    (d / "metrics.csv").write_text("episode,env_steps,paper_metric,team_return,length,wall_time\n" + rows)
    return d


def test_same_metrics_allows_float_noise_only(tmp_path):
    a = _metrics(tmp_path / "a", [-20.5, -18.25, -17.0])
    assert _same_metrics(a, _metrics(tmp_path / "b", [-20.5 + 3e-7, -18.25, -17.0 - 2e-6]))
    assert not _same_metrics(a, _metrics(tmp_path / "c", [-20.5, -18.2, -17.0]))  # a different episode
    assert not _same_metrics(a, _metrics(tmp_path / "d", [-20.5, -18.25]))  # an episode missing


def test_a_difference_is_reported_with_the_missed_deadlines():
    assert same_label({"same_metrics": True}) == "True"
    label = same_label({"same_metrics": False, "up_msg_fallback_copies": 12, "up_default_actions": 0})
    assert label == "False (12 fallbacks, 0 defaults)"
