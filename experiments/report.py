"""Table 1 of the paper, rebuilt from run directories: final performance as mean ± standard error
over seeds, with Welch's t-test of each HAMMER setting against independent learners (IL); next to
it the interquartile mean with a bootstrap 95 % CI and the mean team return; then a table of the
study's declared comparisons (A vs B within one setting: difference, IQM difference with CI,
probability of improvement with CI, Welch p and Holm-corrected p across the family), see
`experiments.stats`."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hammer.experiments.runs import Run, best_rolling, group_runs
from hammer.experiments.stats import holm, iqm_ci, iqm_difference_ci, poi_ci, welch_p


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
    team: float = float("nan")  # mean over seeds of the final team return (same window)
    iqm: float = float("nan")
    iqm_lo: float = float("nan")
    iqm_hi: float = float("nan")


@dataclass
class Comparison:
    """A vs B in one setting, over the runs' final values."""

    setting: str
    a: str
    b: str
    diff: float  # mean(A) - mean(B)
    iqm_diff: float
    iqm_diff_lo: float
    iqm_diff_hi: float
    poi: float  # P(a run of A ends above a run of B)
    poi_lo: float
    poi_hi: float
    p: float | None  # Welch
    p_holm: float | None = None


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


def area_under_curve(run: Run, episodes: int) -> float:
    """Mean paper metric over the run's first `episodes` episodes (in the order they finished): the
    area under its raw learning curve up to that point divided by its width, so higher = better
    sooner. The plans' measure of "learns faster" (docs/results/plan-dose-response.md)."""
    m = _episodes(run)
    if len(m) < episodes:
        raise ValueError(f"{run.path} has {len(m)} episodes, fewer than the AUC's {episodes}")
    return float(np.mean(m[:episodes]))


def build_rows(runs: list[Run], last: int = 500, best_window: int | None = None,
               auc: int | None = None) -> list[Row]:
    """One row per (setting, variant). Each run counts with its final performance, or with its best
    rolling-`best_window` mean, or with its area under the curve over the first `auc` episodes."""
    if best_window is not None and auc is not None:
        raise ValueError("best_window and auc are two different measures: give one")

    def value(r: Run) -> float:
        if auc is not None:
            return area_under_curve(r, auc)
        return final_performance(r, last) if best_window is None else best_performance(r, best_window)

    groups = group_runs(runs)
    finals = {key: np.array([value(r) for r in rs]) for key, rs in groups.items()}
    rows: list[Row] = []
    for (setting, label), rs in sorted(groups.items()):
        x = finals[(setting, label)]
        p = None
        il = finals.get((setting, "il"))
        if label.startswith("hammer") and il is not None:
            p = welch_p(x, il)
        team = float(np.mean([np.mean(r.team_return[:auc] if auc else r.team_return[-last:]) for r in rs]))
        q, lo, hi = iqm_ci(x)
        rows.append(Row(setting, label, len(rs), int(min(len(r.paper_metric) for r in rs)),
                        float(np.mean(x)), sem(x), p, [float(v) for v in x], team, q, lo, hi))
    return rows


def _matches(label: str, name: str) -> bool:
    """`hammer-rl` names `hammer-rl-m4` (any message length), an exact label names itself."""
    return label == name or label.startswith(name + "-m")


def default_comparisons(rows: list[Row]) -> list[tuple[str, str]]:
    """Every variant against IL in each setting that has IL runs, as (A, B) label pairs (none
    when no setting has IL, e.g. an ablation grid that borrows its IL from another grid)."""
    with_il = {r.setting for r in rows if r.label == "il"}
    return sorted({(r.label, "il") for r in rows if r.label != "il" and r.setting in with_il})


def build_comparisons(rows: list[Row], pairs: list[tuple[str, str]]) -> list[Comparison]:
    """Each declared (A, B) in every setting holding both; Holm's correction over all of them (one
    study, one family). A pair that matches no setting is an error: a plan that names a variant the
    runs lack must not silently shrink the family."""
    by_key = {(r.setting, r.label): r for r in rows}
    settings = sorted({r.setting for r in rows})
    out: list[Comparison] = []
    for a_name, b_name in pairs:
        found = False
        for s in settings:
            a = [r for (st, lb), r in by_key.items() if st == s and _matches(lb, a_name)]
            b = [r for (st, lb), r in by_key.items() if st == s and _matches(lb, b_name)]
            for ra in a:
                for rb in b:
                    found = True
                    x, y = np.array(ra.finals), np.array(rb.finals)
                    d, dlo, dhi = iqm_difference_ci(x, y)
                    pi, plo, phi = poi_ci(x, y)
                    out.append(Comparison(s, ra.label, rb.label, float(x.mean() - y.mean()), d, dlo, dhi,
                                          pi, plo, phi, welch_p(x, y)))
        if not found:
            raise ValueError(f"comparison {a_name}:{b_name}: no setting has runs of both "
                             f"(variants here: {', '.join(sorted({r.label for r in rows}))})")
    tested = [c for c in out if c.p is not None]
    for c, ph in zip(tested, holm([c.p for c in tested]), strict=True):
        c.p_holm = ph
    return out


_PLAN_LINE = re.compile(r"^\s*comparisons:\s*(.+?)\s*$", re.MULTILINE | re.IGNORECASE)


def parse_comparisons(text: str) -> list[tuple[str, str]]:
    """`A:B` pairs separated by commas or spaces, e.g. `hammer-rl:il, random:il`."""
    pairs = []
    for item in re.split(r"[,\s]+", text.strip().strip("`")):
        if not item:
            continue
        a, sep, b = item.partition(":")
        if not sep or not a or not b:
            raise ValueError(f"comparisons: {item!r} is not A:B (e.g. hammer-rl:il)")
        pairs.append((a, b))
    return pairs


def comparisons_from_plan(path: Path) -> list[tuple[str, str]]:
    """The pairs on the plan file's `comparisons:` line (docs/results/plan-*.md)."""
    m = _PLAN_LINE.search(Path(path).read_text())
    if m is None:
        raise ValueError(f"{path} has no line `comparisons: A:B, ...`; add one listing the declared comparisons")
    return parse_comparisons(m.group(1))


def to_markdown(rows: list[Row], last: int, best_window: int | None = None,
                comparisons: list[Comparison] | None = None, auc: int | None = None, digits: int = 2) -> str:
    """The report's markdown; `digits` decimals for the metric (a task whose values are small, like the
    warehouse's deliveries per robot, needs more than the default 2)."""
    team_window = f"the first {auc} episodes" if auc else f"the last {last} episodes"
    shortest = min((r.episodes for r in rows), default=last)
    if auc is not None:
        col = f"AUC {auc}"
        what = (f"AUC {auc} = mean paper metric (average reward per local agent per episode) over each seed's "
                f"first {auc} episodes (area under the learning curve / {auc}; higher = better sooner)")
    elif best_window is None:
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
        (f"{what}; mean ± standard error over seeds (no ± with one seed); IQM = interquartile mean over "
        f"seeds with a 95 % stratified-bootstrap CI; team return = mean summed team reward over {team_window}; "
        "p = Welch's t-test against IL in the same setting (uncorrected)."),
        "",
        f"| setting | variant | seeds | episodes | {col} (mean ± s.e.) | IQM [95% CI] | team return | p vs IL |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        p = "" if r.p_vs_il is None else f"{r.p_vs_il:.3g}"
        d, t = digits, max(1, digits - 1)
        se = "" if np.isnan(r.sem) else f" ± {r.sem:.{d}f}"  # one seed has no standard error
        out.append(f"| {r.setting} | {r.label} | {r.n_seeds} | {r.episodes} | {r.mean:.{d}f}{se} | "
                   f"{r.iqm:.{d}f} [{r.iqm_lo:.{d}f}, {r.iqm_hi:.{d}f}] | {r.team:.{t}f} | {p} |")
    if comparisons:
        out += comparisons_markdown(comparisons, digits)
    return "\n".join(out) + "\n"


def comparisons_markdown(comps: list[Comparison], digits: int = 2) -> list[str]:
    out = [
        "",
        (f"Declared comparisons ({len(comps)}, one family): difference of means; IQM(A) − IQM(B) with a 95 % "
        "bootstrap CI (each side's seeds resampled); P(A > B) = probability that a run of A ends above a "
        "run of B, with a 95 % bootstrap CI; Welch p; Holm = Welch p corrected across this family."),
        "",
        "| setting | A | B | A − B | IQM diff [95% CI] | P(A > B) [95% CI] | p (Welch) | p (Holm) |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for c in comps:
        p = "" if c.p is None else f"{c.p:.3g}"
        ph = "" if c.p_holm is None else f"{c.p_holm:.3g}"
        d = digits
        out.append(f"| {c.setting} | {c.a} | {c.b} | {c.diff:+.{d}f} | {c.iqm_diff:+.{d}f} [{c.iqm_diff_lo:+.{d}f}, "
                   f"{c.iqm_diff_hi:+.{d}f}] | {c.poi:.2f} [{c.poi_lo:.2f}, {c.poi_hi:.2f}] | {p} | {ph} |")
    return out
