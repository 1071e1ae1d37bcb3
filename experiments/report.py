"""Table 1 of the paper, rebuilt from run directories: final performance as mean ± standard error
over seeds, with Welch's t-test of each HAMMER setting against independent learners (IL)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from experiments.runs import Run, best_rolling, group_runs


@dataclass
class Row:
    setting: str
    label: str
    n_seeds: int
    episodes: int  # the fewest episodes any seed of this group ran
    mean: float
    sem: float
    p_vs_il: float | None
    finals: list[float]


def _episodes(run: Run) -> np.ndarray:
    if len(run.paper_metric) == 0:
        raise ValueError(f"{run.path} has no episodes yet")
    return run.paper_metric


def final_performance(run: Run, last: int) -> float:
    """Mean paper metric over the run's last `last` episodes: where the run ended."""
    return float(np.mean(_episodes(run)[-last:]))


def best_performance(run: Run, window: int) -> float:
    """The run's best rolling-`window` mean of the paper metric: how high it got."""
    return best_rolling(_episodes(run), window)[0]


def sem(x: np.ndarray) -> float:
    return float(np.std(x, ddof=1) / np.sqrt(len(x))) if len(x) > 1 else float("nan")


def build_rows(runs: list[Run], last: int = 500, best_window: int | None = None) -> list[Row]:
    """One row per (setting, variant). Each run counts with its final performance, or with its best
    rolling-`best_window` mean if that is given."""
    def value(r: Run) -> float:
        return final_performance(r, last) if best_window is None else best_performance(r, best_window)

    groups = group_runs(runs)
    finals = {key: np.array([value(r) for r in rs]) for key, rs in groups.items()}
    rows: list[Row] = []
    for (setting, label), rs in sorted(groups.items()):
        x = finals[(setting, label)]
        p = None
        il = finals.get((setting, "il"))
        if label.startswith("hammer") and il is not None and len(x) > 1 and len(il) > 1:
            p = float(stats.ttest_ind(x, il, equal_var=False).pvalue)
        rows.append(Row(setting, label, len(rs), int(min(len(r.paper_metric) for r in rs)),
                        float(np.mean(x)), sem(x), p, [float(v) for v in x]))
    return rows


def to_markdown(rows: list[Row], last: int, best_window: int | None = None) -> str:
    shortest = min((r.episodes for r in rows), default=last)
    if best_window is None:
        col = "final"
        span = (f"last {last} episodes" if shortest >= last else
                f"last {last} episodes (all of them for runs shorter than that: fewest {shortest})")
        what = (f"Final performance = mean paper metric (average reward per local agent per episode) over each "
                f"seed's {span}")
    else:
        col = "best"
        what = (f"Best performance = each seed's best rolling mean of the paper metric (average reward per "
                f"local agent per episode) over {best_window} episodes, wherever in the run it was")
    out = [
        (f"{what}; mean ± standard error over seeds (no ± with one seed); p = Welch's t-test against IL in the "
         "same setting."),
        "",
        f"| setting | variant | seeds | episodes | {col} (mean ± s.e.) | p vs IL |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        p = "" if r.p_vs_il is None else f"{r.p_vs_il:.3g}"
        se = "" if np.isnan(r.sem) else f" ± {r.sem:.2f}"  # one seed has no standard error
        out.append(f"| {r.setting} | {r.label} | {r.n_seeds} | {r.episodes} | {r.mean:.2f}{se} | {p} |")
    return "\n".join(out) + "\n"
